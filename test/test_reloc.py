"""Keypoint matching and geometric verification (lln_ros.core.reloc) on real images: a photograph under
a known affine warp (the true correspondence of every pixel is known), rtabmap_loop frames, a
Nordland frame, and every kind of input that must end in "not verified" instead of an exception."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.core.reloc import Keypoints, Relocalizer, RelocError, camera_matrix, pair_boxes, region_boxes
from lln_ros.core.similarity import match_pair
from lln_ros.io.image import load_image


@pytest.fixture(scope='module')
def warped(photo):
    """(query, keyframe, A): keyframe = photo; query = photo rotated 6 deg and scaled 0.9 about its
    centre, so a keyframe pixel p appears in the query at A @ [p, 1]."""
    h, w = photo.shape[:2]
    A = cv2.getRotationMatrix2D((w / 2, h / 2), 6, 0.9)
    return cv2.warpAffine(photo, A, (w, h), borderMode=cv2.BORDER_REFLECT), photo, A


def reprojection_error(result, kq, km, A):
    pm = km.uv[result.matches.map_index[result.inlier_mask]]
    pq = kq.uv[result.matches.query_index[result.inlier_mask]]
    return np.linalg.norm(pm @ A[:, :2].T + A[:, 2] - pq, axis=1)


@pytest.mark.parametrize('detector', ['orb', 'sift'])
def test_unconstrained_inliers_are_true_correspondences(warped, detector):
    query, keyframe, A = warped
    reloc = Relocalizer({'detector': detector})
    kq, km = reloc.detect(query), reloc.detect(keyframe)
    assert 200 < len(kq) <= 1000 and 200 < len(km) <= 1000
    r = reloc.relocalize(kq, km)
    assert r.verified and r.reason == '' and r.model == 'F' and r.R is None
    assert r.inliers >= 100 and 0.5 < r.inlier_ratio <= 1
    err = reprojection_error(r, kq, km, A)
    assert np.mean(err < 3.0) > 0.9, np.percentile(err, [50, 90, 99])


def test_region_constrained_matches_stay_in_their_regions(warped, extractor):
    query, keyframe, A = warped
    reloc = Relocalizer()
    a, b = extractor.extract_batch([query, keyframe])
    pairs = match_pair(a, b).pairs(0)
    qb, mb = pair_boxes(a, b, pairs, reloc.conf['margin'])
    assert len(qb) == len(pairs['query_index']) > 5
    kq, km = reloc.detect(query), reloc.detect(keyframe)
    r = reloc.relocalize(kq, km, qb, mb)
    assert r.verified and r.inliers >= 30, r.reason
    # every match lies in one region pair: query keypoint in query box m, keyframe keypoint in map box m
    uq, um = kq.uv[r.matches.query_index], km.uv[r.matches.map_index]
    in_q = (
        (uq[None, :, 0] >= qb[:, None, 0])
        & (uq[None, :, 0] < qb[:, None, 2])
        & (uq[None, :, 1] >= qb[:, None, 1])
        & (uq[None, :, 1] < qb[:, None, 3])
    )
    in_m = (
        (um[None, :, 0] >= mb[:, None, 0])
        & (um[None, :, 0] < mb[:, None, 2])
        & (um[None, :, 1] >= mb[:, None, 1])
        & (um[None, :, 1] < mb[:, None, 3])
    )
    assert (in_q & in_m).any(axis=0).all()
    assert np.mean(reprojection_error(r, kq, km, A) < 3.0) > 0.9
    # one partner per keypoint on both sides
    assert len(set(r.matches.query_index)) == len(set(r.matches.map_index)) == len(r.matches)


def test_region_boxes_scale_with_cell_and_margin():
    boxes = region_boxes(np.array([[100.0, 50.0]]), (40.0, 30.0), 0.5)
    np.testing.assert_allclose(boxes, [[60, 20, 140, 80]])


def test_essential_matrix_and_pose_on_consecutive_rtabmap_frames(tmp_path):
    root = shared_data('rtabmap_loop')
    reloc = Relocalizer()
    kq, km = reloc.detect(load_image(str(root / '42.jpg'))), reloc.detect(load_image(str(root / '41.jpg')))
    yaml_file = tmp_path / 'camera.yaml'  # a ROS camera-calibration file; 512x384, ~60 deg field of view
    yaml_file.write_text(
        'image_width: 512\nimage_height: 384\ncamera_name: rtabmap\n'
        'camera_matrix:\n  rows: 3\n  cols: 3\n  data: [440, 0, 256, 0, 440, 192, 0, 0, 1]\n'
    )
    r = reloc.relocalize(kq, km, K=str(yaml_file))
    assert r.verified and r.model == 'E', r.reason
    assert r.R is not None and r.t is not None
    np.testing.assert_allclose(r.R @ r.R.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(r.R) == pytest.approx(1.0, abs=1e-6)
    assert np.linalg.norm(r.t) == pytest.approx(1.0, abs=1e-6)
    angle = np.degrees(np.arccos(np.clip((np.trace(r.R) - 1) / 2, -1, 1)))
    assert angle < 20  # consecutive frames of a hand-held walk
    # a distant, unrelated place of the same building does not verify
    far = reloc.relocalize(kq, reloc.detect(load_image(str(root / '80.jpg'))))
    assert not far.verified and far.reason


def test_tiny_nordland_frame_is_upsampled_for_detection():
    path = shared_data('nordland_trimmed', 'summer', 'images-03000.png')
    image = load_image(str(path))
    kps = Relocalizer().detect(image)
    assert kps.scale == pytest.approx(288 / 32) and kps.image_size == (64, 32)
    assert len(kps) > 20
    assert (kps.uv >= -0.5).all() and (kps.uv[:, 0] < 64).all() and (kps.uv[:, 1] < 32).all()
    # upsampled frames are blurry: a lower FAST threshold finds many more corners
    assert len(Relocalizer({'fast_threshold': 5}).detect(image)) > 2 * len(kps)
    # a threshold in original pixels would be 9x too loose: verification uses detection pixels
    other = Relocalizer().detect(load_image(str(path).replace('summer', 'winter')))
    r = Relocalizer().relocalize(kps, other)
    assert r.inliers <= len(r.matches)


# ---------------------------------------------------------------------------------- bad input


def test_textureless_image_is_not_verified(photo):
    reloc = Relocalizer()
    blank = reloc.detect(np.full((240, 320), 128, np.uint8))
    assert len(blank) == 0 and blank.descriptors.shape == (0, 32)
    r = reloc.relocalize(blank, reloc.detect(photo))
    assert not r.verified and r.inliers == 0 and 'no keypoints' in r.reason
    r = reloc.relocalize(blank, blank, np.zeros((1, 4)), np.zeros((1, 4)))
    assert not r.verified and 'no keypoints' in r.reason


def test_regions_outside_the_image_are_not_verified(photo):
    reloc = Relocalizer()
    kps = reloc.detect(photo)
    outside = np.array([[-500.0, -500.0, -400.0, -400.0], [2000.0, 0.0, 2100.0, 100.0]])
    r = reloc.relocalize(kps, kps, outside, outside)
    assert not r.verified and 'outside the images' in r.reason
    r = reloc.relocalize(kps, kps, np.zeros((0, 4)), np.zeros((0, 4)))
    assert not r.verified and 'outside the images' in r.reason
    with pytest.raises(RelocError, match='2 query regions but 1'):
        reloc.match(kps, kps, outside, outside[:1])


def collinear_keypoints(n=40, rng=None):
    rng = rng or np.random.default_rng(0)
    u = np.linspace(10, 300, n, dtype=np.float32)
    return Keypoints(
        uv=np.stack([u, 0.5 * u + 20], axis=1),
        size=np.full(n, 31, np.float32),
        angle=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        octave=np.zeros(n, np.int32),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        image_size=(320, 240),
    )


def test_collinear_and_too_few_matches_are_not_verified():
    reloc = Relocalizer()
    line = collinear_keypoints()
    r = reloc.relocalize(line, line)  # identical descriptors: 40 perfect matches, all on one line
    assert len(r.matches) == 40 and not r.verified and 'line' in r.reason
    few = collinear_keypoints(5)
    r = reloc.relocalize(few, few)
    assert not r.verified and '5 matches' in r.reason
    sift = Relocalizer({'detector': 'sift'})
    with pytest.raises(RelocError, match='descriptors differ'):
        sift.match(
            Keypoints(line.uv, line.size, line.angle, line.response, line.octave, np.zeros((40, 128), np.float32)), line
        )


def test_intrinsics_sources_and_errors(tmp_path):
    k = [500.0, 0, 320, 0, 510, 240, 0, 0, 1]

    class CameraInfoLike:  # sensor_msgs/CameraInfo carries K as the flat float64[9] field `k`
        def __init__(self, k):
            self.k = k

    expected = np.array(k).reshape(3, 3)
    np.testing.assert_array_equal(camera_matrix(CameraInfoLike(k)), expected)
    np.testing.assert_array_equal(camera_matrix(expected), expected)
    np.testing.assert_array_equal(camera_matrix({'k': k}), expected)
    (tmp_path / 'k.yaml').write_text(f'K: {k}\n')
    np.testing.assert_array_equal(camera_matrix(tmp_path / 'k.yaml'), expected)
    with pytest.raises(RelocError, match='9 numbers'):
        camera_matrix([1, 2, 3])
    with pytest.raises(RelocError, match='positive fx'):
        camera_matrix([0, 0, 320, 0, 510, 240, 0, 0, 1])
    with pytest.raises(RelocError, match='cannot read'):
        camera_matrix(str(tmp_path / 'missing.yaml'))
    (tmp_path / 'bad.yaml').write_text('camera_matrix: [1, 2\n')
    with pytest.raises(RelocError, match='not valid YAML'):
        camera_matrix(str(tmp_path / 'bad.yaml'))
    (tmp_path / 'none.yaml').write_text('width: 3\n')
    with pytest.raises(RelocError, match='no camera_matrix'):
        camera_matrix(str(tmp_path / 'none.yaml'))


def test_bad_configuration_raises_clear_errors():
    with pytest.raises(RelocError, match='unknown detector'):
        Relocalizer({'detector': 'surf'})
    with pytest.raises(RelocError, match='ratio'):
        Relocalizer({'ratio': 1.5})
    try:
        Relocalizer({'detector': 'akaze'})
    except RelocError as e:  # OpenCV 5 builds without contrib have no AKAZE: say so
        assert 'AKAZE' in str(e)
