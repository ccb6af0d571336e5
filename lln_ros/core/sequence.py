"""Sequence-consistent place recognition: SeqSLAM-style search over a stream of single-frame scores.

Milford and Wyeth, "SeqSLAM", ICRA 2012: a place is recognised by a *sequence* of frames whose
single-frame scores line up along a straight line of the (query x map) score matrix, i.e. the
vehicle moves along the mapped route at a roughly constant velocity. The same search serves every
method (any single-frame similarity, higher = better) offline (lln-eval `--sequence L`, `seqslam`)
and online (the matcher's `sequence_length`), through one class:

    seq = SequenceMatcher({'length': 10})
    for stamp_ns, positions, scores in stream:       # one query: map positions (K,) and their S (K,)
        seq.push(stamp_ns, positions, scores)
        ends, seq_scores = seq.search(map_size)      # map positions, best sequence first

Definitions (causal, so the offline figures are what the node publishes):
- The window is the last L' <= L queries, oldest first; its newest row is the current query.
- A line ending at map position j with velocity v (map frames per query frame) visits position
  j - round(v * b) in the row b frames back (b = 0 .. L'-1); v takes `v_steps` values in
  [v_min, v_max]. Forward motion only (a route driven backwards is not followed).
- A row's unscored positions (not among its top-K, excluded, or off the map) count as that row's
  lowest score: a map frame outside a query's top-K is at most as similar as its worst candidate.
- score_norm 'none' (the default) averages the raw scores (OpenSeqSLAM's search after its own
  contrast enhancement, which `seqslam` keeps); 'zscore' first puts each row in standard deviations
  above its lowest score (`standardise`), so every query weighs the same in a line and a sequence
  score compares across queries, including queries whose true place is not in the map.
- The sequence score of j is max over v of the mean row value along the line; lines through
  no scored entry cannot beat one through a scored entry, so only ends reachable from a scored
  entry are searched (cost O(L * K * V), independent of the map size).

Stream faults (online): a stamp not newer than the last one (out of order or repeated) or a gap
longer than `max_gap_s` empties the window first (the constant-velocity model no longer holds);
smaller gaps (a dropped frame) are absorbed by the velocity range. With fewer than L queries in the
window the line is shorter (the first frames after a start or reset are single-frame-like).

The classic SeqSLAM front end lives here too: `sad_descriptors` (downsampled, patch-normalised grey
images), `sad_difference` (mean absolute difference, FAISS L1) and `contrast_enhance` (the local
normalisation of each query's difference vector over a window of map frames).
"""

from __future__ import annotations

from collections import deque

import cv2
import faiss
import numpy as np

from ..errors import LLNError

default_conf = {
    'length': 10,  # L: queries in a sequence (SeqSLAM's ds)
    'v_min': 0.8,  # velocity range, map frames per query frame (OpenSeqSLAM 0.8 .. 1.2)
    'v_max': 1.2,
    'v_steps': 5,
    'max_gap_s': 1.0,  # online: a stamp gap longer than this starts a new sequence
    # 'zscore': each query's scores in standard deviations above its lowest candidate before the line
    # search, so a query whose S spreads widely does not outvote the others; not the default because
    # it also gives full weight to queries that revisit nothing (a loop's first frames, benchmarks.md)
    'score_norm': 'none',
}
SCORE_NORMS = ('zscore', 'none')

sad_conf = {
    'width': 32,  # downsampled image width; height keeps the first map image's aspect
    'patch': 8,  # patch normalisation: zero mean, unit std in P x P pixel patches
    'enhance_window': 10,  # contrast enhancement: map frames either side (SeqSLAM's R_window / 2)
}


class SequenceError(LLNError):
    """A sequence search that cannot be set up: bad length or velocity range, bad scores."""


def check_conf(conf: dict) -> dict:
    conf = {**default_conf, **(conf or {})}
    if int(conf['length']) < 1:
        raise SequenceError(f'sequence length must be at least 1, got {conf["length"]}')
    if not 0 <= float(conf['v_min']) <= float(conf['v_max']) or int(conf['v_steps']) < 1:
        raise SequenceError(
            f'need 0 <= v_min <= v_max and v_steps >= 1, got {conf["v_min"]}, {conf["v_max"]}, {conf["v_steps"]}'
        )
    if not float(conf['max_gap_s']) > 0:
        raise SequenceError(f'max_gap_s must be positive, got {conf["max_gap_s"]}')
    if conf['score_norm'] not in SCORE_NORMS:
        raise SequenceError(f'score_norm must be one of {SCORE_NORMS}, got {conf["score_norm"]!r}')
    return conf


