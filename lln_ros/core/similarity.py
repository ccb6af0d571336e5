"""Spatially weighted cross matching of landmark sets (Xin et al., ICRA 2019, Sec. III-C).

For a query set A and K candidate sets B_k:
  1. cross_match: keep mutually nearest landmark pairs by cosine similarity s_ij;
  2. offset_mode: the most frequent grid-cell offset (dx, dy) = cell(A_i) - cell(B_j) over the pairs;
  3. offset_weights: w_ij = exp(-1/2 * |offset_ij - mode|^2 / scale^2), offsets in grid cells;
  4. S = sum_ij w_ij * s_ij.
With conf['center'] True (the paper's raw S is False; the default is 'fuse', below; docs/method.md) every
set's descriptors, the query's and each candidate's, are first taken minus their own set's mean and
renormalised (center_sets): what all
landmarks of one image share (its season, light, weather) stops counting as similarity, and the pairs
and S are decided by what makes the places differ. With center = 'whiten' the centred sets are then
whitened with the descriptor space's shipped W for S (core.whitening, purpose 'similarity': learned
from every training set, where the first stage's W is learned from Nordland's seasons).
With center = 'fuse' S is S(raw) + conf['fusion_weight'] * S(centred, whitened), and the pairs,
offsets and weights reported are raw S's: what changes with the season counts less, what changes
with the viewpoint is still compared raw.
All K candidates are done with array operations (no Python loop per candidate), in chunks whose
similarity tensor is bounded (MATCH_CHUNK_ELEMENTS): memory per query does not grow with K x n_max.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DescriptorError
from . import whitening
from .landmarks import LandmarkBatch, LandmarkSet, stack_landmarks

default_conf = {
    'scale': 1.0,  # Gaussian width of the offset weights, in grid cells
    # S's sets (CENTERS): False = raw, the paper's; True = each set minus its own mean landmark
    # (center_sets; lln-eval --similarity-center); 'whiten': centred, then whitened with the shipped
    # W for S (lln-eval --similarity-whitening); 'fuse': raw S + fusion_weight x whitened S
    # (lln-eval --similarity-fusion). 'fuse' is the default since 2026-12-07: chosen on the issue-28
    # folds and the Nordland validation part against raw S (shipped head, top-n 50, landmark first
    # stage, P@100%R): it is at least ACT's and RAND's and within 2 of ALL's on all five folds
    # (raw S on one: lateral 72.8 vs RAND 73.8), Nordland validation lln 46.2 -> 56.9, lln+seq
    # 95.0 -> 93.8; essex3in1 64.8 -> 63.3 (docs/method.md). S is larger than raw S: min_score is
    # chosen for one setting.
    'center': 'fuse',
    # the whitened S's weight in 'fuse'. 2: chosen from 0.5, 1, 2, 4 on Nordland 0.6:0.7
    # (validation, the references alone) in a scratch run: top-1 0.515, 0.555, 0.588, 0.591;
    # whitened S alone 0.605, raw 0.443. 2 keeps raw S's share larger at nearly 4's figure
    'fusion_weight': 2.0,
}
# S by name (the matcher's `similarity`, bench_accuracy_at_scale --similarity) -> its center value
CENTERS = {'raw': False, 'center': True, 'whiten': 'whiten', 'fuse': 'fuse'}
DEFAULT_SIMILARITY = {value: name for name, value in CENTERS.items()}[default_conf['center']]  # its name


def center_sets(descriptors: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Padded sets (K, n, D) minus the mean of each set's valid landmarks (valid (K, n) bool),
    renormalised: float32 (K, n, D). A set of one landmark keeps it as it is (its mean is itself),
    as landmark_index.center does; padded rows stay as given (they are never matched)."""
    x = np.asarray(descriptors, np.float32)
    count = valid.sum(axis=1)  # (K,)
    # a float32 divisor: an int64 one made the mean, and everything after it, float64 (7x slower:
    # 3.9 vs 0.55 ms for 30 candidates of 50 landmarks, and a float64 cross_match after it)
    mean = np.einsum('knd,kn->kd', x, valid.astype(np.float32)) / np.maximum(count, 1).astype(np.float32)[:, None]
    mean[count < 2] = 0.0
    out = x - mean[:, None, :]
    out /= np.maximum(np.linalg.norm(out, axis=2, keepdims=True), 1e-12)
    return np.where(valid[:, :, None], out, x)


