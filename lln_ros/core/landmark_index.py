"""The landmark-level first stage: a FAISS index over every stored landmark descriptor, and the one
scoring of its hits that every path uses (offline rank_all / lln-eval, LandmarkDatabase, both map
backends, the matcher node, lln-demo).

    index = LandmarkIndex(dim=192, conf)
    index.add(descriptors (N, D), keyframe_ids (N,), cells (N, 2))
    ids, scores = index.shortlist(query_set, k=30, below=None)    # keyframe ids, first-stage scores

Why: the holistic (global max-pool) top-K misses most Nordland revisits across seasons (recall@30
0.30, docs/results.md), so the reranker never sees them. Landmark descriptors survive the season
change much better, and matching each query landmark against every map landmark has no such cap.

Scoring (score_hits) -- an approximation of the paper's S computed from the kNN hits only:
  0. centring (center, conf['landmark_center']): the index holds every landmark minus the mean of
     its keyframe's landmarks, renormalised (a query: minus its own mean), then whitened (W x,
     core.whitening). What every landmark of an image shares is its condition (snow, dusk), and
     raw cosines let it outvote the place in a map with winter views of other places;
  1. every query landmark i (the best conf['landmark_query_top'] by score) retrieves its `knn`
     nearest map landmarks by cosine s (FAISS);
  2. burstiness: a query landmark votes at most once per keyframe (its best hit there), and a map
     landmark takes at most one query landmark (its best); ASMK / DELF limit repeated structure
     the same way, so one textured patch (rails, sky, snow) cannot outvote the rest of the image;
  3. selectivity: a hit counts max(0, (s - tau) / (1 - tau))^alpha (ASMK's sigma_alpha with
     threshold tau): CNN features are non-negative, so every pair has a positive cosine and plain
     sums reward keyframes that are merely generic;
  4. spatial consistency, as S does: the mode of the query-minus-map cell offsets of a keyframe's
     hits (similarity.pair_offset_mode, offset_mode on a pair list) and Gaussian weights around it
     (similarity.offset_weights);
  5. the keyframe's score is sum_i w_i * sigma(s_i); the top K go to the exact reranker.

Landmark ids: FAISS holds one int64 per landmark, (keyframe_id << 24) | (row << 12) | col. The cell
is unique within a keyframe (a landmark is one grid cell), so a hit says where it is without any
side table, a keyframe's landmarks are one id range (delete = IDSelectorRange) and "older than
keyframe c" is ids < c << 24 (exclude_recent). Grids up to 4096 x 4096 cells, keyframe ids < 2^39.

Index type: exact (IndexIDMap2(IndexFlatIP)) up to conf['landmark_index_threshold'] landmarks
(the switch-over rule, commented in default_conf); above it conf['landmark_compressed']:
- 'ivfpq-fs-refine' (the default): IndexIVFPQFastScan with D/4 sub-quantisers of 4 bits (D/8 bytes
  per landmark, cheap to scan, so many more IVF cells can be probed: NPROBE) gives a shortlist of
  conf['landmark_k_factor'] x k, re-ranked by the cosine on a scalar-quantised copy of every vector
  (RefineCodes, conf['landmark_refine'], SQ8: D bytes): ~233 bytes per landmark with both ids; its
  recall against exact search, memory and time: default_conf;
- 'ivfpq-fs': IndexIVFPQFastScan, D sub-quantisers of 4 bits = D/2 bytes per landmark, scanned
  with SIMD register look-ups; a 100k-keyframe map (5M landmarks) at ~530 MB with ids;
- 'ivfpq': IndexIVFPQ, D/4 sub-quantisers of 8 bits = D/4 bytes (the oldest maps' format).
All are trained on (a sample of) the map's own descriptors, those of the keyframes up to the one
that crossed the threshold (so the index depends on the keyframe order only, not on how adds were
batched), and probe conf['landmark_nprobe'] (0: the kind's NPROBE) of their IVF cells; the query
landmarks that search (landmark_query_top) go to FAISS in one search call.
A compressed index grown past conf['landmark_retrain_factor'] x the landmarks it was trained on is
rebuilt by its owner (the map store) from the stored descriptors, and so is a file of another kind
(or centring, whitening, refine codes) than the conf asks for. Recall against exact search on
descriptors of real images, and the first stage on the Nordland test split per index type:
bench/bench_landmark_index.py (figures: docs/benchmarks.md, The landmark index, and default_conf).
"""

