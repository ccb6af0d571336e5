"""An RGB-D sequence with ground-truth poses in the TUM RGB-D layout (Sturm et al. 2012).

    seq = read_tum('../shared/data/tum_fr1rpy', step=3)
    seq.frames[i].stamp, .rgb, .depth (Path or None), .pose (7,) tx ty tz qx qy qz qw
    seq.camera                       # io.camera.CameraModel from DIR/camera_info.yaml
    seq.depth_m(i)                   # (H, W) float32 metres, NaN = no reading
    seq.T_world_cam(i)               # (4, 4) float64: x_world = T @ x_cam (optical frame)

Layout: DIR/rgb.txt and DIR/depth.txt (`timestamp file`), DIR/groundtruth.txt (`timestamp tx ty tz
qx qy qz qw`, the colour camera's optical centre in the world frame, metres, ~100 Hz),
DIR/camera_info.yaml (sensor_msgs/CameraInfo; `depth_scale`: depth PNG units per metre, TUM's
5000). Each colour frame takes the nearest depth frame within max_depth_dt (TUM's associate.py
uses 20 ms; none nearer: depth None, counted) and the nearest pose within max_pose_dt (none:
the frame is dropped, counted). Everything listed is checked to exist before it is returned.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import CameraError, DatasetError
from .camera import CameraModel
from .datasets import POSE_MAX_DT, _read_rows

default_conf = {
    'max_depth_dt': 0.02,  # s: TUM associate.py's default pairing tolerance of colour and depth
    'max_pose_dt': POSE_MAX_DT,  # s: as the poses: reader
    'step': 1,  # keep every step-th colour frame (30 Hz repeats itself)
    'depth_scale': 5000.0,  # PNG units per metre when camera_info.yaml has no depth_scale
}


@dataclass
class RGBDFrame:
    stamp: float
    rgb: Path
    depth: Path | None
    pose: np.ndarray  # (7,) tx ty tz qx qy qz qw, unit quaternion


@dataclass
class RGBDSequence:
    name: str
    root: Path
    frames: list
    camera: CameraModel
    depth_scale: float
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def depth_m(self, i: int) -> np.ndarray | None:
        """Frame i's depth in metres (H, W) float32, NaN = no reading; None when it has no depth."""
        path = self.frames[i].depth
        return None if path is None else load_depth_png(path, self.depth_scale, (self.camera.width, self.camera.height))

    def T_world_cam(self, i: int) -> np.ndarray:
        return pose_matrix(self.frames[i].pose)


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    """(7,) tx ty tz qx qy qz qw -> (4, 4) homogeneous transform (x_world = T @ x_cam)."""
    T = np.eye(4)
    x, y, z, w = np.asarray(pose[3:7], np.float64) / np.linalg.norm(pose[3:7])
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = pose[:3]
    return T


def load_depth_png(path, scale: float, size=None) -> np.ndarray:
    """A TUM depth PNG (uint16, `scale` units per metre, 0 = none) as (H, W) float32 metres, NaN = none.
    size (width, height): the colour camera's, which the registered depth must match (CameraError)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f'cannot decode depth image {path}')
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise CameraError(f'depth image {path} must be one-channel uint16, got {raw.dtype} with shape {raw.shape}')
    if size is not None and (raw.shape[1], raw.shape[0]) != tuple(int(s) for s in size):
        raise CameraError(f'depth image {path} is {raw.shape[1]}x{raw.shape[0]}, the camera {size[0]}x{size[1]}')
    m = raw.astype(np.float32) / np.float32(scale)
    m[raw == 0] = np.nan
    return m


def _nearest(times: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index into sorted `times` nearest to each of t, and the time difference (s)."""
    right = np.clip(np.searchsorted(times, t), 0, len(times) - 1)
    left = np.maximum(right - 1, 0)
    j = np.where(np.abs(times[left] - t) <= np.abs(times[right] - t), left, right)
    return j, np.abs(times[j] - t)