def whiten_sets(descriptors: np.ndarray, valid: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Padded sets (K, n, D) -> W x, renormalised, for the valid rows (valid (K, n)); W (D, D)."""
    return np.where(valid[:, :, None], whitening.apply(descriptors, w), descriptors)


@dataclass
class MatchResult:
    """Similarity of one query against K candidates.

    scores (K,) S; offsets (K, 2) the mode (dx, dy) in cells; match (K, n_a) index into the
    candidate's landmarks (-1 where query landmark i has no mutual partner); similarity (K, n_a)
    cosine of the pair; weight (K, n_a) offset weight (0 where no pair).
    """

    scores: np.ndarray
    offsets: np.ndarray
    match: np.ndarray
    similarity: np.ndarray
    weight: np.ndarray

    def pairs(self, k: int) -> dict:
        """Matched pairs of candidate k: query_index, map_index, similarity, weight (arrays of M)."""
        i = np.flatnonzero(self.match[k] >= 0)
        return {
            'query_index': i,
            'map_index': self.match[k, i],
            'similarity': self.similarity[k, i],
            'weight': self.weight[k, i],
        }


def cross_match(
    query: np.ndarray, cands: np.ndarray, valid_q: np.ndarray, valid_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by cosine.

    query (n_a, D), cands (K, n_b, D), both L2-normalised; valid_q (n_a,), valid_c (K, n_b) bool.
    Returns match (K, n_a) int (-1 = no mutual partner) and sims (K, n_a) cosine to the partner.
    """
    k, n_b, d = cands.shape
    n_a = query.shape[0]
    flat = cands.reshape(k * n_b, d)
    # the query in row blocks, so the similarity block (K, n_b, rows) stays within
    # MATCH_CHUNK_ELEMENTS floats whatever n_a; nn_ba is kept as a running max / first argmax over
    # the blocks, which is exactly the argmax of the whole (ties go to the first row, as argmax's)
    step = max(1, MATCH_CHUNK_ELEMENTS // max(1, k * n_b))
    nn_ab, best = np.zeros((k, n_a), np.int64), np.zeros((k, n_a), np.float32)
    col_max, nn_ba = np.full((k, n_b), -np.inf, np.float32), np.zeros((k, n_b), np.int64)
    for start in range(0, n_a, step):
        stop = min(n_a, start + step)
        sims = (flat @ query[start:stop].T).reshape(k, n_b, stop - start)  # one GEMM per block
        np.copyto(sims, -np.inf, where=~valid_c[:, :, None])  # in place: broadcast mask, no temporary
        if not valid_q[start:stop].all():
            sims[:, :, ~valid_q[start:stop]] = -np.inf
        block_ab = sims.argmax(axis=1)  # (K, rows)
        nn_ab[:, start:stop] = block_ab
        best[:, start:stop] = np.take_along_axis(sims, block_ab[:, None, :], axis=1)[:, 0, :]
        block_max, block_arg = sims.max(axis=2), sims.argmax(axis=2)  # (K, n_b)
        better = block_max > col_max
        col_max = np.where(better, block_max, col_max)
        nn_ba = np.where(better, block_arg + start, nn_ba)
    rows = np.arange(k)[:, None]
    mutual = nn_ba[rows, nn_ab] == np.arange(n_a)[None, :]
    mutual &= valid_q[None, :] & valid_c[rows, nn_ab]
    return np.where(mutual, nn_ab, -1), np.where(mutual, best, 0.0).astype(np.float32)


DENSE_BINS = 1 << 22  # offset_mode counts in a dense array up to this many bins (32 MB of float64)


def offset_mode(offsets: np.ndarray, matched: np.ndarray, sims: np.ndarray) -> np.ndarray:
    """Most frequent offset per candidate. offsets (K, n_a, 2) int, matched (K, n_a) bool,
    sims (K, n_a). Returns (K, 2) int; (0, 0) for a candidate with no pairs.

    Ties between equally full bins go to the bin with the larger summed cosine, then to the lower
    bin index, so the result never depends on pair order. Bins are counted in a dense array of
    K * (2 * span + 1)^2 while that is at most DENSE_BINS (the usual case, fastest), otherwise only
    the occupied bins (a sort of the P <= K * n_a pairs; the same result): a grid declared huge (tiny
    cells, a vast image) once made this allocate terabytes."""
    k, n_a, _ = offsets.shape
    span = int(np.abs(offsets).max(initial=0))
    side = 2 * span + 1
    if k * side * side <= DENSE_BINS:
        code = (offsets[..., 1] + span) * side + (offsets[..., 0] + span)  # (K, n_a)
        flat = (np.arange(k, dtype=np.int64)[:, None] * side * side + code)[matched]  # (P,)
        weights = np.maximum(sims[matched], 0.0)
        counts = np.bincount(flat, minlength=k * side * side).astype(np.float64)
        # the cosine sum is < n_a + 1, so scaled by 1/(n_a+1) it only breaks ties between equal counts
        tie = np.bincount(flat, weights=weights, minlength=k * side * side)
        best = (counts + tie / (n_a + 1)).reshape(k, side * side).argmax(axis=1)
        mode = np.stack([best % side - span, best // side - span], axis=1)
        mode[~matched.any(axis=1)] = 0
        return mode
    rows = np.broadcast_to(np.arange(k)[:, None], (k, n_a))[matched]
    return pair_offset_mode(rows, offsets[matched], sims[matched], k, n_a)


def pair_offset_mode(rows: np.ndarray, offsets: np.ndarray, sims: np.ndarray, k: int, n_a: int) -> np.ndarray:
    """offset_mode for P pairs given as a list: rows (P,) the candidate of each pair (0..k-1),
    offsets (P, 2) int, sims (P,); n_a: the query's landmark count (scales the tie-break as
    offset_mode does). Returns (k, 2) int, (0, 0) for a candidate with no pairs. Costs a sort of
    the P pairs, whatever k and the grid: what the first stage uses on thousands of keyframes hit."""
    mode = np.zeros((k, 2), np.int64)
    if not len(rows):
        return mode
    offsets = np.asarray(offsets, np.int64)
    span = int(np.abs(offsets).max(initial=0))
    side = 2 * span + 1
    # bin order = (dy, dx) order, as offset_mode's dense code, so ties go to the same bin
    flat = np.asarray(rows, np.int64) * side * side + (offsets[:, 1] + span) * side + (offsets[:, 0] + span)
    weights = np.maximum(np.asarray(sims, np.float64), 0.0)
    bins, inverse = np.unique(flat, return_inverse=True)  # occupied bins, sorted
    value = np.bincount(inverse).astype(np.float64) + np.bincount(inverse, weights=weights) / (n_a + 1)
    cand = bins // (side * side)
    order = np.lexsort((bins, -value, cand))  # per candidate: best value, then lowest bin
    first = order[np.r_[True, cand[order][1:] != cand[order][:-1]]]
    best = bins[first] % (side * side)
    mode[cand[first]] = np.stack([best % side - span, best // side - span], axis=1)
    return mode


def offset_weights(offsets: np.ndarray, mode: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Gaussian weight of each pair's offset around the mode. offsets (K, n_a, 2), mode (K, 2) -> (K, n_a)."""
    if not scale > 0:
        raise ValueError(f'offset scale must be positive, got {scale}')
    d2 = ((offsets - mode[:, None, :]) ** 2).sum(axis=2)
    return np.exp(-0.5 * d2 / float(scale) ** 2).astype(np.float32)


# float32 elements one step of the match may hold: a chunk of K_c candidates stacked to its own
# longest n_b (K_c x n_b x D descriptors <= this), and the similarity block of that chunk against a
# block of query rows (K_c x n_b x rows <= this; cross_match). 2^22 floats = 16 MiB; with argmax's
# copy of a block the match needs ~2-3 x 16 MiB beyond the sets it matches, whatever K, n_a and the
# landmark counts (bench/bench_hostile.py, docs/interfaces.md "worst-case cost of one message").
# Before (issue 25) one 4,096-landmark keyframe and query padded all 100 candidates to 4096 x 4096
# similarities: 6.3 GB.
MATCH_CHUNK_ELEMENTS = 1 << 22


def chunk_size(n_a: int, n_b: int, d: int, cap: int | None = None) -> int:
    """Candidates of n_b landmarks (D-dim) stacked and matched at once (>= 1); n_a is blocked inside
    cross_match, so it does not size the chunk."""
    cap = MATCH_CHUNK_ELEMENTS if cap is None else cap
    return max(1, cap // max(1, n_b * d))


def match_batch(
    query: LandmarkSet, batch: LandmarkBatch, scale: float = 1.0, center: bool | str | None = None
) -> MatchResult:
    """Similarity S of one query against every set in a LandmarkBatch (an already padded stack),
    in chunks of chunk_size() candidates, each cut to its own longest set. center: centre every set
    first (center_sets; 'whiten': then whiten it, whiten_sets; None = default_conf['center'])."""
    k, n_b, d = batch.descriptors.shape
    if d != query.dim:
        raise DescriptorError(f'descriptor size mismatch: query has D={query.dim}, candidates have D={d}')
    step = chunk_size(len(query), n_b, d)
    center = default_conf['center'] if center is None else center
    if k <= step:
        return _match_chunk(query, batch, scale, center)
    parts = []
    for start in range(0, k, step):
        part = batch.take(np.arange(start, min(k, start + step)))
        used = int(part.valid.any(axis=0).nonzero()[0].max(initial=-1)) + 1
        parts.append(_match_chunk(query, _cut(part, max(used, 1)), scale, center))
    return _concat(parts)


def match_sets(
    query: LandmarkSet, sets: list[LandmarkSet], scale: float = 1.0, center: bool | str | None = None
) -> MatchResult:
    """match_batch against a list of sets (results in list order) without padding them all to the
    longest: the sets are grouped by landmark count (sorted) and stacked chunk by chunk, so the
    stacked descriptors and the similarity blocks stay within MATCH_CHUNK_ELEMENTS floats (one
    candidate at least), and a long keyframe costs only its own candidates' time. Beyond that the
    results are K x n_a (match, similarity, weight, offsets: ~40 bytes per query landmark and
    candidate)."""
    if not sets:
        raise DescriptorError('no landmark sets to match')
    order = np.argsort([len(s) for s in sets], kind='stable')
    parts, idx, start = [], [], 0
    while start < len(order):
        # sorted ascending: the chunk's longest set is its last; grow while it fits
        stop = start + 1
        while stop < len(order):
            n_b = len(sets[order[stop]])
            if stop + 1 - start > chunk_size(len(query), n_b, query.dim):
                break
            stop += 1
        chunk = order[start:stop]
        parts.append(match_batch(query, stack_landmarks([sets[i] for i in chunk]), scale, center))
        idx.append(chunk)
        start = stop
    merged = _concat(parts)
    inverse = np.empty(len(sets), np.int64)
    inverse[np.concatenate(idx)] = np.arange(len(sets))
    return MatchResult(*(getattr(merged, f)[inverse] for f in ('scores', 'offsets', 'match', 'similarity', 'weight')))


def _cut(batch: LandmarkBatch, n: int) -> LandmarkBatch:
    return LandmarkBatch(batch.descriptors[:, :n], batch.cells[:, :n], batch.valid[:, :n], batch.globals)


def _concat(parts: list[MatchResult]) -> MatchResult:
    fields = ('scores', 'offsets', 'match', 'similarity', 'weight')
    return MatchResult(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))


def _match_chunk(query: LandmarkSet, batch: LandmarkBatch, scale: float, center: bool | str) -> MatchResult:
    if center == 'fuse':
        raw, whitened = _match_chunk(query, batch, scale, False), _match_chunk(query, batch, scale, 'whiten')
        raw.scores = (raw.scores + float(default_conf['fusion_weight']) * whitened.scores).astype(np.float32)
        return raw
    q = np.asarray(query.descriptors, np.float32)
    valid_q = np.ones(len(q), bool)
    cands = np.asarray(batch.descriptors, np.float32)
    if center:
        q, cands = center_sets(q[None], valid_q[None])[0], center_sets(cands, batch.valid)
        w = whitening.shipped(query.descriptor_space, 'similarity') if center == 'whiten' else None
        if w is not None:
            q, cands = whiten_sets(q[None], valid_q[None], w)[0], whiten_sets(cands, batch.valid, w)
    match, sims = cross_match(q, cands, valid_q, batch.valid)
    matched = match >= 0
    partner = np.take_along_axis(batch.cells, np.maximum(match, 0)[:, :, None], axis=1)  # (K, n_a, 2)
    offsets = (query.cells[None, :, :] - partner).astype(np.int64)
    mode = offset_mode(offsets, matched, sims)
    weight = np.where(matched, offset_weights(offsets, mode, scale), 0.0).astype(np.float32)
    scores = (weight * sims).sum(axis=1)
    return MatchResult(scores.astype(np.float32), mode, match, sims, weight)


def match_pair(a: LandmarkSet, b: LandmarkSet, scale: float = 1.0, center: bool | str | None = None) -> MatchResult:
    """Similarity of two landmark sets: match_batch with K = 1."""
    check_comparable(a, b)
    return match_batch(a, stack_landmarks([b]), scale, center)


def check_comparable(a: LandmarkSet, b: LandmarkSet) -> None:
    if a.dim != b.dim:
        raise DescriptorError(f'descriptor size mismatch: {a.dim} vs {b.dim}')
    if a.descriptor_space and b.descriptor_space and a.descriptor_space != b.descriptor_space:
        raise DescriptorError(
            f'landmark sets come from different models: {a.descriptor_space!r} vs {b.descriptor_space!r}'
        )
    for s in (a, b):
        s.validate()
