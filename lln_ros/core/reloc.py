"""Relocalization: keypoint matching between a query and a candidate keyframe, then geometric
verification (the paper's mLLN, Xin et al. ICRA 2019, Sec. IV).

    reloc = Relocalizer({'detector': 'orb'})
    kq, km = reloc.detect(query_rgb), reloc.detect(keyframe_rgb)
    boxes_q, boxes_m = pair_boxes(query_set, keyframe_set, pairs, reloc.conf['margin'])
    regions = reloc.match(kq, km, boxes_q, boxes_m)     # mLLN: only inside matched region pairs
    plain = reloc.match(kq, km)                         # baseline: all keypoints against all
    result = reloc.verify(kq, km, regions, K=camera_matrix(camera_info))
    result.verified, result.inliers, result.inlier_ratio, result.R, result.t

Keypoints live in ORIGINAL image pixels even when detection ran on an upsampled copy (tiny images
such as Nordland's 64x32 give ORB nothing to work with at their own size). Anything that cannot be
verified (no texture, regions outside the image, too few or collinear matches, RANSAC failing)
gives a RelocResult with verified=False and a `reason`, never an exception: a node calls this on
every query. Bad *arguments* (unknown detector, malformed K) raise RelocError.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import LLNError
from ..io.camera import load_yaml
from ..io.image import check_image

default_conf = {
    'detector': 'orb',  # orb | sift | akaze
    'max_keypoints': 1000,  # per image (ORB-SLAM's default for 512x384-ish frames)
    'min_height': 288,  # shorter images are upsampled (INTER_LINEAR) to this height to detect
    'fast_threshold': 20,  # ORB's FAST corner threshold (OpenCV's default); upsampled tiny
    # images are blurry: 5 gives Nordland ~240 keypoints instead of ~6
    'ratio': 0.8,  # Lowe ratio: best / second-best descriptor distance
    'margin': 1.0,  # region box = matched cell grown by this many cells on each side
    'ransac_px': 2.0,  # inlier threshold in detection pixels (F: epipolar distance)
    'confidence': 0.999,
    'max_iters': 2000,
    'min_matches': 8,  # fewer ratio-test matches than this: not verified (8-point F)
    'min_inliers': 15,  # fewer RANSAC inliers than this: not verified
    'min_spread': 0.02,  # inliers whose 2nd principal extent is below this fraction of the
    # 1st lie on a line: F/E are not determined by them
}

DETECTORS = ('orb', 'sift', 'akaze')


class RelocError(LLNError):
    """Relocalization arguments that cannot be used: unknown detector, malformed intrinsics."""


@dataclass
class Keypoints:
    """Keypoints of one image in original image pixels.

    uv (N, 2) float32, size (N,) float32 (diameter, original pixels), angle (N,) float32 degrees,
    response (N,) float32, octave (N,) int32, descriptors (N, B) uint8 (ORB/AKAZE, binary) or
    float32 (SIFT); scale = detection pixels per original pixel; image_size (width, height);
    depth (N,) float32 metres or None (no depth image)."""

    uv: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    octave: np.ndarray
    descriptors: np.ndarray
    scale: float = 1.0
    image_size: tuple = (0, 0)
    depth: np.ndarray | None = None  # (N,) float32 metres from a registered depth image, NaN = none

    def __len__(self) -> int:
        return len(self.uv)

    @property
    def binary(self) -> bool:
        return self.descriptors.dtype == np.uint8

    @classmethod
    def empty(cls, image_size=(0, 0), bytes_per_descriptor: int = 32) -> 'Keypoints':
        z = np.zeros(0, np.float32)
        return cls(
            np.zeros((0, 2), np.float32),
            z,
            z,
            z,
            np.zeros(0, np.int32),
            np.zeros((0, bytes_per_descriptor), np.uint8),
            1.0,
            tuple(image_size),
        )


@dataclass
class Matches:
    """Putative matches after the ratio test, one per query and per map keypoint.

    query_index (M,), map_index (M,) int64, distance (M,) float32; ms = matching time."""

    query_index: np.ndarray
    map_index: np.ndarray
    distance: np.ndarray
    ms: float = 0.0
    reason: str = ''  # why there are none, when that is known (e.g. regions outside the image)

    def __len__(self) -> int:
        return len(self.query_index)


@dataclass
class RelocResult:
    """Geometric verification of one query/keyframe pair.

    verified: enough non-degenerate RANSAC inliers; reason: why not ('' when verified);
    matches: the putative Matches; inlier_mask (M,) bool; inliers = inlier_mask.sum();
    inlier_ratio = inliers / M; model 'F' (fundamental) or 'E' (essential, intrinsics known);
    matrix (3, 3) F or E or None; R (3, 3), t (3,) unit-norm relative pose (map camera -> query
    camera, x_q = R x_m + t) when E was estimated and recoverPose succeeded, else None; ms = time
    of verification alone."""

    verified: bool
    reason: str
    matches: Matches
    inlier_mask: np.ndarray
    model: str = 'F'
    matrix: np.ndarray | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    ms: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def inliers(self) -> int:
        return int(self.inlier_mask.sum())

    @property
    def inlier_ratio(self) -> float:
        return float(self.inliers / len(self.matches)) if len(self.matches) else 0.0

    def summary(self) -> dict:
        """JSON-friendly numbers (no arrays but the pose)."""
        return {
            'verified': self.verified,
            'reason': self.reason,
            'matches': len(self.matches),
            'inliers': self.inliers,
            'inlier_ratio': self.inlier_ratio,
            'model': self.model,
            'R': None if self.R is None else self.R.tolist(),
            't': None if self.t is None else self.t.tolist(),
            'ms_match': self.matches.ms,
            'ms_verify': self.ms,
        }


# ------------------------------------------------------------------------------------- intrinsics


def camera_matrix(source) -> np.ndarray:
    """3x3 intrinsic matrix K from a sensor_msgs/CameraInfo (its `k`), a (3, 3) or (9,) sequence,
    a dict from a ROS camera-calibration YAML (`camera_matrix: {data: [...]}`) or `{'k': [...]}`,
    or the path of such a YAML file. Raises RelocError when fx, fy are not positive."""
    if isinstance(source, (str, bytes)) or hasattr(source, '__fspath__'):
        source = load_camera_yaml(source)
    if isinstance(source, dict):
        for key in ('camera_matrix', 'K', 'k'):
            if key in source:
                source = source[key]
                break
        else:
            raise RelocError(f'no camera_matrix / K / k in the intrinsics {sorted(source)}')
        if isinstance(source, dict):
            source = source.get('data')
    elif hasattr(source, 'k'):
        source = source.k
    try:
        k = np.asarray(source, np.float64).reshape(3, 3)
    except (TypeError, ValueError):
        raise RelocError(f'intrinsics must hold 9 numbers (row-major 3x3 K), got {source!r:.80}') from None
    if not (np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0):
        raise RelocError(f'intrinsics need finite, positive fx and fy, got K = {k.ravel().tolist()}')
    return k


def load_camera_yaml(path) -> dict:
    """A ROS camera-calibration YAML as a dict (io.camera.load_yaml), RelocError when unusable."""
    return load_yaml(path, 'camera intrinsics', RelocError)


# ------------------------------------------------------------------------------------------ regions


def region_boxes(centres: np.ndarray, cell_size, margin: float) -> np.ndarray:
    """Boxes (M, 4) x0, y0, x1, y1 in original pixels around region centres (M, 2), each one grid
    cell (cell_size (2,) or (M, 2): w, h) grown by `margin` cells on every side."""
    c = np.asarray(centres, np.float32).reshape(-1, 2)
    half = (0.5 + float(margin)) * np.broadcast_to(np.asarray(cell_size, np.float32), c.shape)
    return np.concatenate([c - half, c + half], axis=1)


def pair_boxes(query, keyframe, pairs: dict, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Region boxes of matched landmark pairs (as MatchResult.pairs) in each image's own pixels:
    the landmark cells scaled back to the original image size, grown by `margin` cells."""
    qi = np.asarray(pairs.get('query_index', ()), np.int64)
    mi = np.asarray(pairs.get('map_index', ()), np.int64)
    return (
        region_boxes(query.centers[qi], query.cell_size, margin),
        region_boxes(keyframe.centers[mi], keyframe.cell_size, margin),
    )