def _stamped(root: Path, name: str, what: str) -> tuple[np.ndarray, list]:
    try:
        rows = sorted((float(t), root / f) for t, f in _read_rows(root / name, 2, what))
    except ValueError as e:
        raise DatasetError(f'{root / name}: non-numeric timestamp: {e}') from e
    return np.array([r[0] for r in rows]), [r[1] for r in rows]


def read_tum(root, conf: dict | None = None, name: str | None = None) -> RGBDSequence:
    """The TUM RGB-D sequence at root (module doc); conf overrides default_conf."""
    conf = {**default_conf, **(conf or {})}
    root = Path(root)
    step = conf['step']
    if not (float(step).is_integer() and step >= 1 and conf['max_depth_dt'] >= 0 and conf['max_pose_dt'] >= 0):
        raise DatasetError(f'read_tum: need a whole step >= 1 and tolerances >= 0, got {conf}')
    info_path = root / 'camera_info.yaml'
    if not info_path.is_file():
        raise DatasetError(f'{root}: no camera_info.yaml (the colour camera intrinsics as a sensor_msgs/CameraInfo)')
    camera = CameraModel.from_camera_info(info_path)
    import yaml

    scale = float(yaml.safe_load(info_path.read_text()).get('depth_scale', conf['depth_scale']))
    if not scale > 0:
        raise DatasetError(f'{info_path}: depth_scale must be positive, got {scale}')
    t_rgb, rgb = _stamped(root, 'rgb.txt', 'timestamp file')
    has_depth_list = (root / 'depth.txt').is_file()
    t_depth, depth = _stamped(root, 'depth.txt', 'timestamp file') if has_depth_list else (np.zeros(0), [])
    try:
        gt = np.array(
            [[float(v) for v in r] for r in _read_rows(root / 'groundtruth.txt', 8, 'timestamp tx ty tz qx qy qz qw')]
        )
    except ValueError as e:
        raise DatasetError(f'{root}: non-numeric pose: {e}') from e
    gt = gt[np.argsort(gt[:, 0], kind='stable')]
    norms = np.linalg.norm(gt[:, 4:8], axis=1)
    if not np.isfinite(gt).all() or np.any(np.abs(norms - 1) > 1e-2):
        raise DatasetError(f'{root / "groundtruth.txt"}: poses with NaN or non-unit quaternions')
    j_pose, dt_pose = _nearest(gt[:, 0], t_rgb)
    if len(t_depth):
        j_depth, dt_depth = _nearest(t_depth, t_rgb)
    else:
        j_depth, dt_depth = np.zeros(len(t_rgb), int), np.full(len(t_rgb), np.inf)
    has_pose = dt_pose <= conf['max_pose_dt']
    if not has_pose.any():
        raise DatasetError(f'{root}: no colour frame has a pose within {conf["max_pose_dt"]} s')
    frames = []
    kept = np.flatnonzero(has_pose)[:: int(step)]
    for i in kept:
        d = depth[j_depth[i]] if dt_depth[i] <= conf['max_depth_dt'] else None
        pose = gt[j_pose[i], 1:8].copy()
        pose[3:] /= np.linalg.norm(pose[3:])
        frames.append(RGBDFrame(float(t_rgb[i]), rgb[i], d, pose))
    missing = [p for f in frames for p in (f.rgb, f.depth) if p is not None and not p.is_file()]
    if missing:
        raise DatasetError(f'{len(missing)} files listed in {root} are missing, e.g. {missing[0]}')
    return RGBDSequence(
        name or root.name,
        root,
        frames,
        camera,
        scale,
        {
            'frames_listed': len(t_rgb),
            'frames_without_pose': int((~has_pose).sum()),
            'frames_without_depth': sum(f.depth is None for f in frames),
            'step': int(step),
            'max_depth_dt': float(conf['max_depth_dt']),
            'max_pose_dt': float(conf['max_pose_dt']),
        },
    )
