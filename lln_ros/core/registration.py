"""The matcher's metric side, without rclpy (issue 27): odometry looked up by stamp, the geometry a
keyframe stores, keyframe gating, recent exclusion in seconds and metres, and the relative pose of
the best candidate with its acceptance.

    reg = Registration(conf, counters)
    reg.set_camera(CameraModel)                    # the query camera (camera_info topic or YAML)
    reg.add_odometry(OdomPose)                     # checked by pose_from_parts when decoded
    odom = reg.odometry_at(stamp_ns)               # OdomPose at the stamp (core.odometry), or None
    geom = reg.keyframe_geometry(image_size, odom) # what store.set_geometry keeps with a keyframe
    n = reg.recent(stamp_ns, odom)                 # newest keyframes closer than exclude_recent_s / _m
    if reg.gate(stamp_ns, odom, best_score, lset): store it; reg.stored(stamp_ns, odom, lset)
    pose = reg.estimate(query_kps, kf_kps, matches, kf_geom, score, odom, image_size)   # PoseAnswer
    reg.reset()                                    # ~/relocalize: forget the consistency state

Frames: an odometry pose is T(frame_id <- child) of the odometry's child frame (usually base_link);
base_to_camera (x y z qx qy qz qw, T(child <- camera optical frame)) stands in for the TF lookup
that tf2 would do (tf2 is not on PyPI). The identity default says the odometry already describes
the camera's optical frame, as TUM RGB-D ground truth does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import LLNError
from . import geometry
from .gating import KeyframeGate
from .gating import default_conf as GATE
from .geometry import Agreement, accept, estimate_pose, in_parent, invert, odometry_pose
from .odometry import OdometryBuffer, OdomPose

IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)

default_conf = {
    'geometry': True,  # estimate T(keyframe <- query) for the best candidate (needs verify keypoints + a camera)
    'odom_max_dt': 0.05,  # s: an odometry pose further in time from a frame is not its pose
    'odom_wait_s': 0.2,  # s: flowing odometry not yet at a frame's stamp is waited for this long (core.odometry)
    'odom_buffer': 2000,  # odometry poses kept (100 Hz odometry: 20 s)
    'base_to_camera': IDENTITY_POSE,  # T(odometry child frame <- camera optical frame), x y z qx qy qz qw
    # mapping mode: which queries become keyframes (core.gating.KeyframeGate; its defaults)
    'keyframe_min_distance': GATE['min_distance_m'],  # with odometry: metres moved since the last keyframe
    'keyframe_min_angle': GATE['min_angle_deg'],  # ... or degrees turned
    'keyframe_max_interval_s': GATE['max_interval_s'],  # and at least every this many seconds; 0 = off
    'keyframe_novelty_max_score': GATE['novelty_max_score'],  # without odometry: only when S is below; 0 = off
    'exclude_recent_s': 0.0,  # mapping mode: keyframes this recent (stamp) are never answers; 0 = off
    'exclude_recent_m': 0.0,  # ... nor those within this path length (odometry); 0 = off
    # the per-frame acceptance (core.geometry.accept) and consecutive-frame agreement
    'pose_min_inliers': geometry.default_conf['min_inliers'],
    'pose_max_reproj_px': geometry.default_conf['max_reproj_px'],
    'pose_ransac_px': geometry.default_conf['ransac_px'],
    'pose_agree_frames': geometry.default_conf['agree_frames'],
    'pose_agree_m': geometry.default_conf['agree_m'],
    'pose_agree_deg': geometry.default_conf['agree_deg'],
}
QUATERNION_TOLERANCE = 1e-3  # |q| must be within this of 1 (drivers normalise; 1e-3 is float32 noise x 100)


def best_raw_score(found) -> float | None:
    """The best raw S (the paper's: sum of weight x cosine over the reported pairs, which are raw S's
    whatever S ranked them; similarity, center='fuse') of a query's candidates (MapCandidate), the
    first-stage score of one without pairs; None for no candidate. The novelty gate's input."""
    raw = [float(np.dot(m.pairs['weight'], m.pairs['similarity'])) if 'weight' in m.pairs else m.score for m in found]
    return max(raw, default=None)


