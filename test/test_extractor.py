"""Landmark extraction on real pixels: shapes, coordinates, methods, determinism, bad input."""

import numpy as np
import pytest
import torch

from lln_ros.core.extractor import Extractor
from lln_ros.core.landmarks import select_landmarks
from lln_ros.core.lln import LLNHead, load_checkpoint, save_checkpoint
from lln_ros.errors import ImageError, ModelError
from lln_ros.io.image import load_image, network_size


def test_landmark_set_shapes_and_coordinates(extractor, photo):
    s = extractor(photo)  # 512x600 portrait: network 256x288 -> 8x9 grid
    assert s.grid == (9, 8)
    assert len(s) == 50 and s.descriptors.shape == (50, 192) and s.global_descriptor.shape == (192,)
    # unit length to float16 precision (descriptors are float16-exact, as the map stores them)
    np.testing.assert_allclose(np.linalg.norm(s.descriptors, axis=1), 1, atol=1e-3)
    np.testing.assert_array_equal(s.descriptors, s.descriptors.astype(np.float16))
    assert abs(np.linalg.norm(s.global_descriptor) - 1) < 1e-5
    np.testing.assert_allclose(s.cell_size, [512 / 8, 600 / 9], rtol=1e-6)
    # centres are in ORIGINAL pixels, at the middle of their cell
    np.testing.assert_allclose(s.centers, (s.cells + 0.5) * s.cell_size, rtol=1e-6)
    assert (s.centers[:, 0] < 512).all() and (s.centers[:, 1] < 600).all()
    assert (np.diff(s.scores) <= 0).all(), 'landmarks must come by descending score'
    assert s.activation.shape == (9, 8) and (s.activation >= 0).all()
    # descriptor at a cell is the L2-normalised backbone feature there
    assert len({tuple(c) for c in s.cells}) == 50


def test_paper_grid_at_384x288(extractor, photo):
    s = extractor(photo[:288, :384])
    assert s.grid == (9, 12) and s.cells[:, 0].max() < 12 and s.cells[:, 1].max() < 9
    assert network_size(512, 384, 288) == (384, 288)
    assert network_size(64, 32, 288) == (576, 288)  # Nordland: 18x9 cells


def test_deterministic_and_batched_equals_single(photo):
    a = Extractor({'num_threads': 2})
    b = Extractor({'num_threads': 2})
    crops = [photo[:288, :384], photo[100:388, 64:448], photo]
    singles = [a(c) for c in crops]
    batched = b.extract_batch(crops)
    for s, t in zip(singles, batched):
        np.testing.assert_array_equal(s.cells, t.cells)
        np.testing.assert_allclose(s.descriptors, t.descriptors, atol=1e-5)
        np.testing.assert_allclose(s.global_descriptor, t.global_descriptor, atol=1e-5)
    assert a.model_info == b.model_info


def test_channel_orders_and_grey(extractor, photo):
    rgb = extractor(photo)
    bgr = extractor(np.ascontiguousarray(photo[:, :, ::-1]), channel_order='bgr')
    np.testing.assert_allclose(rgb.descriptors, bgr.descriptors, atol=1e-6)
    rgba = np.dstack([photo, np.full(photo.shape[:2], 255, np.uint8)])
    np.testing.assert_allclose(extractor(rgba).descriptors, rgb.descriptors, atol=1e-6)
    grey = photo.mean(axis=2).astype(np.uint8)
    g2 = extractor(grey)
    g3 = extractor(np.dstack([grey] * 3))
    np.testing.assert_allclose(g2.descriptors, g3.descriptors, atol=1e-6)
    assert extractor(grey[:, :, None]).grid == g2.grid


def test_methods(photo):
    base = {'num_threads': 2, 'top_n': 20}
    lln = Extractor({**base, 'method': 'lln'})(photo)
    np.testing.assert_array_equal(lln.scores, np.sort(lln.activation.ravel())[::-1][:20])
    act = Extractor({**base, 'method': 'act'})(photo)
    assert (np.diff(act.scores) <= 0).all() and act.scores.min() > 0
    rand_ex = Extractor({**base, 'method': 'rand'})
    r1, r2 = rand_ex(photo), rand_ex(photo[::-1].copy())
    assert {tuple(c) for c in r1.cells} == {tuple(c) for c in r2.cells}, 'RAND: same cells for every image'
    assert len(Extractor({**base, 'method': 'all'})(photo)) == 72  # 8x9: every cell


def test_select_landmarks():
    m = np.array([[0.1, 0.5, 0.5], [0.9, 0.0, 0.2]])
    np.testing.assert_array_equal(select_landmarks(m, 3, 'lln'), [3, 1, 2])  # ties: lower index first
    np.testing.assert_array_equal(select_landmarks(m, 2, 'act'), [3, 1])
    assert sorted(select_landmarks(m, 10, 'all')) == list(range(6))
    rand = select_landmarks(m, 3, 'rand', seed=4)
    # the same cells whatever the scores (the same for every image), listed by descending score
    assert set(rand) == set(select_landmarks(m * 0, 3, 'rand', seed=4))
    assert (np.diff(m.ravel()[rand]) <= 0).all()
    assert set(select_landmarks(m, 3, 'rand', seed=5)) != set(rand)  # the seed decides the cells
    with pytest.raises(ValueError, match='unknown landmark method'):
        select_landmarks(m, 3, 'nope')


