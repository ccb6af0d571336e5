"""Dataset readers: tiny folders made here, and the real layouts in ../shared/data."""
import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros import datasets
from lln_ros.errors import DatasetError


def write_images(folder, n, blank=(), size=(40, 30)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(str(folder)))
    for i in range(n):
        img = np.full((size[1], size[0]), 90, np.uint8) if i in blank else \
            rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8)
        assert cv2.imwrite(str(folder / f'images-{i * 10:05d}.png'), img)
    return folder


def test_aligned_tolerance_range_and_blank_frames(tmp_path):
    ref = write_images(tmp_path / 'summer', 20)
    qry = write_images(tmp_path / 'winter', 20, blank=(12,))
    ds = datasets.aligned(ref, qry, tol=1)
    assert ds.gt.shape == (19, 20) and ds.info['blank_queries_dropped'] == 1
    assert ds.gt[0, :3].tolist() == [True, True, False]
    assert ds.gt.sum(1).max() == 3
    part = datasets.aligned(ref, qry, tol=1, frac=(0.5, 1.0))
    assert len(part.ref_paths) == 10 and part.ref_paths[0].name == 'images-00100.png'
    assert part.info['blank_queries_dropped'] == 1 and len(part.query_paths) == 9
    with pytest.raises(DatasetError, match='range'):
        datasets.aligned(ref, qry, frac=(0.8, 0.2))


def test_natural_order():
    names = ['10.jpg', '2.jpg', '1.jpg']
    assert sorted(names, key=datasets.natural_key) == ['1.jpg', '2.jpg', '10.jpg']


def test_bad_inputs_fail_before_any_work(tmp_path):
    ref = write_images(tmp_path / 'a', 5)
    with pytest.raises(DatasetError, match='does not exist'):
        datasets.aligned(ref, tmp_path / 'missing')
    with pytest.raises(DatasetError, match='differ in length'):
        datasets.aligned(ref, write_images(tmp_path / 'b', 4))
    (tmp_path / 'empty').mkdir()
    with pytest.raises(DatasetError, match='holds no images'):
        datasets.aligned(ref, tmp_path / 'empty')
    bad = write_images(tmp_path / 'c', 5)
    (bad / 'images-00020.png').write_bytes(b'not a png')
    with pytest.raises(DatasetError, match='images-00020.png'):
        datasets.aligned(ref, bad)
    seq = write_images(tmp_path / 'seq', 6)
    np.save(tmp_path / 'gt.npy', np.zeros((5, 5)))
    with pytest.raises(DatasetError, match='must be 6x6'):
        datasets.loop(seq, tmp_path / 'gt.npy')
    with pytest.raises(DatasetError, match='cannot parse'):
        datasets.parse_spec('nonsense:x')


def test_vprbench_layout_clips_missing_refs(tmp_path):
    write_images(tmp_path / 'vpr' / 'query', 3)
    write_images(tmp_path / 'vpr' / 'ref', 4)
    rows = np.empty((3, 2), object)
    for q, refs in enumerate([[0, 1], [1, 2], [3, 4, 5]]):
        rows[q] = [q, refs]
    np.save(tmp_path / 'vpr' / 'ground_truth_new.npy', rows, allow_pickle=True)
    ds = datasets.parse_spec(f'vprbench:{tmp_path / "vpr"}')
    assert ds.gt.tolist() == [[1, 1, 0, 0], [0, 1, 1, 0], [0, 0, 0, 1]]
    assert ds.info['clipped_refs'] == 2


def test_loop_protocol(tmp_path):
    seq = write_images(tmp_path / 'seq', 30)
    gt = np.zeros((30, 30), np.uint8)
    gt[25, 3] = gt[25, 20] = 255   # 20 is too recent (gap 10): not an answer
    cv2.imwrite(str(seq / 'zz_gt.bmp'), gt)
    ds = datasets.loop(seq, seq / 'zz_gt.bmp')   # the matrix in the same folder is not a frame
    assert len(ds.ref_paths) == 30
    assert ds.candidates[25, 15] and not ds.candidates[25, 16]
    assert ds.gt[25, 3] and not ds.gt[25, 20] and ds.queries_with_match == 1


def test_real_layouts():
    nordland = shared_data('nordland_trimmed')
    ds = datasets.parse_spec(f'aligned:{nordland / "summer"},{nordland / "winter"},1', (0.7, 1.0))
    assert len(ds.ref_paths) == 1073 and ds.info['blank_queries_dropped'] < 20
    assert ds.ref_paths[0].name == ds.query_paths[0].name or ds.info['blank_queries_dropped']
    rt = shared_data('rtabmap_loop')
    loop = datasets.parse_spec(f'loop:{rt},{rt / "samples_GT.bmp"}')
    assert len(loop.ref_paths) == 84 and loop.ref_paths[9].name == '10.jpg'
    assert loop.queries_with_match == 44 and not loop.gt[:40].any()
    gp = shared_data('gardens_point_gt', 'ground_truth_new.npy')
    gt, clipped = datasets.vprbench_gt(gp, 200, 200)
    assert gt.shape == (200, 200) and clipped > 0 and gt.any(1).all()


def test_bad_ground_truth_files_and_specs_are_dataset_errors(tmp_path):
    seq = write_images(tmp_path / 'seq', 6)
    (tmp_path / 'corrupt.npy').write_bytes(b'\x93NUMPY garbage')
    with pytest.raises(DatasetError, match='cannot read ground truth'):
        datasets.loop(seq, tmp_path / 'corrupt.npy')
    np.save(tmp_path / 'objects.npy', np.empty((6, 6), object), allow_pickle=True)
    with pytest.raises(DatasetError, match='ground truth'):
        datasets.loop(seq, tmp_path / 'objects.npy')
    write_images(tmp_path / 'vpr' / 'query', 3)
    write_images(tmp_path / 'vpr' / 'ref', 3)
    np.save(tmp_path / 'vpr' / 'ground_truth_new.npy', np.zeros((3, 3)))
    with pytest.raises(DatasetError, match=r'shape \(Q, 2\)'):
        datasets.vprbench(tmp_path / 'vpr')
    (tmp_path / 'vpr' / 'ground_truth_new.npy').write_bytes(b'not numpy at all')
    with pytest.raises(DatasetError, match='cannot read ground truth'):
        datasets.vprbench(tmp_path / 'vpr')
    with pytest.raises(DatasetError, match='whole number'):
        datasets.parse_spec(f'aligned:{seq},{seq},x')
