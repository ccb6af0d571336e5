"""The embedded map backend: one SQLite file plus in-memory FAISS indexes.

The query path, writes, deletes and info of one backend; the file (its schema, laid out in
sqlite_file.py's docstring, creation, migrations, load, check and verify mode's keypoints) is in
sqlite_file.py, the landmark index in sqlite_landmarks.py.

In memory: a FAISS index over the global descriptors, keyed by keyframe id (GlobalIndex): exact
(``IndexIDMap(IndexFlatIP(D))``) up to ``conf['index_threshold']`` keyframes (50,000), IVF above
(``IndexIVFFlat``, trained on the map's own descriptors at open, ~1 s at 100k). It is rebuilt from
SQLite at open and checked against it (count and ids); nothing but SQLite is ever written, so there
is no second file to disagree with after a crash. Landmarks stay on disk; a query
fetches the prefiltered keyframes' landmarks with one ``SELECT ... WHERE id IN (...)``. If another
connection (another process) commits to the file, the next call notices (``PRAGMA data_version``)
and adds the keyframes it appended to the indexes (sqlite_catch_up.py), or rebuilds them when it did
anything else.

Thread safety: every call takes one lock (the connection is shared, ``check_same_thread=False``);
the landmark reranking of ``query`` runs outside the lock.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import threading
import time

import numpy as np

from ..core.landmark_index import LandmarkIndex
from ..core.landmark_index import default_conf as landmark_index_defaults
from ..core.landmarks import LandmarkSet
from ..errors import MapError
from .base import MapStore
from .index import GlobalIndex
from .sqlite_catch_up import SQLiteCatchUp
from .sqlite_file import _KF_COLS, _KF_INSERT, _LM_COLS, _SQL_CHUNK, SQLiteFile
from .sqlite_geometry import SQLiteGeometry
from .sqlite_identity import SQLiteIdentity
from .sqlite_landmarks import SQLiteLandmarks
from .sqlite_sessions import SQLiteSessions
from .uri import backend_for

log = logging.getLogger(__name__)


class SQLiteMapStore(
    SQLiteFile, SQLiteCatchUp, SQLiteLandmarks, SQLiteIdentity, SQLiteGeometry, SQLiteSessions, MapStore
):
    """The embedded map: one SQLite file plus an in-memory FAISS index (see the module docstring).

    SQLiteMapStore(path, model=None, create=True, verify=True, conf=None). verify: run SQLite's
    quick_check at open (reads the whole file once; catches truncation and corruption before they
    surface as bad answers). conf: see default_conf (when the FAISS index turns approximate).
    """

    default_conf = {
        **landmark_index_defaults,
        'index_threshold': 50_000,  # keyframes; above this the global index is IVF, below exact
        'ivf_lists': 0,  # IVF cells; 0 = sqrt(keyframes) (at most keyframes / 39) at (re)build
        'ivf_nprobe': 16,  # IVF cells visited per query (recall vs speed: bench/bench_map.py)
    }

    def __init__(
        self, path, model: dict | None = None, create: bool = True, verify: bool = True, conf: dict | None = None
    ):
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
        self._quarantined: dict = {}
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
            self._conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as e:
            raise MapError(f'cannot open map {self.path}: {e}') from e
        self._remember_identity()  # checked before every write is acknowledged (sqlite_identity.py)
        try:
            self._identify()  # read-only: never modify a file that is not ours
            self._configure()
            self._migrate()
            checked = self._start_quick_check() if verify else None
            try:
                self._load()
            finally:
                if checked is not None:
                    checked()  # its MapError, when the file is damaged, replaces whatever _load raised
            if model is not None:
                self._adopt_model(model)
        except sqlite3.OperationalError as e:  # locked, read-only, I/O error
            self._conn.close()
            self._conn = None
            raise MapError(f'cannot open map {self.path}: {e}') from e
        except sqlite3.DatabaseError as e:  # malformed, not a database
            self._conn.close()
            self._conn = None
            raise MapError(f'map {self.path} is corrupt or truncated: {e}') from e
        except BaseException:
            self._conn.close()
            self._conn = None
            raise

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
            log.info(
                'map %s was built with %s; now used with %s (same descriptor space)', self.path, self._model, model
            )

    @staticmethod
    def _record_model(c: sqlite3.Connection, model: dict) -> None:
        c.executemany(
            'INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)',
            [
                ('model', json.dumps(model, sort_keys=True, default=str)),
                ('descriptor_space', model['descriptor_space']),
                ('descriptor_dim', str(model['descriptor_dim'])),
            ],
        )

    # ------------------------------------------------------------------ plumbing

    def _ready(self) -> None:
        if self._conn is None:
            raise MapError(self._lost or f'map {self.path} is closed')
        # another connection (process) committed: our FAISS index may be stale
        with self._read_errors():
            if self._conn.execute('PRAGMA data_version').fetchone()[0] != self._data_version:
                if not self._catch_up():  # appended keyframes are added; anything else reloads
                    log.info('map %s changed on disk; reloading', self.path)
                    self._load()

    @contextlib.contextmanager
    def _read_errors(self):
        try:
            yield
        except sqlite3.DatabaseError as e:
            raise MapError(f'cannot read map {self.path} (corrupt or truncated?): {e}') from e

    def _write(self, fn):
        """Run fn(conn) in one IMMEDIATE transaction; durable on return (WAL + synchronous=FULL),
        in the file at the path: its identity is checked before and after (SQLiteIdentity), so a
        write into a deleted or replaced file is never acknowledged."""
        self._check_identity('before a write')
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
        self._check_identity('after a write')
        return result

    def _row_to_set(self, row) -> LandmarkSet:
        (kid, sec, nsec, iw, ih, rows, cols, cw, ch, n, glob, cells, centers, scores, desc) = row
        dim = int(self._model['descriptor_dim'])
        sizes = {
            'global_descriptor': (glob, 4 * dim),
            'cells': (cells, 4 * n),
            'centers': (centers, 8 * n),
            'scores': (scores, 4 * n),
            'descriptors': (desc, 2 * n * dim),
        }
        for name, (blob, nbytes) in sizes.items():
            if blob is None or len(blob) != nbytes:
                raise MapError(
                    f'map {self.path} is corrupt: keyframe {kid} {name} is '
                    f'{None if blob is None else len(blob)} bytes, expected {nbytes} (n={n}, D={dim})'
                )
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
            chunk = ids[start : start + _SQL_CHUNK]
            sql = (
                f'SELECT {_KF_COLS}, {_LM_COLS} FROM keyframes k LEFT JOIN landmarks l '
                f'ON l.keyframe_id = k.id WHERE k.id IN ({",".join("?" * len(chunk))})'
            )
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
            records.append(
                (
                    (
                        sec,
                        nsec,
                        float(lset.image_size[0]),
                        float(lset.image_size[1]),
                        rows,
                        cols,
                        float(lset.cell_size[0]),
                        float(lset.cell_size[1]),
                        len(lset),
                        np.ascontiguousarray(lset.global_descriptor, '<f4').tobytes(),
                    ),
                    (
                        np.ascontiguousarray(lset.cells, '<i2').tobytes(),
                        np.ascontiguousarray(lset.centers, '<f4').tobytes(),
                        np.ascontiguousarray(lset.scores, '<f4').tobytes(),
                        np.ascontiguousarray(lset.descriptors, '<f2').tobytes(),
                    ),
                )
            )
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
                            cur = c.execute(
                                f'INSERT INTO keyframes ({_KF_INSERT}) VALUES ({", ".join("?" * 10)})', values
                            )
                        else:
                            cur = c.execute(
                                f'INSERT INTO keyframes (id, {_KF_INSERT}) VALUES ({", ".join("?" * 11)})',
                                (int(ids[i]),) + values,
                            )
                    except sqlite3.IntegrityError:
                        raise MapError(f'map {self.path} already has a keyframe {ids[i]}') from None
                    c.execute(
                        'INSERT INTO landmarks (keyframe_id, cells, centers, scores, descriptors) '
                        'VALUES (?, ?, ?, ?, ?)',
                        (cur.lastrowid,) + blobs,
                    )
                    out.append(int(cur.lastrowid))
                return out

            new_ids = self._write(insert)
            if new_model:
                self._model = given
                self._index = GlobalIndex(given['descriptor_dim'], self.conf)
                self._landmarks = self._new_landmark_index()
            self._index.add(
                np.stack([s.global_descriptor for s in sets]).astype(np.float32), np.asarray(new_ids, np.int64)
            )
            self._landmarks.add_sets(new_ids, sets)
            self._landmarks_dirty = True
            if self._landmarks.needs_rebuild():
                t = time.perf_counter()
                stored = self._stored_counts()
                self._landmarks = self._build_landmarks(self._held_total(stored), len(stored))
                log.info(
                    'map %s: landmark index retrained for %d landmarks (%.1f s)',
                    self.path,
                    self._landmarks.ntotal,
                    time.perf_counter() - t,
                )
            self._ids.extend(new_ids)
            if ids is not None:
                self._ids.sort()
            return new_ids

    def _holistic(
        self, lset: LandmarkSet, k: int, below: int | None, fetch: bool = True
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        hol, ids = self._index.search(lset.global_descriptor, k, below=below)
        return hol, ids, self._fetch(ids) if fetch else {}

    # keypoints for verification (reloc.py): an optional table, created on first use, so maps
    # without it stay valid and readable; rows go with their keyframe (ON DELETE CASCADE)
    _KEYPOINTS_TABLE = (
        'CREATE TABLE IF NOT EXISTS keypoints (keyframe_id INTEGER PRIMARY KEY '
        'REFERENCES keyframes(id) ON DELETE CASCADE, n INTEGER NOT NULL, uv BLOB NOT NULL, '
        'descriptors BLOB NOT NULL)'
    )

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
                    chunk = present[start : start + _SQL_CHUNK]
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
            return {
                'path': self.path,
                'keyframes': len(self._ids),
                'model': self.model,
                'descriptor_space': self._model and self._model['descriptor_space'],
                'descriptor_dim': self._model and int(self._model['descriptor_dim']),
                'schema_version': int(meta['schema_version']),
                'backend': 'sqlite',
                'index': self._index.kind if self._index is not None else None,
                'quarantined': sorted(self._quarantined),
                'landmark_index': self._landmarks.kind if self._landmarks is not None else None,
                'landmarks': self._landmarks.ntotal if self._landmarks is not None else 0,
                'landmark_index_bytes': (
                    os.path.getsize(self.landmark_path) if os.path.exists(self.landmark_path) else 0
                ),
                'first_id': self._ids[0] if self._ids else None,
                'last_id': self._ids[-1] if self._ids else None,
                'file_bytes': db_bytes + wal_bytes,
                'db_bytes': db_bytes,
                'wal_bytes': wal_bytes,
                'created': int(meta.get('created', 0)),
                'created_by': meta.get('created_by', ''),
            }

    def save(self) -> None:
        """Checkpoint the WAL into the main file and truncate it. Not needed for durability (every
        add is durable on return); it keeps the WAL small and the .db file self-contained."""
        with self._lock:
            self._ready()
            self._check_identity('on save')
            self._persist_landmarks()
            try:
                busy, _, _ = self._conn.execute('PRAGMA wal_checkpoint(TRUNCATE)').fetchone()
            except sqlite3.DatabaseError as e:
                raise MapError(f'cannot checkpoint map {self.path}: {e}') from e
            if busy:
                log.warning('map %s: checkpoint incomplete, another connection is reading', self.path)

    def close(self) -> None:
        """Close the file (SQLite checkpoints the WAL when the last connection closes). Idempotent."""
        with self._lock:
            if self._conn is not None:
                try:
                    try:
                        self._check_identity('on close')  # a deleted file is restored before we let go
                    except MapError:
                        pass  # logged as an ERROR by the check
                    if self._conn is None:
                        return
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