@pytest.mark.parametrize(
    'bad, message',
    [
        (np.zeros((0, 0, 3), np.uint8), 'at least'),
        (np.zeros((1, 1), np.uint8), 'at least'),
        (np.zeros((100, 100, 3), np.float32), 'dtype must be uint8'),
        (np.zeros((100, 100, 2), np.uint8), 'shape'),
        (np.zeros((100, 100, 3, 1), np.uint8), 'shape'),
        ([[1, 2], [3, 4]], 'numpy array'),
        (np.zeros((10, 5000), np.uint8), 'aspect'),
    ],
)
def test_bad_images_raise_clear_errors(extractor, bad, message):
    with pytest.raises(ImageError, match=message):
        extractor(bad)


def test_bad_files(tmp_path):
    with pytest.raises(ImageError, match='not found'):
        load_image(str(tmp_path / 'missing.jpg'))
    junk = tmp_path / 'junk.jpg'
    junk.write_bytes(b'\xff\xd8 definitely not a jpeg')
    with pytest.raises(ImageError, match='cannot decode'):
        load_image(str(junk))


def test_bad_configuration():
    with pytest.raises(ModelError, match='unknown backbone'):
        Extractor({'backbone': {'name': 'vgg16'}})
    with pytest.raises(ModelError, match='unknown layer'):
        Extractor({'backbone': {'layer': 'stage9'}})
    with pytest.raises(ModelError, match='unknown method'):
        Extractor({'method': 'best'})
    with pytest.raises(ModelError, match='weights file not found'):
        Extractor({'backbone': {'weights_path': '/nonexistent/lite0.pth'}})


def test_checkpoint_metadata_guards_the_descriptor_space(tmp_path, photo):
    head = LLNHead(320, {'channels': 8})
    path = str(tmp_path / 'head.pt')
    save_checkpoint(path, head, 'efficientnet_lite0', 'stage7', trained=True, note='test')
    loaded, meta = load_checkpoint(path, 'efficientnet_lite0', 'stage7', 320)
    assert meta['note'] == 'test' and meta['descriptor_dim'] == 320 and meta['version'] == 1
    for k, v in head.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    ex = Extractor({'backbone': {'layer': 'stage7'}, 'weights': path, 'num_threads': 2})
    assert ex.model_info['head_trained'] and ex(photo).dim == 320
    # a head for another layer (another descriptor space) is refused by name, before any shape error
    with pytest.raises(ModelError, match="layer='stage7'.*layer='stage6'"):
        Extractor({'weights': path})
    with pytest.raises(ModelError, match='backbone'):
        load_checkpoint(path, backbone='resnet101')
    (tmp_path / 'bad.pt').write_bytes(b'not a checkpoint')
    with pytest.raises(ModelError, match='not an lln_ros checkpoint'):
        load_checkpoint(str(tmp_path / 'bad.pt'))
    with pytest.raises(ModelError, match='not found'):
        load_checkpoint(str(tmp_path / 'nope.pt'))


def test_untrained_head_is_seeded():
    a, b = LLNHead(320), LLNHead(320)
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k])
    c = LLNHead(320, {'seed': 1})
    assert not torch.equal(a.fuse.weight, c.fuse.weight)


def test_lln_ranks_by_head_logits_not_by_index(extractor, photo):
    """Many cells get activation exactly 0 from the final ReLU; they must be ordered by the head's
    logits, not fall back to raster order (the top rows: ceiling, sky)."""
    from lln_ros.io.image import resize_for_network

    feats = extractor.backbone_features(resize_for_network(photo, 288)[None])
    logits = extractor.head.logits(feats)[0].numpy()
    s = extractor(photo)
    assert (s.activation == 0).sum() > 0, 'this check needs silent cells'
    want = np.argsort(-logits.ravel(), kind='stable')[:50]
    np.testing.assert_array_equal(s.cells[:, 1] * s.grid[1] + s.cells[:, 0], want)
    np.testing.assert_allclose(s.scores, np.maximum(logits.ravel()[want], 0), rtol=1e-5)


def test_default_head_is_the_shipped_trained_one(extractor):
    """The package ships a head trained on the first 60% of the Nordland route (validated on
    60-70%), never on the 70-100% test split, with the command that reproduces it."""
    info = extractor.model_info
    assert info['head_trained'] is True and info['weights'].endswith('lln_efficientnet_lite0_stage6.pt')
    meta = extractor.head_meta
    assert meta['train_conf']['objective'] == 'rerank'
    assert '--range 0:0.6' in meta['command'] and '--val-range 0.6:0.7' in meta['command']
