"""Two-stage retrieval: a first stage proposes K map entries, the landmark similarity S reranks them.

    db = LandmarkDatabase()
    db.add(map_sets)                                   # list of LandmarkSet
    candidates = db.retrieve(query_set, prefilter_k=30)                          # landmarks first stage
    candidates = db.retrieve(query_set, prefilter_k=30, prefilter='holistic')    # the paper's
    candidates[0].index, .score, .holistic_score, .pairs

First stages (`prefilter`): 'landmarks' (the default: every query landmark's kNN among all map
landmarks, scored by landmark_index.score_hits), 'holistic' (global-descriptor cosine, the paper's),
'exhaustive' (every map entry; also what prefilter_k 0 means, whatever `prefilter` says).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import faiss
import numpy as np

from ..errors import DescriptorError
from . import landmark_index
from .landmark_index import LandmarkIndex, check_prefilter
from .landmarks import LandmarkBatch, LandmarkSet
from .similarity import match_batch, match_sets

default_conf = {
    'prefilter': 'landmarks',  # first stage: landmarks | holistic | exhaustive (the one default of all paths)
    # first-stage candidates reranked by S; 0 = every map entry. 30, the paper's top-30, since
    # 2026-12-06: fewer candidates give S fewer distractors to prefer. Nordland validation 0.6:0.7,
    # plain / in a 10k-keyframe map (bench_accuracy_at_scale --range 0.6:0.7 --prefilter-k K
    # --sequence-prefilter-k K), lln 0.443 / 0.171 at 100, 0.451 / 0.179 at 50, 0.459 / 0.179 at 30
    # (docs/benchmarks.md, Fewer candidates)
    'prefilter_k': 30,
    # first-stage candidates reranked when a sequence search follows (lln-eval --sequence, the
    # matcher's sequence_length): never fewer than prefilter_k; 0 = every map entry. Same runs,
    # lln+seq 0.927 / 0.908 at 100, 0.933 / 0.910 at 50, 0.933 / 0.924 at 30; with carried places
    # (below) 100 did as well as 500 (0.908 against 0.905; docs/benchmarks.md, Carried places)
    'sequence_prefilter_k': 30,
    # the sequence search also scores where the previous query's N best sequence ends go next (route
    # position + 0..2), beside the first stage's candidates; 0 = off. Same validation map: 0.821 (0),
    # 0.908 (10), 0.899 (30) with 100 candidates
    'sequence_carry': 10,
    # while the sequence window fills (its first sequence_length - 1 queries after a start or reset)
    # rerank this many instead (never fewer than the above); 0 = off. A short window has too few frames
    # to outvote a wrong line through look-alikes. Nordland validation 0.6:0.7, lln+seq plain / 10k /
    # 100k: 0.950 / 0.933 / 0.894 off, 0.950 / 0.933 / 0.941 with 50 or 100 (docs/benchmarks.md,
    # Acquiring the route)
    'sequence_acquire_k': 100,
    'scale': 1.0,  # offset-weight Gaussian width, in grid cells
    **landmark_index.default_conf,
}


@dataclass
class Candidate:
    """One map entry proposed for a query. `pairs`: query_index, map_index, similarity, weight
    (arrays of M matched landmark pairs); `offset`: the mode (dx, dy) in grid cells."""

    index: int
    score: float
    holistic_score: float
    offset: tuple = (0, 0)
    pairs: dict = field(default_factory=dict)


def rerank(
    query: LandmarkSet,
    batch: LandmarkBatch | list,
    indices: np.ndarray,
    holistic: np.ndarray,
    scale: float = 1.0,
    limit: int | None = None,
    center: bool | str | None = None,
) -> list[Candidate]:
    """Score `batch` (the prefiltered candidates, in `indices` order: a LandmarkBatch, or a list of
    LandmarkSets, matched by similarity.match_sets in bounded chunks grouped by landmark count)
    against the query; sort by S. limit: only the best `limit` come back (their pair tables are
    what costs, per candidate); center: similarity's set centring (None = its default_conf)."""
    match = match_sets if isinstance(batch, list) else match_batch
    result = match(query, batch, scale, center)
    order = np.argsort(-result.scores, kind='stable')[:limit]
    return [
        Candidate(
            int(indices[k]),
            float(result.scores[k]),
            float(holistic[k]),
            tuple(int(v) for v in result.offsets[k]),
            result.pairs(k),
        )
        for k in order
    ]