from __future__ import annotations

import logging

import faiss
import numpy as np

from . import landmark_index_file, whitening
from .refine_codes import RefineCodes
from .similarity import offset_weights, pair_offset_mode
from .threads import one_faiss_thread
from .whitening import center

log = logging.getLogger(__name__)

PREFILTERS = ('landmarks', 'holistic', 'exhaustive')

default_conf = {
    'landmark_knn': 20,  # map landmarks each query landmark retrieves
    # Query landmarks (the best by score) that search the index; 0 = all. The search scans per query
    # landmark and is most of a query at 100k keyframes; the rerank still uses every landmark.
    # Chosen on Nordland 0.6:0.7 (validation) padded to 10k keyframes with real distractors
    # (bench/bench_accuracy_at_scale.py --range 0.6:0.7 --sizes 0,10000 --landmark-query-top N),
    # N = 0 / 35 / 25: lln 0.459 / 0.462 / 0.462 plain, 0.176 / 0.174 / 0.168 at 10k; lln+seq
    # 0.933 / 0.936 / 0.950 plain, 0.927 / 0.927 / 0.930 at 10k. Frame to answer at 100k keyframes
    # (bench_frame_to_answer.py, quiet p50, two passes): 37.9 / 34.7, 36.6 / 31.5, 30.4 / 27.7 ms.
    'landmark_query_top': 25,
    # Landmarks of each keyframe (its best by score, after centring on all of them) the index holds;
    # 0 = all. The rerank still uses every stored landmark. 25 (since 2026-12-07, with the SQ8-refined
    # kind below): half the memory, which pays for the re-ranking codes (recall and time below).
    # Validation part in a 10k map (bench_accuracy_at_scale --range 0.6:0.7, nprobe 48): lln 0.168 ->
    # 0.185, lln+seq 0.930 -> 0.933, first stage R@30 0.549 -> 0.552; the 357-keyframe map's
    # unchanged (0.462 / 0.950). docs/benchmarks.md, "HNSW, and a cheaper ...".
    'landmark_index_top': 25,
    # Centre each keyframe's landmarks (and the query's) on their own mean before indexing, then
    # renormalise: what all landmarks of one image share (snow, dusk, the camera's colour) is the
    # condition, not the place. Chosen with tau on Nordland 0.6:0.7 (validation) among 8,927 real
    # distractors: first-stage R@100 0.429 -> 0.546 (raw at tau 0.35 -> centred at 0), references
    # alone R@1 0.342 -> 0.459 (bench/bench_first_stage_scale.py --range 0.6:0.7, docs/benchmarks.md,
    # Accuracy at scale). False: the raw descriptors.
    'landmark_center': True,
    # then x -> W x, renormalised, with the descriptor space's shipped whitening (core.whitening: the
    # directions in which one place's landmarks change between visits count less); none ships: no-op
    'landmark_whitening': True,
    'landmark_tau': 0.0,  # cosine below which a hit does not vote (0.35 on raw, uncentred descriptors)
    'landmark_alpha': 3.0,  # selectivity exponent of a hit's vote
    # Switch-over rule: exact search (IndexFlatIP: recall 1, D multiply-adds per query landmark and
    # map landmark) while the index holds at most this many landmarks (~400 keyframes at n=50),
    # compressed (landmark_compressed) above it. Exact cost grows with the map: 50 query landmarks
    # against 20k landmarks took 118 ms of one core under load 14 on this 2-core machine, 100k 1.1 s.
    'landmark_index_threshold': 20_000,
    # above the threshold (module doc, Index type): 'ivfpq-fs' (IVF + 4-bit PQ fast-scan), 'ivfpq-fs-refine'
    # (IVF + a coarser 4-bit PQ fast-scan shortlist of landmark_k_factor x knn, re-ranked on
    # landmark_refine codes) or 'ivfpq' (IVF + 8-bit PQ, the oldest format). A file of another kind
    # than this is rebuilt by its map store. 'ivfpq-fs-refine' with SQ8 codes, each keyframe's best 25
    # (landmark_index_top), nprobe 56 and a shortlist of 4 x knn is the default since 2026-12-07: at
    # 100k keyframes (2.5M landmarks, 233 bytes each, 583 MB) it finds the exact top-1 neighbour of
    # 0.908 of the 25 query landmarks (top 20: 0.755) in 4.7 ms a frame, where 'ivfpq-fs' with all 50
    # (5M landmarks, 106 bytes, 530 MB), the default before, found 0.682 (0.714) in 4.0 ms, and in
    # 6.9 ms with all 50 query landmarks, as when issue 30 was filed (bench_landmark_index, one call
    # per frame, AVX-512 EPYC). HNSW reached 0.904 only at 2x the time and 464 bytes (and
    # FAISS's HNSW cannot delete), so it is not a kind here.
    'landmark_compressed': 'ivfpq-fs-refine',
    'landmark_retrain_factor': 8,  # a compressed index grown past this x its training size is rebuilt
    'landmark_ivf_lists': 0,  # 0 = sqrt(landmarks x sqrt(retrain factor)), in [64, 4096], <= landmarks / 39
    'landmark_nprobe': 0,  # IVF cells visited per query landmark; 0 = the kind's (NPROBE)
    # PQ sub-quantisers; 0 = the kind's (PQ_M): D at 4 bits (ivfpq-fs: D/2 bytes per landmark; D/2
    # of them lost 2 points of Nordland R@10 against 'ivfpq', D kept every R@K at or above it), D / 4
    # at 8 bits (ivfpq), D / 4 at 4 bits (ivfpq-fs-refine: only a shortlist, re-ranked)
    'landmark_pq_m': 0,
    'landmark_refine': 'SQ8',  # ivfpq-fs-refine: the re-ranking's codes (FAISS SQ: SQ4|SQ6|SQ8|fp16)
    # ivfpq-fs-refine: the fast-scan shortlist is k_factor x the k asked for. At nprobe 56, 4: recall@1
    # 0.908 in 4.7 ms, 3: 0.898 / 4.4 (benchmarks.md, the scan)
    'landmark_k_factor': 4,
    'landmark_pq_bits': 8,  # bits per sub-quantiser code of 'ivfpq' (fast-scan codes are always 4 bits)
    'landmark_train_points': 100_000,  # sample the compressed index is trained on
}
COMPRESSED = ('ivfpq-fs-refine', 'ivfpq-fs', 'ivfpq')
# landmark_nprobe 0: ivfpq-fs-refine 56 (SQ8, best 25, k_factor 4, 100k keyframes: recall@1 0.802 /
# 0.896 / 0.908 / 0.916 at 16 / 48 / 56 / 64 in 2.7-5.0 ms per 25 query landmarks; benchmarks.md)
NPROBE = {'ivfpq-fs-refine': 56, 'ivfpq-fs': 16, 'ivfpq': 16}
PQ_M = {'ivfpq-fs-refine': 4, 'ivfpq-fs': 1, 'ivfpq': 4}  # landmark_pq_m 0: D / this