@dataclass
class PoseAnswer:
    """The relative pose of an answer's best candidate. est: core.geometry.PoseEstimate; accepted:
    passed accept() and the agreement; reason: why not; T_map (4, 4) / cov_map (6, 6) / frame_id:
    the query camera in the stored poses' frame (metric poses of keyframes with an odometry pose)."""

    keyframe_id: int
    est: object
    accepted: bool
    reason: str = ''
    T_map: np.ndarray | None = None
    cov_map: np.ndarray | None = None
    frame_id: str = ''

    def fields(self) -> dict:
        """The FLOAT32 candidate-table fields of this pose (docs/interfaces.md): NaN where unknown."""
        nan = float('nan')
        e = self.est
        out = {
            'pose_accepted': float(self.accepted),
            'pose_metric': float(e.metric) if e.ok else nan,
            'pose_inliers': float(e.inliers),
            'pose_reproj_px': float(e.reproj_px) if e.ok else nan,
        }
        T = e.T if e.ok else None
        q = geometry.quaternion(T[:3, :3]) if T is not None else [nan] * 4
        for name, v in zip(POSE_XYZQ, (*(T[:3, 3] if T is not None else [nan] * 3), *q)):
            out[name] = float(v)
        cov = e.covariance.ravel() if e.ok and e.covariance is not None else [nan] * 36
        out.update({f'cov_{i}': float(v) for i, v in enumerate(cov)})
        return out


POSE_XYZQ = ('tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')
POSE_FIELDS = ('pose_accepted', 'pose_metric', 'pose_inliers', 'pose_reproj_px', *POSE_XYZQ) + tuple(
    f'cov_{i}' for i in range(36)
)


def nan_fields() -> dict:
    return dict.fromkeys(POSE_FIELDS, float('nan'))


def pose_from_parts(position, orientation, tolerance: float = QUATERNION_TOLERANCE) -> np.ndarray:
    """T (4, 4) from a position (3,) and a quaternion (4,) x y z w: core.geometry.odometry_pose, which
    raises PoseError (an LLNError) for NaN or infinity, or a quaternion whose norm is not 1 within
    `tolerance` (normalising a broken one would hide a broken source)."""
    return odometry_pose(position, orientation, tolerance)


def pose_vector(T: np.ndarray) -> np.ndarray:
    """(4, 4) -> (7,) x y z qx qy qz qw (what a map stores)."""
    return np.r_[T[:3, 3], geometry.quaternion(T[:3, :3])]


