"""What a keyframe keeps for registration (issue 27), shared by both backends: the camera model, the
odometry pose of the camera and its frame, and its keypoints' depths.

    store.set_geometry(kid, {'camera': cam.to_dict(), 'pose': (7,), 'frame_id': 'odom'})
    store.set_geometry(kid, {'depth': (N,) float32})      # with the keypoints, aligned with them
    store.geometry(kid) -> {'camera': dict | None, 'pose': (7,) float64 | None, 'frame_id': str,
                            'depth': (N,) float32 | None}, or None when nothing was stored

pose: x y z qx qy qz qw, T(frame_id <- camera optical frame), a unit quaternion. set_geometry
updates only the fields it is given. Every field is checked here before it is written, so a map
never holds a broken pose (MapError names what is wrong).
"""

from __future__ import annotations

import base64
import json
import math

import numpy as np

from ..errors import MapError

FIELDS = ('camera', 'pose', 'frame_id', 'depth')


def check(fields: dict, where: str) -> dict:
    """The fields of `fields` (a subset of FIELDS) checked and normalised; MapError otherwise."""
    unknown = set(fields) - set(FIELDS)
    if unknown:
        raise MapError(f'{where}: unknown geometry fields {sorted(unknown)} (known: {", ".join(FIELDS)})')
    out = {}
    if 'camera' in fields:
        cam = fields['camera']
        if cam is not None:
            from ..io.camera import CameraModel

            try:
                cam = CameraModel.from_camera_info(dict(cam), str(cam.get('frame_id', ''))).to_dict()
            except (ValueError, TypeError) as e:
                raise MapError(f'{where}: camera model refused: {e}') from None
        out['camera'] = cam
    if 'pose' in fields:
        pose = fields['pose']
        if pose is not None:
            pose = np.asarray(pose, np.float64).ravel()
            if pose.shape != (7,) or not np.isfinite(pose).all() or abs(np.linalg.norm(pose[3:]) - 1) > 1e-3:
                raise MapError(f'{where}: pose must be 7 finite numbers with a unit quaternion, got {pose.tolist()}')
        out['pose'] = pose
    if 'frame_id' in fields:
        out['frame_id'] = str(fields['frame_id'] or '')
    if 'depth' in fields:
        depth = fields['depth']
        if depth is not None:
            depth = np.asarray(depth, np.float32).ravel()
            if np.any(np.isinf(depth)) or np.any(depth <= 0):
                raise MapError(f'{where}: keypoint depths must be positive metres or NaN')
        out['depth'] = depth
    return out


def to_json(record: dict) -> str:
    """A full record (every FIELD) as JSON (depth: base64 of float32 little-endian)."""
    pose, depth = record.get('pose'), record.get('depth')
    return json.dumps(
        {
            'camera': record.get('camera'),
            'pose': None if pose is None else [float(v) for v in pose],
            'frame_id': record.get('frame_id', ''),
            'depth': None if depth is None else base64.b64encode(np.asarray(depth, '<f4').tobytes()).decode(),
        }
    )


def from_json(text: str, where: str) -> dict:
    try:
        d = json.loads(text)
        depth = d.get('depth')
        return {
            'camera': d.get('camera'),
            'pose': None if d.get('pose') is None else np.asarray(d['pose'], np.float64),
            'frame_id': str(d.get('frame_id', '')),
            'depth': None if depth is None else np.frombuffer(base64.b64decode(depth), '<f4').copy(),
        }
    except (ValueError, TypeError, AttributeError) as e:
        raise MapError(f'{where} is corrupt: geometry record: {e}') from None


def empty() -> dict:
    return {'camera': None, 'pose': None, 'frame_id': '', 'depth': None}


def finite_pose(pose) -> bool:
    return pose is not None and all(math.isfinite(v) for v in pose)
