"""Learned whitening of landmark descriptors: the directions in which the same place's landmarks
change between visits (season, light, viewpoint) are shrunk before they are compared.

    A, B = landmark_pairs(set_a, set_b)            # (M, D) centred landmarks of one place, two visits
    W = learn(np.concatenate(As), np.concatenate(Bs), beta=0.5)            # (D, D) float32
    W = learn(A, B, groups=dataset_of_each_pair)   # each dataset's pairs weigh the same
    save(path, W, meta); W, meta = load(path)
    W = shipped('efficientnet_lite0/stage6/192')   # the package's, or None for another space
    W = shipped('efficientnet_lite0/stage6/192', 'similarity')   # the rerank's (PURPOSES)

Two ship per descriptor space (PURPOSES), because the two stages need different invariances:
- 'index', the landmark first stage's: learned from Nordland's summer/winter pairs only, since
  what a large map needs is that the query's season stops outvoting the place (below);
- 'similarity', the whitened half of the fused S (similarity, center='fuse' or 'whiten'): learned
  from all four training sets (Nordland 0:0.6, rtabmap_loop, essex3in1, tum_fr1rpy), each set's
  pairs weighing the same (`groups`), so viewpoint and indoor changes shape it as much as the
  season. With Nordland's W the fused S lost 2.3 points on the side-view fold and 1 on the webcam
  fold against untrained selection (issue 28); with this one it does not (docs/method.md).

Why: centring (center below, the index's conf['landmark_center']) removes what all landmarks of one
image share, but winter views of other places still outscore a summer view of the same place in a
large map (docs/benchmarks.md, Accuracy at scale). The supervised whitening of Radenovic et al.
(fine-tuning CNN image retrieval, TPAMI 2019; "Lw") takes the covariance C_S of the differences
between matching descriptors and maps x -> C_S^(-beta) x: a direction in which matching landmarks
differ much counts less. Here the matches are mutual nearest centred landmarks, at most one grid cell apart, of
ground-truth image pairs of the training data. beta = 0.5 (the full whitening) was chosen on the
Nordland validation part 0.6:0.7 among 8,927 real distractors (first stage alone, top 100; 0.25,
0.5, 0.75 and 1.0 tried): R@1 0.104 -> 0.182, R@100 0.546 -> 0.672.

The index applies W after centring and renormalises (landmark_index.LandmarkIndex.prepare). The
rerank S sees the descriptors as extracted unless asked otherwise (similarity, center='whiten').
"""

from __future__ import annotations

import hashlib
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import ModelError

default_conf = {
    'beta': 0.5,  # W = C_S^-beta; 0 = identity, 0.5 = whitening
    'floor': 1e-6,  # eigenvalues of C_S below floor x the largest are raised to it
    'max_cell_distance': 1,  # grid cells (Chebyshev) between two landmarks of a pair
}


def center(descriptors: np.ndarray, keyframe_ids: np.ndarray | None = None) -> np.ndarray:
    """Descriptors (N, D) minus the mean of their keyframe's (keyframe_ids (N,); None = one set),
    renormalised to unit length (float32 (N, D)): conf['landmark_center']. A keyframe of one landmark
    keeps it as it is (its mean is itself)."""
    x = np.atleast_2d(np.asarray(descriptors, np.float32))
    if not len(x):
        return x.copy()
    kf = np.zeros(len(x), np.int64) if keyframe_ids is None else np.asarray(keyframe_ids, np.int64).reshape(-1)
    # stored landmarks come keyframe by keyframe, so the stable sort is the identity there; the means
    # are taken per landmark count as (keyframes, count, D) blocks (np.add.at took 3 s per 200k
    # landmarks, reduceat 0.45 s: a map rebuild centres millions)
    order = np.argsort(kf, kind='stable')
    xs = x[order]
    starts = np.flatnonzero(np.r_[True, kf[order][1:] != kf[order][:-1]])
    counts = np.diff(np.r_[starts, len(x)])
    for c in np.unique(counts[counts > 1]):
        rows = (starts[counts == c][:, None] + np.arange(c)[None, :]).reshape(-1)
        block = xs[rows].reshape(-1, c, x.shape[1])
        xs[rows] = (block - block.mean(axis=1, keepdims=True)).reshape(-1, x.shape[1])
    xs /= np.maximum(np.sqrt(np.einsum('ij,ij->i', xs, xs)), 1e-12)[:, None]
    out = np.empty_like(x)
    out[order] = xs
    return out


def apply(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """W x renormalised, for vectors x (..., D) (D, D) -> float32 (..., D)."""
    y = np.asarray(x, np.float32) @ w.T
    return y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-12)


