"""Two-stage retrieval: holistic top-K by cosine (FAISS), then rerank by the landmark similarity S.

    db = LandmarkDatabase()
    db.add(map_sets)                                   # list of LandmarkSet
    candidates = db.retrieve(query_set, prefilter_k=30)
    candidates[0].index, .score, .holistic_score, .pairs
"""
from __future__ import annotations

from dataclasses import dataclass, field

import faiss
import numpy as np

from .errors import DescriptorError
from .landmarks import LandmarkBatch, LandmarkSet, stack_landmarks
from .similarity import match_batch

default_conf = {
    'prefilter_k': 30,  # holistic candidates reranked by S (the paper's 30); 0 = every map entry
    'scale': 1.0,       # offset-weight Gaussian width, in grid cells
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


def rerank(query: LandmarkSet, batch: LandmarkBatch, indices: np.ndarray, holistic: np.ndarray,
           scale: float = 1.0, limit: int | None = None) -> list[Candidate]:
    """Score `batch` (the prefiltered candidates, in `indices` order) against the query; sort by S.
    limit: only the best `limit` come back (their pair tables are what costs, per candidate)."""
    result = match_batch(query, batch, scale)
    order = np.argsort(-result.scores, kind='stable')[:limit]
    return [Candidate(int(indices[k]), float(result.scores[k]), float(holistic[k]),
                      tuple(int(v) for v in result.offsets[k]), result.pairs(k)) for k in order]


def rank_all(queries: list[LandmarkSet], refs: LandmarkBatch, prefilter_k: int = 30,
             allowed: np.ndarray | None = None, rerank_local: bool = True,
             scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Offline retrieval of many queries against a stacked map (evaluation and validation).

    refs: LandmarkBatch of R map sets; allowed (Q, R) bool: which refs each query may be answered
    with (None = all); prefilter_k 0 = every ref (exhaustive rerank, K = R). Returns ranked (Q, K) ref indices, best first, and their scores (Q, K): S
    after the holistic top-K prefilter (or the holistic cosine when rerank_local is False).
    Rows with fewer than K allowed refs are padded with index -1 and score -inf.
    """
    k = min(int(prefilter_k), len(refs)) if int(prefilter_k) > 0 else len(refs)
    hol = np.stack([q.global_descriptor for q in queries]).astype(np.float32) @ refs.globals.T   # (Q, R)
    if allowed is not None:
        hol = np.where(allowed, hol, -np.inf)
    top = np.argsort(-hol, axis=1, kind='stable')[:, :k]                                         # (Q, K)
    top_hol = np.take_along_axis(hol, top, axis=1)
    ranked = np.full((len(queries), k), -1, np.int64)
    scores = np.full((len(queries), k), -np.inf, np.float32)
    for i, q in enumerate(queries):
        ok = np.isfinite(top_hol[i])
        idx = top[i][ok]
        if not len(idx):
            continue
        s = match_batch(q, refs.take(idx), scale).scores if rerank_local else top_hol[i][ok]
        order = np.argsort(-s, kind='stable')
        ranked[i, :len(idx)], scores[i, :len(idx)] = idx[order], s[order]
    return ranked, scores


def pair_regions(query: LandmarkSet, keyframe: LandmarkSet, pairs: dict) -> dict:
    """Matched landmark pairs as image regions, what a SLAM system constrains keypoint matching
    with. pairs: query_index, map_index, similarity, weight (arrays of M, as MatchResult.pairs).
    Returns those plus query_u, query_v, map_u, map_v (region centres, pixels of each image) and
    cell_w, cell_h (the keyframe's cell size; the query's is query.cell_size), all arrays of M."""
    qi = np.asarray(pairs.get('query_index', ()), np.int64)
    mi = np.asarray(pairs.get('map_index', ()), np.int64)
    m = len(qi)
    return {'query_index': qi, 'map_index': mi,
            'query_u': query.centers[qi, 0].astype(np.float32), 'query_v': query.centers[qi, 1].astype(np.float32),
            'map_u': keyframe.centers[mi, 0].astype(np.float32), 'map_v': keyframe.centers[mi, 1].astype(np.float32),
            'cell_w': np.full(m, keyframe.cell_size[0], np.float32),
            'cell_h': np.full(m, keyframe.cell_size[1], np.float32),
            'similarity': np.asarray(pairs.get('similarity', ()), np.float32),
            'weight': np.asarray(pairs.get('weight', ()), np.float32)}


class LandmarkDatabase:
    """An in-memory map of landmark sets with a FAISS inner-product index of the global descriptors."""

    def __init__(self, conf: dict | None = None):
        self.conf = {**default_conf, **(conf or {})}
        self.sets: list[LandmarkSet] = []
        self.index: faiss.Index | None = None
        self.descriptor_space: str | None = None

    def __len__(self) -> int:
        return len(self.sets)

    def add(self, sets: list[LandmarkSet]) -> None:
        for s in sets:
            s.validate()
            if self.descriptor_space is None:
                self.descriptor_space = s.descriptor_space
                self.index = faiss.IndexFlatIP(s.dim)
            elif s.descriptor_space != self.descriptor_space or s.dim != self.index.d:
                raise DescriptorError(f'map holds {self.descriptor_space!r} descriptors (D={self.index.d}); '
                                      f'refusing {s.descriptor_space!r} (D={s.dim})')
        if sets:
            self.index.add(np.stack([s.global_descriptor for s in sets]).astype(np.float32))
            self.sets.extend(sets)

    def holistic(self, query: LandmarkSet, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-k map indices by global-descriptor cosine, with their scores."""
        if not self.sets:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        self._check_query(query)
        scores, idx = self.index.search(query.global_descriptor[None].astype(np.float32),
                                        min(int(k), len(self.sets)))
        keep = idx[0] >= 0
        return idx[0][keep], scores[0][keep]

    def retrieve(self, query: LandmarkSet, prefilter_k: int | None = None,
                 rerank_local: bool = True) -> list[Candidate]:
        """Holistic top-K reranked by S (rerank_local=False: the holistic ranking alone); K = 0:
        every map entry."""
        k = int(self.conf['prefilter_k'] if prefilter_k is None else prefilter_k) or len(self.sets)
        idx, hol = self.holistic(query, k)
        if not rerank_local:
            return [Candidate(int(i), float(h), float(h)) for i, h in zip(idx, hol)]
        if len(idx) == 0:
            return []
        batch = stack_landmarks([self.sets[i] for i in idx])
        return rerank(query, batch, idx, hol, self.conf['scale'])

    def _check_query(self, query: LandmarkSet) -> None:
        query.validate()
        if query.dim != self.index.d or (query.descriptor_space and
                                         query.descriptor_space != self.descriptor_space):
            raise DescriptorError(f'query descriptors are {query.descriptor_space!r} (D={query.dim}); '
                                  f'the map holds {self.descriptor_space!r} (D={self.index.d})')