_CELL_BITS = 12
_KF_SHIFT = 2 * _CELL_BITS
_MAX_CELL = 1 << _CELL_BITS


def check_prefilter(prefilter: str, prefilter_k: int) -> tuple[str, int]:
    """(prefilter, K) after the backward-compatible rule: prefilter_k 0 means exhaustive whatever
    `prefilter` says (older configs wrote `prefilter_k: 0` for "score every keyframe")."""
    if prefilter not in PREFILTERS:
        raise ValueError(f'prefilter must be one of {"|".join(PREFILTERS)}, got {prefilter!r}')
    if int(prefilter_k) < 0:
        raise ValueError(f'need prefilter_k >= 0 (0 = every keyframe), got {prefilter_k}')
    return ('exhaustive' if int(prefilter_k) == 0 else prefilter), int(prefilter_k)


def held_count(stored: int, conf: dict) -> int:
    """Landmarks an index of `conf` holds for a keyframe of `stored` landmarks (landmark_index_top)."""
    top = int(conf.get('landmark_index_top', default_conf['landmark_index_top']))
    return min(int(stored), top) if top > 0 else int(stored)


def encode_ids(keyframe_ids: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """int64 landmark ids from keyframe ids (N,) and cells (N, 2) as (col, row)."""
    kf = np.asarray(keyframe_ids, np.int64)
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    if len(cells) and (cells.min() < 0 or cells.max() >= _MAX_CELL):
        raise ValueError(f'landmark cells must be in [0, {_MAX_CELL}) for the landmark index')
    if len(kf) and (kf.min() < 0 or kf.max() >= 1 << (63 - _KF_SHIFT)):
        raise ValueError('keyframe ids must be in [0, 2^39) for the landmark index')
    return (kf << _KF_SHIFT) | (cells[:, 1] << _CELL_BITS) | cells[:, 0]


def decode_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(keyframe ids, cells (..., 2) as (col, row)) from landmark ids; -1 ids give keyframe -1."""
    ids = np.asarray(ids, np.int64)
    kf = np.where(ids >= 0, ids >> _KF_SHIFT, -1)
    cells = np.stack([ids & (_MAX_CELL - 1), (ids >> _CELL_BITS) & (_MAX_CELL - 1)], axis=-1)
    return kf, cells


def score_hits(
    query_cells: np.ndarray,
    sims: np.ndarray,
    keyframes: np.ndarray,
    map_cells: np.ndarray,
    conf: dict,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """First-stage score of every keyframe hit (see the module doc).

    query_cells (n, 2) (col, row) of the query landmarks; sims (n, k) cosines of each one's k hits;
    keyframes (n, k) keyframe id of each hit (-1 = no hit); map_cells (n, k, 2) cell of each hit.
    Returns keyframe ids (M,) and scores (M,), best first (ties: the newer keyframe first, as an
    online map prefers the latest view of a place)."""
    conf = {**default_conf, **conf}
    n, k = sims.shape
    qi = np.repeat(np.arange(n), k)
    kf, s = keyframes.reshape(-1), sims.reshape(-1).astype(np.float32)
    mc = map_cells.reshape(-1, 2).astype(np.int64)
    tau = float(conf['landmark_tau'])
    keep = (kf >= 0) & (s > tau)
    qi, kf, s, mc = qi[keep], kf[keep], s[keep], mc[keep]
    if not len(kf):
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    # burstiness: best hit per (query landmark, keyframe), then per (keyframe, map landmark)
    order = np.lexsort((-s, qi, kf))
    qi, kf, s, mc = qi[order], kf[order], s[order], mc[order]
    first = np.ones(len(kf), bool)
    first[1:] = (kf[1:] != kf[:-1]) | (qi[1:] != qi[:-1])
    qi, kf, s, mc = qi[first], kf[first], s[first], mc[first]
    cell_code = mc[:, 1] * _MAX_CELL + mc[:, 0]
    order = np.lexsort((-s, cell_code, kf))
    qi, kf, s, mc, cell_code = qi[order], kf[order], s[order], mc[order], cell_code[order]
    first = np.ones(len(kf), bool)
    first[1:] = (kf[1:] != kf[:-1]) | (cell_code[1:] != cell_code[:-1])
    qi, kf, s, mc = qi[first], kf[first], s[first], mc[first]
    # per keyframe hit: the mode of its pairs' offsets, as S takes it, from the pair list (a sort of
    # the <= n*k pairs; dense keyframe x query-landmark tables cost 10x more at knn 200)
    uniq, row = np.unique(kf, return_inverse=True)
    offsets = np.asarray(query_cells, np.int64)[qi] - mc  # (P, 2)
    mode = pair_offset_mode(row, offsets, s, len(uniq), n)
    weight = offset_weights(offsets[:, None, :], mode[row], scale)[:, 0]  # (P,)
    vote = np.clip((s - tau) / (1.0 - tau), 0.0, None) ** float(conf['landmark_alpha'])
    scores = np.bincount(row, weights=weight * vote, minlength=len(uniq)).astype(np.float32)
    best = np.lexsort((-uniq, -scores))
    return uniq[best], scores[best]


def fill(ids: np.ndarray, scores: np.ndarray, holistic_ids: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The landmark shortlist (ids (M,), scores (M,)) topped up to k from the holistic ranking
    (holistic_ids, best first), the added ones with first-stage score 0: when few landmarks clear
    tau (a small map, or a query with little texture), the reranker still sees k candidates."""
    if len(ids) >= k:
        return ids[:k], scores[:k]
    extra = np.asarray([i for i in holistic_ids if i not in set(ids.tolist())], np.int64)[: k - len(ids)]
    return np.concatenate([ids, extra]).astype(np.int64), np.concatenate(
        [scores, np.zeros(len(extra), np.float32)]
    ).astype(np.float32)


class LandmarkIndex:
    """FAISS inner-product index of landmark descriptors (D,), ids as encode_ids (module doc).
    With conf['landmark_center'] it holds center()ed descriptors: every entry point that takes stored
    descriptors (add, build, train) centres them by keyframe, and search centres the query."""

    def __init__(self, dim: int, conf: dict | None = None, space: str = ''):
        """space: the descriptor space ('backbone/layer/D'), which picks the shipped whitening."""
        self.dim = int(dim)
        self.conf = {**default_conf, **(conf or {})}
        self.whitening = whitening.shipped(space) if self.conf['landmark_whitening'] and space else None
        self.index = self._exact()
        self.refine: RefineCodes | None = None  # the re-ranking codes of 'ivfpq-fs-refine'
        self.trained_on = 0  # landmarks the IVF-PQ was trained on (0: exact)

    def _exact(self):
        return faiss.IndexIDMap2(faiss.IndexFlatIP(self.dim))

    @property
    def kind(self) -> str:
        """'exact', 'ivfpq-fs-refine', 'ivfpq-fs' or 'ivfpq' (module doc)."""
        if isinstance(self.index, faiss.IndexIVFPQFastScan):
            return 'ivfpq-fs' if self.refine is None else 'ivfpq-fs-refine'
        return 'ivfpq' if isinstance(self.index, faiss.IndexIVF) else 'exact'

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal)

    def __len__(self) -> int:
        return self.ntotal

    # ------------------------------------------------------------------ building
    def train_stride(self, total: int) -> int:
        """A store trains the index of `total` landmarks on every this-th keyframe (~landmark_train_points)."""
        return max(1, int(total) // max(1, int(self.conf['landmark_train_points'])))

    def train(self, sample: list[np.ndarray], total: int) -> None:
        """Make this an empty compressed index trained on prepare()d sample parts (each (n, D)), sized
        for `total` landmarks, that the store then streams every stored landmark into."""
        self.index = self._compressed(np.concatenate(sample), total)

    def _compressed(self, x: np.ndarray, total: int | None = None):
        """An empty compressed index (conf['landmark_compressed']) trained on x (N, D) (a sample of
        what it will hold: prepare()d vectors), sized for `total` landmarks (N)."""
        n = int(total or len(x))
        # sized for the geometric middle of the sizes it holds before its retrain (n .. factor x n),
        # not for n: a map that grows 8x on 8x fewer lists scans 8x more codes per probe at the end
        middle = n * np.sqrt(max(1.0, float(self.conf['landmark_retrain_factor'])))
        lists = int(self.conf['landmark_ivf_lists']) or int(max(1, min(np.clip(np.sqrt(middle), 64, 4096), n // 39)))
        kind = self.conf['landmark_compressed']
        if kind not in COMPRESSED:
            raise ValueError(f'landmark_compressed must be one of {"|".join(COMPRESSED)}, got {kind!r}')
        fast = kind != 'ivfpq'
        m = int(self.conf['landmark_pq_m']) or max(1, self.dim // PQ_M[kind])
        if self.dim % m:
            raise ValueError(f'landmark_pq_m {m} must divide the descriptor size {self.dim}')
        if fast:
            index = faiss.IndexIVFPQFastScan(
                faiss.IndexFlatIP(self.dim), self.dim, lists, m, 4, faiss.METRIC_INNER_PRODUCT
            )
        else:
            index = faiss.IndexIVFPQ(
                faiss.IndexFlatIP(self.dim),
                self.dim,
                lists,
                m,
                int(self.conf['landmark_pq_bits']),
                faiss.METRIC_INNER_PRODUCT,
            )
        index.cp.max_points_per_centroid = 64
        rng = np.random.default_rng(0)
        sample = (
            x
            if len(x) <= self.conf['landmark_train_points']
            else x[np.sort(rng.choice(len(x), int(self.conf['landmark_train_points']), replace=False))]
        )
        # one_faiss_thread: a 2,000-landmark training under load took over 10 minutes with two
        refine = RefineCodes(self.dim, self.conf['landmark_refine']) if kind == 'ivfpq-fs-refine' else None
        with one_faiss_thread():
            index.train(np.ascontiguousarray(sample, np.float32))
            if refine is not None:
                refine.train(sample)
        index.nprobe = self.nprobe(kind)
        self.trained_on = n
        self.refine = refine
        return index

    def nprobe(self, kind: str | None = None) -> int:
        """IVF cells visited per query landmark: conf['landmark_nprobe'], or the kind's (NPROBE)."""
        return int(self.conf['landmark_nprobe']) or NPROBE.get(kind or self.kind, 16)

    def _add(self, index, x: np.ndarray, ids: np.ndarray) -> None:
        index.add_with_ids(x, ids)
        if self.refine is not None and isinstance(index, faiss.IndexIVF):
            self.refine.add(x, ids)

    def prepare(
        self, descriptors: np.ndarray, keyframe_ids: np.ndarray | None = None, held: bool = False
    ) -> np.ndarray:
        """The vectors this index holds for stored descriptors (N, D) of keyframe_ids (N,) (None =
        one keyframe or one query): centre()d when conf['landmark_center'], then whitened (W x,
        renormalised) when the index has a whitening, else as given. held: only the rows the index
        holds (held_rows), after centring on all of them."""
        x = np.ascontiguousarray(descriptors, np.float32).reshape(-1, self.dim)
        if self.conf['landmark_center']:
            x = center(x, keyframe_ids)
        if held:
            x = x[self.held_rows(np.zeros(len(x), np.int64) if keyframe_ids is None else keyframe_ids)]
        return x if self.whitening is None else whitening.apply(x, self.whitening)

    def held_rows(self, keyframe_ids: np.ndarray) -> np.ndarray:
        """bool (N,): which of a keyframe's stored landmarks (N,), in stored order (best score
        first, as the extractor ranks them), the index holds: the first conf['landmark_index_top']."""
        kf = np.asarray(keyframe_ids, np.int64).reshape(-1)
        top = int(self.conf['landmark_index_top'])
        if top <= 0 or not len(kf):
            return np.ones(len(kf), bool)
        starts = np.r_[True, kf[1:] != kf[:-1]]  # a keyframe's landmarks come together
        first = np.maximum.accumulate(np.where(starts, np.arange(len(kf)), 0))
        return np.arange(len(kf)) - first < top

    def needs_rebuild(self) -> bool:
        """An IVF-PQ trained on far fewer landmarks than it now holds (its cells are overfull and
        every query scans more): the owner rebuilds it from the stored descriptors."""
        return self.kind != 'exact' and self.ntotal > self.conf['landmark_retrain_factor'] * max(self.trained_on, 1)

    def build(self, x: np.ndarray, ids: np.ndarray, prepared: bool = False) -> None:
        """Replace the contents with stored descriptors x (N, D) under landmark ids (N,), choosing
        the type (prepared: x is already what the index holds, see prepare)."""
        ids = np.ascontiguousarray(ids, np.int64)
        x = np.ascontiguousarray(x, np.float32).reshape(-1, self.dim)
        if not prepared:
            kf = decode_ids(ids)[0]
            x, ids = self.prepare(x, kf, held=True), ids[self.held_rows(kf)]
        if len(ids) > self.conf['landmark_index_threshold']:
            index = self._compressed(x)
        else:
            index, self.refine = self._exact(), None
        for start in range(0, len(ids), 200_000):
            self._add(index, x[start : start + 200_000], ids[start : start + 200_000])
        self.index = index

    def add(self, descriptors: np.ndarray, keyframe_ids: np.ndarray, cells: np.ndarray) -> None:
        """Add landmarks: descriptors (N, D), their keyframe ids (N,) and cells (N, 2)."""
        keyframe_ids = np.asarray(keyframe_ids, np.int64).reshape(-1)
        x = self.prepare(np.asarray(descriptors, np.float32).reshape(-1, self.dim), keyframe_ids, held=True)
        held = self.held_rows(keyframe_ids)
        keyframe_ids, ids = keyframe_ids[held], encode_ids(keyframe_ids, cells)[held]
        threshold = int(self.conf['landmark_index_threshold'])
        if self.kind == 'exact' and self.ntotal + len(ids) > threshold:
            # Train on the landmarks up to the end of the keyframe that crosses the threshold, not on
            # the whole call: the index then depends only on the order of the keyframes, never on
            # how they were batched, so lln-eval's one add of a whole map gives the index a matcher
            # grew keyframe by keyframe (the main job's online == offline comparison).
            ends = np.append(np.flatnonzero(np.diff(keyframe_ids)) + 1, len(ids))
            p = int(ends[np.searchsorted(ends, threshold - self.ntotal + 1)])
            old = self.index.index.reconstruct_n(0, self.ntotal) if self.ntotal else np.zeros((0, self.dim), np.float32)
            old_ids = faiss.vector_to_array(self.index.id_map).astype(np.int64)
            log.info('landmark index passed %d landmarks: training %s', threshold, self.conf['landmark_compressed'])
            self.build(np.concatenate([old, x[:p]]), np.concatenate([old_ids, ids[:p]]), prepared=True)
            x, ids = x[p:], ids[p:]
            if not len(ids):
                return
        self._add(self.index, x, ids)

    def add_sets(self, keyframe_ids, sets) -> None:
        """Add every landmark of the LandmarkSets `sets`, stored under `keyframe_ids`."""
        if not len(sets):
            return
        desc = np.concatenate([np.asarray(s.descriptors, np.float32) for s in sets])
        kf = np.concatenate([np.full(len(s), int(i), np.int64) for i, s in zip(keyframe_ids, sets)])
        self.add(desc, kf, np.concatenate([np.asarray(s.cells).reshape(-1, 2) for s in sets]))

    def remove_keyframes(self, keyframe_ids) -> int:
        """Drop every landmark of these keyframes; returns how many landmarks went."""
        kids = sorted({int(i) for i in keyframe_ids})
        if self.refine is not None and kids:
            held = self.refine.ids
            self.refine.remove(held[np.isin(decode_ids(held)[0], kids)])
        if len(kids) > 4:  # one pass over the index for many keyframes, not one per keyframe
            held = self.landmark_ids()
            drop = np.ascontiguousarray(held[np.isin(decode_ids(held)[0], kids)])
            return int(self.index.remove_ids(drop)) if len(drop) else 0
        removed = 0
        for kid in kids:
            removed += int(self.index.remove_ids(faiss.IDSelectorRange(kid << _KF_SHIFT, (kid + 1) << _KF_SHIFT)))
        return removed

    def reset(self) -> None:
        self.index, self.refine = self._exact(), None

    # ------------------------------------------------------------------ reading
    def landmark_ids(self) -> np.ndarray:
        """Every landmark id held (unsorted), for the consistency check against the store."""
        if self.kind == 'exact':
            return faiss.vector_to_array(self.index.id_map).astype(np.int64)
        lists = self.index.invlists
        out = [
            faiss.rev_swig_ptr(lists.get_ids(c), lists.list_size(c)).copy()
            for c in range(lists.nlist)
            if lists.list_size(c)
        ]
        return np.concatenate(out).astype(np.int64) if out else np.zeros(0, np.int64)

    def keyframe_counts(self) -> dict[int, int]:
        """{keyframe id: landmarks held}."""
        kf, _ = decode_ids(self.landmark_ids())
        ids, counts = np.unique(kf, return_counts=True)
        return dict(zip(ids.tolist(), counts.tolist()))

    def search(self, descriptors: np.ndarray, k: int, below: int | None = None, top: int = 0):
        """kNN of each query landmark: sims (n, k), keyframe ids (n, k) (-1 = none), cells (n, k, 2).
        below: only keyframes with id < below (exclude_recent). descriptors (N, D) are one query's
        (centred together when conf['landmark_center']); top > 0: only the first `top` of them search
        (n = min(N, top)), still centred on the mean of all N as the map's keyframes are."""
        q = self.prepare(np.asarray(descriptors, np.float32).reshape(-1, self.dim))
        sims, ids = self.search_prepared(q[: int(top)] if top > 0 else q, k, below)
        kf, cells = decode_ids(ids)
        return sims, kf, cells

    def search_prepared(self, q: np.ndarray, k: int, below: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """sims (n, k) and landmark ids (n, k) (-1 = none) of vectors q (n, D) as the index holds them
        (prepare()d), in one FAISS call (+ the re-ranking of 'ivfpq-fs-refine')."""
        params = None
        if below is not None:
            sel = faiss.IDSelectorRange(0, int(below) << _KF_SHIFT)
            params = (
                faiss.SearchParametersIVF(sel=sel, nprobe=self.index.nprobe)
                if self.kind != 'exact'
                else faiss.SearchParameters(sel=sel)
            )
        k = int(k)
        wide = k if self.refine is None else min(k * int(self.conf['landmark_k_factor']), max(self.ntotal, k))
        with one_faiss_thread():
            sims, ids = self.index.search(q, wide, params=params)
        if self.refine is not None:
            sims, ids = self.refine.rerank(q, ids, k)
        return sims, ids

    def shortlist(self, query, k: int, below: int | None = None, scale: float = 1.0):
        """The first stage: the top k keyframe ids (K,) and their first-stage scores (K,) for a query
        LandmarkSet; fewer when fewer keyframes were hit."""
        if not self.ntotal or not len(query):
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        top = int(self.conf['landmark_query_top'])
        sims, kf, cells = self.search(query.descriptors, min(int(self.conf['landmark_knn']), self.ntotal), below, top)
        ids, scores = score_hits(np.asarray(query.cells)[: len(sims)], sims, kf, cells, self.conf, scale)
        return ids[: int(k)], scores[: int(k)]

    # ------------------------------------------------------------------ persistence (IVF-PQ maps)
    def write(self, path: str, header: dict) -> None:
        """Serialise to path atomically (landmark_index_file.write: the file format)."""
        landmark_index_file.write(self, path, header)

    @classmethod
    def read(cls, path: str, dim: int, conf: dict | None = None, space: str = '') -> tuple['LandmarkIndex', dict]:
        """(index, header) from a file `write` made (landmark_index_file.read); MapError naming the
        problem when it is unusable or not what `conf` asks for (its owner rebuilds it)."""
        return landmark_index_file.read(cls, path, dim, conf, space)