class Registration:
    """Per-query metric state of a matcher (module doc). counters: core.counters.Counters."""

    def __init__(self, conf: dict | None = None, counters=None):
        self.conf = c = {**default_conf, **(conf or {})}
        check_conf(c)
        self.counters = counters
        self.camera, self.image_size = None, None  # image_size (w, h): of the latest landmark set
        self.odometry = OdometryBuffer(c['odom_buffer'])
        self.base_to_camera = pose_from_parts(c['base_to_camera'][:3], c['base_to_camera'][3:])
        self.agreement = Agreement(self._geometry_conf())
        self.history: list[tuple[int, np.ndarray | None]] = []  # this session's stored keyframes: stamp, position
        self.path_m = 0.0  # odometry path length of the stored keyframes, for exclude_recent_m
        self.last_stored: OdomPose | None = None
        # the last keyframe stored (LandmarkSet): novelty is judged against it too, because it is
        # always among the recent keyframes a query's answers exclude (a still camera's twin)
        self.last_landmarks = None
        self.gate_ = self._make_gate()

    def _make_gate(self) -> KeyframeGate:
        c = self.conf
        return KeyframeGate(
            {
                'min_distance_m': c['keyframe_min_distance'],
                'min_angle_deg': c['keyframe_min_angle'],
                'max_interval_s': c['keyframe_max_interval_s'],
                'novelty_max_score': c['keyframe_novelty_max_score'],
            }
        )

    def _geometry_conf(self) -> dict:
        c = self.conf
        return {
            'min_inliers': c['pose_min_inliers'],
            'max_reproj_px': c['pose_max_reproj_px'],
            'ransac_px': c['pose_ransac_px'],
            'agree_frames': c['pose_agree_frames'],
            'agree_m': c['pose_agree_m'],
            'agree_deg': c['pose_agree_deg'],
        }

    def update(self, changes: dict) -> None:
        """Run-time parameter changes (already checked by check_conf)."""
        self.conf.update(changes)
        if any(k.startswith('pose_agree') for k in changes):
            self.agreement = Agreement(self._geometry_conf())
        if any(k.startswith('keyframe_') for k in changes):
            self.gate_ = self._make_gate()

    def _count(self, key: str) -> None:
        if self.counters is not None:
            self.counters.count(key)

    def set_camera(self, camera) -> None:
        """Use this camera model from now on; CameraError (and the previous model kept) when it is
        for another image size than the landmark sets seen so far."""
        if self.image_size is not None and (camera.width, camera.height) != self.image_size:
            from ..errors import CameraError

            raise CameraError(
                f'camera info is for {camera.width}x{camera.height} images, the images are '
                f'{self.image_size[0]}x{self.image_size[1]}'
            )
        self.camera = camera

    def add_odometry(self, odom: OdomPose) -> None:
        self.odometry.add(odom)

    def odometry_at(self, stamp_ns: int) -> OdomPose | None:
        """The odometry pose of a frame; None without odometry, or (counted as odometry_missing)
        when odometry comes but none is within odom_max_dt of this stamp."""
        if not self.odometry.poses:
            return None
        found = self.odometry.at(stamp_ns, self.conf['odom_max_dt'], self.conf['odom_wait_s'])
        if found is None and self.counters is not None:
            st = self.odometry.stamps
            self.counters.problem(
                'odometry_missing',
                f'no odometry within {self.conf["odom_max_dt"]} s of the frame at {stamp_ns * 1e-9:.3f} s '
                f'(odometry buffered from {st[0] * 1e-9:.3f} to {st[-1] * 1e-9:.3f} s, {len(st)} poses)',
            )
        return found

    def camera_for(self, image_size) -> object | None:
        """The camera model when it describes images of image_size (w, h), else None (counted as
        camera_size_mismatch: a camera_info of another camera or resolution must not be used)."""
        w, h = (int(round(float(v))) for v in image_size)
        self.image_size = (w, h)
        if self.camera is None:
            return None
        if (w, h) != (self.camera.width, self.camera.height):
            self._count('camera_size_mismatch')
            return None
        return self.camera

    def keyframe_geometry(self, image_size, odom: OdomPose | None) -> dict:
        """What the map keeps with a keyframe besides its keypoints: camera (CameraModel.to_dict or
        None), pose (7,) T(frame <- camera) or None, frame_id."""
        cam = self.camera_for(image_size)
        out = {'camera': cam.to_dict() if cam is not None else None, 'pose': None, 'frame_id': ''}
        if odom is not None:
            out['pose'] = pose_vector(odom.T @ self.base_to_camera)
            out['frame_id'] = odom.frame_id
        return out

    # ------------------------------------------------------------------ mapping mode

    def gate(
        self, stamp_ns: int, odom: OdomPose | None, best_score: float | None = None, lset=None, scale: float = 1.0
    ) -> bool:
        """Store this query as a keyframe? core.gating.KeyframeGate on the camera's odometry pose
        (moved keyframe_min_distance or turned keyframe_min_angle since the last keyframe), or
        without odometry on novelty: the best raw S below keyframe_novelty_max_score (0 = every
        frame), where the best raw S is that of the answers (best_score: best_raw_score, None: no
        answer) or, when higher, the query landmark set lset's raw S against the last stored
        keyframe. Raw S (the paper's) whatever S ranks the answers (the matcher's `similarity`): the
        threshold is in its units. Without the latter a camera
        standing still stores a keyframe per frame until its twins pass exclude_recent, then closes
        loops with itself. Odometry in a new frame_id starts the gate afresh (poses of two frames do
        not compare)."""
        if odom is not None and self.last_stored is not None and odom.frame_id != self.last_stored.frame_id:
            self.gate_ = self._make_gate()
        T = odom.T @ self.base_to_camera if odom is not None else None
        if T is None and lset is not None and self.last_landmarks is not None and self.gate_.judges_novelty:
            from .similarity import match_pair

            last = float(match_pair(lset, self.last_landmarks, scale, center=False).scores[0])
            best_score = last if best_score is None else max(best_score, last)
        return self.gate_.decide(stamp_ns * 1e-9, T, best_score)[0]

    def stored(self, stamp_ns: int, odom: OdomPose | None, lset=None) -> None:
        self.last_landmarks = lset
        if odom is not None and self.last_stored is not None and self.last_stored.frame_id == odom.frame_id:
            self.path_m += float(np.linalg.norm(odom.T[:3, 3] - self.last_stored.T[:3, 3]))
        if odom is not None:
            self.last_stored = odom
        self.history.append((int(stamp_ns), self.path_m if odom is not None else None))
        del self.history[: -int(self.conf['odom_buffer'])]

    def recent(self, stamp_ns: int, odom: OdomPose | None) -> int:
        """How many of the newest keyframes (this session's) are within exclude_recent_s of the
        query's stamp, or within exclude_recent_m of path length (odometry) of the query."""
        c = self.conf
        s, m = float(c['exclude_recent_s']), float(c['exclude_recent_m'])
        if (s <= 0 and m <= 0) or not self.history:
            return 0
        here = self.path_m
        if odom is not None and self.last_stored is not None and self.last_stored.frame_id == odom.frame_id:
            here += float(np.linalg.norm(odom.T[:3, 3] - self.last_stored.T[:3, 3]))
        n = 0
        for st, path in reversed(self.history):
            near_t = s > 0 and abs(stamp_ns - st) * 1e-9 < s
            near_m = m > 0 and path is not None and odom is not None and here - path < m
            if not (near_t or near_m):
                break
            n += 1
        return n

    def forget(self) -> None:
        """~/clear: the stored keyframes are gone."""
        self.history, self.path_m, self.last_stored, self.last_landmarks = [], 0.0, None, None
        self.gate_ = self._make_gate()

    # ------------------------------------------------------------------ the answer's pose

    def reset(self) -> None:
        """Relocalization from scratch (kidnapped robot): no earlier estimate vouches for the next."""
        self.agreement.reset()

    def pose_of(self, kps, kf_kps, result, kf_geom, best, odom, image_size):
        """PoseAnswer of the answer's best candidate (a mapstore.MapCandidate) from its verification
        (reloc.RelocResult: the region-constrained matches), or None when the query or the keyframe
        has no keypoints (counted as pose_no_keypoints; it breaks the run of agreeing estimates)."""
        if kps is None or result is None or kf_kps is None:
            self.agreement.update(None)
            self._count('pose_no_keypoints')
            return None
        # accept()'s min_score is in raw S, whatever S ranked the candidates
        raw = best_raw_score([best])
        return self.estimate(kps, kf_kps, result.matches, kf_geom, raw, odom, image_size, best.keyframe_id)

    def estimate(self, query_kps, kf_kps, matches, kf_geom: dict | None, score: float, odom, image_size, keyframe_id):
        """PoseAnswer for the best candidate (module doc), or None when it cannot be estimated (no
        camera for the query or keyframe: counted as pose_no_camera)."""
        from ..io.camera import CameraModel

        qcam = self.camera_for(image_size)
        kcam = None
        if kf_geom and kf_geom.get('camera'):
            try:
                kcam = CameraModel.from_camera_info(kf_geom['camera'])
            except Exception:  # noqa: BLE001  a stored camera that no longer validates: no pose, counted
                kcam = None
        if qcam is None or kcam is None:
            self._count('pose_no_camera')
            return None
        z = kf_geom.get('depth') if kf_geom else None
        if z is not None and len(z) != len(kf_kps):
            z = None
        gconf = self._geometry_conf()
        est = estimate_pose(query_kps, kf_kps, matches, qcam, kcam, z, gconf)
        self._count('poses_estimated')
        ok, why = accept(est, score, gconf)
        T_map = cov_map = None
        frame = ''
        kf_pose = kf_geom.get('pose') if kf_geom else None
        if ok and est.metric and kf_pose is not None:
            T_map_kf = pose_from_parts(kf_pose[:3], kf_pose[3:], 1e-2)
            T_map, cov_map = T_map_kf @ est.T, in_parent(T_map_kf, est.covariance)
            frame = kf_geom.get('frame_id', '')
        # consistency: the estimate in a frame consecutive answers share (the map's when poses are stored)
        T_query = T_map if T_map is not None else (est.T if ok else None)
        T_odom = odom.T @ self.base_to_camera if odom is not None else None
        agrees = self.agreement.update(T_query, T_odom, bool(est.metric))
        if ok and not agrees:
            ok, why = False, f'disagrees with the previous {self.conf["pose_agree_frames"]} estimates'
        self._count('poses_accepted' if ok else 'poses_refused')
        if not ok:
            T_map = cov_map = None
        return PoseAnswer(int(keyframe_id), est, ok, why, T_map, cov_map, frame)