def landmark_pairs(a, b, max_cell_distance: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Matching landmarks of two LandmarkSets of one place: each set centred on its own mean, then
    the mutual nearest neighbours by cosine among those at most max_cell_distance cells apart.
    Returns (A (M, D), B (M, D)) float32, row i of A matching row i of B."""
    ca, cb = center(a.descriptors), center(b.descriptors)
    if not len(ca) or not len(cb):
        d = ca.shape[1] if ca.ndim == 2 else 0
        return np.zeros((0, d), np.float32), np.zeros((0, d), np.float32)
    sims = ca @ cb.T
    far = np.abs(np.asarray(a.cells)[:, None, :] - np.asarray(b.cells)[None, :, :]).max(axis=-1) > max_cell_distance
    sims[far] = -np.inf
    best_b, best_a = sims.argmax(axis=1), sims.argmax(axis=0)
    rows = np.flatnonzero((best_a[best_b] == np.arange(len(ca))) & np.isfinite(sims.max(axis=1)))
    return ca[rows], cb[best_b[rows]]


def learn(
    a: np.ndarray, b: np.ndarray, beta: float = 0.5, floor: float = 1e-6, groups: np.ndarray | None = None
) -> np.ndarray:
    """W = C_S^-beta (D, D) float32 from matching rows of a, b (M, D): C_S = mean (a - b)(a - b)^T,
    or with groups (M,) (e.g. the dataset of each pair) the mean of each group's C_S, so that a
    large dataset does not decide the whitening alone."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 2 or len(a) <= a.shape[1]:
        raise ModelError(f'whitening needs more matching pairs than dimensions, got {a.shape} and {b.shape}')
    d = a - b
    g = np.zeros(len(d), np.int64) if groups is None else np.asarray(groups).reshape(-1)
    if len(g) != len(d):
        raise ModelError(f'whitening: {len(g)} group labels for {len(d)} pairs')
    cov = np.mean([d[g == k].T @ d[g == k] / np.count_nonzero(g == k) for k in np.unique(g)], axis=0)
    values, vectors = np.linalg.eigh(cov)
    values = np.maximum(values, floor * values.max())
    return ((vectors * values**-beta) @ vectors.T).astype(np.float32)


def fingerprint(w: np.ndarray | None) -> str:
    """A short content hash of W ('' = no whitening): the landmark index file records it."""
    return '' if w is None else hashlib.sha256(np.ascontiguousarray(w, np.float32).tobytes()).hexdigest()[:16]


def save(path, w: np.ndarray, meta: dict) -> None:
    np.savez(path, w=np.asarray(w, np.float32), **{k: np.asarray(str(v)) for k, v in meta.items()})


def load(path) -> tuple[np.ndarray, dict]:
    with np.load(path) as f:
        return f['w'].astype(np.float32), {k: str(f[k]) for k in f.files if k != 'w'}


# what a shipped whitening is for (module doc) -> its file name's prefix
PURPOSES = {'index': 'whiten', 'similarity': 'whiten_similarity'}


def default_path(descriptor_space: str, purpose: str = 'index') -> Path:
    """Where the package keeps a descriptor space's ('backbone/layer/D') whitening for `purpose`."""
    if purpose not in PURPOSES:
        raise ModelError(f'whitening purpose {purpose!r}: one of {", ".join(PURPOSES)}')
    backbone, layer = (descriptor_space.split('/') + ['', ''])[:2]
    return Path(str(resources.files('lln_ros') / 'weights' / f'{PURPOSES[purpose]}_{backbone}_{layer}.npz'))


def shipped_path(descriptor_space: str, purpose: str = 'index') -> Path | None:
    """The package's whitening file for a descriptor space and purpose, if one ships."""
    path = default_path(descriptor_space, purpose)
    return path if descriptor_space.count('/') == 2 and path.is_file() else None


_SHIPPED: dict[tuple[str, str], np.ndarray | None] = {}


def shipped(descriptor_space: str, purpose: str = 'index') -> np.ndarray | None:
    """The shipped W of this descriptor space for `purpose` (PURPOSES) (D, D), or None when none
    ships (no whitening)."""
    key = (descriptor_space, purpose)
    if key not in _SHIPPED:
        path = shipped_path(descriptor_space, purpose)
        w = load(path)[0] if path else None
        dim = descriptor_space.split('/')[-1]
        if w is not None and (w.shape != (w.shape[0],) * 2 or str(w.shape[0]) != dim):
            raise ModelError(f'whitening {path} is {w.shape}, not ({dim}, {dim}) for {descriptor_space}')
        _SHIPPED[key] = w
    return _SHIPPED[key]