def _inside(uv: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(M, N) bool: keypoint n lies in box m."""
    u, v = uv[None, :, 0], uv[None, :, 1]
    return (u >= boxes[:, None, 0]) & (u < boxes[:, None, 2]) & (v >= boxes[:, None, 1]) & (v < boxes[:, None, 3])


# -------------------------------------------------------------------------------------- relocalizer


class Relocalizer:
    """Keypoint detection, (region-constrained) ratio-test matching and RANSAC verification."""

    def __init__(self, conf: dict | None = None):
        self.conf = conf = {**default_conf, **(conf or {})}
        name = str(conf['detector']).lower()
        if name not in DETECTORS:
            raise RelocError(f'unknown detector {conf["detector"]!r}; choose one of {DETECTORS}')
        n = int(conf['max_keypoints'])
        if n < 1:
            raise RelocError(f'max_keypoints must be at least 1, got {n}')
        if not 0 < float(conf['ratio']) <= 1:
            raise RelocError(f'ratio must be in (0, 1], got {conf["ratio"]}')
        if name == 'orb':
            self.detector = cv2.ORB_create(nfeatures=n, fastThreshold=int(conf['fast_threshold']))
        elif name == 'sift':
            self.detector = cv2.SIFT_create(nfeatures=n)
        else:
            if not hasattr(cv2, 'AKAZE_create'):
                raise RelocError(
                    f'this OpenCV ({cv2.__version__}) has no AKAZE (OpenCV 5 moved it to '
                    'opencv-contrib); use orb or sift'
                )
            self.detector = cv2.AKAZE_create()
        self.name = name
        self.norm = cv2.NORM_L2 if name == 'sift' else cv2.NORM_HAMMING
        self.matcher = cv2.BFMatcher(self.norm)

    def detect(self, image: np.ndarray, channel_order: str = 'rgb') -> Keypoints:
        """Keypoints of an image (uint8 grey or colour). A textureless image gives none."""
        rgb = check_image(image, channel_order)
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        h, w = grey.shape
        scale = max(1.0, float(self.conf['min_height']) / h)
        if scale > 1:
            grey = cv2.resize(grey, (int(round(w * scale)), int(round(h * scale))), interpolation=cv2.INTER_LINEAR)
        kps, desc = self.detector.detectAndCompute(grey, None)
        if desc is None or not kps:
            return Keypoints.empty((w, h), 32 if self.name == 'orb' else 0)
        if self.name == 'akaze':
            k = min(len(kps), int(self.conf['max_keypoints']))  # AKAZE has no nfeatures: keep the strongest
            keep = np.argsort([-p.response for p in kps], kind='stable')[:k]
            kps, desc = [kps[i] for i in keep], desc[keep]
        uv = np.array([p.pt for p in kps], np.float32).reshape(-1, 2)
        # detection pixel centres -> original pixel centres (pixel centre at +0.5 in both grids)
        uv = (uv + 0.5) / np.float32(scale) - 0.5
        return Keypoints(
            uv=uv,
            size=np.array([p.size for p in kps], np.float32) / scale,
            angle=np.array([p.angle for p in kps], np.float32),
            response=np.array([p.response for p in kps], np.float32),
            octave=np.array([p.octave for p in kps], np.int32),
            descriptors=np.ascontiguousarray(desc),
            scale=scale,
            image_size=(w, h),
        )

    def match(
        self,
        query: Keypoints,
        keyframe: Keypoints,
        query_boxes: np.ndarray | None = None,
        map_boxes: np.ndarray | None = None,
    ) -> Matches:
        """Ratio-test matches. Without boxes: every query keypoint against every keyframe keypoint
        (the unconstrained baseline). With boxes (M, 4) each (region pair m): query keypoints in
        query_boxes[m] only against keyframe keypoints in map_boxes[m] (mLLN); a keypoint in
        several overlapping regions is matched against the keypoints of all their partner regions
        (one masked brute-force pass). One match per keypoint on each side."""
        t0 = time.perf_counter()
        if not len(query) or not len(keyframe):
            return _matches([], [], [], t0, 'no keypoints (textureless image?)')
        if (
            query.descriptors.dtype != keyframe.descriptors.dtype
            or query.descriptors.shape[1] != keyframe.descriptors.shape[1]
        ):
            raise RelocError(
                f'keypoint descriptors differ: {query.descriptors.dtype}x{query.descriptors.shape[1]} '
                f'vs {keyframe.descriptors.dtype}x{keyframe.descriptors.shape[1]}'
            )
        if query_boxes is None:
            qi, mi, d = self._ratio_match(query.descriptors, keyframe.descriptors)
            return _matches(qi, mi, d, t0)
        qb = np.asarray(query_boxes, np.float32).reshape(-1, 4)
        mb = np.asarray(map_boxes, np.float32).reshape(-1, 4)
        if len(qb) != len(mb):
            raise RelocError(f'{len(qb)} query regions but {len(mb)} keyframe regions')
        in_q, in_m = _inside(query.uv, qb), _inside(keyframe.uv, mb)  # (M, Nq), (M, Nm)
        if not (in_q.any(1) & in_m.any(1)).any():
            outside = not len(qb) or not (
                _overlaps(qb, query.image_size).any() and _overlaps(mb, keyframe.image_size).any()
            )
            return _matches(
                [],
                [],
                [],
                t0,
                'the matched regions lie outside the images' if outside else 'no keypoints inside the matched regions',
            )
        # (Nq, Nm) which pairs share a region pair; the matcher skips the rest (no distance computed).
        # Filled block by block: a float GEMM here hits BLAS thread start-up (~20 ms on a busy CPU)
        allowed = np.zeros((len(query), len(keyframe)), bool)
        for a, b in zip(in_q, in_m):
            allowed[np.ix_(a, b)] = True
        qi, mi, d = self._ratio_match(query.descriptors, keyframe.descriptors, allowed)
        return _matches(qi, mi, d, t0)

    def _ratio_match(self, da: np.ndarray, db: np.ndarray, allowed: np.ndarray | None = None):
        """Lowe ratio test a -> b, with allowed (Na, Nb) bool among the pairs that may match. A
        keypoint with a single allowed partner has no second neighbour and passes (its regions
        hold one keypoint). Returns query idx, map idx, distance."""
        mask = None if allowed is None else allowed.astype(np.uint8)
        knn = self.matcher.knnMatch(da, db, k=2, mask=mask) if mask is not None else self.matcher.knnMatch(da, db, k=2)
        ratio = float(self.conf['ratio'])
        rows = [
            (m[0].queryIdx, m[0].trainIdx, m[0].distance)
            for m in knn
            if len(m) == 1 or (len(m) == 2 and m[0].distance < ratio * m[1].distance)
        ]
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
        r = np.array(rows, np.float64)
        return r[:, 0].astype(np.int64), r[:, 1].astype(np.int64), r[:, 2].astype(np.float32)

    def verify(self, query: Keypoints, keyframe: Keypoints, matches: Matches, K=None, K_map=None) -> RelocResult:
        """RANSAC on the putative matches: the fundamental matrix, or with intrinsics K (query
        camera; K_map for the keyframe camera, default K) the essential matrix and relative pose.
        Never raises for degenerate input: verified=False with a reason."""
        t0 = time.perf_counter()
        conf = self.conf
        model = 'F' if K is None else 'E'
        kq = None if K is None else camera_matrix(K)
        km = None if K is None else (kq if K_map is None else camera_matrix(K_map))
        m = len(matches)

        def fail(reason, mask=None, **kw):
            mask = np.zeros(m, bool) if mask is None else mask
            return RelocResult(False, reason, matches, mask, model, ms=_ms(t0), **kw)

        if m < int(conf['min_matches']):
            return fail(
                matches.reason or f'{m} matches after the ratio test; at least {conf["min_matches"]} are needed'
            )
        pq = query.uv[matches.query_index].astype(np.float64)
        pm = keyframe.uv[matches.map_index].astype(np.float64)
        if _collinear(pq, conf['min_spread']) or _collinear(pm, conf['min_spread']):
            return fail('matched keypoints lie on a line (degenerate geometry)')
        # the threshold is in detection pixels: upsampled tiny images get a proportionally smaller one
        px = float(conf['ransac_px']) / max(query.scale, keyframe.scale)
        R = t = None
        try:
            if kq is None:
                mat, mask = cv2.findFundamentalMat(
                    pm, pq, cv2.FM_RANSAC, px, float(conf['confidence']), int(conf['max_iters'])
                )
            else:
                # normalised coordinates let the two cameras differ; the threshold follows the focal length
                nq = cv2.undistortPoints(pq.reshape(-1, 1, 2), kq, None).reshape(-1, 2)
                nm = cv2.undistortPoints(pm.reshape(-1, 1, 2), km, None).reshape(-1, 2)
                f = 0.25 * (kq[0, 0] + kq[1, 1] + km[0, 0] + km[1, 1])
                mat, mask = cv2.findEssentialMat(
                    nm, nq, np.eye(3), cv2.RANSAC, float(conf['confidence']), px / f, int(conf['max_iters'])
                )
        except cv2.error as e:
            return fail(f'RANSAC failed: {str(e).strip().splitlines()[-1]}')
        if mat is None or mask is None or mat.shape[0] < 3:
            return fail('RANSAC found no model')
        mat = mat[:3]  # several 3x3 solutions may be stacked; RANSAC's mask belongs to the first
        inl = mask.ravel().astype(bool)
        if kq is not None and inl.sum() >= 5:
            n_good, R, t, pose_mask = cv2.recoverPose(mat, nm, nq, np.eye(3), mask=mask.copy())
            if n_good > 0:
                inl = inl & (pose_mask.ravel() > 0)  # cheirality: points in front of both cameras
                t = t.ravel()
            else:
                R = t = None
        n = int(inl.sum())
        if n < int(conf['min_inliers']):
            return fail(
                f'{n} RANSAC inliers of {m} matches; at least {conf["min_inliers"]} are needed',
                inl,
                matrix=mat,
                R=R,
                t=t,
            )
        if _collinear(pq[inl], conf['min_spread']) or _collinear(pm[inl], conf['min_spread']):
            return fail('RANSAC inliers lie on a line (degenerate geometry)', inl, matrix=mat)
        return RelocResult(True, '', matches, inl, model, mat, R, t, ms=_ms(t0))

    def relocalize(
        self, query: Keypoints, keyframe: Keypoints, query_boxes=None, map_boxes=None, K=None, K_map=None
    ) -> RelocResult:
        """match + verify; with boxes the region-constrained (mLLN) pipeline, else unconstrained."""
        return self.verify(query, keyframe, self.match(query, keyframe, query_boxes, map_boxes), K, K_map)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _matches(qi, mi, d, t0: float, reason: str = '') -> Matches:
    """Matches with one partner per keypoint on each side (the closest wins), sorted by distance."""
    qi, mi = np.asarray(qi, np.int64), np.asarray(mi, np.int64)
    d = np.asarray(d, np.float32)
    order = np.argsort(d, kind='stable')
    qi, mi, d = qi[order], mi[order], d[order]
    keep = np.zeros(len(qi), bool)
    _, first_q = np.unique(qi, return_index=True)
    keep[first_q] = True
    qi, mi, d = qi[keep], mi[keep], d[keep]
    _, first_m = np.unique(mi, return_index=True)
    first_m = np.sort(first_m)
    return Matches(qi[first_m], mi[first_m], d[first_m], _ms(t0), reason if not len(first_m) else '')


def _overlaps(boxes: np.ndarray, image_size) -> np.ndarray:
    w, h = image_size
    return (boxes[:, 2] > 0) & (boxes[:, 3] > 0) & (boxes[:, 0] < w) & (boxes[:, 1] < h)


def _collinear(points: np.ndarray, min_spread: float) -> bool:
    """True when the points' second principal extent is below min_spread of the first (a line or
    a single point): an epipolar geometry is not determined by them."""
    if len(points) < 3:
        return True
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(s[0] == 0 or s[1] < float(min_spread) * s[0])


def detection_scale(image_height: float, min_height: float) -> float:
    """Detection pixels per original pixel of an image of this height (see Relocalizer.detect)."""
    return max(1.0, float(min_height) / float(image_height)) if image_height > 0 else 1.0


def verify_candidates(
    reloc: Relocalizer, query: Keypoints, query_cell_size, candidates: list, keyframe_keypoints
) -> list[tuple]:
    """Region-constrained verification of map candidates (mapstore.MapCandidate: keyframe_id,
    score, image_size, pairs with query_u/v, map_u/v, cell_w/h), re-ranked by inliers.

    keyframe_keypoints(candidate) -> Keypoints or None (none stored). Returns (candidate,
    RelocResult or None) best first: verified candidates by inliers, then the rest by inliers,
    unverifiable ones (no keypoints) last; ties keep the place-recognition order."""
    margin = reloc.conf['margin']
    out = []
    for rank, c in enumerate(candidates):
        km = keyframe_keypoints(c)
        if km is None:
            out.append((c, None, rank))
            continue
        p = c.pairs
        qb = region_boxes(np.stack([p['query_u'], p['query_v']], axis=1), query_cell_size, margin)
        mb = region_boxes(
            np.stack([p['map_u'], p['map_v']], axis=1), np.stack([p['cell_w'], p['cell_h']], axis=1), margin
        )
        out.append((c, reloc.relocalize(query, km, qb, mb), rank))
    out.sort(
        key=lambda x: (
            x[1] is None,
            not (x[1] is not None and x[1].verified),
            -(x[1].inliers if x[1] is not None else 0),
            x[2],
        )
    )
    return [(c, r) for c, r, _ in out]
