"""The persistent map behind the matcher node: keyframes' landmark sets, embedded or in Milvus.

    with MapStore.open('~/.ros/lln/map.db', model=extractor.model_info) as store:
        kf = store.add(landmarks, stamp=(sec, nanosec))           # durable when it returns
        for c in store.query(landmarks, exclude_recent=20):       # online loop closure
            c.keyframe_id, c.score, c.stamp, c.pairs['map_u'], ...

No rclpy here: the node wraps this class, tests use it directly. ``MapStore(uri)`` returns the
backend the URI names (backend_for): a plain path is the embedded SQLiteMapStore below;
``milvus://host:port`` and ``milvus-lite:///path.db`` are MilvusMapStore (lln_ros/mapstore_milvus.py).
Both have the API listed in MapStore's docstring and pass one test suite (test/test_map_backends.py).

Storage
-------
One SQLite file in WAL mode with ``synchronous=FULL``: ``add`` commits one transaction and fsyncs
the WAL before it returns, so an acknowledged keyframe survives ``kill -9`` and power loss. New files
are built under a temporary name and linked into place, so a file at the map path is always either a
complete map or not ours (never half-created). Schema version 1::

    meta       key TEXT PRIMARY KEY, value TEXT
               format='lln_ros-map', schema_version='1', created (unix s), created_by,
               model (JSON of Extractor.model_info, or {descriptor_space, descriptor_dim}; written on
               first use), descriptor_space, descriptor_dim
    keyframes  id INTEGER PRIMARY KEY AUTOINCREMENT   -- never reused, not even after clear()
               stamp_sec INTEGER, stamp_nanosec INTEGER
               image_w REAL, image_h REAL              -- original image pixels
               grid_rows INTEGER, grid_cols INTEGER
               cell_w REAL, cell_h REAL                -- one grid cell in original pixels
               n INTEGER                               -- number of landmarks (>= 1)
               global_descriptor BLOB                  -- float32 little-endian (D,)
    landmarks  keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE
               cells BLOB        -- int16 LE (n, 2), (col, row)
               centers BLOB      -- float32 LE (n, 2), (u, v) region centre in original pixels
               scores BLOB       -- float32 LE (n,)
               descriptors BLOB  -- float16 LE (n, D), L2-normalised (float16: ~1e-3 relative)
    keypoints  (optional, created by the first add_keypoints; for the matcher's verify mode)
               keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE
               n INTEGER, uv BLOB (float32 LE (n, 2), original pixels), descriptors BLOB (uint8 (n, B))
               -- 40 bytes per ORB keypoint (B = 32): 20 KB per keyframe at 500 keypoints

All landmarks of a keyframe are one row (a row per landmark would be ~50x more rows and far slower to
insert and fetch). ``landmarks`` is its own table so the scan at open, which rebuilds the FAISS index,
reads only the small ``keyframes`` rows; the large ``descriptors`` blob is the LAST column so the small
blobs are read without touching its overflow pages. The activation map and ``LandmarkSet.meta`` are
not stored.

Bytes per keyframe at n=50 with the default model (D=192): blobs 768 (global) + 19,200
(descriptors) + 200 (cells) + 400 (centers) + 200 (scores) = 20,768; measured 21.3 KB per keyframe in a
1,000-keyframe .db file after a checkpoint. At D=320 the blobs are 34,080
and the .db file measured ~34.7-34.9 KB per keyframe after a checkpoint (4 KiB pages; record
headers, b-tree and overflow-page slack add ~2%). float32 descriptors would double the descriptor
part.

Migrations: ``MIGRATIONS[v]`` upgrades a map from schema v to v+1 inside one transaction at open.
A map newer than this code is refused, never modified.

In memory: a FAISS index over the global descriptors, keyed by keyframe id (GlobalIndex): exact
(``IndexIDMap(IndexFlatIP(D))``) up to ``conf['index_threshold']`` keyframes (50,000), IVF above
(``IndexIVFFlat``, trained on the map's own descriptors at open, ~1 s at 100k). It is rebuilt from
SQLite at open and checked against it (count and ids); nothing but SQLite is ever written, so there
is no second file to disagree with after a crash. Landmarks stay on disk; a query
fetches the prefiltered keyframes' landmarks with one ``SELECT ... WHERE id IN (...)``. If another
connection (another process) commits to the file, the next call notices (``PRAGMA data_version``)
and rebuilds the index.

Thread safety: every call takes one lock (the connection is shared, ``check_same_thread=False``);
the landmark reranking of ``query`` runs outside the lock.
"""
from __future__ import annotations

import abc
import contextlib
import json
import logging
import os
import sqlite3
import struct
import threading
import time
import uuid
from dataclasses import dataclass, field

import faiss
import numpy as np

from . import landmark_index
from .errors import DescriptorError, MapError
from .landmark_index import LandmarkIndex, check_prefilter
from .landmarks import LandmarkSet, stack_landmarks
from .retrieval import Candidate, default_conf as retrieval_conf, pair_regions, rerank

log = logging.getLogger(__name__)

FORMAT = 'lln_ros-map'
SCHEMA_VERSION = 1
SQLITE_MAGIC = b'SQLite format 3\x00'

SCHEMA = """
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE keyframes (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    stamp_sec         INTEGER NOT NULL,
    stamp_nanosec     INTEGER NOT NULL,
    image_w           REAL    NOT NULL,
    image_h           REAL    NOT NULL,
    grid_rows         INTEGER NOT NULL,
    grid_cols         INTEGER NOT NULL,
    cell_w            REAL    NOT NULL,
    cell_h            REAL    NOT NULL,
    n                 INTEGER NOT NULL,
    global_descriptor BLOB    NOT NULL
);
CREATE TABLE landmarks (
    keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
    cells       BLOB NOT NULL,
    centers     BLOB NOT NULL,
    scores      BLOB NOT NULL,
    descriptors BLOB NOT NULL
);
"""

# schema version v -> function(conn) that upgrades a v map to v + 1 (called inside a transaction)
MIGRATIONS: dict = {}

_KF_COLS = 'k.id, k.stamp_sec, k.stamp_nanosec, k.image_w, k.image_h, k.grid_rows, k.grid_cols, ' \
           'k.cell_w, k.cell_h, k.n, k.global_descriptor'
_LM_COLS = 'l.cells, l.centers, l.scores, l.descriptors'
_KF_INSERT = ('stamp_sec, stamp_nanosec, image_w, image_h, grid_rows, grid_cols, cell_w, cell_h, n, '
              'global_descriptor')
_SQL_CHUNK = 900  # ids per IN (...) list, below SQLite's oldest variable limit (999)


@dataclass
class MapCandidate:
    """A map keyframe proposed for a query.

    score: the landmark similarity S (the holistic cosine when reranking is off); holistic_score:
    global-descriptor cosine; stamp (sec, nanosec) of the keyframe; offset (dx, dy): the mode of
    the query-minus-map cell offsets, in grid cells; cell_size / image_size (w, h) of the keyframe.
    pairs: the M mutually matched landmark regions, a dict of arrays of length M:
        query_index, map_index   landmark indices in the query set and the keyframe's set
        query_u, query_v         region centre in the query image, pixels
        map_u, map_v             region centre in the keyframe image, pixels
        cell_w, cell_h           region size in the keyframe image, pixels (the query's region is
                                 the query set's cell_size; equal when the images are the same size)
        similarity               cosine of the pair
        weight                   spatial-consistency weight of the pair
    """
    keyframe_id: int
    score: float
    holistic_score: float
    stamp: tuple
    offset: tuple = (0, 0)
    cell_size: tuple = (0.0, 0.0)
    image_size: tuple = (0.0, 0.0)
    pairs: dict = field(default_factory=dict)

    @property
    def n_pairs(self) -> int:
        return len(self.pairs.get('query_index', ()))


