"""The metric inputs and outputs of issue 27 as ROS messages: sensor_msgs/CameraInfo, REP 118 depth
images (sensor_msgs/Image 16UC1 mm / 32FC1 m), nav_msgs/Odometry and geometry_msgs/PoseWithCovarianceStamped.

    cam = camera_info_to_model(msg)                   # io.camera.CameraModel; CameraError when unusable
    depth_m = depth_image_to_metres(msg, (w, h))      # (H, W) float32 metres, NaN = none; CameraError
    odom = odometry_to_pose(msg)                      # core.odometry.OdomPose; PoseError (NaN, |q| != 1)
    msg = pose_to_message(T, covariance, stamp_ns, frame_id)   # PoseWithCovarianceStamped
    camera_model_to_info / depth_to_image / pose_to_odometry    # the other way (bags, tests)

Validation itself is ROS-free (io.camera.check_intrinsics / depth_metres, core.registration.pose_from_parts):
these functions only move fields between messages and arrays.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image

from ...core.geometry import quaternion
from ...core.odometry import OdomPose
from ...core.registration import pose_from_parts
from ...errors import CameraError, MessageError
from ...io.camera import DEPTH_ENCODINGS, CameraModel, depth_metres
from .headers import header_stamp_ns, make_header

__all__ = [
    'camera_info_to_model',
    'camera_model_to_info',
    'depth_image_to_metres',
    'depth_to_image',
    'odometry_to_pose',
    'pose_to_odometry',
    'pose_to_message',
]


def camera_info_to_model(msg: CameraInfo) -> CameraModel:
    """io.camera.CameraModel from a sensor_msgs/CameraInfo (frame_id from its header). An
    uncalibrated camera's all-zero K, NaN, a principal point outside width x height and distortion
    coefficients its model does not define raise CameraError."""
    if not isinstance(msg, CameraInfo):
        raise MessageError(f'camera info: expected a sensor_msgs/CameraInfo, got {type(msg).__name__}')
    return CameraModel.from_camera_info(
        {
            'width': int(msg.width),
            'height': int(msg.height),
            'k': list(msg.k),
            'd': list(msg.d),
            'distortion_model': str(msg.distortion_model),
        },
        frame_id=msg.header.frame_id,
    )


def camera_model_to_info(cam: CameraModel, stamp_ns: int = 0) -> CameraInfo:
    """sensor_msgs/CameraInfo of a camera model (P = [K | 0], R = I: a monocular, rectified-as-is camera)."""
    msg = CameraInfo(header=make_header(stamp_ns, cam.frame_id))
    msg.width, msg.height = int(cam.width), int(cam.height)
    msg.distortion_model = cam.distortion_model
    msg.d = [float(v) for v in cam.D]
    msg.k = [float(v) for v in cam.K.ravel()]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [float(v) for v in np.c_[cam.K, np.zeros(3)].ravel()]
    return msg


def depth_image_to_metres(msg: Image, size=None, max_pixels: int | None = None) -> np.ndarray:
    """(H, W) float32 metres (NaN = no reading) from a REP 118 depth image registered to the colour
    camera: 16UC1 (or mono16) millimetres, 32FC1 metres. size (width, height): the colour image's,
    which it must match. CameraError for another encoding or size, MessageError for a short buffer."""
    if not isinstance(msg, Image):
        raise MessageError(f'depth image: expected a sensor_msgs/Image, got {type(msg).__name__}')
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise CameraError(f'depth encoding {enc!r} is not a REP 118 depth image (use 16UC1 in mm or 32FC1 in m)')
    dtype = np.dtype(DEPTH_ENCODINGS[enc][0]).newbyteorder('>' if msg.is_bigendian else '<')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if max_pixels is not None and w * h > max_pixels:
        raise MessageError(f'depth image: {w}x{h} is more than max_image_pixels {max_pixels}')
    if h == 0 or w == 0 or step < w * dtype.itemsize or len(msg.data) < step * h:
        raise MessageError(f'depth image: {w}x{h} {enc} with step {step} does not fit its {len(msg.data)} bytes')
    raw = np.frombuffer(bytes(msg.data[: step * h]), np.uint8).reshape(h, step)[:, : w * dtype.itemsize]
    depth = np.ascontiguousarray(raw).view(dtype).reshape(h, w).astype(dtype.newbyteorder('='))
    return depth_metres(depth, enc, size)


def depth_to_image(depth: np.ndarray, encoding: str = '16UC1', stamp_ns: int = 0, frame_id: str = '') -> Image:
    """sensor_msgs/Image from a (H, W) uint16 (16UC1, mm) or float32 (32FC1, m) depth array."""
    dtype = {'16UC1': np.dtype('<u2'), '32FC1': np.dtype('<f4')}.get(encoding)
    if dtype is None:
        raise MessageError(f'depth_to_image: encoding must be 16UC1 or 32FC1, got {encoding!r}')
    depth = np.ascontiguousarray(depth, dtype)
    if depth.ndim != 2:
        raise MessageError(f'depth_to_image: need (H, W), got shape {depth.shape}')
    msg = Image(header=make_header(stamp_ns, frame_id), encoding=encoding, is_bigendian=0)
    msg.height, msg.width = depth.shape
    msg.step = depth.shape[1] * dtype.itemsize
    msg.data = depth.tobytes()
    return msg


def odometry_to_pose(msg: Odometry) -> OdomPose:
    """core.odometry.OdomPose (stamp, T(frame <- child) (4, 4), frame_id, child_frame_id) from a
    nav_msgs/Odometry. PoseError for NaN or a non-unit quaternion, MessageError for an empty frame_id."""
    if not isinstance(msg, Odometry):
        raise MessageError(f'odometry: expected a nav_msgs/Odometry, got {type(msg).__name__}')
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    T = pose_from_parts((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
    if not msg.header.frame_id:
        raise MessageError('odometry: header.frame_id is empty (the frame the poses are in must be named)')
    return OdomPose(header_stamp_ns(msg.header, 'odometry'), T, msg.header.frame_id, msg.child_frame_id)


def _fill_pose(pose, T: np.ndarray) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    q = quaternion(T[:3, :3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)


def pose_to_odometry(T: np.ndarray, stamp_ns: int, frame_id: str, child_frame_id: str = '') -> Odometry:
    """nav_msgs/Odometry with pose T(frame <- child) (4, 4) (zero covariance and twist)."""
    msg = Odometry(header=make_header(stamp_ns, frame_id), child_frame_id=child_frame_id)
    _fill_pose(msg.pose.pose, np.asarray(T, np.float64))
    return msg


def pose_to_message(T: np.ndarray, covariance: np.ndarray, stamp_ns: int, frame_id: str) -> PoseWithCovarianceStamped:
    """geometry_msgs/PoseWithCovarianceStamped: pose T(frame <- camera) (4, 4), covariance (6, 6)
    of [x y z roll pitch yaw] (row-major, as core.geometry computes it)."""
    msg = PoseWithCovarianceStamped(header=make_header(stamp_ns, frame_id))
    _fill_pose(msg.pose.pose, np.asarray(T, np.float64))
    msg.pose.covariance = [float(v) for v in np.asarray(covariance, np.float64).reshape(36)]
    return msg
