"""The map interface every backend implements: MapStore (an abstract base with the one query
template, first stage -> fetch -> rerank -> answer) and MapCandidate, what a query answers."""

from __future__ import annotations

import abc
import bisect
from dataclasses import dataclass, field

import numpy as np

from ..core import landmark_index
from ..core.landmark_index import LandmarkIndex, check_prefilter
from ..core.landmarks import LandmarkSet
from ..core.limits import KEYFRAME_ID_MAX, parse_model_json, stamp_problem, validate_model
from ..core.retrieval import Candidate, pair_regions, rerank
from ..core.retrieval import default_conf as retrieval_conf
from ..errors import DescriptorError, MapError, ModelError
from .index import landmark_disagreements
from .uri import backend_for

FORMAT = 'lln_ros-map'


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
    session_id: the map's number of the session that stored the keyframe (store.sessions(); 0 =
    unknown, a keyframe of before schema 3).
    """

    keyframe_id: int
    score: float
    holistic_score: float
    stamp: tuple
    offset: tuple = (0, 0)
    cell_size: tuple = (0.0, 0.0)
    image_size: tuple = (0.0, 0.0)
    pairs: dict = field(default_factory=dict)
    session_id: int = 0

    @property
    def n_pairs(self) -> int:
        return len(self.pairs.get('query_index', ()))


def _describe(model: dict | None) -> str:
    if not model:
        return '<none>'
    text = f'{model.get("descriptor_space")!r} (D={model.get("descriptor_dim")}'
    if model.get('weights'):
        text += f', weights {model["weights"]}'
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
    problem = stamp_problem(sec, nsec)  # what the answers' stamp_sec (INT32) and nanosec can carry
    if problem:
        raise ValueError(problem)
    return sec, nsec


def _without(drop: set, keep: int, ids, *arrays) -> tuple:
    """(*arrays, ids) without the ids in drop, at most keep of each (a first stage's ranking)."""
    if not drop:
        return (*arrays, ids)
    mask = np.array([int(i) not in drop for i in ids], bool)
    return (*(np.asarray(a)[mask][:keep] for a in arrays), np.asarray(ids, np.int64)[mask][:keep])


def _sorted_has(ids: list, i: int) -> bool:
    """Whether ascending ids hold i (quarantined keyframes are not among a store's _ids)."""
    at = bisect.bisect_left(ids, i)
    return at < len(ids) and ids[at] == i


class MapStore(abc.ABC):
    """The map interface; ``MapStore(uri, ...)`` / ``MapStore.open(uri, ...)`` returns the backend the
    URI names (see backend_for): SQLiteMapStore (default) or MilvusMapStore. Both keep this API:

    add(lset, stamp) -> id; add_many(sets, stamps, ids=None) -> ids; query(lset, ...) -> [MapCandidate];
    start_session(robot) -> Session; sessions(); set_origin(id, session_id, seq); origins(ids);
    get(id) -> LandmarkSet; delete(ids); ids(); len(); `id in store`; model; use_model(model); clear();
    info() -> dict; save(); compact(); check() -> [problem]; keyframes(batch) -> iterator of
    (id, stamp, LandmarkSet); close(); context manager.

    model: Extractor.model_info (needs descriptor_space and descriptor_dim). Recorded on first use;
    a map from another descriptor space is refused with MapError.
    """

    def __new__(cls, path=None, *args, **kwargs):
        if cls is MapStore:
            from . import backend_class

            cls = backend_class(backend_for(path)[0])
        return super().__new__(cls)

    @classmethod
    def open(
        cls, path, model: dict | None = None, create: bool = True, verify: bool = True, conf: dict | None = None
    ) -> 'MapStore':
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
    def _holistic(
        self, lset: LandmarkSet, k: int, below: int | None, fetch: bool = True
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """The holistic first stage: (cosines (K,), ids (K,), their sets by id), top k by the global
        descriptor among keyframes with id < below (all when None); fetch=False: no sets ({})."""

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

    # keyframe identity (sessions.py): start_session(robot, label=None, started_ns=None) -> Session,
    # sessions() -> [Session], set_origin(keyframe_id, session_id, seq), origins(ids=None) -> {id: Origin}

    @abc.abstractmethod
    def origins(self, keyframe_ids=None) -> dict: ...

    # ------------------------------------------------------------------ shared by the backends

    def query(
        self,
        lset: LandmarkSet,
        prefilter_k: int = retrieval_conf['prefilter_k'],
        k: int = 5,
        min_score: float | None = None,
        exclude_recent: int = 0,
        method_rerank: bool = True,
        scale: float = 1.0,
        prefilter: str | None = None,
        exclude_ids=None,
        include_ids=None,
        center: bool | str | None = None,
    ) -> list[MapCandidate]:
        """The best k keyframes for a query landmark set, best first: first stage -> fetch -> rerank.

        prefilter (default retrieval.default_conf['prefilter']): 'landmarks' = the top prefilter_k
        keyframes of the landmark index (landmark_index.score_hits), 'holistic' = the top
        prefilter_k by global-descriptor cosine, 'exhaustive' (or prefilter_k 0) = every allowed
        keyframe. The exclude_recent most recently added keyframes are never answers. The
        candidates are reranked by the landmark similarity S (method_rerank=False: the first-stage
        ranking alone, its score as `score`), those below min_score dropped. include_ids: keyframes
        reranked besides the first stage's (the sequence search's next places, Localizer
        sequence_carry); excluded ones and ids not in the map are left out. center: S's sets (similarity
        center: False raw, True centred, 'whiten', 'fuse'; None = similarity.default_conf's).
        """
        prefilter, prefilter_k = check_prefilter(prefilter or retrieval_conf['prefilter'], prefilter_k)
        k, exclude_recent = self._query_args(lset, k, exclude_recent, method_rerank)
        with self._lock:
            self._ready()
            if self._model is None or not self._ids:
                return []
            given = {
                'descriptor_space': lset.descriptor_space or self._model['descriptor_space'],
                'descriptor_dim': lset.dim,
            }
            if not self._same_space(given):
                raise self._mismatch(given, 'a query')
            if exclude_recent >= len(self._ids):
                return []
            cutoff = self._ids[-exclude_recent] if exclude_recent else None
            drop = {int(i) for i in exclude_ids} if exclude_ids is not None and len(exclude_ids) else set()
            first, more = None, len(drop)  # each stage asks for `more` extra, then drops them
            if prefilter == 'exhaustive':
                hol, ids, sets = self._every_keyframe(lset, exclude_recent)
                hol, ids = _without(drop, len(ids), ids, hol)
            elif prefilter == 'holistic':
                hol, ids, sets = self._holistic(lset, min(prefilter_k + more, len(self._ids)), cutoff)
                hol, ids = _without(drop, prefilter_k, ids, hol)
            else:
                if self._landmarks is None:
                    raise MapError(f'map {self.path} has no landmark index')
                ids, first = self._landmarks.shortlist(lset, prefilter_k + more, below=cutoff, scale=scale)
                first, ids = _without(drop, prefilter_k, ids, first)
                found = len(ids)
                if found < prefilter_k:
                    # topped up from the holistic ranking; only the sets that are used are fetched
                    # (fetching all prefilter_k holistic ones took 8 of 31 ms a query at 1k keyframes)
                    k_hol = min(prefilter_k + more, len(self._ids))
                    _, hol_ids, _ = self._holistic(lset, k_hol, cutoff, fetch=False)
                    ids, first = landmark_index.fill(ids, first, _without(drop, len(hol_ids), hol_ids)[0], prefilter_k)
                sets = self._fetch(ids)
                self._check_fetched(ids[:found], sets)
                kept = np.array([int(i) in sets for i in ids], bool)  # a damaged fill was just quarantined
                ids, first = ids[kept], first[kept]
                hol = self._cosines(lset, ids, sets)
            if include_ids is not None and len(include_ids) and prefilter != 'exhaustive':
                ids, hol, sets, first = self._include(lset, include_ids, ids, hol, sets, first, drop, cutoff)
        # the numeric work runs outside the lock
        return self._answer(lset, ids, hol, sets, k, min_score, method_rerank, scale, first, center)

    def _include(self, lset: LandmarkSet, include_ids, ids, hol, sets: dict, first, drop: set, cutoff):
        """The first stage's ids (K,), cosines (K,), sets and first-stage scores (K,) or None, with
        the include_ids that are new, allowed (not in drop, id below cutoff) and stored appended; their
        first-stage score is the lowest (they were not among the first stage's)."""
        have = {int(i) for i in ids}
        new = [i for i in dict.fromkeys(int(i) for i in include_ids) if i not in have and i not in drop]
        new = [i for i in new if (cutoff is None or i < cutoff) and _sorted_has(self._ids, i)]
        more = self._fetch(new) if new else {}
        new = np.array([i for i in new if i in more], np.int64)
        if not len(new):
            return ids, hol, sets, first
        if first is not None:
            first = np.concatenate([first, np.full(len(new), first.min() if len(first) else 0.0, np.float32)])
        hol = np.concatenate([hol, self._cosines(lset, new, more)])
        return np.concatenate([ids, new]), hol, {**sets, **more}, first

    @staticmethod
    def _cosines(lset: LandmarkSet, ids, sets: dict) -> np.ndarray:
        if not len(ids):
            return np.zeros(0, np.float32)
        return np.stack([sets[int(i)].global_descriptor for i in ids]).astype(np.float32) @ np.asarray(
            lset.global_descriptor, np.float32
        )

    # the landmark index (lln_ros/core/landmark_index.py) kept in step with the stored keyframes

    def _new_landmark_index(self) -> LandmarkIndex:
        return LandmarkIndex(int(self._model['descriptor_dim']), self.conf, self._model['descriptor_space'])

    def _held_total(self, stored: dict) -> int:
        """Landmarks the landmark index holds for stored {keyframe id: n} (landmark_index_top)."""
        return sum(landmark_index.held_count(n, self.conf) for n in stored.values())

    def _landmark_problems(self, stored: dict) -> list[str]:
        """Disagreements between the landmark index and stored {keyframe id: n}."""
        if self._landmarks is None:
            return [f'no landmark index but {len(stored)} keyframes'] if stored else []
        wrong = landmark_disagreements(self._landmarks, stored)
        if not wrong:
            return []
        return [
            f'landmark index disagrees with the stored keyframes on {len(wrong)} keyframes (e.g. '
            + ', '.join(f'{i}: {held} indexed, {due} expected' for i, (held, due) in list(wrong.items())[:5])
            + ')'
        ]

    path: str = ''
    _model: dict | None = None

    @staticmethod
    def _check_model_dict(model: dict) -> dict:
        """The model validated by lln_ros.core.limits.validate_model (the one check the node, both
        backends and lln-map share): nothing unvalidated is ever written as a model record."""
        try:
            return validate_model(model)
        except ModelError as e:
            raise MapError(
                f'model for map must be Extractor.model_info (descriptor_space, descriptor_dim): {e}'
            ) from None

    def _read_model_record(self, text: str) -> dict:
        """The model record of the map file, validated; MapError explains a bad one."""
        try:
            return validate_model(parse_model_json(text, 'model record'))
        except (ValueError, RecursionError) as e:  # ModelError and JSONDecodeError are ValueErrors
            raise MapError(
                f'map {self.path} has a bad model record ({e}): {text[:200]!r}; '
                f'the map cannot be used until the record is repaired'
            ) from None

    @property
    def quarantined(self) -> dict:
        """{keyframe id: what is wrong} of damaged keyframes found at open: left in the file, never
        answered or returned by ids() (the SQLite backend; lln-map check lists them too)."""
        return dict(getattr(self, '_quarantined', {}))

    def _mismatch(self, other: dict, what: str) -> MapError:
        return MapError(
            f'map {self.path} was built with model {_describe(self._model)}; refusing {what} '
            f'from model {_describe(other)}: descriptors from different models cannot be '
            f'compared (use a map file made with this model, or delete this one)'
        )

    def _same_space(self, model: dict) -> bool:
        return model['descriptor_space'] == self._model['descriptor_space'] and int(model['descriptor_dim']) == int(
            self._model['descriptor_dim']
        )

    def _check_storable(self, lset: LandmarkSet) -> dict:
        """Validate a keyframe before storing it; returns its {descriptor_space, descriptor_dim}."""
        lset.validate()
        if len(lset) == 0:
            raise DescriptorError('landmark set has no landmarks; nothing to store')
        if not lset.descriptor_space:
            raise MapError(
                f'landmark set has no descriptor_space; refusing to store it in map {self.path} '
                f'(a persistent map must know which model made its descriptors)'
            )
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
        ids = np.asarray(self._ids[: len(self._ids) - exclude_recent], np.int64)
        sets = self._fetch(ids)
        self._check_fetched(ids, sets)
        if not len(ids):
            return np.zeros(0, np.float32), ids, sets
        hol = np.stack([sets[int(i)].global_descriptor for i in ids]).astype(np.float32) @ np.asarray(
            lset.global_descriptor, np.float32
        )
        order = np.argsort(-hol, kind='stable')
        return hol[order], ids[order], sets

    def _check_fetched(self, ids, sets: dict) -> None:
        missing = [int(i) for i in ids if int(i) not in sets]
        if missing:
            raise MapError(f'map {self.path}: keyframes {missing[:10]} are in the index but not in the store')

    def _answer(
        self,
        lset: LandmarkSet,
        ids: np.ndarray,
        hol: np.ndarray,
        sets: dict,
        k: int,
        min_score: float | None,
        method_rerank: bool,
        scale: float,
        first: np.ndarray | None = None,
        center: bool | str | None = None,
    ) -> list[MapCandidate]:
        """Rerank the first stage's keyframes (ids (K,), holistic cosines (K,), their sets by id;
        first (K,): the landmark first-stage scores, None = holistic order; center: S's, as query's)."""
        self._check_fetched(ids, sets)
        if not len(ids):
            return []
        if method_rerank:
            # a list: matched in chunks grouped by landmark count (similarity.match_sets), so one
            # long keyframe neither pads the others nor sizes the batch; sorted: min_score drops a tail
            ranked = rerank(lset, [sets[int(i)] for i in ids], ids, hol, scale, limit=k, center=center)
        else:
            first = hol if first is None else first
            ranked = [Candidate(int(i), float(f), float(h)) for i, f, h in zip(ids, first, hol)]
        out = []
        for c in ranked:
            if min_score is not None and c.score < min_score:
                continue
            s = sets[c.index]
            pairs = pair_regions(lset, s, c.pairs)
            out.append(
                MapCandidate(
                    c.index,
                    float(c.score),
                    float(c.holistic_score),
                    s.meta['stamp'],
                    tuple(int(v) for v in c.offset),
                    (float(s.cell_size[0]), float(s.cell_size[1])),
                    (float(s.image_size[0]), float(s.image_size[1])),
                    pairs,
                )
            )
            if len(out) == k:
                break
        origins = self.origins([m.keyframe_id for m in out]) if out else {}
        for m in out:
            m.session_id = origins[m.keyframe_id].session_id if m.keyframe_id in origins else 0
        return out

    def add(self, lset: LandmarkSet, stamp=(0, 0)) -> int:
        """Store one keyframe; returns its id once it is durably stored."""
        return self.add_many([lset], [stamp])[0]

    def _check_many(self, sets: list[LandmarkSet], stamps, ids) -> tuple[list, dict]:
        """Validate an add_many call; returns the (sec, nanosec) stamps and the sets' descriptor space."""
        stamps = [_stamp(st) for st in stamps]
        if len(stamps) != len(sets) or (ids is not None and len(ids) != len(sets)):
            raise ValueError(
                f'{len(sets)} landmark sets need as many stamps (and ids); got {len(stamps)}'
                f'{"" if ids is None else f" and {len(ids)}"}'
            )
        if ids is not None and any(not 1 <= int(i) <= KEYFRAME_ID_MAX for i in ids):
            raise ValueError(f'keyframe ids must be in [1, {KEYFRAME_ID_MAX}] (the answers carry them as UINT32)')
        spaces = [self._check_storable(lset) for lset in sets]
        given = spaces[0]
        if any(sp != given for sp in spaces):
            raise MapError(
                f'landmark sets from different models in one add_many: {given}, '
                f'{next(sp for sp in spaces if sp != given)}'
            )
        # validated as any model is: a new map's model record may be written from it
        return stamps, self._check_model_dict(given)

    def __len__(self) -> int:
        with self._lock:
            self._ready()
            return len(self._ids)

    def __contains__(self, keyframe_id) -> bool:
        with self._lock:
            self._ready()
            return int(keyframe_id) in set(self._ids)

    def ids(self) -> list[int]:
        """Keyframe ids, ascending (insertion order, except in a Milvus map several processes write:
        each takes ids from blocks of its own, milvus_claims.py)."""
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
            chunk = ids[start : start + batch]
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