def _describe(model: dict | None) -> str:
    if not model:
        return '<none>'
    text = f"{model.get('descriptor_space')!r} (D={model.get('descriptor_dim')}"
    if model.get('weights'):
        text += f", weights {model['weights']}"
    return text + ')'


def _stamp(stamp) -> tuple[int, int]:
    """(sec, nanosec) from a tuple or anything with .sec and .nanosec (builtin_interfaces/Time)."""
    if hasattr(stamp, 'sec') and hasattr(stamp, 'nanosec'):
        sec, nsec = stamp.sec, stamp.nanosec
    else:
        try:
            sec, nsec = stamp
        except (TypeError, ValueError):
            raise ValueError(f'stamp must be (sec, nanosec) or a builtin_interfaces/Time, got {stamp!r}') from None
    sec, nsec = int(sec), int(nsec)
    if not 0 <= nsec < 1_000_000_000:
        raise ValueError(f'stamp nanosec must be in [0, 1e9), got {nsec}')
    return sec, nsec


def backend_for(uri) -> tuple[str, str]:
    """('sqlite' | 'milvus', location) for a map URI.

    plain path or sqlite:///path        the embedded backend (SQLite file + in-memory FAISS)
    milvus://host:port[/db][?map=name]  a Milvus server or cluster
    milvus-lite:///path.db              Milvus Lite, the embedded Milvus (a directory at path.db)
    an existing Milvus Lite directory   Milvus Lite (it holds LOCK, collections/, databases/)
    """
    text = os.fspath(uri)
    if text.startswith('sqlite://'):
        return 'sqlite', text[len('sqlite://'):]
    if text.startswith(('milvus://', 'milvus-lite:')):
        return 'milvus', text
    path = os.path.abspath(os.path.expanduser(text))
    if os.path.isdir(path) and os.path.isdir(os.path.join(path, 'collections')):
        return 'milvus', 'milvus-lite://' + path
    return 'sqlite', text


