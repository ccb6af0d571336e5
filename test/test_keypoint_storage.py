"""Keypoints on the wire (msgs.keypoints_to_cloud / cloud_to_keypoints) and in the map
(MapStore.add_keypoints / keypoints), with real ORB keypoints of the matplotlib photograph."""

import numpy as np
import pytest

from lln_ros.core.reloc import Relocalizer
from lln_ros.errors import DescriptorError, MessageError
from lln_ros.mapstore import MapStore
from lln_ros.ros import msgs


@pytest.fixture(scope='module')
def kps(photo):
    return Relocalizer({'max_keypoints': 400}).detect(photo)


def test_cloud_round_trip(kps):
    cloud = msgs.keypoints_to_cloud(kps, msgs.make_header(123, 'cam'))
    assert cloud.width == len(kps) == 400 and cloud.point_step == 5 * 4 + 4 + 32
    back = msgs.cloud_to_keypoints(cloud, (512, 600), scale=1.0)
    for name in ('uv', 'size', 'angle', 'response', 'octave', 'descriptors'):
        np.testing.assert_array_equal(getattr(back, name), getattr(kps, name), err_msg=name)
    assert back.image_size == (512, 600)
    empty = msgs.cloud_to_keypoints(msgs.keypoints_to_cloud(Relocalizer().detect(np.zeros((50, 50), np.uint8))))
    assert len(empty) == 0 and empty.descriptors.shape == (0, 32)


def test_bad_clouds_are_message_errors(kps):
    cloud = msgs.keypoints_to_cloud(kps)
    cloud.data = cloud.data[:-3]
    with pytest.raises(MessageError, match='truncated'):
        msgs.cloud_to_keypoints(cloud)
    landmarks_like = msgs.array_to_cloud(np.zeros(3, [('u', '<f4'), ('v', '<f4')]))
    with pytest.raises(MessageError, match="'size' is missing"):
        msgs.cloud_to_keypoints(landmarks_like)
    table = np.zeros(
        2,
        [
            ('u', '<f4'),
            ('v', '<f4'),
            ('size', '<f4'),
            ('angle', '<f4'),
            ('response', '<f4'),
            ('octave', '<i4'),
            ('descriptor', 'u1', (32,)),
        ],
    )
    table['u'][0] = np.nan
    with pytest.raises(MessageError, match="'u' contains NaN"):
        msgs.cloud_to_keypoints(msgs.array_to_cloud(table))
    sift = Relocalizer({'detector': 'sift', 'max_keypoints': 10}).detect(np.full((64, 64), 9, np.uint8))
    with pytest.raises(MessageError, match='uint8'):
        msgs.keypoints_to_cloud(sift)


def test_map_keeps_keypoints_per_keyframe(kps, extractor, photo, tmp_path):
    lset = extractor(photo)
    path = tmp_path / 'map.db'
    with MapStore(path, model=extractor.model_info) as store:
        a, b = store.add(lset, (1, 0)), store.add(lset, (2, 0))
        assert store.keypoints(a) is None  # no table yet: a map without keypoints stays valid
        store.add_keypoints(a, kps.uv, kps.descriptors)
        assert store.keypoints(b) is None
        with pytest.raises(KeyError):
            store.add_keypoints(999, kps.uv, kps.descriptors)
        with pytest.raises(DescriptorError, match='uint8'):
            store.add_keypoints(b, kps.uv, kps.descriptors.astype(np.float32))
        store.add_keypoints(b, kps.uv[:0], kps.descriptors[:0])  # a textureless keyframe: zero keypoints
        assert store.check() == []
    with MapStore(path, create=False) as store:  # durable, and read back exactly
        uv, desc = store.keypoints(a)
        np.testing.assert_array_equal(uv, kps.uv)
        np.testing.assert_array_equal(desc, kps.descriptors)
        assert store.keypoints(b)[0].shape == (0, 2)
        store.clear()  # keypoints go with their keyframes
        assert store.keypoints(a) is None