def check_conf(c: dict) -> None:
    """ValueError naming a bad registration setting."""
    for key in (
        'odom_max_dt',
        'odom_wait_s',
        'keyframe_min_distance',
        'keyframe_min_angle',
        'keyframe_max_interval_s',
        'keyframe_novelty_max_score',
        'exclude_recent_s',
        'exclude_recent_m',
    ):
        if not (isinstance(c[key], (int, float)) and math.isfinite(c[key]) and c[key] >= 0):
            raise ValueError(f'{key} must be a number >= 0, got {c[key]!r}')
    if int(c['odom_buffer']) < 1:
        raise ValueError(f'odom_buffer must be >= 1, got {c["odom_buffer"]}')
    b = c['base_to_camera']
    if len(b) != 7:
        raise ValueError(f'base_to_camera needs 7 numbers (x y z qx qy qz qw), got {list(b)}')
    try:
        pose_from_parts(b[:3], b[3:])
    except LLNError as e:
        raise ValueError(f'base_to_camera: {e}') from None


__all__ = [
    'OdomPose',
    'OdometryBuffer',
    'POSE_FIELDS',
    'PoseAnswer',
    'Registration',
    'default_conf',
    'invert',
    'nan_fields',
    'pose_from_parts',
    'pose_vector',
]