class GlobalIndex:
    """The in-memory FAISS index of the global descriptors (D,), keyed by keyframe id, inner product.

    Exact (IndexIDMap(IndexFlatIP)) up to conf['index_threshold'] keyframes; above it an IVF index
    (IndexIVFFlat, trained on the descriptors it is built from, conf['ivf_lists'] cells, searching
    conf['ivf_nprobe'] of them). Crossing the threshold while adding rebuilds it once as IVF.
    """

    def __init__(self, dim: int, conf: dict):
        self.dim, self.conf = int(dim), conf
        self.index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))

    @property
    def kind(self) -> str:
        return 'ivf' if isinstance(self.index, faiss.IndexIVF) else 'exact'

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal)

    def build(self, x: np.ndarray, ids: np.ndarray) -> None:
        """Replace the contents with x (N, D) float32 under ids (N,) int64, choosing the index type."""
        x, ids = np.ascontiguousarray(x, np.float32).reshape(-1, self.dim), np.asarray(ids, np.int64)
        if len(ids) > self.conf['index_threshold']:
            # FAISS wants >= 39 training points per cell; 64 per cell keeps k-means (the bulk of a
            # 100k map's cold start) to about a second
            lists = int(self.conf['ivf_lists']) or max(1, min(int(np.sqrt(len(ids))), len(ids) // 39))
            index = faiss.IndexIVFFlat(faiss.IndexFlatIP(self.dim), self.dim, lists, faiss.METRIC_INNER_PRODUCT)
            index.cp.max_points_per_centroid = 64
            index.train(x)
            index.nprobe = int(self.conf['ivf_nprobe'])
        else:
            index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))
        if len(ids):
            index.add_with_ids(x, ids)
        self.index = index

    def add(self, x: np.ndarray, ids: np.ndarray) -> None:
        if self.kind == 'exact' and self.ntotal + len(ids) > self.conf['index_threshold']:
            old_x = self.index.index.reconstruct_n(0, self.ntotal) if self.ntotal else np.zeros((0, self.dim))
            self.build(np.concatenate([old_x, np.asarray(x, np.float32).reshape(-1, self.dim)]),
                       np.concatenate([faiss.vector_to_array(self.index.id_map), np.asarray(ids, np.int64)]))
            log.info('global index passed %d keyframes: now IVF', self.conf['index_threshold'])
            return
        self.index.add_with_ids(np.ascontiguousarray(x, np.float32).reshape(-1, self.dim),
                                np.asarray(ids, np.int64))

    def remove(self, ids) -> None:
        self.index.remove_ids(np.asarray(list(ids), np.int64))

    def reset(self) -> None:
        self.index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))

    def search(self, q: np.ndarray, k: int, below: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top k (scores (k',), ids (k',)) for one query q (D,), only ids < below when given."""
        params = None
        if below is not None:
            selector = faiss.IDSelectorRange(0, int(below))
            params = (faiss.SearchParametersIVF(sel=selector, nprobe=self.index.nprobe)
                      if self.kind == 'ivf' else faiss.SearchParameters(sel=selector))
        scores, ids = self.index.search(np.ascontiguousarray(q, np.float32).reshape(1, self.dim), int(k),
                                        params=params)
        keep = ids[0] >= 0
        return scores[0][keep], ids[0][keep]

    def ids(self) -> list[int]:
        """Every id in the index, sorted (for the consistency check against SQLite)."""
        if self.kind == 'exact':
            return sorted(faiss.vector_to_array(self.index.id_map).tolist())
        lists = self.index.invlists
        out = []
        for cell in range(lists.nlist):
            size = lists.list_size(cell)
            if size:
                out.extend(faiss.rev_swig_ptr(lists.get_ids(cell), size).tolist())
        return sorted(out)


class MapStore(abc.ABC):
    """The map interface; ``MapStore(uri, ...)`` / ``MapStore.open(uri, ...)`` returns the backend the
    URI names (see backend_for): SQLiteMapStore (default) or MilvusMapStore. Both keep this API:

    add(lset, stamp) -> id; add_many(sets, stamps, ids=None) -> ids; query(lset, ...) -> [MapCandidate];
    get(id) -> LandmarkSet; delete(ids); ids(); len(); `id in store`; model; use_model(model); clear();
    info() -> dict; save(); compact(); check() -> [problem]; keyframes(batch) -> iterator of
    (id, stamp, LandmarkSet); close(); context manager.

    model: Extractor.model_info (needs descriptor_space and descriptor_dim). Recorded on first use;
    a map from another descriptor space is refused with MapError.
    """

    def __new__(cls, path=None, *args, **kwargs):
        if cls is MapStore:
            kind, _ = backend_for(path)
            if kind == 'milvus':
                from .mapstore_milvus import MilvusMapStore
                cls = MilvusMapStore
            else:
                cls = SQLiteMapStore
        return super().__new__(cls)

    @classmethod
    def open(cls, path, model: dict | None = None, create: bool = True, verify: bool = True,
             conf: dict | None = None) -> 'MapStore':
        return cls(path, model=model, create=create, verify=verify, conf=conf)

    # ------------------------------------------------------------------ what a backend provides
    # (state every backend keeps: path, conf, _lock (RLock), _model (dict | None), _ids (sorted
    # keyframe ids), _landmarks (LandmarkIndex | None); each public call takes _lock)

    @abc.abstractmethod
    def _ready(self) -> None:
        """Raise MapError when closed; refresh in-memory state another writer made stale."""

    @abc.abstractmethod
    def _fetch(self, ids) -> dict[int, LandmarkSet]:
        """The stored sets of these keyframe ids (meta: keyframe_id, stamp), by id."""

    @abc.abstractmethod
    def _holistic(self, lset: LandmarkSet, k: int, below: int | None) -> tuple[np.ndarray, np.ndarray, dict]:
        """The holistic first stage: (cosines (K,), ids (K,), their sets by id), top k by the global
        descriptor among keyframes with id < below (all when None)."""

    @abc.abstractmethod
    def add_many(self, sets: list[LandmarkSet], stamps, ids=None) -> list[int]: ...

    @abc.abstractmethod
    def use_model(self, model: dict) -> None: ...

    @abc.abstractmethod
    def get(self, keyframe_id: int) -> LandmarkSet: ...

    @abc.abstractmethod
    def delete(self, keyframe_ids) -> int: ...

    @abc.abstractmethod
    def clear(self) -> int: ...

    @abc.abstractmethod
    def info(self) -> dict: ...

    @abc.abstractmethod
    def save(self) -> None: ...

    @abc.abstractmethod
    def compact(self) -> dict: ...

    @abc.abstractmethod
    def check(self, limit: int = 20) -> list[str]: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    # ------------------------------------------------------------------ shared by the backends

    def query(self, lset: LandmarkSet, prefilter_k: int = retrieval_conf['prefilter_k'], k: int = 5,
              min_score: float | None = None, exclude_recent: int = 0, method_rerank: bool = True,
              scale: float = 1.0, prefilter: str | None = None) -> list[MapCandidate]:
        """The best k keyframes for a query landmark set, best first: first stage -> fetch -> rerank.

        prefilter (default retrieval.default_conf['prefilter']): 'landmarks' = the top prefilter_k
        keyframes of the landmark index (landmark_index.score_hits), 'holistic' = the top
        prefilter_k by global-descriptor cosine, 'exhaustive' (or prefilter_k 0) = every allowed
        keyframe. The exclude_recent most recently added keyframes are never answers. The
        candidates are reranked by the landmark similarity S (method_rerank=False: the first-stage
        ranking alone, its score as `score`), those below min_score dropped.
        """
        prefilter, prefilter_k = check_prefilter(prefilter or retrieval_conf['prefilter'], prefilter_k)
        k, exclude_recent = self._query_args(lset, k, exclude_recent, method_rerank)
        with self._lock:
            self._ready()
            if self._model is None or not self._ids:
                return []
            given = {'descriptor_space': lset.descriptor_space or self._model['descriptor_space'],
                     'descriptor_dim': lset.dim}
            if not self._same_space(given):
                raise self._mismatch(given, 'a query')
            if exclude_recent >= len(self._ids):
                return []
            cutoff = self._ids[-exclude_recent] if exclude_recent else None
            first = None
            if prefilter == 'exhaustive':
                hol, ids, sets = self._every_keyframe(lset, exclude_recent)
            elif prefilter == 'holistic':
                hol, ids, sets = self._holistic(lset, min(prefilter_k, len(self._ids)), cutoff)
            else:
                if self._landmarks is None:
                    raise MapError(f'map {self.path} has no landmark index')
                ids, first = self._landmarks.shortlist(lset, prefilter_k, below=cutoff, scale=scale)
                sets = {}
                if len(ids) < prefilter_k:
                    _, hol_ids, sets = self._holistic(lset, min(prefilter_k, len(self._ids)), cutoff)
                    ids, first = landmark_index.fill(ids, first, hol_ids, prefilter_k)
                sets.update(self._fetch([i for i in ids if int(i) not in sets]))
                self._check_fetched(ids, sets)
                hol = self._cosines(lset, ids, sets)
        # the numeric work runs outside the lock
        return self._answer(lset, ids, hol, sets, k, min_score, method_rerank, scale, first)

    @staticmethod
    def _cosines(lset: LandmarkSet, ids, sets: dict) -> np.ndarray:
        if not len(ids):
            return np.zeros(0, np.float32)
        return np.stack([sets[int(i)].global_descriptor for i in ids]).astype(np.float32) @ \
            np.asarray(lset.global_descriptor, np.float32)

    # the landmark index (lln_ros/landmark_index.py) kept in step with the stored keyframes

    def _new_landmark_index(self) -> LandmarkIndex:
        return LandmarkIndex(int(self._model['descriptor_dim']), self.conf)

    def _landmark_problems(self, stored: dict) -> list[str]:
        """Disagreements between the landmark index and stored {keyframe id: n}."""
        if self._landmarks is None:
            return [f'no landmark index but {len(stored)} keyframes'] if stored else []
        held = self._landmarks.keyframe_counts()
        wrong = sorted(i for i in set(held) | set(stored) if held.get(i) != stored.get(i))
        if not wrong:
            return []
        return [f'landmark index disagrees with the stored keyframes on {len(wrong)} keyframes (e.g. '
                + ', '.join(f'{i}: {held.get(i, 0)} indexed, {stored.get(i, 0)} stored' for i in wrong[:5]) + ')']

    path: str = ''
    _model: dict | None = None

    @staticmethod
    def _check_model_dict(model: dict) -> dict:
        if not isinstance(model, dict) or not model.get('descriptor_space') or not model.get('descriptor_dim'):
            raise MapError(f'model for map must be a dict with descriptor_space and descriptor_dim '
                           f'(Extractor.model_info), got {model!r}')
        model = dict(model)
        model['descriptor_dim'] = int(model['descriptor_dim'])
        return model

    def _mismatch(self, other: dict, what: str) -> MapError:
        return MapError(f'map {self.path} was built with model {_describe(self._model)}; refusing {what} '
                        f'from model {_describe(other)}: descriptors from different models cannot be '
                        f'compared (use a map file made with this model, or delete this one)')

    def _same_space(self, model: dict) -> bool:
        return (model['descriptor_space'] == self._model['descriptor_space']
                and int(model['descriptor_dim']) == int(self._model['descriptor_dim']))

    def _check_storable(self, lset: LandmarkSet) -> dict:
        """Validate a keyframe before storing it; returns its {descriptor_space, descriptor_dim}."""
        lset.validate()
        if len(lset) == 0:
            raise DescriptorError('landmark set has no landmarks; nothing to store')
        if not lset.descriptor_space:
            raise MapError(f'landmark set has no descriptor_space; refusing to store it in map {self.path} '
                           f'(a persistent map must know which model made its descriptors)')
        rows, cols = (int(v) for v in lset.grid)
        if not (0 < rows < 32768 and 0 < cols < 32768):
            raise DescriptorError(f'grid {rows}x{cols} cannot be stored (int16 cells)')
        return {'descriptor_space': lset.descriptor_space, 'descriptor_dim': lset.dim}

    @staticmethod
    def _query_args(lset: LandmarkSet, k, exclude_recent, method_rerank) -> tuple[int, int]:
        if int(k) < 1 or int(exclude_recent) < 0:
            raise ValueError(f'need k >= 1, exclude_recent >= 0; got {k}, {exclude_recent}')
        lset.validate()
        if method_rerank and len(lset) == 0:
            raise DescriptorError('query landmark set has no landmarks; cannot rerank')
        return int(k), int(exclude_recent)

    def _every_keyframe(self, lset: LandmarkSet, exclude_recent: int) -> tuple[np.ndarray, np.ndarray, dict]:
        """The exhaustive prefilter (prefilter_k = 0): every allowed keyframe in holistic order, as
        the index search would give them: (cosines (K,), ids (K,), their sets by id)."""
        ids = np.asarray(self._ids[:len(self._ids) - exclude_recent], np.int64)
        sets = self._fetch(ids)
        self._check_fetched(ids, sets)
        if not len(ids):
            return np.zeros(0, np.float32), ids, sets
        hol = np.stack([sets[int(i)].global_descriptor for i in ids]).astype(np.float32) @ \
            np.asarray(lset.global_descriptor, np.float32)
        order = np.argsort(-hol, kind='stable')
        return hol[order], ids[order], sets

    def _check_fetched(self, ids, sets: dict) -> None:
        missing = [int(i) for i in ids if int(i) not in sets]
        if missing:
            raise MapError(f'map {self.path}: keyframes {missing[:10]} are in the index but not in the store')

    def _answer(self, lset: LandmarkSet, ids: np.ndarray, hol: np.ndarray, sets: dict, k: int,
                min_score: float | None, method_rerank: bool, scale: float,
                first: np.ndarray | None = None) -> list[MapCandidate]:
        """Rerank the first stage's keyframes (ids (K,), holistic cosines (K,), their sets by id;
        first (K,): the landmark first-stage scores, None = holistic order)."""
        self._check_fetched(ids, sets)
        if not len(ids):
            return []
        if method_rerank:
            batch = stack_landmarks([sets[int(i)] for i in ids])
            ranked = rerank(lset, batch, ids, hol, scale, limit=k)  # sorted: min_score drops a tail
        else:
            first = hol if first is None else first
            ranked = [Candidate(int(i), float(f), float(h)) for i, f, h in zip(ids, first, hol)]
        out = []
        for c in ranked:
            if min_score is not None and c.score < min_score:
                continue
            s = sets[c.index]
            pairs = pair_regions(lset, s, c.pairs)
            out.append(MapCandidate(c.index, float(c.score), float(c.holistic_score), s.meta['stamp'],
                                    tuple(int(v) for v in c.offset),
                                    (float(s.cell_size[0]), float(s.cell_size[1])),
                                    (float(s.image_size[0]), float(s.image_size[1])), pairs))
            if len(out) == k:
                break
        return out

    def add(self, lset: LandmarkSet, stamp=(0, 0)) -> int:
        """Store one keyframe; returns its id once it is durably stored."""
        return self.add_many([lset], [stamp])[0]

    def _check_many(self, sets: list[LandmarkSet], stamps, ids) -> tuple[list, dict]:
        """Validate an add_many call; returns the (sec, nanosec) stamps and the sets' descriptor space."""
        stamps = [_stamp(st) for st in stamps]
        if len(stamps) != len(sets) or (ids is not None and len(ids) != len(sets)):
            raise ValueError(f'{len(sets)} landmark sets need as many stamps (and ids); got {len(stamps)}'
                             f'{"" if ids is None else f" and {len(ids)}"}')
        spaces = [self._check_storable(lset) for lset in sets]
        given = spaces[0]
        if any(sp != given for sp in spaces):
            raise MapError(f'landmark sets from different models in one add_many: {given}, '
                           f'{next(sp for sp in spaces if sp != given)}')
        return stamps, given

    def __len__(self) -> int:
        with self._lock:
            self._ready()
            return len(self._ids)

    def __contains__(self, keyframe_id) -> bool:
        with self._lock:
            self._ready()
            return int(keyframe_id) in set(self._ids)

    def ids(self) -> list[int]:
        """Keyframe ids in insertion order (ascending)."""
        with self._lock:
            self._ready()
            return list(self._ids)

    @property
    def model(self) -> dict | None:
        with self._lock:
            return dict(self._model) if self._model else None

    def keyframes(self, batch: int = 256):
        """Every keyframe as (id, (sec, nanosec), LandmarkSet), in id order, `batch` per read."""
        ids = self.ids()
        for start in range(0, len(ids), batch):
            chunk = ids[start:start + batch]
            with self._lock:
                self._ready()
                sets = self._fetch(chunk)
            for i in chunk:
                if i in sets:
                    yield i, sets[i].meta['stamp'], sets[i]

    def __enter__(self) -> 'MapStore':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SQLiteMapStore(MapStore):
    """The embedded map: one SQLite file plus an in-memory FAISS index (see the module docstring).

    SQLiteMapStore(path, model=None, create=True, verify=True, conf=None). verify: run SQLite's
    quick_check at open (reads the whole file once; catches truncation and corruption before they
    surface as bad answers). conf: see default_conf (when the FAISS index turns approximate).
    """

    default_conf = {
        **landmark_index.default_conf,
        'index_threshold': 50_000,  # keyframes; above this the global index is IVF, below exact
        'ivf_lists': 0,             # IVF cells; 0 = sqrt(keyframes) (at most keyframes / 39) at (re)build
        'ivf_nprobe': 16,           # IVF cells visited per query (recall vs speed: bench/bench_map.py)
    }

    def __init__(self, path, model: dict | None = None, create: bool = True, verify: bool = True,
                 conf: dict | None = None):
        self.conf = {**self.default_conf, **(conf or {})}
        kind, location = backend_for(path)
        if kind != 'sqlite':
            raise MapError(f'{path} is not an SQLite map URI')
        path = location
        self.path = os.path.abspath(os.path.expanduser(os.fspath(path)))
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None
        self._model: dict | None = None
        self._index = None
        self._landmarks: LandmarkIndex | None = None
        self._landmarks_dirty = False
        self._unindexed: set[int] = set()  # corrupt keyframes the landmark index cannot hold
        self.landmark_path = self.path + '.landmarks'
        self._ids: list[int] = []
        self._data_version = None
        if model is not None:
            model = self._check_model_dict(model)
        if os.path.isdir(self.path):
            raise MapError(f'map path {self.path} is a directory, not a map file')
        if not os.path.exists(self.path):
            if not create:
                raise MapError(f'no map at {self.path} (create=False)')
            self._create_file()
        else:
            self._check_file()
        try:
            self._conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None,
                                         check_same_thread=False)
        except sqlite3.Error as e:
            raise MapError(f'cannot open map {self.path}: {e}') from e
        try:
            self._identify()          # read-only: never modify a file that is not ours
            self._configure()
            self._migrate()
            if verify:
                rows = [r[0] for r in self._conn.execute('PRAGMA quick_check(20)')]
                if rows != ['ok']:
                    raise MapError(f'map {self.path} is corrupt (SQLite quick_check): ' + '; '.join(rows))
            self._load()
            if model is not None:
                self._adopt_model(model)
        except sqlite3.OperationalError as e:     # locked, read-only, I/O error
            self._conn.close()
            self._conn = None
            raise MapError(f'cannot open map {self.path}: {e}') from e
        except sqlite3.DatabaseError as e:        # malformed, not a database
            self._conn.close()
            self._conn = None
            raise MapError(f'map {self.path} is corrupt or truncated: {e}') from e
        except BaseException:
            self._conn.close()
            self._conn = None
            raise

    # ------------------------------------------------------------------ opening

    def _create_file(self) -> None:
        """Build an empty map under a temporary name, then link it into place (no half-made maps)."""
        parent = os.path.dirname(self.path)
        os.makedirs(parent, exist_ok=True)
        for suffix in ('-wal', '-shm', '-journal'):  # left over from a deleted file: never replay them
            try:
                os.remove(self.path + suffix)
            except FileNotFoundError:
                pass
        tmp = f'{self.path}.creating-{os.getpid()}-{uuid.uuid4().hex[:8]}'
        try:
            conn = sqlite3.connect(tmp, isolation_level=None)
            try:
                conn.execute('BEGIN')
                for statement in SCHEMA.split(';'):
                    if statement.strip():
                        conn.execute(statement)
                from . import __version__
                conn.executemany('INSERT INTO meta (key, value) VALUES (?, ?)', [
                    ('format', FORMAT), ('schema_version', str(SCHEMA_VERSION)),
                    ('created', str(int(time.time()))), ('created_by', f'lln_ros {__version__}'),
                    ('map_uuid', uuid.uuid4().hex)])
                conn.execute('COMMIT')
            finally:
                conn.close()
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            try:
                os.link(tmp, self.path)        # fails if someone else created the map meanwhile
            except FileExistsError:
                pass
            except OSError:                    # no hard links on this filesystem
                if not os.path.exists(self.path):
                    os.replace(tmp, self.path)
            dfd = os.open(parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except (OSError, sqlite3.Error) as e:
            raise MapError(f'cannot create map {self.path}: {e}') from e
        finally:
            for f in (tmp, tmp + '-journal'):
                try:
                    os.remove(f)
                except FileNotFoundError:
                    pass

    def _check_file(self) -> None:
        """Cheap checks on the raw file before SQLite sees it: header magic and truncation."""
        try:
            size = os.path.getsize(self.path)
            with open(self.path, 'rb') as f:
                head = f.read(100)
        except OSError as e:
            raise MapError(f'cannot read map {self.path}: {e}') from e
        if size == 0:
            raise MapError(f'{self.path} is an empty file (0 bytes), not an lln_ros map; '
                           f'delete it to start a new map')
        if len(head) < 100 or head[:16] != SQLITE_MAGIC:
            raise MapError(f'{self.path} is not an lln_ros map: not an SQLite database '
                           f'(corrupt, truncated or some other file; {size} bytes)')
        page_size = struct.unpack('>H', head[16:18])[0]
        page_size = 65536 if page_size == 1 else page_size
        change, pages, valid_for = (struct.unpack('>I', head[o:o + 4])[0] for o in (24, 28, 92))
        wal = self.path + '-wal'
        wal_pending = os.path.exists(wal) and os.path.getsize(wal) > 0
        # with a pending WAL the main file may legitimately lag behind; quick_check covers that case
        if pages and change == valid_for and not wal_pending and size < pages * page_size:
            raise MapError(f'map {self.path} is truncated: {size} bytes, its header says '
                           f'{pages} pages of {page_size} bytes ({pages * page_size} bytes)')

    def _identify(self) -> None:
        c = self._conn
        tables = {r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if 'meta' not in tables:
            raise MapError(f'{self.path} is an SQLite database but not an lln_ros map '
                           f'(no meta table; tables: {sorted(tables) or "none"})')
        meta = self._meta()
        if meta.get('format') != FORMAT:
            raise MapError(f'{self.path} is an SQLite database but not an lln_ros map '
                           f'(meta format is {meta.get("format")!r}, expected {FORMAT!r})')
        try:
            version = int(meta.get('schema_version', ''))
        except ValueError:
            raise MapError(f'map {self.path} has no valid schema_version '
                           f'({meta.get("schema_version")!r})') from None
        if version > SCHEMA_VERSION:
            raise MapError(f'map {self.path} has schema version {version}; this lln_ros reads up to '
                           f'{SCHEMA_VERSION}: upgrade lln_ros')
        missing = {'keyframes', 'landmarks'} - tables
        if missing and version == SCHEMA_VERSION:
            raise MapError(f'map {self.path} is damaged: missing tables {sorted(missing)}')

    def _configure(self) -> None:
        c = self._conn
        mode = c.execute('PRAGMA journal_mode=WAL').fetchone()[0]
        if str(mode).lower() != 'wal':
            raise MapError(f'cannot put map {self.path} in WAL mode (got {mode!r}); '
                           f'is it on a network filesystem or read-only?')
        c.execute('PRAGMA synchronous=FULL')
        c.execute('PRAGMA foreign_keys=ON')

    def _migrate(self) -> None:
        version = int(self._meta()['schema_version'])
        while version < SCHEMA_VERSION:
            step = MIGRATIONS.get(version)
            if step is None:
                raise MapError(f'map {self.path} has schema version {version} and there is no '
                               f'migration to {version + 1}')
            self._conn.execute('BEGIN IMMEDIATE')
            try:
                step(self._conn)
                self._conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'",
                                   (str(version + 1),))
                self._conn.execute('COMMIT')
            except BaseException:
                self._conn.execute('ROLLBACK')
                raise
            log.info('migrated map %s from schema %d to %d', self.path, version, version + 1)
            version += 1

    def _meta(self) -> dict:
        return {k: v for k, v in self._conn.execute('SELECT key, value FROM meta')}

    def _load(self) -> None:
        """(Re)read the model record and rebuild the FAISS index from the keyframes table."""
        c = self._conn
        self._data_version = c.execute('PRAGMA data_version').fetchone()[0]
        meta = self._meta()
        self._model = json.loads(meta['model']) if 'model' in meta else None
        count = c.execute('SELECT count(*) FROM keyframes').fetchone()[0]
        self._ids = []
        self._index = None
        self._landmarks = None
        if self._model is None:
            if count:
                raise MapError(f'map {self.path} is damaged: {count} keyframes but no model record')
            return
        dim = int(self._model['descriptor_dim'])
        # streamed into one preallocated array: a 100k map's rows as Python objects would double the peak
        x = np.empty((count, dim), np.float32)
        cursor = c.execute('SELECT id, global_descriptor FROM keyframes ORDER BY id')
        bad = []
        while rows := cursor.fetchmany(4096):
            for kid, blob in rows:
                if len(blob) != 4 * dim:
                    bad.append(kid)
                elif len(self._ids) < count:
                    x[len(self._ids)] = np.frombuffer(blob, '<f4')
                    self._ids.append(int(kid))
        if bad:
            raise MapError(f'map {self.path} is corrupt: global descriptors of keyframes {bad[:10]} are '
                           f'not {dim} float32 values')
        self._index = GlobalIndex(dim, self.conf)
        self._index.build(x[:len(self._ids)], np.asarray(self._ids, np.int64))
        problems = self._faiss_problems()
        if problems:
            raise MapError(f'map {self.path}: in-memory index disagrees with the file: {"; ".join(problems)}')
        self._load_landmarks()

    # ------------------------------------------------------------------ the landmark index
    # Exact (below conf['landmark_index_threshold'] landmarks): rebuilt from the landmarks table at
    # every open, like the global index. IVF-PQ (above): trained once, persisted in
    # `<map>.landmarks` by save() and close(), loaded at open and reconciled with the keyframes
    # table (keyframes added after the last save are added, deleted ones removed), rebuilt from
    # SQLite when the file is missing, corrupt or from another map (meta map_uuid).

    def _stored_counts(self) -> dict[int, int]:
        """{keyframe id: n} the landmark index must hold (corrupt keyframes it cannot hold excluded)."""
        return {int(i): int(n) for i, n in self._conn.execute('SELECT id, n FROM keyframes')
                if int(i) not in self._unindexed}

    def _landmark_rows(self, ids=None, every: int = 1):
        """Landmarks of the given keyframes (None = all; every: only ids divisible by it) in chunks:
        (keyframe ids (m,), cells (m, 2), descriptors (m, D) float32)."""
        dim = int(self._model['descriptor_dim'])
        if ids is None:
            chunks = [None]
        else:
            ids = sorted(int(i) for i in ids)
            chunks = [ids[i:i + _SQL_CHUNK] for i in range(0, len(ids), _SQL_CHUNK)]
        for chunk in chunks:
            where = f'WHERE k.id IN ({",".join("?" * len(chunk))})' if chunk is not None else \
                (f'WHERE k.id % {int(every)} = 0' if every > 1 else '')
            with self._read_errors():   # the join: orphan landmark rows are check()'s business, not the index's
                cursor = self._conn.execute('SELECT k.id, l.cells, l.descriptors FROM keyframes k JOIN landmarks l '
                                            f'ON l.keyframe_id = k.id {where} ORDER BY k.id', chunk or ())
                while rows := cursor.fetchmany(512):
                    kf, cells, desc = [], [], []
                    for kid, c, d in rows:
                        n = len(c) // 4
                        if len(c) != 4 * n or len(d) != 2 * n * dim:
                            # not indexed, and named: check() reports it, a query that fetches it raises
                            log.error('map %s is corrupt: keyframe %d landmark blobs are %d + %d bytes (D=%d)',
                                      self.path, kid, len(c), len(d), dim)
                            self._unindexed.add(int(kid))
                            continue
                        if n == 0:
                            continue
                        kf.append(np.full(n, kid, np.int64))
                        cells.append(np.frombuffer(c, '<i2').reshape(n, 2))
                        desc.append(np.frombuffer(d, '<f2').reshape(n, dim))
                    if kf:
                        yield np.concatenate(kf), np.concatenate(cells), np.concatenate(desc).astype(np.float32)

    def _map_uuid(self, create: bool = False) -> str | None:
        uid = self._meta().get('map_uuid')
        if uid is None and create:
            uid = uuid.uuid4().hex
            self._write(lambda c: c.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('map_uuid', ?)", (uid,)))
            uid = self._meta()['map_uuid']
        return uid

    def _load_landmarks(self) -> None:
        self._unindexed: set[int] = set()
        stored = self._stored_counts()
        total = sum(stored.values())
        index, why = None, 'missing'
        if total > self.conf['landmark_index_threshold'] and os.path.exists(self.landmark_path):
            try:
                index, header = LandmarkIndex.read(self.landmark_path, int(self._model['descriptor_dim']), self.conf)
                if header.get('map_uuid') != self._map_uuid():
                    index, why = None, 'from another map'
            except MapError as e:
                index, why = None, str(e)
        if index is not None:
            held = index.keyframe_counts()
            stale = [i for i, c in held.items() if stored.get(i) != c]
            missing = [i for i, n in stored.items() if held.get(i) != n]
            index.remove_keyframes(stale)
            for kf, cells, desc in self._landmark_rows(missing):
                index.add(desc, kf, cells)
            self._landmarks_dirty = bool(stale or missing)
            if stale or missing:
                log.info('map %s: landmark index caught up (%d keyframes added, %d removed)',
                         self.path, len(missing), len(stale))
        else:
            if total > self.conf['landmark_index_threshold']:
                log.warning('map %s: landmark index %s (%s); rebuilding it from the map (%d landmarks)',
                            self.path, self.landmark_path, why, total)
            index = self._build_landmarks(total, len(stored))
            self._landmarks_dirty = index.kind != 'exact'
        self._landmarks = index
        problems = self._landmark_problems(self._stored_counts())
        if problems:
            raise MapError(f'map {self.path}: {"; ".join(problems)}')
        if index.kind == 'exact':
            self._drop_landmark_file()

    def _build_landmarks(self, total: int, keyframes: int) -> LandmarkIndex:
        index = self._new_landmark_index()
        if total > self.conf['landmark_index_threshold']:
            # train on a sample of keyframes, then stream every landmark in: never all of them as float32
            every = max(1, int(total // max(1, self.conf['landmark_train_points'])))
            sample = np.concatenate([d for _, _, d in self._landmark_rows(every=every)])
            index.index = index._compressed(sample, total)
            del sample
        for kf, cells, desc in self._landmark_rows():
            index.index.add_with_ids(desc, landmark_index.encode_ids(kf, cells))
        return index

    def _persist_landmarks(self) -> None:
        if self._landmarks is None or self._landmarks.kind == 'exact' or not self._landmarks_dirty:
            return
        self._landmarks.write(self.landmark_path, {'map_uuid': self._map_uuid(create=True)})
        self._landmarks_dirty = False

    def _drop_landmark_file(self) -> None:
        try:
            os.remove(self.landmark_path)
        except FileNotFoundError:
            pass
        except OSError as e:
            log.warning('map %s: cannot remove %s: %s', self.path, self.landmark_path, e)

    def _faiss_problems(self) -> list[str]:
        ids = [r[0] for r in self._conn.execute('SELECT id FROM keyframes ORDER BY id')]
        if self._index is None:
            return [f'no FAISS index but {len(ids)} keyframes'] if ids else []
        problems = []
        if self._index.ntotal != len(ids):
            problems.append(f'FAISS index holds {self._index.ntotal} keyframes, SQLite {len(ids)}')
        faiss_ids = self._index.ids()
        if faiss_ids != ids or self._ids != ids:
            only_f, only_s = sorted(set(faiss_ids) - set(ids)), sorted(set(ids) - set(faiss_ids))
            problems.append(f'FAISS and SQLite keyframe ids differ (only in FAISS: {only_f[:10]}, '
                            f'only in SQLite: {only_s[:10]})')
        return problems

    # ------------------------------------------------------------------ model

    def use_model(self, model: dict) -> None:
        """Declare the model whose descriptors will arrive (e.g. the extractor's model_info):
        recorded when the map has none yet, MapError when it is from another descriptor space."""
        model = self._check_model_dict(model)
        with self._lock:
            self._ready()
            self._adopt_model(model)

    def _adopt_model(self, model: dict) -> None:
        """Record the model on first use, or refuse one from another descriptor space."""
        if self._model is None:
            self._write(lambda c: self._record_model(c, model))
            self._model = model
            self._index = GlobalIndex(model['descriptor_dim'], self.conf)
            self._landmarks = self._new_landmark_index()
        elif not self._same_space(model):
            raise self._mismatch(model, 'the extractor')
        elif model != self._model:
            log.info('map %s was built with %s; now used with %s (same descriptor space)',
                     self.path, self._model, model)

    @staticmethod
    def _record_model(c: sqlite3.Connection, model: dict) -> None:
        c.executemany('INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)', [
            ('model', json.dumps(model, sort_keys=True, default=str)),
            ('descriptor_space', model['descriptor_space']),
            ('descriptor_dim', str(model['descriptor_dim']))])

    # ------------------------------------------------------------------ plumbing

    def _ready(self) -> None:
        if self._conn is None:
            raise MapError(f'map {self.path} is closed')
        # another connection (process) committed: our FAISS index may be stale
        with self._read_errors():
            if self._conn.execute('PRAGMA data_version').fetchone()[0] != self._data_version:
                log.info('map %s changed on disk; reloading', self.path)
                self._load()

    @contextlib.contextmanager
    def _read_errors(self):
        try:
            yield
        except sqlite3.DatabaseError as e:
            raise MapError(f'cannot read map {self.path} (corrupt or truncated?): {e}') from e

    def _write(self, fn):
        """Run fn(conn) in one IMMEDIATE transaction; durable on return (WAL + synchronous=FULL)."""
        c = self._conn
        try:
            c.execute('BEGIN IMMEDIATE')
            try:
                result = fn(c)
                c.execute('COMMIT')
            except BaseException:
                if c.in_transaction:
                    c.execute('ROLLBACK')
                raise
        except sqlite3.OperationalError as e:
            raise MapError(f'cannot write map {self.path}: {e}') from e
        except sqlite3.DatabaseError as e:
            raise MapError(f'map {self.path} is corrupt: {e}') from e
        return result

    def _row_to_set(self, row) -> LandmarkSet:
        (kid, sec, nsec, iw, ih, rows, cols, cw, ch, n, glob, cells, centers, scores, desc) = row
        dim = int(self._model['descriptor_dim'])
        sizes = {'global_descriptor': (glob, 4 * dim), 'cells': (cells, 4 * n), 'centers': (centers, 8 * n),
                 'scores': (scores, 4 * n), 'descriptors': (desc, 2 * n * dim)}
        for name, (blob, nbytes) in sizes.items():
            if blob is None or len(blob) != nbytes:
                raise MapError(f'map {self.path} is corrupt: keyframe {kid} {name} is '
                               f'{None if blob is None else len(blob)} bytes, expected {nbytes} (n={n}, D={dim})')
        return LandmarkSet(
            global_descriptor=np.frombuffer(glob, '<f4').astype(np.float32),
            descriptors=np.frombuffer(desc, '<f2').reshape(n, dim).astype(np.float32),
            cells=np.frombuffer(cells, '<i2').reshape(n, 2).astype(np.int32),
            centers=np.frombuffer(centers, '<f4').reshape(n, 2).astype(np.float32),
            scores=np.frombuffer(scores, '<f4').astype(np.float32),
            cell_size=np.array([cw, ch], np.float32),
            image_size=np.array([iw, ih], np.float32),
            grid=(int(rows), int(cols)),
            activation=None,
            descriptor_space=self._model['descriptor_space'],
            meta={'keyframe_id': int(kid), 'stamp': (int(sec), int(nsec))},
        )

    def _fetch(self, ids) -> dict[int, LandmarkSet]:
        out = {}
        ids = [int(i) for i in ids]
        for start in range(0, len(ids), _SQL_CHUNK):
            chunk = ids[start:start + _SQL_CHUNK]
            sql = (f'SELECT {_KF_COLS}, {_LM_COLS} FROM keyframes k LEFT JOIN landmarks l '
                   f'ON l.keyframe_id = k.id WHERE k.id IN ({",".join("?" * len(chunk))})')
            with self._read_errors():
                rows = self._conn.execute(sql, chunk).fetchall()
            for row in rows:
                out[int(row[0])] = self._row_to_set(row)
        return out

    # ------------------------------------------------------------------ public API

    def add_many(self, sets: list[LandmarkSet], stamps, ids=None) -> list[int]:
        """Store keyframes in one transaction; returns their ids once they are durably on disk.
        ids: keep these ids (export / import between maps); MapError if one is taken."""
        if not sets:
            return []
        stamps, given = self._check_many(sets, stamps, ids)
        records = []
        for lset, (sec, nsec) in zip(sets, stamps):
            rows, cols = (int(v) for v in lset.grid)
            records.append(((sec, nsec, float(lset.image_size[0]), float(lset.image_size[1]), rows, cols,
                             float(lset.cell_size[0]), float(lset.cell_size[1]), len(lset),
                             np.ascontiguousarray(lset.global_descriptor, '<f4').tobytes()),
                            (np.ascontiguousarray(lset.cells, '<i2').tobytes(),
                             np.ascontiguousarray(lset.centers, '<f4').tobytes(),
                             np.ascontiguousarray(lset.scores, '<f4').tobytes(),
                             np.ascontiguousarray(lset.descriptors, '<f2').tobytes())))
        with self._lock:
            self._ready()
            new_model = self._model is None
            if not new_model and not self._same_space(given):
                raise self._mismatch(given, 'a landmark set')

            def insert(c):
                if new_model:
                    self._record_model(c, given)
                out = []
                for i, (values, blobs) in enumerate(records):
                    try:
                        if ids is None:
                            cur = c.execute(f'INSERT INTO keyframes ({_KF_INSERT}) VALUES ({", ".join("?" * 10)})',
                                            values)
                        else:
                            cur = c.execute(f'INSERT INTO keyframes (id, {_KF_INSERT}) '
                                            f'VALUES ({", ".join("?" * 11)})', (int(ids[i]),) + values)
                    except sqlite3.IntegrityError:
                        raise MapError(f'map {self.path} already has a keyframe {ids[i]}') from None
                    c.execute('INSERT INTO landmarks (keyframe_id, cells, centers, scores, descriptors) '
                              'VALUES (?, ?, ?, ?, ?)', (cur.lastrowid,) + blobs)
                    out.append(int(cur.lastrowid))
                return out

            new_ids = self._write(insert)
            if new_model:
                self._model = given
                self._index = GlobalIndex(given['descriptor_dim'], self.conf)
                self._landmarks = self._new_landmark_index()
            self._index.add(np.stack([s.global_descriptor for s in sets]).astype(np.float32),
                            np.asarray(new_ids, np.int64))
            self._landmarks.add_sets(new_ids, sets)
            self._landmarks_dirty = True
            if self._landmarks.needs_rebuild():
                t = time.perf_counter()
                stored = self._stored_counts()
                self._landmarks = self._build_landmarks(sum(stored.values()), len(stored))
                log.info('map %s: landmark index retrained for %d landmarks (%.1f s)', self.path,
                         self._landmarks.ntotal, time.perf_counter() - t)
            self._ids.extend(new_ids)
            if ids is not None:
                self._ids.sort()
            return new_ids

    def _holistic(self, lset: LandmarkSet, k: int, below: int | None) -> tuple[np.ndarray, np.ndarray, dict]:
        hol, ids = self._index.search(lset.global_descriptor, k, below=below)
        return hol, ids, self._fetch(ids)

    # keypoints for verification (reloc.py): an optional table, created on first use, so maps
    # without it stay valid and readable; rows go with their keyframe (ON DELETE CASCADE)
    _KEYPOINTS_TABLE = ('CREATE TABLE IF NOT EXISTS keypoints (keyframe_id INTEGER PRIMARY KEY '
                        'REFERENCES keyframes(id) ON DELETE CASCADE, n INTEGER NOT NULL, uv BLOB NOT NULL, '
                        'descriptors BLOB NOT NULL)')

    def add_keypoints(self, keyframe_id: int, uv: np.ndarray, descriptors: np.ndarray) -> None:
        """Store a keyframe's keypoints: uv (N, 2) float32 original pixels, binary descriptors
        (N, B) uint8, as float32 / uint8 blobs (8 + B bytes per keypoint). Replaces earlier ones."""
        uv = np.ascontiguousarray(uv, '<f4').reshape(-1, 2)
        desc = np.ascontiguousarray(descriptors)
        if desc.dtype != np.uint8 or desc.ndim != 2 or len(desc) != len(uv):
            raise DescriptorError(f'keypoints need (N, B) uint8 descriptors for N={len(uv)} points, '
                                  f'got {desc.dtype} {desc.shape}')
        with self._lock:
            self._ready()
            if int(keyframe_id) not in set(self._ids):
                raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
            self._write(lambda c: (c.execute(self._KEYPOINTS_TABLE), c.execute(
                'INSERT OR REPLACE INTO keypoints (keyframe_id, n, uv, descriptors) VALUES (?, ?, ?, ?)',
                (int(keyframe_id), len(uv), uv.tobytes(), desc.tobytes()))))

    def keypoints(self, keyframe_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(uv (N, 2) float32, descriptors (N, B) uint8) of a keyframe, or None when none were stored."""
        with self._lock:
            self._ready()
            with self._read_errors():
                if not self._conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'keypoints'").fetchone():
                    return None
                row = self._conn.execute('SELECT n, uv, descriptors FROM keypoints WHERE keyframe_id = ?',
                                         (int(keyframe_id),)).fetchone()
        if row is None:
            return None
        n, uv, desc = row
        if len(uv) != 8 * n or (n and len(desc) % n) or (not n and desc):
            raise MapError(f'map {self.path} is corrupt: keyframe {keyframe_id} keypoints are {len(uv)} + '
                           f'{len(desc)} bytes for n={n}')
        return (np.frombuffer(uv, '<f4').reshape(n, 2).copy(),
                np.frombuffer(desc, np.uint8).reshape(n, len(desc) // n if n else 32).copy())

    def get(self, keyframe_id: int) -> LandmarkSet:
        """The stored landmark set of a keyframe (descriptors back from float16; no activation map)."""
        with self._lock:
            self._ready()
            sets = self._fetch([int(keyframe_id)]) if self._model else {}
        if int(keyframe_id) not in sets:
            raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
        return sets[int(keyframe_id)]

    def clear(self) -> int:
        """Remove every keyframe (returns how many); the model record stays, and ids are not reused."""
        with self._lock:
            self._ready()
            self._write(lambda c: (c.execute('DELETE FROM landmarks'), c.execute('DELETE FROM keyframes')))
            removed, self._ids = len(self._ids), []
            if self._index is not None:
                self._index.reset()
                self._landmarks.reset()
            self._drop_landmark_file()
            return removed

    def delete(self, keyframe_ids) -> int:
        """Remove keyframes (and their landmarks) by id; returns how many existed. Ids are not reused."""
        wanted = sorted({int(i) for i in keyframe_ids})
        with self._lock:
            self._ready()
            present = sorted(set(wanted) & set(self._ids))
            if not present:
                return 0

            def remove(c):
                for start in range(0, len(present), _SQL_CHUNK):
                    chunk = present[start:start + _SQL_CHUNK]
                    marks = ','.join('?' * len(chunk))
                    c.execute(f'DELETE FROM landmarks WHERE keyframe_id IN ({marks})', chunk)
                    c.execute(f'DELETE FROM keyframes WHERE id IN ({marks})', chunk)
            self._write(remove)
            gone = set(present)
            self._ids = [i for i in self._ids if i not in gone]
            self._index.remove(present)
            self._landmarks.remove_keyframes(present)
            self._landmarks_dirty = True
            return len(present)

    def compact(self) -> dict:
        """Checkpoint, then VACUUM: give the pages of deleted keyframes back to the filesystem.
        Returns {'bytes_before', 'bytes_after'} (the .db plus its WAL)."""
        with self._lock:
            self._ready()
            before = self.info()['file_bytes']
            self.save()
            try:
                self._conn.execute('VACUUM')
            except sqlite3.DatabaseError as e:
                raise MapError(f'cannot compact map {self.path}: {e}') from e
            self.save()
            return {'bytes_before': before, 'bytes_after': self.info()['file_bytes']}

    def info(self) -> dict:
        with self._lock:
            self._ready()
            with self._read_errors():
                meta = self._meta()
            wal = self.path + '-wal'
            db_bytes = os.path.getsize(self.path)
            wal_bytes = os.path.getsize(wal) if os.path.exists(wal) else 0
            return {'path': self.path, 'keyframes': len(self._ids), 'model': self.model,
                    'descriptor_space': self._model and self._model['descriptor_space'],
                    'descriptor_dim': self._model and int(self._model['descriptor_dim']),
                    'schema_version': int(meta['schema_version']), 'backend': 'sqlite',
                    'index': self._index.kind if self._index is not None else None,
                    'landmark_index': self._landmarks.kind if self._landmarks is not None else None,
                    'landmarks': self._landmarks.ntotal if self._landmarks is not None else 0,
                    'landmark_index_bytes': (os.path.getsize(self.landmark_path)
                                             if os.path.exists(self.landmark_path) else 0),
                    'first_id': self._ids[0] if self._ids else None,
                    'last_id': self._ids[-1] if self._ids else None,
                    'file_bytes': db_bytes + wal_bytes, 'db_bytes': db_bytes, 'wal_bytes': wal_bytes,
                    'created': int(meta.get('created', 0)), 'created_by': meta.get('created_by', '')}

    def save(self) -> None:
        """Checkpoint the WAL into the main file and truncate it. Not needed for durability (every
        add is durable on return); it keeps the WAL small and the .db file self-contained."""
        with self._lock:
            self._ready()
            self._persist_landmarks()
            try:
                busy, _, _ = self._conn.execute('PRAGMA wal_checkpoint(TRUNCATE)').fetchone()
            except sqlite3.DatabaseError as e:
                raise MapError(f'cannot checkpoint map {self.path}: {e}') from e
            if busy:
                log.warning('map %s: checkpoint incomplete, another connection is reading', self.path)

    def check(self, limit: int = 20) -> list[str]:
        """Problems found in the map (empty list = healthy): SQLite integrity_check, format and
        schema version, model record, blob sizes against n and D, orphan rows, FAISS vs SQLite."""
        problems: list[str] = []

        def add(items, what):
            items = list(items)
            problems.extend(what(x) for x in items[:limit])
            if len(items) > limit:
                problems.append(f'... and {len(items) - limit} more like that')

        with self._lock:
            self._ready()
            c = self._conn
            try:
                rows = [r[0] for r in c.execute(f'PRAGMA integrity_check({int(limit)})')]
                if rows != ['ok']:
                    add(rows, lambda r: f'integrity_check: {r}')
                    return problems
                meta = self._meta()
                if meta.get('format') != FORMAT:
                    problems.append(f'meta format is {meta.get("format")!r}, expected {FORMAT!r}')
                if meta.get('schema_version') != str(SCHEMA_VERSION):
                    problems.append(f'schema_version is {meta.get("schema_version")!r}, expected {SCHEMA_VERSION}')
                n_kf = c.execute('SELECT count(*) FROM keyframes').fetchone()[0]
                if self._model is None:
                    if n_kf:
                        problems.append(f'{n_kf} keyframes but no model record')
                    return problems
                dim = int(self._model['descriptor_dim'])
                if meta.get('descriptor_dim') != str(dim) or \
                        meta.get('descriptor_space') != self._model['descriptor_space']:
                    problems.append('meta descriptor_space/descriptor_dim disagree with the model record')
                sizes = c.execute(
                    'SELECT k.id, k.n, k.grid_rows, k.grid_cols, k.stamp_nanosec, length(k.global_descriptor), '
                    'length(l.cells), length(l.centers), length(l.scores), length(l.descriptors), '
                    'l.keyframe_id IS NULL FROM keyframes k LEFT JOIN landmarks l ON l.keyframe_id = k.id')
                bad = []
                for kid, n, rows_, cols_, nsec, lg, lc, lce, ls, ld, orphan in sizes:
                    if orphan:
                        bad.append(f'keyframe {kid} has no landmarks row')
                        continue
                    want = (4 * dim, 4 * n, 8 * n, 4 * n, 2 * n * dim)
                    if (lg, lc, lce, ls, ld) != want or n < 1:
                        bad.append(f'keyframe {kid}: blob sizes (global, cells, centers, scores, descriptors) '
                                   f'{(lg, lc, lce, ls, ld)} do not fit n={n}, D={dim} (expected {want})')
                    if rows_ < 1 or cols_ < 1 or not 0 <= nsec < 1_000_000_000:
                        bad.append(f'keyframe {kid}: bad grid {rows_}x{cols_} or stamp nanosec {nsec}')
                add(bad, str)
                orphans = [r[0] for r in c.execute(
                    'SELECT keyframe_id FROM landmarks WHERE keyframe_id NOT IN (SELECT id FROM keyframes)')]
                add(orphans, lambda i: f'landmarks row {i} has no keyframe')
                problems.extend(self._faiss_problems())
                problems.extend(self._landmark_problems(self._stored_counts()))
            except sqlite3.DatabaseError as e:
                problems.append(f'SQLite error while checking: {e}')
        return problems

    def close(self) -> None:
        """Close the file (SQLite checkpoints the WAL when the last connection closes). Idempotent."""
        with self._lock:
            if self._conn is not None:
                try:
                    try:
                        self._persist_landmarks()
                    except MapError as e:  # the file is rebuilt from SQLite at the next open
                        log.warning('%s', e)
                    self._conn.close()
                finally:
                    self._conn = None
                    self._index = None
                    self._landmarks = None
                    self._ids = []

    def __repr__(self) -> str:
        state = 'closed' if self._conn is None else f'{len(self._ids)} keyframes'
        return f'SQLiteMapStore({self.path!r}, {state})'
