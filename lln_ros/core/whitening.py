"""Learned whitening of the landmark first stage: the directions in which the same place's landmarks
change between visits (season, light) are shrunk before the landmark index compares them.

    A, B = landmark_pairs(set_a, set_b)            # (M, D) centred landmarks of one place, two visits
    W = learn(np.concatenate(As), np.concatenate(Bs), beta=0.5)            # (D, D) float32
    save(path, W, meta); W, meta = load(path)
    W = shipped('efficientnet_lite0/stage6/192')   # the package's, or None for another space

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


def learn(a: np.ndarray, b: np.ndarray, beta: float = 0.5, floor: float = 1e-6) -> np.ndarray:
    """W = C_S^-beta (D, D) float32 from matching rows of a, b (M, D): C_S = mean (a - b)(a - b)^T."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 2 or len(a) <= a.shape[1]:
        raise ModelError(f'whitening needs more matching pairs than dimensions, got {a.shape} and {b.shape}')
    d = a - b
    values, vectors = np.linalg.eigh(d.T @ d / len(d))
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


def default_path(descriptor_space: str) -> Path:
    """Where the package keeps the whitening of a descriptor space ('backbone/layer/D')."""
    backbone, layer = (descriptor_space.split('/') + ['', ''])[:2]
    return Path(str(resources.files('lln_ros') / 'weights' / f'whiten_{backbone}_{layer}.npz'))


def shipped_path(descriptor_space: str) -> Path | None:
    """The package's whitening file for a descriptor space, if one ships."""
    path = default_path(descriptor_space)
    return path if descriptor_space.count('/') == 2 and path.is_file() else None


_SHIPPED: dict[str, np.ndarray | None] = {}


def shipped(descriptor_space: str) -> np.ndarray | None:
    """The shipped W of this descriptor space (D, D), or None when none ships (no whitening)."""
    if descriptor_space not in _SHIPPED:
        path = shipped_path(descriptor_space)
        w = load(path)[0] if path else None
        dim = descriptor_space.split('/')[-1]
        if w is not None and (w.shape != (w.shape[0],) * 2 or str(w.shape[0]) != dim):
            raise ModelError(f'whitening {path} is {w.shape}, not ({dim}, {dim}) for {descriptor_space}')
        _SHIPPED[descriptor_space] = w
    return _SHIPPED[descriptor_space]
