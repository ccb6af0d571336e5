"""The Milvus map backend: the same MapStore API on a Milvus server, cluster or Milvus Lite.

    MapStore.open('milvus-lite:///data/map.db')                 # Milvus Lite (embedded, a directory)
    MapStore.open('milvus://milvus.fleet:19530/lln?map=city')   # a Milvus server or cluster

URI: ``milvus://host:port[/database][?map=name]`` talks to ``http://host:port`` (token from the
environment variable MILVUS_TOKEN, e.g. ``user:password``); ``milvus-lite://PATH`` opens Milvus Lite
at PATH (must end in .db). ``map`` (default ``lln``) prefixes the collection names, so one database
holds many maps. Written with the pymilvus MilvusClient API, which Milvus Lite also speaks.

Collections (Milvus needs one vector field per collection)::

    {map}_meta       key VARCHAR primary, value VARCHAR, unused FLOAT_VECTOR(2)   -- format,
                     schema_version, model, descriptor_space, descriptor_dim, next_id (ids never reused)
    {map}_keyframes  id INT64 primary, stamp_sec, stamp_nanosec INT64, image_w, image_h, cell_w,
                     cell_h FLOAT, grid_rows, grid_cols, n INT32,
                     global_descriptor FLOAT_VECTOR(D), FLAT index, inner product
    {map}_landmarks  pk INT64 auto, keyframe_id INT64 (INVERTED index), rank INT32 (0..n-1),
                     col, row INT16, score FLOAT, center FLOAT_VECTOR(2) (u, v pixels),
                     descriptor ARRAY<INT16>(D): the float16 descriptor's bits

Milvus Lite 3.2 has no FLOAT16_VECTOR or BINARY field, so descriptors travel as int16 arrays
holding float16 bits (same precision as the SQLite backend). One writer per map: the id list and
next_id are kept in memory and only this process adds to the map. ``add`` returns when Milvus has
acknowledged the insert; ``save`` flushes (seals) the segments. Not kill -9 tested (the SQLite
backend is).
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from urllib.parse import parse_qs, urlparse

import numpy as np

from .. import landmark_index
from ..errors import MapError
from ..landmarks import LandmarkSet
from .base import FORMAT, MapStore

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
_QUERY_ROWS = 16384  # Milvus caps offset + limit of one query at 16384 rows


def parse_uri(uri: str) -> dict:
    """{'uri', 'db_name', 'map', 'label'} for pymilvus from a milvus:// or milvus-lite:// URI."""
    text = os.fspath(uri)
    if text.startswith('milvus-lite:'):
        path = text[len('milvus-lite:'):]
        path = path[2:] if path.startswith('//') else path
        path, _, query = path.partition('?')
        path = os.path.abspath(os.path.expanduser(path))
        if not path.endswith('.db'):
            raise MapError(f'Milvus Lite map path must end in .db, got {path}')
        name = parse_qs(query).get('map', ['lln'])[0]
        return {'uri': path, 'db_name': '', 'map': name, 'label': f'milvus-lite://{path}?map={name}'}
    url = urlparse(text)
    if url.scheme != 'milvus' or not url.hostname:
        raise MapError(f"Milvus map URI must look like 'milvus://host:port[/database][?map=name]', got {text!r}")
    name = parse_qs(url.query).get('map', ['lln'])[0]
    db = url.path.strip('/')
    endpoint = f'http://{url.hostname}:{url.port or 19530}'
    return {'uri': endpoint, 'db_name': db, 'map': name, 'label': f'milvus://{url.netloc}/{db}?map={name}'}


