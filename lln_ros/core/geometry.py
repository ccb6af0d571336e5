"""Where, not only which: the relative pose of a query camera in a candidate keyframe's camera frame,
from keypoint matches constrained to the matched landmark regions (lln_ros.core.reloc, mLLN).

    est = estimate_pose(query_kps, keyframe_kps, matches, query_cam, keyframe_cam, keyframe_depth_m)
    est.ok, est.reason, est.method            # 'pnp' (metric, keyframe depth) | 'essential' (no depth)
    est.T          (4, 4) T(keyframe <- query): x_keyframe = T @ x_query, camera optical frames
    est.covariance (6, 6) of [x y z roll pitch yaw] (module doc)
    accepted, why = accept(est, score, conf)  # the per-frame acceptance rule
    agree = Agreement(conf); agree.update(T_map_query, T_odom_query)   # consecutive-frame consistency

With depth (the keyframe's depth registered to its colour camera) each matched keyframe keypoint is
back-projected to a 3-D point and the query pose is found by cv2.solvePnPRansac, then
cv2.solvePnPRefineLM on the inliers (twice, re-selecting inliers after the first refinement).
Without depth, cv2.findEssentialMat (USAC_ACCURATE) + cv2.recoverPose give the rotation and the translation
direction: est.T's translation is unit-norm and est.metric is False.

Covariance, in the order of geometry_msgs/PoseWithCovariance ([x y z roll pitch yaw], row-major
6x6): the pose perturbation is t' = t + d_t, R' = exp([d_r]x) R, i.e. a translation and a small
rotation about the axes of the keyframe (parent) frame, which is what a ROS consumer assumes for
small angles. It is s^2 (J^T J)^-1 with J the numerical Jacobian (central differences) of the inlier
residuals (PnP: normalised reprojection errors; essential: Sampson distances) with respect to
that perturbation and s^2 the residual variance (sum r^2 / (n - 6)). The essential matrix cannot
see the scale: J^T J is rank 5, its pseudo-inverse is taken and unknown_scale_variance is added
along the translation direction, so a pose graph does not trust the length of t.

Degenerate input (too few matches, depth missing at the keypoints, RANSAC failing) gives ok=False
with a reason, never an exception: a node calls this for every answered query.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import PoseError
from ..io.rgbd import pose_matrix
from .reloc import _collinear
from .reloc import default_conf as reloc_conf

default_conf = {
    'ransac_px': 3.0,  # inlier threshold, pixels of the query image (PnP reprojection / E Sampson distance)
    'confidence': 0.999,
    'max_iters': 1000,
    'min_matches': 8,  # fewer region-constrained matches: no pose
    'min_points': 8,  # fewer matches with a valid keyframe depth: the essential matrix instead of PnP
    # inliers whose 2nd principal extent is below this fraction of the 1st lie on a line: degenerate
    'min_spread': reloc_conf['min_spread'],
    'min_depth_m': 0.2,  # depth readings outside [min, max] are not used (Kinect: ~0.5-4.5 m)
    'max_depth_m': 8.0,
    'depth_window': 1,  # half-size (pixels) of the window a keypoint's depth is read from
    'depth_max_spread': 0.03,  # (max - min) / median depth in that window above this: a depth edge, unused
    # USAC with local optimisation: on synthetic 0.5 px noise, 0.02 deg / 0.2 deg (rotation / direction)
    # where plain RANSAC's unrefined minimal solution gave 0.8 / 6.6 deg
    'essential_method': 'USAC_ACCURATE',
    'unknown_scale_variance': 1e6,  # m^2 along t for essential-matrix poses (scale unobservable)
    # acceptance (accept()): the rule lln-eval --geometry chose with depth on the first half of
    # tum_fr1rpy (docs/geometry.md); S is the shipped head's landmark similarity
    'min_score': 10.0,  # raw landmark similarity S (the paper's) of the candidate, whatever S ranks
    'min_inliers': 20,
    'min_inlier_ratio': 0.0,  # inliers / region-constrained matches
    'max_reproj_px': 2.0,  # median inlier residual, pixels
    'max_rot_std_deg': 0.0,  # largest rotation standard deviation from the covariance; 0 = off
    'max_trans_std_m': 0.0,  # largest translation standard deviation (PnP only); 0 = off
    # Agreement: the last agree_frames estimates (consecutive queries) must agree, after odometry
    'agree_frames': 0,  # 0 = off
    'agree_m': 0.10,
    'agree_deg': 5.0,
}


@dataclass
class PoseEstimate:
    """One query/keyframe relative pose (module doc). matches: region-constrained matches used;
    inliers: RANSAC inliers after refinement; inlier_mask (matches,) bool; reproj_px: median
    inlier residual in query pixels; points_3d: matches with a usable keyframe depth (PnP)."""

    ok: bool
    reason: str
    method: str = ''
    T: np.ndarray | None = None
    covariance: np.ndarray | None = None
    matches: int = 0
    inliers: int = 0
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    reproj_px: float = math.inf
    points_3d: int = 0
    ms: float = 0.0

    @property
    def metric(self) -> bool:
        return self.method == 'pnp'

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / self.matches if self.matches else 0.0

    def summary(self) -> dict:
        """JSON-friendly fields (what an answer carries)."""
        return {
            'ok': self.ok,
            'reason': self.reason,
            'method': self.method,
            'T': None if self.T is None else self.T.tolist(),
            'covariance': None if self.covariance is None else self.covariance.ravel().tolist(),
            'matches': self.matches,
            'inliers': self.inliers,
            'reproj_px': self.reproj_px,
            'points_3d': self.points_3d,
        }


# ------------------------------------------------------------------------------------ small maths


def rotation_deg(R: np.ndarray) -> float:
    """Angle (degrees) of a rotation matrix (3, 3)."""
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))))


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4, 4)."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.ravel(t)
    return T


def perturb(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    """T with d (6,) = [dx dy dz droll dpitch dyaw] applied as t + d_t, exp([d_r]x) R (module doc)."""
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.asarray(d[3:], np.float64).reshape(3, 1))[0] @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + d[:3]
    return out


def interpolate(T0: np.ndarray, T1: np.ndarray, w: float) -> np.ndarray:
    """The rigid transform (4, 4) a fraction w in [0, 1] of the way from T0 to T1: the translation
    linearly, the rotation along the geodesic (R0 exp(w log(R0^T R1)), i.e. slerp)."""
    r = cv2.Rodrigues(np.ascontiguousarray(T0[:3, :3].T @ T1[:3, :3], np.float64))[0]
    return rigid(T0[:3, :3] @ cv2.Rodrigues(w * r)[0], (1.0 - w) * T0[:3, 3] + w * T1[:3, 3])


def quaternion(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,) x y z w, w >= 0."""
    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    angle = float(np.linalg.norm(rvec))
    axis = rvec / angle if angle > 0 else np.zeros(3)
    q = np.r_[axis * math.sin(angle / 2), math.cos(angle / 2)]
    return q if q[3] >= 0 else -q