def batch_index(refs: LandmarkBatch, conf: dict | None = None) -> LandmarkIndex:
    """The landmark index of a stacked map: every valid landmark, keyed by its set's position."""
    k, n, d = refs.descriptors.shape
    index = LandmarkIndex(d, {**default_conf, **(conf or {})}, refs.descriptor_space)
    owner = np.broadcast_to(np.arange(k)[:, None], (k, n))[refs.valid]
    index.add(refs.descriptors[refs.valid], owner, refs.cells[refs.valid])
    return index


def _prefix(row: np.ndarray) -> int | None:
    """m when the allowed row is exactly refs [0, m) (the loop protocol), else None."""
    m = int(row.sum())
    return m if row[:m].all() else None


def cosine_top(
    query_vectors: np.ndarray, ref_vectors: np.ndarray, k: int, allowed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Top k refs by inner product of unit vectors (holistic descriptors): query_vectors (Q, D),
    ref_vectors (R, D), allowed (Q, R) bool -> ranked (Q, k) ref indices and scores (Q, k), padded
    with -1 / -inf where fewer refs are allowed."""
    k = min(int(k), len(ref_vectors))
    sims = np.asarray(query_vectors, np.float32) @ np.asarray(ref_vectors, np.float32).T  # (Q, R)
    if allowed is not None:
        sims = np.where(allowed, sims, -np.inf)
    top = np.argsort(-sims, axis=1, kind='stable')[:, :k]  # (Q, k)
    top_s = np.take_along_axis(sims, top, axis=1)
    ok = np.isfinite(top_s)
    ranked = np.full(top.shape, -1, np.int64)
    scores = np.full(top.shape, -np.inf, np.float32)
    ranked[ok], scores[ok] = top[ok], top_s[ok]
    return ranked, scores


def first_stage(
    queries: list[LandmarkSet],
    refs: LandmarkBatch,
    k: int,
    prefilter: str = 'landmarks',
    allowed: np.ndarray | None = None,
    conf: dict | None = None,
    scale: float = 1.0,
    index: LandmarkIndex | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The K candidates of each query before the rerank: ranked (Q, K) ref indices, best first, and
    their first-stage scores (Q, K) (holistic cosine, or landmark_index.score_hits); rows with
    fewer candidates are padded with -1 / -inf. 'exhaustive' = every allowed ref in holistic order.
    index: batch_index(refs, conf) when the caller already built it (building trains a compressed
    index on a large map, which an evaluation would otherwise pay once per call)."""
    conf = {**default_conf, **(conf or {})}
    n_q, r = len(queries), len(refs)
    k = min(int(k), r)
    if prefilter in ('holistic', 'exhaustive'):
        return cosine_top(np.stack([q.global_descriptor for q in queries]), refs.globals, k, allowed)
    ranked = np.full((n_q, k), -1, np.int64)
    scores = np.full((n_q, k), -np.inf, np.float32)
    if prefilter != 'landmarks':
        raise ValueError(f'unknown prefilter {prefilter!r}')
    index = index if index is not None else batch_index(refs, conf)
    hol_rank, _ = first_stage(queries, refs, k, 'holistic', allowed)  # tops up short landmark lists
    for i, q in enumerate(queries):
        below = None
        if allowed is not None:
            below = _prefix(allowed[i])
            if below == 0:
                continue
        ids, s = index.shortlist(q, k if below is not None or allowed is None else r, below, scale)
        if allowed is not None and below is None:  # not a prefix: filter the hits afterwards
            keep = allowed[i, ids]
            ids, s = ids[keep][:k], s[keep][:k]
        ids, s = landmark_index.fill(ids, s, hol_rank[i][hol_rank[i] >= 0], k)
        ranked[i, : len(ids)], scores[i, : len(ids)] = ids, s
    return ranked, scores


def candidates_k(prefilter_k: int, sequence_prefilter_k: int, sequence: bool) -> int:
    """First-stage candidates per query: prefilter_k, or with a sequence search following
    max(prefilter_k, sequence_prefilter_k); 0 (every map entry) when either is 0 in that case."""
    prefilter_k, sequence_prefilter_k = int(prefilter_k), int(sequence_prefilter_k)
    if prefilter_k < 0 or sequence_prefilter_k < 0:
        raise ValueError(f'need prefilter_k, sequence_prefilter_k >= 0, got {prefilter_k}, {sequence_prefilter_k}')
    if not sequence or not prefilter_k:
        return prefilter_k
    return max(prefilter_k, sequence_prefilter_k) if sequence_prefilter_k else 0


def rank_all_at(
    queries: list[LandmarkSet],
    refs: LandmarkBatch,
    ks: tuple,
    allowed: np.ndarray | None = None,
    scale: float = 1.0,
    prefilter: str = default_conf['prefilter'],
    conf: dict | None = None,
    index: LandmarkIndex | None = None,
    center: bool | str | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """rank_all for several K at once: one first stage of max(ks) candidates, one rerank of them,
    and for each K in ks the rerank of the first K first-stage candidates (the same as rank_all
    with that K: first stages are prefix-consistent). K = 0: every ref; ks[0] = 0 also makes the
    first stage exhaustive (check_prefilter). Returns [(ranked (Q, K), scores (Q, K))] in ks order."""
    r = len(refs)
    sizes = [min(int(k), r) if int(k) else r for k in ks]
    prefilter, _ = check_prefilter(prefilter, ks[0])  # the first K decides (0: exhaustive)
    top, _ = first_stage(queries, refs, max(sizes), prefilter, allowed, conf, scale, index)
    s_top = np.full(top.shape, -np.inf, np.float32)
    for i, q in enumerate(queries):
        ok = top[i] >= 0
        if ok.any():
            s_top[i, ok] = match_batch(q, refs.take(top[i][ok]), scale, center).scores
    out = []
    for k in sizes:
        t, s = top[:, :k], s_top[:, :k]
        order = np.argsort(-s, axis=1, kind='stable')
        ranked, scores = np.take_along_axis(t, order, 1), np.take_along_axis(s, order, 1)
        out.append((np.where(np.isfinite(scores), ranked, -1), scores))
    return out


def rank_all(
    queries: list[LandmarkSet],
    refs: LandmarkBatch,
    prefilter_k: int = default_conf['prefilter_k'],
    allowed: np.ndarray | None = None,
    rerank_local: bool = True,
    scale: float = 1.0,
    prefilter: str = default_conf['prefilter'],
    conf: dict | None = None,
    index: LandmarkIndex | None = None,
    center: bool | str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Offline retrieval of many queries against a stacked map (evaluation and validation).

    refs: LandmarkBatch of R map sets; allowed (Q, R) bool: which refs each query may be answered
    with (None = all); prefilter: the first stage (module doc), its top prefilter_k (0 = every ref:
    exhaustive, K = R). Returns ranked (Q, K) ref indices, best first, and their scores (Q, K): S
    after the first stage (the first-stage score when rerank_local is False); center: S's set
    centring (similarity.default_conf['center'] when None).
    Rows with fewer than K candidates are padded with index -1 and score -inf.
    """
    prefilter, prefilter_k = check_prefilter(prefilter, prefilter_k)
    k = min(prefilter_k, len(refs)) if prefilter_k else len(refs)
    top, top_s = first_stage(queries, refs, k, prefilter, allowed, conf, scale, index)
    if not rerank_local:
        return top, top_s
    ranked = np.full_like(top, -1)
    scores = np.full(top.shape, -np.inf, np.float32)
    for i, q in enumerate(queries):
        idx = top[i][top[i] >= 0]
        if not len(idx):
            continue
        s = match_batch(q, refs.take(idx), scale, center).scores
        order = np.argsort(-s, kind='stable')
        ranked[i, : len(idx)], scores[i, : len(idx)] = idx[order], s[order]
    return ranked, scores


def pair_regions(query: LandmarkSet, keyframe: LandmarkSet, pairs: dict) -> dict:
    """Matched landmark pairs as image regions, what a SLAM system constrains keypoint matching
    with. pairs: query_index, map_index, similarity, weight (arrays of M, as MatchResult.pairs).
    Returns those plus query_u, query_v, map_u, map_v (region centres, pixels of each image) and
    cell_w, cell_h (the keyframe's cell size; the query's is query.cell_size), all arrays of M."""
    qi = np.asarray(pairs.get('query_index', ()), np.int64)
    mi = np.asarray(pairs.get('map_index', ()), np.int64)
    m = len(qi)
    return {
        'query_index': qi,
        'map_index': mi,
        'query_u': query.centers[qi, 0].astype(np.float32),
        'query_v': query.centers[qi, 1].astype(np.float32),
        'map_u': keyframe.centers[mi, 0].astype(np.float32),
        'map_v': keyframe.centers[mi, 1].astype(np.float32),
        'cell_w': np.full(m, keyframe.cell_size[0], np.float32),
        'cell_h': np.full(m, keyframe.cell_size[1], np.float32),
        'similarity': np.asarray(pairs.get('similarity', ()), np.float32),
        'weight': np.asarray(pairs.get('weight', ()), np.float32),
    }


class LandmarkDatabase:
    """An in-memory map of landmark sets: a FAISS inner-product index of the global descriptors and
    a LandmarkIndex of every landmark (the first stages), keyed by position in `sets`."""

    def __init__(self, conf: dict | None = None):
        self.conf = {**default_conf, **(conf or {})}
        check_prefilter(self.conf['prefilter'], self.conf['prefilter_k'])
        self.sets: list[LandmarkSet] = []
        self.index: faiss.Index | None = None
        self.landmarks: LandmarkIndex | None = None
        self.descriptor_space: str | None = None

    def __len__(self) -> int:
        return len(self.sets)

    def add(self, sets: list[LandmarkSet]) -> None:
        for s in sets:
            s.validate()
            if self.descriptor_space is None:
                self.descriptor_space = s.descriptor_space
                self.index = faiss.IndexFlatIP(s.dim)
                self.landmarks = LandmarkIndex(s.dim, self.conf, s.descriptor_space)
            elif s.descriptor_space != self.descriptor_space or s.dim != self.index.d:
                raise DescriptorError(
                    f'map holds {self.descriptor_space!r} descriptors (D={self.index.d}); '
                    f'refusing {s.descriptor_space!r} (D={s.dim})'
                )
        if sets:
            self.index.add(np.stack([s.global_descriptor for s in sets]).astype(np.float32))
            self.landmarks.add_sets(range(len(self.sets), len(self.sets) + len(sets)), sets)
            self.sets.extend(sets)

    def holistic(self, query: LandmarkSet, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-k map indices by global-descriptor cosine, with their scores."""
        if not self.sets:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        self._check_query(query)
        scores, idx = self.index.search(query.global_descriptor[None].astype(np.float32), min(int(k), len(self.sets)))
        keep = idx[0] >= 0
        return idx[0][keep], scores[0][keep]

    def retrieve(
        self,
        query: LandmarkSet,
        prefilter_k: int | None = None,
        rerank_local: bool = True,
        prefilter: str | None = None,
    ) -> list[Candidate]:
        """The first stage's top K reranked by S (rerank_local=False: the first-stage ranking
        alone, its score as `score`); K = 0: every map entry."""
        prefilter, k = check_prefilter(
            prefilter or self.conf['prefilter'], self.conf['prefilter_k'] if prefilter_k is None else prefilter_k
        )
        if not self.sets:
            return []
        self._check_query(query)
        k = k or len(self.sets)
        if prefilter == 'landmarks':
            idx, first = self.landmarks.shortlist(query, k, scale=self.conf['scale'])
            idx, first = landmark_index.fill(idx, first, self.holistic(query, k)[0], k)
            hol = (
                np.stack([self.sets[i].global_descriptor for i in idx]).astype(np.float32)
                @ query.global_descriptor.astype(np.float32)
                if len(idx)
                else np.zeros(0, np.float32)
            )
        else:
            idx, hol = self.holistic(query, k)
            first = hol
        if not rerank_local:
            return [Candidate(int(i), float(f), float(h)) for i, f, h in zip(idx, first, hol)]
        if len(idx) == 0:
            return []
        return rerank(query, [self.sets[i] for i in idx], idx, hol, self.conf['scale'])

    def _check_query(self, query: LandmarkSet) -> None:
        query.validate()
        if query.dim != self.index.d or (query.descriptor_space and query.descriptor_space != self.descriptor_space):
            raise DescriptorError(
                f'query descriptors are {query.descriptor_space!r} (D={query.dim}); '
                f'the map holds {self.descriptor_space!r} (D={self.index.d})'
            )