class MilvusMapStore(MapStore):
    """A map in Milvus collections (see the module docstring); MapStore's API and error behaviour."""

    default_conf = {
        **landmark_index.default_conf,
        'index_type': 'FLAT',   # global-descriptor index; on a cluster e.g. 'HNSW' or 'AUTOINDEX'
        'timeout': 30.0,        # seconds per Milvus call
    }

    def __init__(self, path, model: dict | None = None, create: bool = True, verify: bool = True,
                 conf: dict | None = None):
        try:
            from pymilvus import MilvusClient  # needed by this backend only
        except ImportError as e:
            raise MapError(f'map {path} needs the Milvus backend: pip install pymilvus==3.0.2 '
                           f'milvus-lite==3.2.2 ({e})') from e
        self.conf = {**self.default_conf, **(conf or {})}
        where = parse_uri(path)
        self.path = where['label']
        self._lock = threading.RLock()
        self._model = None
        self._ids: list[int] = []
        self._landmarks = None
        self._next_id = 1
        names = {k: f"{where['map']}_{k}" for k in ('meta', 'keyframes', 'landmarks')}
        self._meta_c, self._kf_c, self._lm_c = names['meta'], names['keyframes'], names['landmarks']
        is_lite = not where['uri'].startswith('http')
        if is_lite and os.path.exists(where['uri']) and not os.path.isdir(where['uri']):
            raise MapError(f'{where["uri"]} is a file, not a Milvus Lite map (a directory); '
                           f'an SQLite map is opened by its plain path')
        if is_lite and not create and not os.path.isdir(where['uri']):
            raise MapError(f'no map at {self.path} (create=False)')
        if is_lite:
            try:
                os.makedirs(os.path.dirname(where['uri']), exist_ok=True)
            except OSError as e:
                raise MapError(f'cannot create map {self.path}: {e}') from e
        try:
            kwargs = {'uri': where['uri'], 'timeout': self.conf['timeout']}
            if where['db_name']:
                kwargs['db_name'] = where['db_name']
            if os.environ.get('MILVUS_TOKEN') and not is_lite:
                kwargs['token'] = os.environ['MILVUS_TOKEN']
            self._client = MilvusClient(**kwargs)
        except Exception as e:  # pymilvus raises MilvusException, ConnectionError, OSError ...
            raise MapError(f'cannot open map {self.path}: {e}') from e
        try:
            with self._errors('open'):
                if not self._client.has_collection(self._meta_c):
                    if not create:
                        raise MapError(f'no map at {self.path} (create=False; no {self._meta_c} collection)')
                    self._create_meta()
                self._load()
            if model is not None:
                self.use_model(model)
        except BaseException:
            self._client.close()
            self._client = None
            raise

    # ------------------------------------------------------------------ plumbing

    @contextlib.contextmanager
    def _errors(self, what: str):
        from pymilvus.exceptions import MilvusException
        try:
            yield
        except MilvusException as e:
            raise MapError(f'map {self.path}: {what} failed: {e}') from e

    def _ready(self) -> None:
        if self._client is None:
            raise MapError(f'map {self.path} is closed')

    def _create_meta(self) -> None:
        from pymilvus import DataType, MilvusClient
        schema = MilvusClient.create_schema(auto_id=False)
        schema.add_field('key', DataType.VARCHAR, is_primary=True, max_length=64)
        schema.add_field('value', DataType.VARCHAR, max_length=65535)
        schema.add_field('unused', DataType.FLOAT_VECTOR, dim=2)
        index = self._client.prepare_index_params()
        index.add_index('unused', index_type='FLAT', metric_type='L2')
        self._client.create_collection(self._meta_c, schema=schema, index_params=index)
        from .. import __version__
        self._put_meta({'format': FORMAT, 'schema_version': str(SCHEMA_VERSION),
                        'created': str(int(time.time())), 'created_by': f'lln_ros {__version__}',
                        'next_id': '1'})

    def _put_meta(self, values: dict) -> None:
        self._client.upsert(self._meta_c, [{'key': k, 'value': str(v), 'unused': [0.0, 0.0]}
                                           for k, v in values.items()])

    def _meta(self) -> dict:
        rows = self._client.query(self._meta_c, filter='key != ""', output_fields=['key', 'value'])
        return {r['key']: r['value'] for r in rows}

    def _create_data_collections(self, dim: int) -> None:
        from pymilvus import DataType, MilvusClient
        if not self._client.has_collection(self._kf_c):
            schema = MilvusClient.create_schema(auto_id=False)
            schema.add_field('id', DataType.INT64, is_primary=True)
            for name in ('stamp_sec', 'stamp_nanosec'):
                schema.add_field(name, DataType.INT64)
            for name in ('image_w', 'image_h', 'cell_w', 'cell_h'):
                schema.add_field(name, DataType.FLOAT)
            for name in ('grid_rows', 'grid_cols', 'n'):
                schema.add_field(name, DataType.INT32)
            schema.add_field('global_descriptor', DataType.FLOAT_VECTOR, dim=dim)
            index = self._client.prepare_index_params()
            index.add_index('global_descriptor', index_type=self.conf['index_type'], metric_type='IP')
            self._client.create_collection(self._kf_c, schema=schema, index_params=index)
        if not self._client.has_collection(self._lm_c):
            schema = MilvusClient.create_schema(auto_id=True)
            schema.add_field('pk', DataType.INT64, is_primary=True)
            schema.add_field('keyframe_id', DataType.INT64)
            schema.add_field('rank', DataType.INT32)
            schema.add_field('col', DataType.INT16)
            schema.add_field('row', DataType.INT16)
            schema.add_field('score', DataType.FLOAT)
            schema.add_field('center', DataType.FLOAT_VECTOR, dim=2)
            schema.add_field('descriptor', DataType.ARRAY, element_type=DataType.INT16, max_capacity=dim)
            index = self._client.prepare_index_params()
            index.add_index('center', index_type='FLAT', metric_type='L2')
            index.add_index('keyframe_id', index_type='INVERTED')
            self._client.create_collection(self._lm_c, schema=schema, index_params=index)

    def _load(self) -> None:
        for name in (self._meta_c, self._kf_c, self._lm_c):
            # a fresh server process (Milvus Lite in a new process) starts with collections released
            if self._client.has_collection(name):
                self._client.load_collection(name)
        meta = self._meta()
        if meta.get('format') != FORMAT:
            raise MapError(f'{self.path} is a Milvus database but not an lln_ros map '
                           f'(meta format is {meta.get("format")!r}, expected {FORMAT!r})')
        version = int(meta.get('schema_version', '0') or 0)
        if version > SCHEMA_VERSION:
            raise MapError(f'map {self.path} has schema version {version}; this lln_ros reads up to '
                           f'{SCHEMA_VERSION}: upgrade lln_ros')
        self._model = json.loads(meta['model']) if 'model' in meta else None
        self._next_id = int(meta.get('next_id', 1))
        self._ids = []
        if self._model is None:
            return
        self._create_data_collections(int(self._model['descriptor_dim']))
        it = self._client.query_iterator(self._kf_c, batch_size=4096, filter='id >= 0', output_fields=['id'])
        try:
            while rows := it.next():
                self._ids.extend(int(r['id']) for r in rows)
        finally:
            it.close()
        self._ids.sort()
        if self._ids and self._ids[-1] >= self._next_id:
            raise MapError(f'map {self.path} is damaged: keyframe {self._ids[-1]} but next_id {self._next_id}')
        self._load_landmarks()

    # ------------------------------------------------------------------ model

    def use_model(self, model: dict) -> None:
        """Record the model on first use, or refuse one from another descriptor space."""
        model = self._check_model_dict(model)
        with self._lock, self._errors('recording the model'):
            self._ready()
            if self._model is None:
                self._create_data_collections(model['descriptor_dim'])
                self._put_meta({'model': json.dumps(model, sort_keys=True, default=str),
                                'descriptor_space': model['descriptor_space'],
                                'descriptor_dim': str(model['descriptor_dim'])})
                self._model = model
                self._landmarks = self._new_landmark_index()
            elif not self._same_space(model):
                raise self._mismatch(model, 'the extractor')

    # ------------------------------------------------------------------ rows <-> sets

    def _rows_to_sets(self, kf_rows: list, lm_rows: list) -> dict[int, LandmarkSet]:
        dim = int(self._model['descriptor_dim'])
        by_kf: dict[int, list] = {}
        for r in lm_rows:
            by_kf.setdefault(int(r['keyframe_id']), []).append(r)
        out = {}
        for k in kf_rows:
            kid, n = int(k['id']), int(k['n'])
            lms = sorted(by_kf.get(kid, []), key=lambda r: r['rank'])
            if len(lms) != n:
                raise MapError(f'map {self.path} is damaged: keyframe {kid} has {len(lms)} landmarks, expected {n}')
            desc = np.array([r['descriptor'] for r in lms], np.int16)
            if desc.shape != (n, dim):
                raise MapError(f'map {self.path} is damaged: keyframe {kid} descriptors are {desc.shape}, '
                               f'expected {(n, dim)}')
            out[kid] = LandmarkSet(
                global_descriptor=np.asarray(k['global_descriptor'], np.float32),
                descriptors=desc.view(np.float16).astype(np.float32),
                cells=np.array([[r['col'], r['row']] for r in lms], np.int32),
                centers=np.array([r['center'] for r in lms], np.float32),
                scores=np.array([r['score'] for r in lms], np.float32),
                cell_size=np.array([k['cell_w'], k['cell_h']], np.float32),
                image_size=np.array([k['image_w'], k['image_h']], np.float32),
                grid=(int(k['grid_rows']), int(k['grid_cols'])), activation=None,
                descriptor_space=self._model['descriptor_space'],
                meta={'keyframe_id': kid, 'stamp': (int(k['stamp_sec']), int(k['stamp_nanosec']))})
        return out

    def _fetch(self, ids, kf_rows: list | None = None) -> dict[int, LandmarkSet]:
        ids = [int(i) for i in ids]
        if not ids:
            return {}
        with self._errors('read'):
            return self._fetch_rows(ids, kf_rows)

    def _fetch_rows(self, ids: list[int], kf_rows: list | None) -> dict[int, LandmarkSet]:
        if kf_rows is None:
            kf_rows = self._client.query(self._kf_c, filter=f'id in {ids}', output_fields=['*'])
        by_id = {int(k['id']): k for k in kf_rows}
        lm_rows, chunk, rows_in_chunk = [], [], 0
        for i in [i for i in ids if i in by_id] + [None]:
            n = int(by_id[i]['n']) if i is not None else 0
            if chunk and (i is None or rows_in_chunk + n > _QUERY_ROWS):
                lm_rows += self._client.query(self._lm_c, filter=f'keyframe_id in {chunk}', limit=rows_in_chunk,
                                              output_fields=['keyframe_id', 'rank', 'col', 'row', 'score',
                                                             'center', 'descriptor'])
                chunk, rows_in_chunk = [], 0
            if i is not None:
                chunk.append(i)
                rows_in_chunk += n
        return self._rows_to_sets(list(by_id.values()), lm_rows)

    # ------------------------------------------------------------------ public API

    def add_many(self, sets: list[LandmarkSet], stamps, ids=None) -> list[int]:
        """Store keyframes; returns their ids once Milvus acknowledged both inserts.
        ids: keep these ids (export / import between maps); MapError if one is taken."""
        if not sets:
            return []
        stamps, given = self._check_many(sets, stamps, ids)
        with self._lock, self._errors('insert'):
            self._ready()
            if self._model is None:
                self.use_model(given)
            elif not self._same_space(given):
                raise self._mismatch(given, 'a landmark set')
            if ids is None:
                new_ids = list(range(self._next_id, self._next_id + len(sets)))
            else:
                new_ids = [int(i) for i in ids]
                taken = sorted(set(new_ids) & set(self._ids))
                if taken:
                    raise MapError(f'map {self.path} already has keyframes {taken[:10]}')
            next_id = max(self._next_id, max(new_ids) + 1)
            # next_id first: a crash between the writes may skip ids, never reuse them
            self._put_meta({'next_id': next_id})
            kf_rows, lm_rows = [], []
            for kid, lset, (sec, nsec) in zip(new_ids, sets, stamps):
                kf_rows.append({'id': kid, 'stamp_sec': sec, 'stamp_nanosec': nsec,
                                'image_w': float(lset.image_size[0]), 'image_h': float(lset.image_size[1]),
                                'cell_w': float(lset.cell_size[0]), 'cell_h': float(lset.cell_size[1]),
                                'grid_rows': int(lset.grid[0]), 'grid_cols': int(lset.grid[1]), 'n': len(lset),
                                'global_descriptor': np.asarray(lset.global_descriptor, np.float32).tolist()})
                bits = np.ascontiguousarray(lset.descriptors, np.float16).view(np.int16)
                for j in range(len(lset)):
                    lm_rows.append({'keyframe_id': kid, 'rank': j, 'col': int(lset.cells[j, 0]),
                                    'row': int(lset.cells[j, 1]), 'score': float(lset.scores[j]),
                                    'center': lset.centers[j].astype(np.float32).tolist(),
                                    'descriptor': bits[j].tolist()})
            # landmarks before keyframes: a keyframe the index can find always has its landmarks
            self._client.insert(self._lm_c, lm_rows)
            self._client.insert(self._kf_c, kf_rows)
            self._next_id = next_id
            self._ids.extend(new_ids)
            self._ids.sort()
            self._landmarks.add_sets(new_ids, sets)
            return new_ids

    def _holistic(self, lset: LandmarkSet, k: int, below: int | None) -> tuple[np.ndarray, np.ndarray, dict]:
        """The holistic first stage in Milvus (its keyframe rows come back with the hits)."""
        with self._errors('query'):
            where = f'id < {int(below)}' if below is not None else ''
            hits = self._client.search(self._kf_c, data=[np.asarray(lset.global_descriptor, np.float32).tolist()],
                                       anns_field='global_descriptor', limit=k, filter=where,
                                       search_params={'metric_type': 'IP'}, output_fields=['*'])[0]
            ids = np.array([int(h['id']) for h in hits], np.int64)
            hol = np.array([float(h['distance']) for h in hits], np.float32)
            return hol, ids, self._fetch(ids, [{**h['entity'], 'id': h['id']} for h in hits])

    def _load_landmarks(self) -> None:
        """The landmark index is local (FAISS), built from the stored keyframes at every open."""
        self._landmarks = self._new_landmark_index()
        for start in range(0, len(self._ids), 512):
            chunk = self._ids[start:start + 512]
            sets = self._fetch(chunk)
            self._landmarks.add_sets(list(sets), list(sets.values()))

    def get(self, keyframe_id: int) -> LandmarkSet:
        with self._lock, self._errors('get'):
            self._ready()
            sets = self._fetch([int(keyframe_id)]) if self._model and int(keyframe_id) in self._ids else {}
        if int(keyframe_id) not in sets:
            raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
        return sets[int(keyframe_id)]

    def delete(self, keyframe_ids) -> int:
        with self._lock, self._errors('delete'):
            self._ready()
            present = sorted({int(i) for i in keyframe_ids} & set(self._ids))
            if present:
                # keyframes first: the index never finds a keyframe whose landmarks are gone
                self._client.delete(self._kf_c, filter=f'id in {present}')
                self._client.delete(self._lm_c, filter=f'keyframe_id in {present}')
                gone = set(present)
                self._ids = [i for i in self._ids if i not in gone]
                self._landmarks.remove_keyframes(present)
            return len(present)

    def clear(self) -> int:
        with self._lock, self._errors('clear'):
            self._ready()
            if self._model is not None:
                self._client.delete(self._kf_c, filter='id >= 0')
                self._client.delete(self._lm_c, filter='keyframe_id >= 0')
            removed, self._ids = len(self._ids), []
            if self._landmarks is not None:
                self._landmarks.reset()
            return removed

    def info(self) -> dict:
        with self._lock, self._errors('info'):
            self._ready()
            meta = self._meta()
            return {'path': self.path, 'backend': 'milvus', 'keyframes': len(self._ids), 'model': self.model,
                    'descriptor_space': self._model and self._model['descriptor_space'],
                    'descriptor_dim': self._model and int(self._model['descriptor_dim']),
                    'schema_version': int(meta['schema_version']), 'index': self.conf['index_type'],
                    'landmark_index': self._landmarks.kind if self._landmarks is not None else None,
                    'landmarks': self._landmarks.ntotal if self._landmarks is not None else 0,
                    'first_id': self._ids[0] if self._ids else None,
                    'last_id': self._ids[-1] if self._ids else None,
                    'created': int(meta.get('created', 0)), 'created_by': meta.get('created_by', '')}

    def save(self) -> None:
        """Flush (seal) the collections' growing segments."""
        with self._lock, self._errors('flush'):
            self._ready()
            for name in (self._meta_c, self._kf_c, self._lm_c):
                if self._client.has_collection(name):
                    self._client.flush(name)

    def compact(self) -> dict:
        with self._lock, self._errors('compact'):
            self._ready()
            self.save()
            for name in (self._kf_c, self._lm_c):
                if self._client.has_collection(name):
                    self._client.compact(name)
            return {}

    def check(self, limit: int = 20) -> list[str]:
        """Problems found (empty list = healthy): format, model record, keyframe ids against the
        collection, every keyframe's landmark count against its n."""
        problems: list[str] = []
        with self._lock:
            self._ready()
            try:
                meta = self._meta()
                if meta.get('schema_version') != str(SCHEMA_VERSION):
                    problems.append(f'schema_version is {meta.get("schema_version")!r}, expected {SCHEMA_VERSION}')
                if self._model is None:
                    return problems
                counts, n_of = {}, {}
                for coll, field, sink in ((self._lm_c, 'keyframe_id', counts), (self._kf_c, 'id', n_of)):
                    it = self._client.query_iterator(coll, batch_size=4096, filter=f'{field} >= 0',
                                                     output_fields=[field] + (['n'] if coll == self._kf_c else []))
                    try:
                        while rows := it.next():
                            for r in rows:
                                key = int(r[field])
                                sink[key] = r['n'] if coll == self._kf_c else sink.get(key, 0) + 1
                    finally:
                        it.close()
                if sorted(n_of) != self._ids:
                    problems.append(f'keyframes collection holds {len(n_of)} ids, this process knows {len(self._ids)}')
                bad = [f'keyframe {k}: {counts.get(k, 0)} landmark rows, expected n={n}'
                       for k, n in n_of.items() if counts.get(k, 0) != n]
                orphans = sorted(set(counts) - set(n_of))
                bad += [f'landmark rows of keyframe {k} but no such keyframe' for k in orphans]
                problems.extend(bad[:limit])
                if len(bad) > limit:
                    problems.append(f'... and {len(bad) - limit} more like that')
                problems.extend(self._landmark_problems(n_of))
            except MapError as e:
                problems.append(str(e))
            except Exception as e:  # MilvusException and friends: the check reports, it does not raise
                problems.append(f'Milvus error while checking: {e}')
        return problems

    def close(self) -> None:
        with self._lock:
            if self._client is not None:
                try:
                    self._client.close()
                finally:
                    self._client = None
                    self._landmarks = None
                    self._ids = []

    def __repr__(self) -> str:
        state = 'closed' if self._client is None else f'{len(self._ids)} keyframes'
        return f'MilvusMapStore({self.path!r}, {state})'
