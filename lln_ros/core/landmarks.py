"""Landmark sets: what an image becomes, and how the landmarks are chosen.

A `LandmarkSet` holds, for one image with a (rows, cols) feature grid and n landmarks of size D:

    global_descriptor  (D,)      global max pool of the feature map, L2-normalised
    descriptors        (n, D)    local features f_ij of the landmarks, L2-normalised, by descending score
    cells              (n, 2)    grid cell of each landmark as (col, row) integers
    centers            (n, 2)    region centre (u, v) in ORIGINAL image pixels
    scores             (n,)      selection score (LLN activation; feature norm for `act`; fused rank
                                 in [0, 1] for lln with act_fusion > 0)
    cell_size          (2,)      (w, h) of one grid cell in original image pixels
    image_size         (2,)      (width, height) of the original image
    activation         (rows, cols)  the full LLN activation map (for plots and the `score` of row 0)
    descriptor_space   str       backbone/layer/D: sets from different spaces must never be compared
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import DescriptorError

METHODS = ('lln', 'act', 'rand', 'all')


@dataclass
class LandmarkSet:
    global_descriptor: np.ndarray
    descriptors: np.ndarray
    cells: np.ndarray
    centers: np.ndarray
    scores: np.ndarray
    cell_size: np.ndarray
    image_size: np.ndarray
    grid: tuple
    activation: np.ndarray | None = None
    descriptor_space: str = ''
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def dim(self) -> int:
        return int(self.global_descriptor.shape[0])

    def validate(self) -> 'LandmarkSet':
        """Check shapes and values; raises DescriptorError naming the first problem."""
        d = self.global_descriptor
        if d.ndim != 1 or d.shape[0] == 0:
            raise DescriptorError(f'global descriptor must be a non-empty vector, got shape {d.shape}')
        n = self.descriptors.shape[0]
        if self.descriptors.ndim != 2 or self.descriptors.shape[1] != d.shape[0]:
            raise DescriptorError(
                f'landmark descriptors have shape {self.descriptors.shape}, expected (n, {d.shape[0]})'
            )
        for name, arr, shape in (
            ('cells', self.cells, (n, 2)),
            ('centers', self.centers, (n, 2)),
            ('scores', self.scores, (n,)),
        ):
            if arr.shape != shape:
                raise DescriptorError(f'{name} has shape {arr.shape}, expected {shape}')
        if not (np.isfinite(d).all() and np.isfinite(self.descriptors).all()):
            raise DescriptorError('descriptors contain NaN or inf')
        rows, cols = self.grid
        if n and (self.cells.min() < 0 or (self.cells[:, 0] >= cols).any() or (self.cells[:, 1] >= rows).any()):
            raise DescriptorError(f'landmark cells fall outside the {cols}x{rows} grid')
        return self


def l2_normalize(x: np.ndarray, axis: int = -1) -> np.ndarray:
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.maximum(norm, 1e-12)


def select_landmarks(score_map: np.ndarray, n: int, method: str = 'lln', seed: int = 0) -> np.ndarray:
    """Flat indices (row * cols + col) of the selected cells, ordered by descending score.

    score_map (rows, cols): the map to rank by (LLN activation for lln/rand/all, feature norm for act).
    `rand` draws n cells from a generator seeded with `seed`, so every image with the same grid
    gets the same cells (the paper's RAND baseline: same locations for query and map). `all` keeps
    every cell. Ties keep the lower index first, so the result is deterministic.
    """
    if method not in METHODS:
        raise ValueError(f'unknown landmark method {method!r}; choose one of {METHODS}')
    flat = np.asarray(score_map, dtype=np.float32).ravel()
    if n < 1 and method != 'all':
        raise ValueError(f'top_n must be at least 1, got {n}')
    if method == 'rand':
        cells = np.random.default_rng(seed).permutation(flat.size)[:n]
    elif method == 'all':
        cells = np.arange(flat.size)
    else:
        cells = np.argsort(-flat, kind='stable')[:n]
    # order the chosen cells by score, stable on index
    return cells[np.lexsort((cells, -flat[cells]))]


@dataclass
class LandmarkBatch:
    """Many landmark sets stacked and padded to one n, for batched matching.

    descriptors (K, n, D) float32, cells (K, n, 2) int32, valid (K, n) bool, globals (K, D) float32;
    descriptor_space: the sets' (LandmarkSet.descriptor_space).
    """

    descriptors: np.ndarray
    cells: np.ndarray
    valid: np.ndarray
    globals: np.ndarray
    descriptor_space: str = ''

    def __len__(self) -> int:
        return len(self.descriptors)

    def take(self, indices) -> 'LandmarkBatch':
        """The sub-batch of the given set indices, in that order."""
        idx = np.asarray(indices, np.int64)
        return LandmarkBatch(
            self.descriptors[idx], self.cells[idx], self.valid[idx], self.globals[idx], self.descriptor_space
        )


def stack_landmarks(sets: list[LandmarkSet], dtype=np.float32) -> LandmarkBatch:
    """Pad a list of landmark sets (any n, same D and descriptor space) into a LandmarkBatch."""
    if not sets:
        raise DescriptorError('no landmark sets to stack')
    dims = {s.dim for s in sets}
    spaces = {s.descriptor_space for s in sets}
    if len(dims) > 1 or len(spaces) > 1:
        raise DescriptorError(
            f'cannot stack landmark sets from different models: sizes {sorted(dims)}, spaces {sorted(spaces)}'
        )
    k, n, d, space = len(sets), max(len(s) for s in sets), dims.pop(), spaces.pop()
    desc = np.zeros((k, n, d), dtype)
    cells = np.zeros((k, n, 2), np.int32)
    valid = np.zeros((k, n), bool)
    for i, s in enumerate(sets):
        m = len(s)
        desc[i, :m] = s.descriptors
        cells[i, :m] = s.cells
        valid[i, :m] = True
    globals_ = np.stack([s.global_descriptor for s in sets]).astype(np.float32)
    return LandmarkBatch(desc, cells, valid, globals_, space)
