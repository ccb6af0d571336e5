"""The matcher's parameters of the metric side (issue 27), with descriptors; defaults from the
ROS-free lln_ros.core.registration.default_conf (one source)."""

from __future__ import annotations

import math

from ..core.registration import default_conf as REG
from .parameters import Param


def _pose7(value) -> str:
    v = list(value)
    if len(v) != 7 or not all(isinstance(x, float) and math.isfinite(x) for x in v):
        return f'must be 7 finite numbers x y z qx qy qz qw, got {v}'
    if abs(math.sqrt(sum(x * x for x in v[3:])) - 1) > 1e-3:
        return f'needs a unit quaternion, got {v[3:]}'
    return ''


PARAMETERS = {
    'geometry': Param(
        REG['geometry'], "verify mode: estimate each answer's T(keyframe <- query) and its covariance (pose_* fields)"
    ),
    'camera_info_file': Param(
        '', "camera_calibration YAML of the colour camera; '' = subscribe 'camera_info' (sensor_msgs/CameraInfo)"
    ),
    'sensor_reliability': Param(
        'best_effort',
        'camera_info / odom subscription reliability (best_effort matches every publisher; reliable: for bags)',
        choices=('reliable', 'best_effort'),
    ),
    'odom_max_dt': Param(
        REG['odom_max_dt'],
        "seconds: odometry samples this close to a frame's stamp give its pose (interpolated between the two "
        'around it)',
        range=(0.0, 10.0),
    ),
    'odom_wait_s': Param(
        REG['odom_wait_s'],
        "seconds: flowing odometry that has not yet reached a frame's stamp is waited for this long (it lags "
        'the frames under load); 0 = never wait',
        range=(0.0, 2.0),
    ),
    'odom_buffer': Param(REG['odom_buffer'], 'odometry poses kept for the look-up by stamp', range=(1, 1_000_000)),
    'base_to_camera': Param(
        [float(v) for v in REG['base_to_camera']],
        'T(odometry child frame <- camera optical frame), x y z qx qy qz qw (stands in for TF: tf2 is not on '
        'PyPI); the identity = the odometry describes the camera',
        check=_pose7,
    ),
    'keyframe_min_distance': Param(
        REG['keyframe_min_distance'],
        'mapping mode with odometry: metres from the last keyframe before a query is stored (or the angle); 0 = off',
        dynamic=True,
        range=(0.0, 1e6),
    ),
    'keyframe_min_angle': Param(
        REG['keyframe_min_angle'],
        'mapping mode with odometry: degrees turned since the last keyframe before a query is stored; 0 = off',
        dynamic=True,
        range=(0.0, 360.0),
    ),
    'keyframe_max_interval_s': Param(
        REG['keyframe_max_interval_s'],
        'mapping mode: a query is stored at least every this many seconds, whatever the gate says; 0 = off',
        dynamic=True,
        range=(0.0, 1e9),
    ),
    'keyframe_novelty_max_score': Param(
        REG['keyframe_novelty_max_score'],
        'mapping mode without odometry: a query is stored only when its best S (answers and the last keyframe) is '
        'below this; 0 = every query',
        dynamic=True,
        range=(0.0, 1e6),
    ),
    'exclude_recent_s': Param(
        REG['exclude_recent_s'],
        'mapping mode: keyframes stored less than this many seconds before the query are never answers; 0 = off',
        dynamic=True,
        range=(0.0, 1e9),
    ),
    'exclude_recent_m': Param(
        REG['exclude_recent_m'],
        'mapping mode with odometry: nor those less than this path length (metres) back; 0 = off',
        dynamic=True,
        range=(0.0, 1e9),
    ),
    'pose_min_inliers': Param(
        REG['pose_min_inliers'], 'acceptance: pose RANSAC inliers at least', dynamic=True, range=(6, 100_000)
    ),
    'pose_max_reproj_px': Param(
        REG['pose_max_reproj_px'], 'acceptance: median inlier residual (pixels) at most', dynamic=True, range=(0.0, 1e3)
    ),
    'pose_ransac_px': Param(
        REG['pose_ransac_px'], 'pose RANSAC inlier threshold, pixels', dynamic=True, range=(0.1, 100.0)
    ),
    'pose_agree_frames': Param(
        REG['pose_agree_frames'],
        'acceptance: the previous N estimates must agree (after odometry); 0 = off',
        dynamic=True,
        range=(0, 1000),
    ),
    'pose_agree_m': Param(REG['pose_agree_m'], 'agreement: metres', dynamic=True, range=(0.0, 1e3)),
    'pose_agree_deg': Param(REG['pose_agree_deg'], 'agreement: degrees', dynamic=True, range=(0.0, 180.0)),
}
# the Registration settings among them (the rest are the node's: where the inputs come from)
KEYS = tuple(k for k in PARAMETERS if k in REG)


def registration_conf(values: dict) -> dict:
    conf = {k: values[k] for k in KEYS}
    conf['base_to_camera'] = tuple(float(v) for v in conf['base_to_camera'])
    return conf