def standardise(scores: np.ndarray) -> np.ndarray:
    """(K,) one query's scores -> (K,) in standard deviations above their minimum (>= 0; all 0 when
    they do not spread, or spread beyond float range). The minimum, not the mean, is the origin so
    that unscored positions (the row's lowest score) are 0 and a sequence score is never negative; an
    origin per row moves every line's mean by the same amount, so the ranking is that of z-scores."""
    with np.errstate(over='ignore', invalid='ignore'):
        spread = scores.std() if len(scores) else 0.0
    return (scores - scores.min()) / spread if 0 < spread < np.inf else np.zeros_like(scores)


class SequenceMatcher:
    """A bounded ring of the last L queries' single-frame results and the sequence search over it.

    Each entry: (stamp_ns, positions (K,) int map positions, scores (K,) float). Map positions are
    indices into the map in route order (offline: reference index; online: keyframe order)."""

    def __init__(self, conf: dict | None = None):
        self.conf = check_conf(conf)
        self.length = int(self.conf['length'])
        self.ring: deque = deque(maxlen=self.length)
        velocities = np.linspace(float(self.conf['v_min']), float(self.conf['v_max']), int(self.conf['v_steps']))
        # back[v, b]: how many map frames a line of velocity v moved in the last b query frames
        self.back = np.rint(velocities[:, None] * np.arange(self.length)[None]).astype(np.int64)  # (V, L)
        self.resets = {'out_of_order': 0, 'gap': 0}

    def __len__(self) -> int:
        return len(self.ring)

    def reset(self) -> None:
        self.ring.clear()

    def reset_reason(self, stamp_ns: int) -> str | None:
        """Why pushing a query of stamp_ns would empty the window first ('out_of_order', 'gap'), or None."""
        if not self.ring:
            return None
        last = self.ring[-1][0]
        if stamp_ns <= last:
            return 'out_of_order'
        return 'gap' if stamp_ns - last > float(self.conf['max_gap_s']) * 1e9 else None

    def filling(self, stamp_ns: int) -> bool:
        """Whether the window will hold fewer than `length` queries once a query of stamp_ns is pushed:
        the first length - 1 after a start, or after a reset this stamp causes."""
        held = 0 if self.reset_reason(stamp_ns) else len(self.ring)
        return held + 1 < self.length

    def push(self, stamp_ns: int, positions, scores) -> str | None:
        """Add one query's scored map positions. Returns why the window was emptied first
        ('out_of_order', 'gap') or None."""
        positions = np.asarray(positions, np.int64).reshape(-1)
        scores = np.asarray(scores, np.float64).reshape(-1)
        if positions.shape != scores.shape:
            raise SequenceError(f'{len(positions)} positions but {len(scores)} scores')
        keep = np.isfinite(scores) & (positions >= 0)
        positions, scores = positions[keep], scores[keep]
        if self.conf['score_norm'] == 'zscore':
            scores = standardise(scores)
        reason = self.reset_reason(stamp_ns)
        if reason:
            self.resets[reason] += 1
            self.ring.clear()
        self.ring.append((int(stamp_ns), positions, scores))
        return reason

    def ahead(self, ends, map_size: int) -> np.ndarray:
        """Map positions (M,) where lines ending at positions `ends` go next: each end + 0 ..
        ceil(v_max) (the end and its next step at any velocity of the range), within the map."""
        steps = np.arange(int(np.ceil(float(self.conf['v_max']))) + 1)
        nxt = (np.asarray(ends, np.int64).reshape(-1, 1) + steps[None]).ravel()
        return np.unique(nxt[(nxt >= 0) & (nxt < map_size)])

    def search(self, map_size: int, allowed_ends=None, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Sequence scores of the line ends reachable from the window's scored entries.

        map_size: R, the number of map positions; allowed_ends: optional (R,) bool, which positions
        may be answers (loop protocol, exclude_recent). Returns (ends (E,), scores (E,)), best
        first, at most k of them (None = all). Empty when the window holds no scored entry."""
        rows = [r for r in self.ring]
        scored = [r for r in rows if len(r[1])]
        if not scored or map_size < 1:
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        n = len(rows)
        back = self.back[:, :n]  # (V, n), b = 0 is the newest
        # the window as a dense (n + pad, R) matrix, rows newest first, unscored = the row's minimum
        floor = np.array([r[2].min() if len(r[2]) else np.nan for r in reversed(rows)])
        floor = np.where(np.isfinite(floor), floor, np.nanmin(floor))  # an empty row: the window's minimum
        dense = np.empty((n, map_size + 1))  # last column = off the map
        dense[:] = floor[:, None]
        for b, (_, pos, sc) in enumerate(reversed(rows)):
            inside = pos < map_size
            dense[b, pos[inside]] = sc[inside]
        # ends: a scored entry b rows back is on the line ending at pos + back[v, b] (a mask, not a
        # sort: with every keyframe scored, prefilter_k 0, there are L * R * V of them)
        reach = np.zeros(map_size, bool)
        for b, (_, pos, _) in enumerate(reversed(rows)):
            e = (pos[:, None] + back[:, b][None]).ravel()
            reach[e[(e >= 0) & (e < map_size)]] = True
        ends = np.flatnonzero(reach)
        if allowed_ends is not None:
            ends = ends[np.asarray(allowed_ends, bool)[ends]]
        if not len(ends):
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        visit = ends[None, None, :] - back[:, :, None]  # (V, n, E)
        visit = np.where(visit >= 0, visit, map_size)  # off the map: the row's floor
        visit += (np.arange(n) * (map_size + 1))[None, :, None]  # flat index into dense
        values = dense.ravel().take(visit)  # (V, n, E)
        best = values.sum(axis=1).max(axis=0) / n  # (E,) mean along the best line
        order = np.argsort(-best, kind='stable')[:k]
        return ends[order], best[order]


def rank_sequences(
    ranked: np.ndarray,
    scores: np.ndarray,
    n_refs: int,
    conf: dict | None = None,
    allowed: np.ndarray | None = None,
    k: int = 30,
    carry: int = 0,
    score_of=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Offline: single-frame rankings of a query sequence (in stream order) -> sequence rankings.

    ranked (Q, K) ref indices (-1 = none) and scores (Q, K) of any method; allowed (Q, R) bool or
    None. Queries are fed to one SequenceMatcher in order with stamps 0, 1, 2 ... (no gaps), the
    way the node sees a stream. Returns ranked (Q, k) and sequence scores (Q, k), -1 / -inf padded.
    carry N with score_of(q, refs (M,)) -> scores (M,): the matcher's sequence_carry, the previous
    query's N best ends' next refs (SequenceMatcher.ahead) scored beside query q's own ranking."""
    seq = SequenceMatcher({**(conf or {}), 'max_gap_s': float('inf')})
    out = np.full((len(ranked), k), -1, np.int64)
    out_scores = np.full((len(ranked), k), -np.inf, np.float32)
    carried = np.zeros(0, np.int64)
    for q in range(len(ranked)):
        ok = ranked[q] >= 0
        pos, sc = ranked[q][ok], scores[q][ok]
        new = np.setdiff1d(seq.ahead(carried, n_refs), pos) if score_of is not None else carried[:0]
        new = new[allowed[q][new]] if allowed is not None else new
        if len(new):
            pos, sc = np.r_[pos, new], np.r_[sc, score_of(q, new)]
        seq.push(q, pos, sc)
        ends, s = seq.search(n_refs, None if allowed is None else allowed[q], max(k, int(carry)))
        carried, ends, s = ends[: int(carry)], ends[:k], s[:k]
        out[q, : len(ends)], out_scores[q, : len(ends)] = ends, s
    return out, out_scores


def acquiring(base: tuple, wide: tuple, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Offline, the matcher's sequence_acquire_k: a stream's single-frame ranking (ranked, scores) (Q, K)
    whose first n queries (the window filling: sequence length - 1) come from the wider ranking wide
    (Q, K') instead; K' >= K, the rest padded with -1 / -inf to K'."""
    ranked = np.full(wide[0].shape, -1, np.int64)
    scores = np.full(wide[1].shape, -np.inf, np.float32)
    k = base[0].shape[1]
    ranked[:, :k], scores[:, :k] = base
    ranked[:n], scores[:n] = wide[0][:n], wide[1][:n]
    return ranked, scores


def dense_to_ranked(
    similarity: np.ndarray, allowed: np.ndarray | None = None, k: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) similarity (higher = better) -> ranked (Q, k) indices and scores, disallowed = -1/-inf."""
    sim = np.asarray(similarity, np.float64)
    if allowed is not None:
        sim = np.where(allowed, sim, -np.inf)
    k = sim.shape[1] if k is None else min(int(k), sim.shape[1])
    top = np.argsort(-sim, axis=1, kind='stable')[:, :k]
    top_s = np.take_along_axis(sim, top, axis=1)
    return np.where(np.isfinite(top_s), top, -1), top_s.astype(np.float32)


# ------------------------------------------------------------------------- SeqSLAM front end (sad)


def sad_size(image_size, conf: dict | None = None) -> tuple[int, int]:
    """(width, height) the SAD front end resizes to: conf width, height keeping image_size's aspect,
    both multiples of the patch size."""
    c = {**sad_conf, **(conf or {})}
    p, w = int(c['patch']), int(c['width'])
    h = max(p, int(round(w * image_size[1] / image_size[0] / p)) * p)
    return w, h


def sad_descriptors(grey_images, size: tuple[int, int], conf: dict | None = None) -> np.ndarray:
    """Downsampled, patch-normalised grey images, flattened: (N, w*h) float32.

    Each P x P patch is shifted to zero mean and scaled to unit std (a flat patch stays zero), which
    removes most of the illumination change between traverses (SeqSLAM's front end)."""
    c = {**sad_conf, **(conf or {})}
    p = int(c['patch'])
    w, h = size
    out = np.empty((len(grey_images), w * h), np.float32)
    for i, im in enumerate(grey_images):
        small = cv2.resize(np.asarray(im), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        patches = small.reshape(h // p, p, w // p, p)
        mean = patches.mean(axis=(1, 3), keepdims=True)
        std = patches.std(axis=(1, 3), keepdims=True)
        out[i] = ((patches - mean) / np.where(std > 1e-6, std, 1.0)).reshape(-1)
    return out


def sad_difference(queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """(Q, R) mean absolute difference between descriptor rows (FAISS L1 distances / length)."""
    q, r = np.ascontiguousarray(queries, np.float32), np.ascontiguousarray(refs, np.float32)
    return faiss.pairwise_distances(q, r, metric=faiss.METRIC_L1) / max(q.shape[1], 1)


def contrast_enhance(difference: np.ndarray, window: int = 10) -> np.ndarray:
    """SeqSLAM's local contrast enhancement: each query's difference to map frame r is normalised
    by the mean and std of its differences to map frames r - window .. r + window. (Q, R) -> (Q, R)."""
    d = np.asarray(difference, np.float64)
    r = d.shape[1]
    # windowed sums with cumulative sums along the map axis
    c1 = np.concatenate([np.zeros((len(d), 1)), np.cumsum(d, axis=1)], axis=1)
    c2 = np.concatenate([np.zeros((len(d), 1)), np.cumsum(d * d, axis=1)], axis=1)
    lo = np.clip(np.arange(r) - int(window), 0, r)
    hi = np.clip(np.arange(r) + int(window) + 1, 0, r)
    n = (hi - lo)[None]
    mean = (c1[:, hi] - c1[:, lo]) / n
    var = np.maximum((c2[:, hi] - c2[:, lo]) / n - mean * mean, 0.0)
    return (d - mean) / np.sqrt(np.maximum(var, 1e-12))


class KeyframeSequence:
    """Online: a SequenceMatcher over a map of keyframes in route order, keyed by id.

    Route order is each session's keyframes in the order that session stored them, sessions one
    after another (by session number): a map that several robots or runs write interleaves their
    ids, and a line through interleaved ids would follow no trajectory (issue 29). Keyframes without
    an origin (maps of schema < 5, stores without sessions) come first, by id, as before.

    The caller tells it the map's ids when they change (`set_map`, with the origins of the new ones)
    and feeds every answered query:

        seq = KeyframeSequence({'length': 10})
        seq.follow(store)  # or seq.set_map(ids, {id: Origin}) of the new ids
        reason, ranked = seq.update(stamp_ns, {keyframe_id: S, ...}, excluded=recent_ids, k=5)
        ranked: [(keyframe_id, sequence_score), ...] best first

    A keyframe that joins inside the route (another session's) moves the later positions: the
    entries already in the window are re-mapped by id, so the window survives. Ids that vanished
    are dropped from them; clearing the map (set_map with no ids) empties the window."""

    def __init__(self, conf: dict | None = None):
        self.matcher = SequenceMatcher(conf)
        self.ids = np.zeros(0, np.int64)  # (R,) keyframe ids in route order
        self._route_key: dict[int, tuple[int, int]] = {}  # id -> (session_id, seq); (0, id) without origin
        self._sorted, self._where = np.zeros(0, np.int64), np.zeros(0, np.int64)  # ids ascending, their positions
        self.carried = np.zeros(0, np.int64)  # ids of the last search's best ends (update's carry), for ahead()

    @classmethod
    def of(cls, conf: dict) -> KeyframeSequence | None:
        """The search a matcher (Localizer) conf asks for: sequence_length, sequence_max_gap,
        sequence_score_norm; None when sequence_length is 0 (single-frame ranking)."""
        n, norm = int(conf['sequence_length']), conf['sequence_score_norm']
        return cls({'length': n, 'max_gap_s': conf['sequence_max_gap'], 'score_norm': norm}) if n > 0 else None

    @property
    def resets(self) -> dict:
        return self.matcher.resets

    def set_map(self, ids, origins: dict | None = None) -> None:
        """ids: every keyframe of the map, any order; origins: {id: Origin} for (at least) the ids not
        given before (an id without one is placed by its id, before every session)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if not len(ids):
            self.matcher.reset()
            self._route_key.clear()
        for kid, origin in (origins or {}).items():
            self._route_key[int(kid)] = (int(origin.session_id), int(origin.seq))
        keys = [self._route_key.setdefault(int(k), (0, int(k))) for k in ids.tolist()]
        route = ids[sorted(range(len(ids)), key=keys.__getitem__)] if len(ids) else ids
        old_ids, self.ids = self.ids, route
        self._sorted = np.sort(route)
        self._where = np.argsort(route, kind='stable')  # position of the i-th smallest id
        if len(old_ids) and not np.array_equal(route[: len(old_ids)], old_ids):  # not an append: re-map
            ring = list(self.matcher.ring)
            self.matcher.ring.clear()
            for stamp, pos, sc in ring:
                new_pos, known = self.positions(old_ids[pos])
                self.matcher.ring.append((stamp, new_pos[known], sc[known]))

    def follow(self, store) -> None:
        """Re-read a MapStore's ids when its size changed (keyframes only join, or ~/clear empties
        it), with the origins of the new ones: they place them in route order."""
        if len(store) != len(self.ids):
            ids = store.ids()
            new = np.setdiff1d(ids, self.ids)
            self.set_map(ids, store.origins(new) if len(new) and hasattr(store, 'origins') else {})

    def positions(self, ids) -> tuple[np.ndarray, np.ndarray]:
        """Route positions (N,) of these ids and whether each is in the map (N,) bool."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if not len(self._sorted):
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        i = np.minimum(np.searchsorted(self._sorted, ids), len(self._sorted) - 1)
        known = self._sorted[i] == ids
        return self._where[i], known

    def ahead(self) -> np.ndarray:
        """Keyframe ids (M,) where the last search's carried ends lead next: route positions p + 0 ..
        ceil(v_max) of each end p (the end and its lines' next step at any velocity of the range).
        The Localizer has them scored beside the first stage's candidates (sequence_carry), so a line
        that holds stays scored where the first stage misses its next place. Empty before a search."""
        pos, known = self.positions(self.carried)
        return self.ids[self.matcher.ahead(pos[known], len(self.ids))]

    def update(
        self, stamp_ns: int, scores: dict, excluded=None, k: int = 5, carry: int = 0
    ) -> tuple[str | None, list[tuple[int, float]]]:
        """Push one query's single-frame scores {keyframe_id: S} and search. excluded: ids that may
        not be answers (mapping mode: this session's newest, exclude_recent); None = none. carry: the
        best ends kept for ahead() (0 = none)."""
        ids = np.fromiter(scores.keys(), np.int64, len(scores))
        values = np.fromiter(scores.values(), np.float64, len(scores))
        pos, known = self.positions(ids)
        reason = self.matcher.push(stamp_ns, pos[known], values[known])
        mask = None
        if excluded is not None and len(excluded):
            mask = ~np.isin(self.ids, np.asarray(excluded, np.int64))
        ends, seq_scores = self.matcher.search(len(self.ids), mask, max(int(k), int(carry)))
        self.carried = self.ids[ends[: int(carry)]]
        return reason, [(int(self.ids[e]), float(s)) for e, s in zip(ends[: int(k)], seq_scores[: int(k)])]