def in_parent(T_parent_child: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance (6, 6) of T(child <- x) re-expressed for T(parent <- x) = T_parent_child @ T(child <- x),
    T_parent_child taken as exact: both blocks rotate by R_parent_child (module doc's perturbation)."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = T_parent_child[:3, :3]
    return A @ covariance @ A.T


def pose_with_covariance(T: np.ndarray, covariance: np.ndarray) -> dict:
    """geometry_msgs/PoseWithCovariance fields: position (3,), orientation (4,) x y z w, covariance (36,)."""
    return {
        'position': T[:3, 3].tolist(),
        'orientation': quaternion(T[:3, :3]).tolist(),
        'covariance': np.asarray(covariance, np.float64).ravel().tolist(),
    }


def odometry_pose(position, orientation, tolerance: float = 1e-3) -> np.ndarray:
    """(4, 4) T(odom <- camera) from a nav_msgs/Odometry-like position (3,) and orientation (4,)
    x y z w. PoseError for NaN or infinity, or a quaternion whose norm is off 1 by more than
    tolerance (renormalised within it): a keyframe is never stored with a broken pose."""
    p = np.asarray(position, np.float64).ravel()
    q = np.asarray(orientation, np.float64).ravel()
    if p.shape != (3,) or q.shape != (4,):
        raise PoseError(f'a pose needs 3 position and 4 quaternion values, got {p.size} and {q.size}')
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise PoseError(f'pose holds NaN or infinity: position {p.tolist()}, orientation {q.tolist()}')
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > tolerance:
        raise PoseError(f'orientation quaternion has norm {n:.6g}, not 1 (x y z w = {q.tolist()})')
    return pose_matrix(np.r_[p, q / n])


# ------------------------------------------------------------------------------------------ depth


def keypoint_depth(depth_m: np.ndarray, uv: np.ndarray, conf: dict | None = None) -> np.ndarray:
    """Depth (N,) metres at keypoints uv (N, 2) (original pixels) of a (H, W) float32 metre image
    (NaN = none): the median over a (2w+1)^2 window, NaN where fewer than half the window has a
    reading in range or the readings spread more than depth_max_spread (a depth edge: the corner
    may belong to either surface)."""
    c = {**default_conf, **(conf or {})}
    h, w = depth_m.shape
    if not len(uv):
        return np.zeros(0)
    r = int(c['depth_window'])
    u = np.rint(np.asarray(uv, np.float64)[:, 0]).astype(np.int64)
    v = np.rint(np.asarray(uv, np.float64)[:, 1]).astype(np.int64)
    offs = np.arange(-r, r + 1)
    uu = np.clip(u[:, None, None] + offs[None, None, :], 0, w - 1)
    vv = np.clip(v[:, None, None] + offs[None, :, None], 0, h - 1)
    win = depth_m[vv, uu].reshape(len(u), -1).astype(np.float64)  # (N, (2r+1)^2)
    win[(win < c['min_depth_m']) | (win > c['max_depth_m'])] = np.nan
    good = np.isfinite(win)
    out = np.full(len(u), np.nan)
    enough = (good.sum(1) * 2 >= win.shape[1]) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if enough.any():
        sub = win[enough]
        med = np.nanmedian(sub, axis=1)
        spread = (np.nanmax(sub, axis=1) - np.nanmin(sub, axis=1)) / med
        out[np.flatnonzero(enough)[spread <= c['depth_max_spread']]] = med[spread <= c['depth_max_spread']]
    return out


# -------------------------------------------------------------------------------------- estimation


def estimate_pose(
    query, keyframe, matches, query_cam, keyframe_cam, keyframe_depth: np.ndarray | None = None, conf=None
) -> PoseEstimate:
    """T(keyframe <- query) from reloc.Matches between reloc.Keypoints query and keyframe, with
    io.camera.CameraModel query_cam and keyframe_cam and the keyframe's depth (H, W) float32
    metres (NaN = none), or the keyframe keypoints' depths (N,) metres (NaN = none), or None. PnP
    when at least min_points matches have a depth, else the
    essential matrix. Never raises for degenerate input (module doc)."""
    c = {**default_conf, **(conf or {})}
    if not isinstance(getattr(cv2, str(c['essential_method']), None), int):
        raise ValueError(
            f'essential_method must name an OpenCV robust method (USAC_ACCURATE, RANSAC), got {c["essential_method"]!r}'
        )
    t0 = time.perf_counter()
    m = len(matches)
    if m < int(c['min_matches']):
        return PoseEstimate(False, f'{m} matches; at least {c["min_matches"]} are needed', matches=m, ms=_ms(t0))
    pq = query.uv[matches.query_index].astype(np.float64)
    pk = keyframe.uv[matches.map_index].astype(np.float64)
    nq, nk = query_cam.normalise(pq), keyframe_cam.normalise(pk)
    thr = float(c['ransac_px']) / query_cam.focal  # normalised units
    est = None
    if keyframe_depth is not None:
        # (H, W) depth image, or (N,) depths of the keyframe's keypoints (read when they were detected)
        if np.ndim(keyframe_depth) == 1:
            z = np.asarray(keyframe_depth, np.float64)[matches.map_index]
            z[~((z >= c['min_depth_m']) & (z <= c['max_depth_m']))] = np.nan
        else:
            z = keypoint_depth(keyframe_depth, pk, c)
        valid = np.isfinite(z)
        if valid.sum() >= int(c['min_points']):
            X = np.c_[nk * z[:, None], z]  # (M, 3) keyframe camera frame, NaN rows where no depth
            est = _pnp(X, nq, valid, thr, c)
            est.points_3d = int(valid.sum())
    if est is None:
        est = _essential(nq, nk, thr, c)
    est.matches, est.ms = m, _ms(t0)
    est.reproj_px *= query_cam.focal
    return est


def _pnp(X: np.ndarray, nq: np.ndarray, valid: np.ndarray, thr: float, c: dict) -> PoseEstimate:
    idx = np.flatnonzero(valid)
    obj, img = X[idx], nq[idx]
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            np.eye(3),
            None,
            iterationsCount=int(c['max_iters']),
            reprojectionError=thr,
            confidence=float(c['confidence']),
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error as e:
        return PoseEstimate(False, f'PnP RANSAC failed: {str(e).strip().splitlines()[-1]}', 'pnp')
    if not ok or inl is None or len(inl) < 6:
        return PoseEstimate(False, 'PnP RANSAC found no pose', 'pnp')
    sel = inl.ravel()
    for _ in range(2):  # refine on the inliers, then re-select the inliers with the refined pose
        rvec, tvec = cv2.solvePnPRefineLM(obj[sel], img[sel], np.eye(3), None, rvec, tvec)
        T_kq = invert(rigid(cv2.Rodrigues(rvec)[0], tvec))
        err = np.linalg.norm(_reproject(T_kq, obj, img).reshape(-1, 2), axis=1)
        sel = np.flatnonzero(err < thr)
        if len(sel) < 6:
            return PoseEstimate(False, f'{len(sel)} PnP inliers after refinement', 'pnp')
    X_q = (obj[sel] - T_kq[:3, 3]) @ T_kq[:3, :3]
    if np.mean(X_q[:, 2] > 0) < 0.99:  # a pose that puts the scene behind the query camera
        return PoseEstimate(False, 'PnP pose puts the points behind the query camera', 'pnp')
    if _collinear(img[sel], c['min_spread']):
        return PoseEstimate(False, 'PnP inliers lie on a line or a point in the query (degenerate)', 'pnp')
    mask = np.zeros(len(X), bool)
    mask[idx[sel]] = True
    cov = _covariance(lambda T: _reproject(T, obj[sel], img[sel]), T_kq)
    return PoseEstimate(
        True, '', 'pnp', T_kq, cov, inliers=len(sel), inlier_mask=mask, reproj_px=float(np.median(err[sel]))
    )


def _reproject(T_kq: np.ndarray, X_k: np.ndarray, nq: np.ndarray) -> np.ndarray:
    """Residuals (2N,) of keyframe points X_k (N, 3) projected into the query (normalised nq (N, 2))."""
    X_q = (X_k - T_kq[:3, 3]) @ T_kq[:3, :3]  # x_q = R^T (x_k - t), row form
    z = np.where(np.abs(X_q[:, 2]) < 1e-9, 1e-9, X_q[:, 2])
    return (X_q[:, :2] / z[:, None] - nq).ravel()


def _essential(nq: np.ndarray, nk: np.ndarray, thr: float, c: dict) -> PoseEstimate:
    try:
        E, mask = cv2.findEssentialMat(
            nq,
            nk,
            np.eye(3),
            getattr(cv2, str(c['essential_method'])),
            float(c['confidence']),
            thr,
            int(c['max_iters']),
        )
        if E is None or mask is None or E.shape[0] < 3:
            return PoseEstimate(False, 'essential-matrix RANSAC found no model', 'essential')
        E = E[:3]
        # points2 = R points1 + t with points1 the query: (R, t) is T(keyframe <- query), |t| = 1
        n_good, R, t, pose_mask = cv2.recoverPose(E, nq, nk, np.eye(3), mask=mask.copy())
    except cv2.error as e:
        return PoseEstimate(False, f'essential RANSAC failed: {str(e).strip().splitlines()[-1]}', 'essential')
    sel = np.flatnonzero(pose_mask.ravel() > 0)
    if n_good < 6 or len(sel) < 6:
        return PoseEstimate(False, f'{len(sel)} inliers in front of both cameras', 'essential')
    if _collinear(nq[sel], c['min_spread']) or _collinear(nk[sel], c['min_spread']):
        return PoseEstimate(False, 'essential inliers lie on a line or a point (degenerate)', 'essential')
    T_kq = rigid(R, t.ravel())
    res = np.abs(_sampson(T_kq, nq[sel], nk[sel]))
    cov = _covariance(lambda T: _sampson(T, nq[sel], nk[sel]), T_kq, rank=5)
    t_unit = T_kq[:3, 3] / np.linalg.norm(T_kq[:3, 3])
    cov[:3, :3] += float(c['unknown_scale_variance']) * np.outer(t_unit, t_unit)
    mask_all = np.zeros(len(nq), bool)
    mask_all[sel] = True
    return PoseEstimate(
        True, '', 'essential', T_kq, cov, inliers=len(sel), inlier_mask=mask_all, reproj_px=float(np.median(res))
    )


def _sampson(T_kq: np.ndarray, nq: np.ndarray, nk: np.ndarray) -> np.ndarray:
    """Sampson distances (N,) of correspondences nq <-> nk (N, 2) under E = [t]x R of T(keyframe <- query)
    (the normalised translation: the distance does not depend on |t|)."""
    t = T_kq[:3, 3] / max(np.linalg.norm(T_kq[:3, 3]), 1e-12)
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T_kq[:3, :3]
    x1, x2 = np.c_[nq, np.ones(len(nq))], np.c_[nk, np.ones(len(nk))]
    Ex1, Etx2 = x1 @ E.T, x2 @ E
    num = np.sum(x2 * Ex1, axis=1)
    den = np.sqrt(Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2)
    return num / np.maximum(den, 1e-12)


def _covariance(residuals, T: np.ndarray, rank: int = 6, eps: float = 1e-6) -> np.ndarray:
    """s^2 (J^T J)^-1 (pseudo-inverse when rank < 6) for residuals(T) -> (n,) (module doc)."""
    r0 = residuals(T)
    J = np.empty((len(r0), 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        J[:, i] = (residuals(perturb(T, d)) - residuals(perturb(T, -d))) / (2 * eps)
    dof = max(len(r0) - rank, 1)
    s2 = float(r0 @ r0) / dof
    JtJ = J.T @ J
    inv = np.linalg.pinv(JtJ, rcond=1e-10, hermitian=True) if rank < 6 else _inv(JtJ)
    cov = s2 * inv
    return 0.5 * (cov + cov.T)


def _inv(A: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(A, hermitian=True)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


# -------------------------------------------------------------------------------------- acceptance


def accept(est: PoseEstimate, score: float, conf: dict | None = None) -> tuple[bool, str]:
    """The per-frame rule: (accepted, reason when not). S >= min_score, a pose with at least
    min_inliers inliers, inlier ratio >= min_inlier_ratio, median residual <= max_reproj_px, and
    (when set) covariance standard deviations within max_rot_std_deg / max_trans_std_m."""
    c = {**default_conf, **(conf or {})}
    if not score >= c['min_score']:
        return False, f'score {score:.3g} below min_score {c["min_score"]:g}'
    if not est.ok:
        return False, est.reason
    if est.inliers < c['min_inliers']:
        return False, f'{est.inliers} inliers, min_inliers is {c["min_inliers"]}'
    if est.inlier_ratio < c['min_inlier_ratio']:
        return False, f'inlier ratio {est.inlier_ratio:.2f} below {c["min_inlier_ratio"]:g}'
    if not est.reproj_px <= c['max_reproj_px']:
        return False, f'median residual {est.reproj_px:.2f} px above max_reproj_px {c["max_reproj_px"]:g}'
    var = np.diag(est.covariance) if est.covariance is not None else np.full(6, np.inf)
    if c['max_rot_std_deg'] > 0 and not math.degrees(math.sqrt(max(var[3:].max(), 0))) <= c['max_rot_std_deg']:
        return False, 'rotation too uncertain'
    if c['max_trans_std_m'] > 0 and est.metric and not math.sqrt(max(var[:3].max(), 0)) <= c['max_trans_std_m']:
        return False, 'translation too uncertain'
    return True, ''


class Agreement:
    """Consistency over consecutive queries: an estimate is trusted when the previous agree_frames
    estimates, carried forward by odometry (identity motion without it), give the same pose within
    agree_m and agree_deg (translation compared only when both are metric). A query without an
    estimate breaks the run. agree_frames 0: every estimate agrees."""

    def __init__(self, conf: dict | None = None):
        c = {**default_conf, **(conf or {})}
        self.n, self.max_m, self.max_deg = int(c['agree_frames']), float(c['agree_m']), float(c['agree_deg'])
        self.history: list[tuple] = []  # (T_map_query (4, 4), T_odom_query (4, 4) or None, metric)

    def reset(self) -> None:
        self.history.clear()

    def update(self, T_map_query: np.ndarray | None, T_odom_query: np.ndarray | None = None, metric=True) -> bool:
        """Record this query's estimate (None: it had none) and say whether it agrees."""
        if self.n <= 0:
            return T_map_query is not None
        if T_map_query is None:
            self.history.clear()
            return False
        agrees = len(self.history) >= self.n
        for T_prev, odom_prev, metric_prev in self.history[-self.n :]:
            pred = T_prev
            if odom_prev is not None and T_odom_query is not None:
                pred = T_prev @ invert(odom_prev) @ T_odom_query
            if rotation_deg(pred[:3, :3].T @ T_map_query[:3, :3]) > self.max_deg:
                agrees = False
            if metric and metric_prev and np.linalg.norm(pred[:3, 3] - T_map_query[:3, 3]) > self.max_m:
                agrees = False
        self.history.append((T_map_query, T_odom_query, metric))
        del self.history[: -max(self.n, 1)]
        return agrees
