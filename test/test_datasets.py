"""Dataset readers: tiny folders made here, and the real layouts in ../shared/data."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.errors import DatasetError
from lln_ros.io import datasets


def write_images(folder, n, blank=(), size=(40, 30)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(str(folder)))
    for i in range(n):
        img = (
            np.full((size[1], size[0]), 90, np.uint8)
            if i in blank
            else rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8)
        )
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


def test_drop_modes_blank_with_a_logo_and_frozen_runs(tmp_path):
    """drop=blank catches a dark frame with a small bright overlay (std above BLANK_STD, so `flat`
    misses it); drop=frozen drops the repeats of a stalled frame but keeps its first; refs stay."""
    ref = write_images(tmp_path / 'summer', 12)
    qry = write_images(tmp_path / 'winter', 12)
    tunnel = np.full((30, 40), 6, np.uint8)
    tunnel[2:5, 30:38] = 200  # a channel logo: 2% of the pixels
    assert tunnel.std() > datasets.BLANK_STD
    assert cv2.imwrite(str(qry / 'images-00030.png'), tunnel)
    stalled = cv2.imread(str(qry / 'images-00070.png'), cv2.IMREAD_UNCHANGED)
    for i in (8, 9, 10):
        assert cv2.imwrite(str(qry / f'images-{i * 10:05d}.png'), stalled)
    default = datasets.aligned(ref, qry, tol=0)
    assert len(default.query_paths) == 12 and default.info['drop'] == 'flat'
    assert default.info['blank_queries_dropped'] == 0 and default.info['frozen_queries_dropped'] == 0
    both = datasets.parse_spec(f'aligned:{ref},{qry},0,drop=blank+frozen')
    assert [p.name for p in both.query_paths] == [f'images-{i * 10:05d}.png' for i in (0, 1, 2, 4, 5, 6, 7, 11)]
    assert both.info['blank_queries_dropped'] == 1 and both.info['frozen_queries_dropped'] == 3
    assert len(both.ref_paths) == 12 and both.gt.shape == (8, 12)
    assert both.gt[3].tolist() == [i == 4 for i in range(12)]  # the truth follows the file index
    only_frozen = datasets.parse_spec(f'aligned:{ref},{qry},0,drop=frozen')
    assert len(only_frozen.query_paths) == 9 and only_frozen.info['blank_queries_dropped'] == 0
    assert len(datasets.parse_spec(f'aligned:{ref},{qry},0,drop=none').query_paths) == 12
    with pytest.raises(DatasetError, match='drop= takes none or'):
        datasets.parse_spec(f'aligned:{ref},{qry},0,drop=dark')


def test_sequence_flag_per_reader_and_spec_option(tmp_path):
    """Aligned traverses and loops are routes; a VPR-Bench folder is not unless the spec says so."""
    ref = write_images(tmp_path / 'a', 4)
    qry = write_images(tmp_path / 'b', 4)
    assert datasets.parse_spec(f'aligned:{ref},{qry}').sequence is True
    assert datasets.parse_spec(f'aligned:{ref},{qry},1,sequence=0').sequence is False
    vpr = tmp_path / 'vpr'
    write_images(vpr / 'query', 3)
    write_images(vpr / 'ref', 3)
    rows = np.empty((3, 2), object)
    for q in range(3):
        rows[q] = [q, [q]]
    np.save(vpr / 'ground_truth_new.npy', rows, allow_pickle=True)
    assert datasets.parse_spec(f'vprbench:{vpr}').sequence is False
    assert datasets.parse_spec(f'vprbench:{vpr},sequence=1').sequence is True
    seq = write_images(tmp_path / 'seq', 12)
    np.save(tmp_path / 'gt.npy', np.zeros((12, 12)))
    assert datasets.parse_spec(f'loop:{seq},{tmp_path / "gt.npy"}').sequence is True
    with pytest.raises(DatasetError, match="unknown option 'drop' for vprbench"):
        datasets.parse_spec(f'vprbench:{vpr},drop=blank')
    with pytest.raises(DatasetError, match='sequence= takes 0 or 1'):
        datasets.parse_spec(f'vprbench:{vpr},sequence=true')


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
    gt[25, 3] = gt[25, 20] = 255  # 20 is too recent (gap 10): not an answer
    cv2.imwrite(str(seq / 'zz_gt.bmp'), gt)
    ds = datasets.loop(seq, seq / 'zz_gt.bmp')  # the matrix in the same folder is not a frame
    assert len(ds.ref_paths) == 30
    assert ds.candidates[25, 15] and not ds.candidates[25, 16]
    assert ds.gt[25, 3] and not ds.gt[25, 20] and ds.queries_with_match == 1


def test_real_layouts():
    nordland = shared_data('nordland_trimmed')
    ds = datasets.parse_spec(f'aligned:{nordland / "summer"},{nordland / "winter"},1', (0.7, 1.0))
    assert len(ds.ref_paths) == len(ds.query_paths) == 1073 and ds.info['blank_queries_dropped'] == 0
    assert ds.ref_paths[0].name == ds.query_paths[0].name and ds.sequence
    # the Nordland filter: 10 tunnel queries (logo on black) and the last 14 repeats of the frozen
    # final winter frame go; the references stay
    clean = datasets.parse_spec(f'aligned:{nordland / "summer"},{nordland / "winter"},1,drop=blank+frozen', (0.7, 1.0))
    assert clean.info['blank_queries_dropped'] == 10 and clean.info['frozen_queries_dropped'] == 14
    assert len(clean.query_paths) == 1049 and len(clean.ref_paths) == 1073 and clean.gt.shape == (1049, 1073)
    assert ds.info['blank_refs'] == 0 and clean.info['blank_refs'] == 77  # summer tunnels: black, kept in the map
    assert clean.query_paths[-1].name == 'images-35620.png' and clean.gt[-1, -3:].tolist() == [False, False, False]
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


def write_pose_sequence(root, poses, times=None, rate=10.0):
    """A TUM RGB-D layout: rgb/<t>.png, rgb.txt and groundtruth.txt (poses: (N, 7) tx ty tz qx qy qz qw)."""
    write_images(root / 'rgb', len(poses))
    frames = sorted((root / 'rgb').iterdir(), key=datasets.natural_key)
    times = np.arange(len(poses)) / rate if times is None else np.asarray(times)
    (root / 'rgb.txt').write_text(
        '# color images\n# timestamp filename\n' + ''.join(f'{t:.6f} rgb/{f.name}\n' for t, f in zip(times, frames))
    )
    # poses at 10x the frame rate, each a little off the frame's time, as motion capture is
    lines = ['# ground truth trajectory', '# timestamp tx ty tz qx qy qz qw']
    for t, p in zip(times, poses):
        for dt in (-0.004, 0.001, 0.006):  # the 0.001 one is nearest and carries the true pose
            q = p if dt == 0.001 else [p[0] + 5, p[1], p[2], 0, 0, 0, 1]  # a wrong pose nearby in time
            lines.append(f'{t + dt:.4f} ' + ' '.join(f'{v:.4f}' for v in q))
    (root / 'groundtruth.txt').write_text('\n'.join(lines) + '\n')


def yaw(deg):
    return [0.0, 0.0, np.sin(np.radians(deg) / 2), np.cos(np.radians(deg) / 2)]


def test_pose_sequence_same_place_from_rotation_distance_and_time_gap(tmp_path):
    # frames 0..5: yaw 0, 40, 80, 12, 0 (1 m away), 50 deg, 1 s apart
    poses = [
        [0, 0, 0] + yaw(0),
        [0, 0, 0] + yaw(40),
        [0, 0, 0] + yaw(80),
        [0.1, 0, 0] + yaw(12),
        [1.0, 0, 0] + yaw(0),
        [0, 0, 0] + yaw(50),
    ]
    write_pose_sequence(tmp_path, poses, rate=1.0)
    ds = datasets.parse_spec(f'poses:{tmp_path}')  # 15 deg, 0.3 m, 2 s
    assert len(ds.query_paths) == 6 and ds.ref_paths == ds.query_paths
    # frame 3 (12 deg, 0.1 m from frame 0, 3 s later) revisits 0; frame 4 is 1 m away: no;
    # frame 5 (10 deg from frame 1, 4 s later) revisits 1
    assert np.argwhere(ds.gt).tolist() == [[3, 0], [5, 1]]
    assert ds.candidates[3].tolist() == [True, True, False, False, False, False]  # >= 2 s older only
    loose = datasets.parse_spec(f'poses:{tmp_path},15,2,2')
    assert np.argwhere(loose.gt).tolist() == [[3, 0], [4, 0], [5, 1]]
    near = datasets.parse_spec(f'poses:{tmp_path},15,0.3,0')  # no gap: every older frame, never itself
    assert near.candidates[1, 0] and not near.candidates.diagonal().any() and not near.candidates[0].any()
    assert near.info['min_gap_s'] == 0 and near.info['frames_without_pose'] == 0
    every_other = datasets.parse_spec(f'poses:{tmp_path},15,0.3,2,2')  # frames 0, 2, 4
    assert [p.name for p in every_other.query_paths] == [ds.query_paths[i].name for i in (0, 2, 4)]
    assert not every_other.gt.any() and every_other.candidates[2].tolist() == [True, True, False]


def test_pose_sequence_bad_input(tmp_path):
    write_pose_sequence(tmp_path, [[0, 0, 0] + yaw(0)] * 3)
    with pytest.raises(DatasetError, match='numbers'):
        datasets.parse_spec(f'poses:{tmp_path},fifteen')
    with pytest.raises(DatasetError, match='MAX_DEG > 0'):
        datasets.parse_spec(f'poses:{tmp_path},0')
    with pytest.raises(DatasetError, match='whole STEP'):
        datasets.parse_spec(f'poses:{tmp_path},15,0.3,2,1.5')
    (tmp_path / 'groundtruth.txt').write_text('1000 0 0 0 0 0 0 1\n')  # another clock
    with pytest.raises(DatasetError, match='same clock'):
        datasets.parse_spec(f'poses:{tmp_path}')
    (tmp_path / 'groundtruth.txt').write_text('0.0 0 0 0\n')
    with pytest.raises(DatasetError, match='8 columns'):
        datasets.parse_spec(f'poses:{tmp_path}')
    (tmp_path / 'groundtruth.txt').unlink()
    with pytest.raises(DatasetError, match='not found'):
        datasets.parse_spec(f'poses:{tmp_path}')


def test_real_pose_sequence():
    root = shared_data('tum_fr1rpy')
    ds = datasets.parse_spec(f'poses:{root}')
    assert len(ds.query_paths) == 723 and ds.info['frames_without_pose'] == 0
    assert ds.info['query_sizes'][0] == (640, 480)
    # rotating in place: about two thirds of the frames see an earlier view again (>= 2 s before)
    assert 400 < ds.queries_with_match < 560
    assert not (ds.gt & ~ds.candidates).any()
