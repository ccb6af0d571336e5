"""A part of MilvusMapStore (milvus.py), as a mixin: creating the collections and the meta record
(schema version 5, laid out in milvus.py's docstring), and the map-wide operations delete, clear,
info, save, compact and check. State is MilvusMapStore's."""

from __future__ import annotations

import logging
import time
import uuid

from ..errors import MapError
from .base import FORMAT
from .milvus_rows import _PIECES, _QUERY_ROWS, _SCALARS, explain, row_problem

log = logging.getLogger(__name__.rsplit('_', 1)[0])  # lln_ros.mapstore.milvus, as the backend logs

SCHEMA_VERSION = 5  # 3: the geometry collection (milvus_geometry.py); 4: sessions, origins (milvus_sessions.py);
# 5: claims (milvus_claims.py)


class MilvusCollections:
    """Collections, meta record, info / save / compact / check of a MilvusMapStore."""

    def _use_database(self, db: str, create: bool) -> None:
        names = self._client.list_databases()
        if db not in names:
            if not create:
                raise MapError(
                    f'no map at {self.path}: the server has no database {db!r} (it has {sorted(names)}; create=False)'
                )
            try:
                self._client.create_database(db)
            except Exception:
                # fleet matchers starting together: another one created it a moment ago
                if db not in self._client.list_databases():
                    raise
                return
            log.info('created database %s for map %s', db, self.path)

    def _create(self, name: str, fields: list, vector: str, dim: int) -> None:
        from pymilvus import DataType, MilvusClient

        schema = MilvusClient.create_schema(auto_id=False)
        for field, kind, extra in fields:
            schema.add_field(field, getattr(DataType, kind), **extra)
        schema.add_field(vector, DataType.FLOAT_VECTOR, dim=dim)
        index = self._client.prepare_index_params()
        index.add_index(
            vector, index_type=self.conf['index_type'] if dim > 2 else 'FLAT', metric_type='IP' if dim > 2 else 'L2'
        )
        self._client.create_collection(
            name, schema=schema, index_params=index, consistency_level=self.conf['consistency']
        )

    def _load_ready(self, name: str) -> None:
        """Load a collection once it has its index. Another writer may have created it a moment ago
        (fleet matchers starting together): create_collection with index params is several calls,
        and loading or inserting before the index exists fails 'index not found' (test_milvus_fleet's
        concurrent writers on the claims collection, once in a fresh-clone CI). Waits up to
        conf['timeout'] s; a collection still without one is loaded anyway, and its error is the server's."""
        deadline = time.monotonic() + float(self.conf['timeout'])
        while not self._client.list_indexes(name) and time.monotonic() < deadline:
            time.sleep(0.2)
        self._client.load_collection(name)

    def _create_meta(self) -> None:
        self._create(
            self._meta_c,
            [('key', 'VARCHAR', {'is_primary': True, 'max_length': 64}), ('value', 'VARCHAR', {'max_length': 65535})],
            'unused',
            2,
        )
        from .. import __version__

        self._put_meta(
            {
                'format': FORMAT,
                'schema_version': str(SCHEMA_VERSION),
                'created': str(int(time.time())),
                'created_by': f'lln_ros {__version__}',
                'next_id': '1',
                'map_uuid': uuid.uuid4().hex,  # names this map to its landmark index files
            }
        )

    def _create_frames(self, dim: int) -> None:
        pieces = {'element_type': None, 'max_capacity': _PIECES, 'max_length': 65535}
        from pymilvus import DataType

        pieces['element_type'] = DataType.VARCHAR
        self._create(
            self._fr_c,
            [('id', 'INT64', {'is_primary': True})]
            + [(f, 'INT64', {}) for f in _SCALARS[:2]]
            + [(f, 'FLOAT', {}) for f in _SCALARS[2:6]]
            + [(f, 'INT32', {}) for f in _SCALARS[6:]]
            + [('landmarks', 'ARRAY', pieces)],
            'global_descriptor',
            dim,
        )

    def _put_meta(self, values: dict) -> None:
        self._client.upsert(
            self._meta_c, [{'key': k, 'value': str(v), 'unused': [0.0, 0.0]} for k, v in values.items()]
        )

    def _meta(self, strong: bool = False) -> dict:
        rows = self._client.query(
            self._meta_c,
            filter='key != ""',
            output_fields=['key', 'value'],
            **({'consistency_level': 'Strong'} if strong else {}),
        )
        return {r['key']: r['value'] for r in rows}

    def info(self) -> dict:
        with self._lock, self._errors('info'):
            self._ready()
            meta = self._meta()
            return {
                'path': self.path,
                'backend': 'milvus',
                'keyframes': len(self._ids),
                'model': self.model,
                'descriptor_space': self._model and self._model['descriptor_space'],
                'descriptor_dim': self._model and int(self._model['descriptor_dim']),
                'schema_version': int(meta['schema_version']),
                'index': self.conf['index_type'],
                'landmark_index': self._landmarks.kind if self._landmarks is not None else None,
                'landmarks': self._landmarks.ntotal if self._landmarks is not None else 0,
                'quarantined': sorted(self._quarantined),
                'cache_keyframes': len(self._cache),
                'cache_mb': round(self._cache.bytes / 2**20, 1),
                'first_id': self._ids[0] if self._ids else None,
                'last_id': self._ids[-1] if self._ids else None,
                'created': int(meta.get('created', 0)),
                'created_by': meta.get('created_by', ''),
            }

    def save(self) -> None:
        """Flush (seal) the collections' growing segments; keep a changed trained landmark index."""
        with self._lock, self._errors('flush'):
            self._ready()
            for name in (self._meta_c, self._fr_c, self._kp_c):
                if self._client.has_collection(name):
                    self._client.flush(name)
            self._persist_landmarks()

    def compact(self) -> dict:
        with self._lock, self._errors('compact'):
            self._ready()
            self.save()
            for name in (self._fr_c, self._kp_c):
                if self._client.has_collection(name):
                    self._client.compact(name)
            return {}

    def check(self, limit: int = 20) -> list[str]:
        """Problems found (empty list = healthy): format, schema version, the id list against the
        collection, every keyframe's landmark bytes against its n and D, keypoints without keyframe."""
        problems: list[str] = []
        with self._lock:
            self._ready()
            try:
                meta = self._meta()
                if meta.get('schema_version') != str(SCHEMA_VERSION):
                    problems.append(f'schema_version is {meta.get("schema_version")!r}, expected {SCHEMA_VERSION}')
                if self._model is None:
                    return problems
                found, bad, n_of, dim = [], [], {}, int(self._model['descriptor_dim'])
                for rows in self._scan_rows():
                    for row in rows:
                        found.append(row['id'])
                        # the same check the open runs: the node quarantines exactly these keyframes
                        problem = row_problem(row, dim)
                        if problem:
                            bad.append(f'{problem} (quarantined: never answered)')
                        else:
                            n_of[row['id']] = int(row['n'])
                if sorted(n_of) != self._ids:
                    problems.append(
                        f'frames collection holds {len(n_of)} healthy keyframes, this process knows {len(self._ids)}'
                    )
                if self._has_keypoints:
                    kp = self._client.query(
                        self._kp_c, filter='keyframe_id >= 0', output_fields=['keyframe_id'], limit=_QUERY_ROWS
                    )
                    bad += [
                        f'keypoints of keyframe {k} but no such keyframe'
                        for k in sorted({int(r['keyframe_id']) for r in kp} - set(found))
                    ]
                problems.extend(bad[:limit])
                if len(bad) > limit:
                    problems.append(f'... and {len(bad) - limit} more like that')
                problems.extend(self._landmark_problems(n_of))
            except MapError as e:
                problems.append(str(e))
            except Exception as e:  # MilvusException and friends: the check reports, it does not raise
                problems.append(f'Milvus error while checking: {explain(e)}')
        return problems

    def _delete_ids(self, present: list[int]) -> None:
        for start in range(0, len(present), 4096):
            chunk = present[start : start + 4096]
            # keyframes first: the index never finds a keyframe whose keypoints are gone
            self._client.delete(self._fr_c, filter=f'id in {chunk}')
            if self._has_keypoints:
                self._client.delete(self._kp_c, filter=f'keyframe_id in {chunk}')
            self._delete_geometry(chunk)
            self._delete_origins(chunk)

    def delete(self, keyframe_ids) -> int:
        with self._lock, self._errors('delete'):
            self._ready()
            present = sorted({int(i) for i in keyframe_ids} & set(self._ids))
            if present:
                self._delete_ids(present)
                gone = set(present)
                self._deleted |= gone
                self._ids = [i for i in self._ids if i not in gone]
                self._cache.drop(present)
                self._landmarks.remove_keyframes(present)
                self._landmarks_dirty = True
            return len(present)

    def clear(self) -> int:
        with self._lock, self._errors('clear'):
            self._ready()
            every = sorted(set(self._ids) | set(self._quarantined))  # damaged keyframes go too
            self._delete_ids(every)
            self._deleted |= set(every)
            removed, self._ids, self._quarantined = len(self._ids), [], {}
            self._cache.clear()
            if self._landmarks is not None:
                self._landmarks.reset()
                self._landmarks_dirty = True
            return removed

    def close(self) -> None:
        with self._lock:
            if self._client is not None:
                try:
                    try:
                        with self._errors('keeping the landmark index'):
                            self._persist_landmarks()
                    except MapError as e:  # rebuilt from the map at the next open
                        log.warning('%s', e)
                    self._client.close()
                finally:
                    self._client = None
                    self._landmarks = None
                    self._ids = []
                    self._cache.clear()
