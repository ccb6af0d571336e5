"""The metric codecs (lln_ros.ros.msgs.geometry) and the keypoints' depth field, on real rclpy
messages: round trips, and every refusal a clear LLNError."""

import math

import numpy as np
import pytest
from sensor_msgs.msg import Image

from lln_ros.core.reloc import Keypoints
from lln_ros.errors import CameraError, LLNError, MessageError, PoseError
from lln_ros.io.camera import CameraModel
from lln_ros.ros import msgs

CAM = CameraModel.from_camera_info(
    {'width': 640, 'height': 480, 'k': [525, 0, 319.5, 0, 525, 239.5, 0, 0, 1], 'd': [0.1, 0, 0, 0, 0]},
    'camera_rgb_optical_frame',
)


def test_camera_info_round_trip_and_refusals():
    info = msgs.camera_model_to_info(CAM, 5)
    back = msgs.camera_info_to_model(info)
    assert back.frame_id == 'camera_rgb_optical_frame' and (back.width, back.height) == (640, 480)
    np.testing.assert_array_equal(back.K, CAM.K)
    np.testing.assert_array_equal(back.D, CAM.D)
    for change in (
        lambda m: setattr(m, 'k', [0.0] * 9),  # uncalibrated
        lambda m: setattr(m, 'k', [math.nan] + list(m.k[1:])),
        lambda m: (setattr(m, 'width', 320), setattr(m, 'height', 200)),  # principal point outside
        lambda m: setattr(m, 'd', [0.1, 0.2]),  # plumb_bob takes 5
    ):
        bad = msgs.camera_model_to_info(CAM)
        change(bad)
        with pytest.raises(CameraError):
            msgs.camera_info_to_model(bad)
    with pytest.raises(MessageError):
        msgs.camera_info_to_model(Image())


@pytest.mark.parametrize('encoding', ['16UC1', '32FC1'])
def test_depth_round_trip(encoding):
    rng = np.random.default_rng(0)
    mm = rng.integers(0, 5000, (48, 64)).astype(np.uint16)
    depth = mm if encoding == '16UC1' else np.where(mm > 0, mm / 1000.0, np.nan).astype(np.float32)
    m = msgs.depth_image_to_metres(msgs.depth_to_image(depth, encoding, 7), (64, 48))
    want = np.where(mm > 0, mm / 1000.0, np.nan)
    np.testing.assert_allclose(m, want, rtol=1e-6)


def test_depth_refusals():
    ok = msgs.depth_to_image(np.ones((48, 64), np.uint16) * 1000, '16UC1')
    with pytest.raises(CameraError, match='registered'):
        msgs.depth_image_to_metres(ok, (640, 480))  # another size than the colour image
    rgb = Image(height=48, width=64, encoding='rgb8', step=192, data=bytes(48 * 192))
    with pytest.raises(CameraError, match='REP 118'):
        msgs.depth_image_to_metres(rgb, (64, 48))
    short = msgs.depth_to_image(np.ones((48, 64), np.uint16), '16UC1')
    short.data = bytes(100)
    with pytest.raises(MessageError):
        msgs.depth_image_to_metres(short, (64, 48))


def test_odometry_round_trip_and_refusals():
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [1, 2, 3]
    odom = msgs.odometry_to_pose(msgs.pose_to_odometry(T, 11, 'odom', 'base_link'))
    assert (odom.stamp_ns, odom.frame_id, odom.child_frame_id) == (11, 'odom', 'base_link')
    np.testing.assert_allclose(odom.T, T, atol=1e-12)
    nan = msgs.pose_to_odometry(T, 11, 'odom')
    nan.pose.pose.position.y = math.nan
    long_q = msgs.pose_to_odometry(T, 11, 'odom')
    long_q.pose.pose.orientation.w = 1.5
    for bad in (nan, long_q):
        with pytest.raises(PoseError):
            msgs.odometry_to_pose(bad)
    with pytest.raises(MessageError, match='frame_id'):
        msgs.odometry_to_pose(msgs.pose_to_odometry(T, 11, ''))


def test_pose_message_layout():
    T = np.eye(4)
    T[:3, 3] = [0.5, 0, 0]
    cov = np.arange(36, dtype=float).reshape(6, 6)
    m = msgs.pose_to_message(T, cov, 3_000_000_001, 'world')
    assert m.header.frame_id == 'world' and msgs.stamp_to_ns(m.header) == 3_000_000_001
    assert m.pose.pose.position.x == 0.5 and m.pose.pose.orientation.w == 1.0
    assert list(m.pose.covariance) == list(range(36))  # row-major [x y z roll pitch yaw]


def test_keypoints_depth_field():
    rng = np.random.default_rng(1)
    n = 5
    kps = Keypoints(
        rng.uniform(0, 100, (n, 2)).astype(np.float32),
        np.full(n, 7, np.float32),
        np.zeros(n, np.float32),
        np.ones(n, np.float32),
        np.zeros(n, np.int32),
        rng.integers(0, 255, (n, 32)).astype(np.uint8),
        depth=np.array([1.0, np.nan, 2.5, 0.7, np.nan], np.float32),
    )
    cloud = msgs.keypoints_to_cloud(kps)
    assert cloud.point_step == 60
    back = msgs.cloud_to_keypoints(cloud, (100, 100))
    np.testing.assert_array_equal(back.depth, kps.depth)
    kps.depth = None
    assert msgs.cloud_to_keypoints(msgs.keypoints_to_cloud(kps)).depth is None  # the old layout
    kps.depth = np.array([1.0, -1.0, 2, 3, 4], np.float32)
    with pytest.raises(LLNError):
        msgs.cloud_to_keypoints(msgs.keypoints_to_cloud(kps))
