"""The Milvus map backend: the same MapStore API on a Milvus server, cluster or Milvus Lite.

The class is split by part: the row format, read cache and integrity check (each described there)
are in milvus_rows.py; the collections, the meta record and the map-wide operations (delete, clear,
info, save, compact, check, close) in milvus_collections.py; the open's read of every row and the
keypoints in milvus_mixins.py; the claimed id blocks and session numbers of many writers, and the
refresh that follows them, in milvus_claims.py; the schema 1 reader in milvus_schema1.py.

    MapStore.open('milvus-lite:///data/map.db')                 # Milvus Lite (embedded, a directory)
    MapStore.open('milvus://milvus.fleet:19530/lln?map=city')   # a Milvus server or cluster

URI: ``milvus://host:port[/database][?map=name]`` talks to ``http://host:port`` (token from the
environment variable MILVUS_TOKEN, e.g. ``user:password``); the database is created when a new map
is created in it. ``milvus-lite://PATH`` opens Milvus Lite at PATH (must end in .db). ``map``
(default ``lln``) prefixes the collection names, so one database holds many maps. Written with the
pymilvus MilvusClient API; tested on Milvus Lite 3.2.2 and on a real Milvus 2.3.5 standalone server
(test/test_milvus_server.py).

Schema version 5 (collections; Milvus 2.3 allows one vector field per collection; 3 added
{map}_geometry, milvus_geometry.py; 4 {map}_sessions and {map}_origins, milvus_sessions.py;
5 {map}_claims, milvus_claims.py)::

    {map}_meta       key VARCHAR primary, value VARCHAR, unused FLOAT_VECTOR(2)   -- format,
                     schema_version, model, descriptor_space, descriptor_dim, next_id (the floor of
                     claimed ids: what schema 4's one writer had reserved; 1 in a new map),
                     map_uuid (names the map to this machine's landmark index file)
    {map}_frames     one row per keyframe: id INT64 primary, stamp_sec, stamp_nanosec INT64,
                     image_w, image_h, cell_w, cell_h FLOAT, grid_rows, grid_cols, n INT32,
                     global_descriptor FLOAT_VECTOR(D) (FLAT index, inner product; searched by Milvus),
                     landmarks ARRAY<VARCHAR(65535)>(64): base64 of the SQLite backend's four blobs
                     concatenated, cells int16 (n, 2) | centers float32 (n, 2) | scores float32 (n,) |
                     descriptors float16 (n, D), little-endian, cut into 65,532-character pieces
    {map}_keypoints  (created by the first add_keypoints; verify mode) keyframe_id INT64 primary,
                     n, width INT32, data ARRAY<VARCHAR>: base64 of uv float32 (n, 2) | descriptors
                     uint8 (n, width), unused FLOAT_VECTOR(2)

One row per keyframe because a query's candidates are then one fetch by primary key (or none: the
read cache below); schema 1 had a row per landmark ({map}_keyframes + {map}_landmarks)
and a query filtered ~1,500 rows (526 ms p50 at 1,000 keyframes on Milvus Lite). A keyframe holds up
to 3.1 MB of landmarks (n * D <= ~1.5 M). Schema 1 maps are migrated at open (MIGRATIONS).

Consistency: collections use Session consistency (this client reads its own writes at once; Milvus's
default, Bounded, hid the meta record just written). Opening reads with Strong consistency, so a map
written by another process is seen whole. Any number of processes may write one map: each takes
keyframe ids from blocks of ID_BLOCK it claimed and session numbers it claimed (milvus_claims.py),
so an add costs one insert; a process that stops leaves the rest of its block unused (ids are
unique and never reused, not consecutive: writers' blocks interleave). Every process sees the
others' new keyframes within conf['refresh_s'] (the id list is refreshed at most that often). ``add``
returns once Milvus acknowledged the insert; inserts go in batches of at most conf['insert_bytes']
(the server refuses gRPC messages over 64 MB). Every pymilvus / gRPC error becomes a MapError naming the map.


Landmark index: local FAISS (lln_ros.core.landmark_index), built from the rows at open; once trained
(IVF-PQ) it is kept in a file on this machine (conf['landmark_dir']) and caught up with the rows at
the next open instead of training again.

"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time

import numpy as np

from ..core import landmark_index
from ..core.landmarks import LandmarkSet
from ..errors import LLNError, MapError
from .base import FORMAT, MapStore
from .milvus_claims import ID_BLOCK, MilvusClaims  # noqa: F401  (ID_BLOCK: this module's API too)
from .milvus_collections import SCHEMA_VERSION, MilvusCollections
from .milvus_geometry import MilvusGeometry
from .milvus_mixins import MilvusKeypoints, MilvusLandmarks
from .milvus_rows import (  # noqa: F401  (pack, unpack, parse_uri, RowCache: this module's API too)
    _FETCH_IDS,
    _PIECES,
    _QUERY_ROWS,
    _SCALARS,
    RowCache,
    _is_milvus_error,
    compact_row,
    explain,
    pack,
    parse_uri,
    row_problem,
    scan_ids,
    unpack,
)
from .milvus_schema1 import MIGRATIONS
from .milvus_sessions import MilvusSessions

log = logging.getLogger(__name__)


class MilvusMapStore(
    MilvusCollections, MilvusClaims, MilvusLandmarks, MilvusKeypoints, MilvusGeometry, MilvusSessions, MapStore
):
    """A map in Milvus collections (see the module docstring); MapStore's API and error behaviour."""

    default_conf = {
        **landmark_index.default_conf,
        'index_type': 'FLAT',  # global-descriptor index; on a cluster e.g. 'HNSW' or 'AUTOINDEX'
        'timeout': 30.0,  # seconds per Milvus call
        'insert_bytes': 16 << 20,  # largest insert message; the 2.3 server refuses gRPC messages > 64 MB
        'refresh_s': 1.0,  # a reader re-reads the id list (other processes' writes) at most this often
        'consistency': 'Session',  # collections' consistency level; Strong waits ~0.4 s per read
        'seal_rows': 1000,  # flush (seal) after this many inserted rows: searching unsealed rows is
        # brute force and slow (Milvus Lite: 30 -> 500 ms at 4,000 unsealed)
        'landmark_dir': '~/.cache/lln_ros/milvus-landmarks',  # where this machine keeps a trained
        # (IVF-PQ) landmark index between opens, a file per map, caught up with the rows at open
        # (training it again took minutes on a loaded 2-core machine); '' = rebuilt at every open
        'cache_mb': 512,  # read cache of stored keyframes (~21 KB each at n=50, D=192: ~24k keyframes);
        # 0 = every query fetches its candidates from the server
    }

    def __init__(
        self, path, model: dict | None = None, create: bool = True, verify: bool = True, conf: dict | None = None
    ):
        try:
            from pymilvus import MilvusClient  # needed by this backend only
        except ImportError as e:
            raise MapError(
                f'map {path} needs the Milvus backend: pip install pymilvus==3.0.2 milvus-lite==3.2.2 ({e})'
            ) from e
        self.conf = {**self.default_conf, **(conf or {})}
        where = parse_uri(path)
        self.path = where['label']
        self._lock = threading.RLock()
        self._model = None
        self._ids: list[int] = []
        self._landmarks = None  # the landmark first stage: a local FAISS index, built at open
        # ids this process deleted: with Session consistency another read may still list them for a while,
        # and a refresh must not bring them back (into _ids or the landmark index)
        self._deleted: set[int] = set()
        self._claims_init()
        self._refreshed = time.monotonic()
        self._has_keypoints = False
        self._uuid, self._landmarks_dirty = None, False
        self._quarantined: dict[int, str] = {}  # damaged keyframes found by a read: never answered
        self._cache = RowCache(float(self.conf['cache_mb']) * 2**20)
        m = where['map']
        self._meta_c, self._fr_c, self._kp_c = f'{m}_meta', f'{m}_frames', f'{m}_keypoints'
        self._v1 = (f'{m}_keyframes', f'{m}_landmarks')
        is_lite = not where['uri'].startswith('http')
        if is_lite and os.path.exists(where['uri']) and not os.path.isdir(where['uri']):
            raise MapError(
                f'{where["uri"]} is a file, not a Milvus Lite map (a directory); '
                f'an SQLite map is opened by its plain path'
            )
        if is_lite and not create and not os.path.isdir(where['uri']):
            raise MapError(f'no map at {self.path} (create=False)')
        if is_lite:
            try:
                os.makedirs(os.path.dirname(where['uri']), exist_ok=True)
            except OSError as e:
                raise MapError(f'cannot create map {self.path}: {e}') from e
        self._client, self._broken = None, False
        self._unsealed = 0
        try:
            with self._errors('open'):
                kwargs = {'uri': where['uri'], 'timeout': self.conf['timeout']}
                if os.environ.get('MILVUS_TOKEN') and not is_lite:
                    kwargs['token'] = os.environ['MILVUS_TOKEN']
                self._client = MilvusClient(**kwargs)
                if where['db_name']:
                    self._use_database(where['db_name'], create)
                    self._client.close()  # use_database asks DescribeDatabase, which a 2.3 server lacks
                    kwargs['db_name'] = where['db_name']
                    self._client = MilvusClient(**kwargs)
                self._connect_kwargs = kwargs
                if not self._client.has_collection(self._meta_c):
                    if not create:
                        raise MapError(f'no map at {self.path} (create=False; no {self._meta_c} collection)')
                    self._create_meta()
                self._load()
            if model is not None:
                self.use_model(model)
        except BaseException:
            if self._client is not None:
                self._client.close()
            self._client = None
            raise

    # ------------------------------------------------------------------ plumbing

    @contextlib.contextmanager
    def _errors(self, what: str):
        try:
            yield
        except LLNError:
            raise
        except Exception as e:
            if not _is_milvus_error(e):
                raise
            text = explain(e)
            # pymilvus's own recovery can stay failed after a server restart: a new client next call
            self._broken = self._broken or any(w in text for w in ('UNAVAILABLE', 'Fail connecting', 'onnection'))
            raise MapError(f'map {self.path}: {what} failed: {text}') from e

    def _reconnect(self) -> None:
        from pymilvus import MilvusClient

        with self._errors('reconnecting'):
            try:
                self._client.close()
            except Exception:  # the old channel is broken anyway
                pass
            self._client = MilvusClient(**self._connect_kwargs)
            for name in (self._meta_c, self._fr_c, self._kp_c):
                if self._client.has_collection(name):
                    self._load_ready(name)
            self._broken = False
            log.info('map %s: reconnected to the Milvus server', self.path)

    def _ready(self) -> None:
        if self._client is None:
            raise MapError(f'map {self.path} is closed')
        if self._broken:
            self._broken = False
            self._reconnect()
        if time.monotonic() - self._refreshed >= self.conf['refresh_s']:
            self._refresh()

    def _scan_ids(self) -> list[int]:
        return scan_ids(self._client, self._fr_c)

    def _creators_meta(self) -> dict:
        """The meta rows of a map another writer is creating right now: its meta collection exists but
        is still empty (fleet matchers starting together on a new map; one refused to start with 'not
        an lln_ros map' in bench_fleet). Waits up to conf['timeout'] s; {} if they never come."""
        deadline = time.monotonic() + float(self.conf['timeout'])
        while time.monotonic() < deadline:
            time.sleep(0.2)
            meta = self._meta(strong=True)
            if meta:
                return meta
        return {}

    def _load(self) -> None:
        for name in (self._meta_c, self._fr_c, self._kp_c):
            # a fresh server process (Milvus Lite in a new process) starts with collections released
            if self._client.has_collection(name):
                self._load_ready(name)
        meta = self._meta(strong=True) or self._creators_meta()
        if meta.get('format') != FORMAT:
            raise MapError(
                f'{self.path} is a Milvus database but not an lln_ros map '
                f'(meta format is {meta.get("format")!r}, expected {FORMAT!r})'
            )
        version = int(meta.get('schema_version', '0') or 0)
        if version > SCHEMA_VERSION:
            raise MapError(
                f'map {self.path} has schema version {version}; this lln_ros reads up to '
                f'{SCHEMA_VERSION}: upgrade lln_ros'
            )
        while version < SCHEMA_VERSION:
            if version not in MIGRATIONS:
                raise MapError(
                    f'map {self.path} has schema version {version} and there is no migration to {version + 1}'
                )
            MIGRATIONS[version](self, meta)
            self._put_meta({'schema_version': str(version + 1)})  # the commit point of the migration
            log.info('migrated map %s from schema %d to %d', self.path, version, version + 1)
            version += 1
            meta = self._meta(strong=True)
        for old in self._v1:  # left by a migration that stopped after its commit point
            if self._client.has_collection(old):
                self._client.drop_collection(old)
        self._model = self._read_model_record(meta['model']) if 'model' in meta else None
        self._uuid = meta.get('map_uuid')
        self._floor = int(meta.get('next_id', 1))
        self._ids = []
        self._has_keypoints = self._client.has_collection(self._kp_c)
        if self._model is None:
            return
        if not self._client.has_collection(self._fr_c):
            self._create_frames(int(self._model['descriptor_dim']))
        self._load_landmarks()  # reads and checks every row
        self._refreshed = time.monotonic()
        self._check_claimed(max(self._ids[-1] if self._ids else 0, max(self._quarantined, default=0)))

    # ------------------------------------------------------------------ model

    def use_model(self, model: dict) -> None:
        """Record the model on first use, or refuse one from another descriptor space."""
        model = self._check_model_dict(model)
        with self._lock, self._errors('recording the model'):
            self._ready()
            if self._model is None:
                if not self._client.has_collection(self._fr_c):
                    self._create_frames(model['descriptor_dim'])
                self._put_meta(
                    {
                        'model': json.dumps(model, sort_keys=True, default=str),
                        'descriptor_space': model['descriptor_space'],
                        'descriptor_dim': str(model['descriptor_dim']),
                    }
                )
                self._model = model
                self._landmarks = self._new_landmark_index()
            elif not self._same_space(model):
                raise self._mismatch(model, 'the extractor')

    # ------------------------------------------------------------------ rows <-> sets

    @staticmethod
    def _frame_row(kid: int, lset: LandmarkSet, sec: int, nsec: int) -> dict:
        return {
            'id': kid,
            'stamp_sec': sec,
            'stamp_nanosec': nsec,
            'image_w': float(lset.image_size[0]),
            'image_h': float(lset.image_size[1]),
            'cell_w': float(lset.cell_size[0]),
            'cell_h': float(lset.cell_size[1]),
            'grid_rows': int(lset.grid[0]),
            'grid_cols': int(lset.grid[1]),
            'n': len(lset),
            'global_descriptor': np.asarray(lset.global_descriptor, np.float32).tolist(),
            'landmarks': pack(
                np.ascontiguousarray(lset.cells, '<i2'),
                np.ascontiguousarray(lset.centers, '<f4'),
                np.ascontiguousarray(lset.scores, '<f4'),
                np.ascontiguousarray(lset.descriptors, '<f2'),
            ),
        }

    def _row_to_set(self, row: dict) -> LandmarkSet:
        """A compact row (compact_row) -> its LandmarkSet; MapError when it is damaged."""
        kid, n, dim = row['id'], int(row['n']), int(self._model['descriptor_dim'])
        problem = row_problem(row, dim)
        if problem:
            raise MapError(f'map {self.path} is corrupt: {problem}')
        blob = row['blob']
        cells = np.frombuffer(blob, '<i2', 2 * n, 0).reshape(n, 2)
        centers = np.frombuffer(blob, '<f4', 2 * n, 4 * n).reshape(n, 2)
        scores = np.frombuffer(blob, '<f4', n, 12 * n)
        desc = np.frombuffer(blob, '<f2', n * dim, 16 * n).reshape(n, dim)
        return LandmarkSet(
            global_descriptor=row['gd'],
            descriptors=desc.astype(np.float32),
            cells=cells.astype(np.int32),
            centers=centers.astype(np.float32),
            scores=scores.astype(np.float32),
            cell_size=np.array([row['cell_w'], row['cell_h']], np.float32),
            image_size=np.array([row['image_w'], row['image_h']], np.float32),
            grid=(int(row['grid_rows']), int(row['grid_cols'])),
            activation=None,
            descriptor_space=self._model['descriptor_space'],
            meta={'keyframe_id': kid, 'stamp': (int(row['stamp_sec']), int(row['stamp_nanosec']))},
        )

    def _fetch(self, ids) -> dict[int, LandmarkSet]:
        """The sets of these ids: from the read cache, the rest in one query by primary key per
        _FETCH_IDS; a damaged row is quarantined (left out of the answer)."""
        sets, missing = {}, []
        for i in ids:
            row = self._cache.get(int(i))
            if row is None:
                missing.append(int(i))
            else:
                sets[row['id']] = self._row_to_set(row)
        if not missing:
            return sets
        dim, bad = int(self._model['descriptor_dim']), {}
        with self._errors('read'):
            for start in range(0, len(missing), _FETCH_IDS):
                chunk = missing[start : start + _FETCH_IDS]
                for r in self._client.query(self._fr_c, filter=f'id in {chunk}', output_fields=['*'], limit=len(chunk)):
                    row = compact_row(r)
                    problem = row_problem(row, dim)
                    if problem:
                        bad[row['id']] = problem
                        continue
                    self._cache.put(row)
                    sets[row['id']] = self._row_to_set(row)
        if bad:
            self._quarantine(bad)
        return sets

    # ------------------------------------------------------------------ public API

    def add_many(self, sets: list[LandmarkSet], stamps, ids=None) -> list[int]:
        """Store keyframes; returns their ids once Milvus acknowledged every insert. ids: keep these
        ids (export / import between maps); MapError if one is taken. Inserts go in messages of at
        most conf['insert_bytes']; if one fails, the keyframes of the batches before it stay stored."""
        if not sets:
            return []
        stamps, given = self._check_many(sets, stamps, ids)
        with self._lock, self._errors('insert'):
            self._ready()
            if self._model is None:
                self.use_model(given)
            elif not self._same_space(given):
                raise self._mismatch(given, 'a landmark set')
            if ids is None:  # from this store's claimed block (milvus_claims.py): no other writer's
                new_ids = self._allocate(len(sets))
            else:
                new_ids = [int(i) for i in ids]
                taken = sorted(set(new_ids) & (set(self._ids) | set(self._quarantined)))
                if taken:
                    raise MapError(f'map {self.path} already has keyframes {taken[:10]}')
                self._claim_given(new_ids)
            rows = [self._frame_row(kid, lset, sec, nsec) for kid, lset, (sec, nsec) in zip(new_ids, sets, stamps)]
            batch, size = [], 0
            for row in rows + [None]:
                nbytes = (
                    0 if row is None else sum(map(len, row['landmarks'])) + 12 * len(row['global_descriptor']) + 256
                )
                if batch and (row is None or size + nbytes > self.conf['insert_bytes']):
                    self._client.insert(self._fr_c, batch)
                    for r in batch:  # acknowledged: what a later query reads
                        self._cache.put(compact_row(r))
                    self._ids.extend(r['id'] for r in batch)
                    self._unsealed += len(batch)
                    batch, size = [], 0
                if row is not None:
                    batch.append(row)
                    size += nbytes
            self._ids.sort()  # another writer's keyframes may have higher ids (blocks interleave)
            self._landmarks.add_sets(new_ids, sets)
            self._landmarks_dirty = True
            self._retrain_if_needed()
            if self.conf['seal_rows'] and self._unsealed >= self.conf['seal_rows']:
                self._client.flush(self._fr_c)
                self._unsealed = 0
            return new_ids

    def _holistic(
        self, lset: LandmarkSet, k: int, below: int | None, fetch: bool = True
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """The holistic first stage: one Milvus search, then the hits' landmarks (fetch=False: none)."""
        with self._errors('query'):
            where = f'id < {int(below)}' if below is not None else ''
            hits = self._client.search(
                self._fr_c,
                data=[np.asarray(lset.global_descriptor, np.float32).tolist()],
                anns_field='global_descriptor',
                limit=min(k, _QUERY_ROWS),
                filter=where,
                search_params={'metric_type': 'IP'},
                output_fields=['id'],  # the rows come from the read cache or one fetch by primary key
            )[0]
            # a search right after a delete may still see the deleted rows (Session consistency, a loaded
            # server): answer only with keyframes this process knows to be live
            live = set(self._ids)
            hits = [h for h in hits if int(h['id']) in live]
            ids = np.array([int(h['id']) for h in hits], np.int64)
            hol = np.array([float(h['distance']) for h in hits], np.float32)
            if not fetch:
                return hol, ids, {}
            sets = self._fetch(ids)
            keep = np.array([int(i) in sets for i in ids], bool)  # a damaged row was just quarantined
            return hol[keep], ids[keep], sets

    def get(self, keyframe_id: int) -> LandmarkSet:
        with self._lock, self._errors('get'):
            self._ready()
            sets = self._fetch([int(keyframe_id)]) if self._model and int(keyframe_id) in self._ids else {}
        if int(keyframe_id) not in sets:
            raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
        return sets[int(keyframe_id)]

    def __repr__(self) -> str:
        state = 'closed' if self._client is None else f'{len(self._ids)} keyframes'
        return f'MilvusMapStore({self.path!r}, {state})'
