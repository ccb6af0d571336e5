"""The SQLite map file: schema, creation under a temporary name, raw-file checks, identification,
migrations, the load that rebuilds the in-memory indexes and check() (a mixin of SQLiteMapStore).

Storage
-------
One SQLite file in WAL mode with ``synchronous=FULL``: ``add`` commits one transaction and fsyncs
the WAL before it returns, so an acknowledged keyframe survives ``kill -9`` and power loss. New files
are built under a temporary name and linked into place, so a file at the map path is always either a
complete map or not ours (never half-created). Schema version 3 (2 without sessions and origins, 1
without the geometry table)::

    meta       key TEXT PRIMARY KEY, value TEXT
               format='lln_ros-map', schema_version='3', created (unix s), created_by,
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
    geometry   (schema 2) keyframe_id, camera JSON, pose (7,) float64, frame_id, keypoint depths (N,)
               float32: what registration needs (sqlite_geometry.py, geometry_record.py)
    sessions   (schema 3) id, robot, label, started_ns: who wrote into the map, run by run
    origins    (schema 3) keyframe_id, session_id, seq: a keyframe's (robot, session, seq) identity
               (sqlite_sessions.py, sessions.py)

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

Migrations: ``MIGRATIONS[v]`` upgrades a map from schema v to v+1 inside one transaction at open
(1 -> 2: the geometry table; 2 -> 3: sessions and origins).
A map newer than this code is refused, never modified.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import struct
import threading
import time
import uuid

import numpy as np

from ..core.limits import stamp_problem
from ..errors import DescriptorError, MapError
from .base import FORMAT
from .index import GlobalIndex
from .sqlite_geometry import GEOMETRY_TABLE, migrate_1_to_2
from .sqlite_sessions import SESSION_TABLES, migrate_2_to_3

log = logging.getLogger(__name__)

SCHEMA_VERSION = 3  # 2: geometry (sqlite_geometry.py); 3: sessions and origins (sqlite_sessions.py)
SQLITE_MAGIC = b'SQLite format 3\x00'

SCHEMA = (
    """
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
    + GEOMETRY_TABLE
    + ';'
    + SESSION_TABLES
    + ';'
)

# schema version v -> function(conn) that upgrades a v map to v + 1 (called inside a transaction)
MIGRATIONS: dict = {1: migrate_1_to_2, 2: migrate_2_to_3}

_KF_COLS = (
    'k.id, k.stamp_sec, k.stamp_nanosec, k.image_w, k.image_h, k.grid_rows, k.grid_cols, '
    'k.cell_w, k.cell_h, k.n, k.global_descriptor'
)
_LM_COLS = 'l.cells, l.centers, l.scores, l.descriptors'
_KF_INSERT = 'stamp_sec, stamp_nanosec, image_w, image_h, grid_rows, grid_cols, cell_w, cell_h, n, global_descriptor'
_SQL_CHUNK = 900  # ids per IN (...) list, below SQLite's oldest variable limit (999)


def fsync_path(path) -> None:
    """fsync a file or folder by path (a folder: so a new name in it survives power loss)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class SQLiteFile:
    """Opening and loading an SQLite map (SQLiteMapStore's; reads its path, conf and _conn)."""

    def _create_file(self) -> None:
        """Build an empty map under a temporary name, then link it into place (no half-made maps)."""
        parent = os.path.dirname(self.path)
        try:
            os.makedirs(parent, exist_ok=True)
        except OSError as e:  # e.g. a parent that is a regular file: [Errno 17] alone names nothing
            raise MapError(f'cannot create map {self.path}: its folder {parent} cannot be made ({e})') from e
        for suffix in ('-wal', '-shm', '-journal'):  # left over from a deleted file: never replay them
            try:
                os.remove(self.path + suffix)
                log.warning(
                    'no map at %s but its %s was left there: a map file was deleted; starting a NEW, EMPTY map',
                    self.path,
                    suffix,
                )
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
                from .. import __version__

                conn.executemany(
                    'INSERT INTO meta (key, value) VALUES (?, ?)',
                    [
                        ('format', FORMAT),
                        ('schema_version', str(SCHEMA_VERSION)),
                        ('created', str(int(time.time()))),
                        ('created_by', f'lln_ros {__version__}'),
                        ('map_uuid', uuid.uuid4().hex),
                    ],
                )
                conn.execute('COMMIT')
            finally:
                conn.close()
            fsync_path(tmp)
            try:
                os.link(tmp, self.path)  # fails if someone else created the map meanwhile
            except FileExistsError:
                pass
            except OSError:  # no hard links on this filesystem
                if not os.path.exists(self.path):
                    os.replace(tmp, self.path)
            fsync_path(parent)
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
            raise MapError(f'{self.path} is an empty file (0 bytes), not an lln_ros map; delete it to start a new map')
        if len(head) < 100 or head[:16] != SQLITE_MAGIC:
            raise MapError(
                f'{self.path} is not an lln_ros map: not an SQLite database '
                f'(corrupt, truncated or some other file; {size} bytes)'
            )
        page_size = struct.unpack('>H', head[16:18])[0]
        page_size = 65536 if page_size == 1 else page_size
        change, pages, valid_for = (struct.unpack('>I', head[o : o + 4])[0] for o in (24, 28, 92))
        wal = self.path + '-wal'
        wal_pending = os.path.exists(wal) and os.path.getsize(wal) > 0
        # with a pending WAL the main file may legitimately lag behind; quick_check covers that case
        if pages and change == valid_for and not wal_pending and size < pages * page_size:
            raise MapError(
                f'map {self.path} is truncated: {size} bytes, its header says '
                f'{pages} pages of {page_size} bytes ({pages * page_size} bytes)'
            )

    def _identify(self) -> None:
        c = self._conn
        tables = {r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if 'meta' not in tables:
            raise MapError(
                f'{self.path} is an SQLite database but not an lln_ros map '
                f'(no meta table; tables: {sorted(tables) or "none"})'
            )
        meta = self._meta()
        if meta.get('format') != FORMAT:
            raise MapError(
                f'{self.path} is an SQLite database but not an lln_ros map '
                f'(meta format is {meta.get("format")!r}, expected {FORMAT!r})'
            )
        try:
            version = int(meta.get('schema_version', ''))
        except ValueError:
            raise MapError(f'map {self.path} has no valid schema_version ({meta.get("schema_version")!r})') from None
        if version > SCHEMA_VERSION:
            raise MapError(
                f'map {self.path} has schema version {version}; this lln_ros reads up to '
                f'{SCHEMA_VERSION}: upgrade lln_ros'
            )
        missing = {'keyframes', 'landmarks', 'geometry', 'sessions', 'origins'} - tables
        if missing and version == SCHEMA_VERSION:
            raise MapError(f'map {self.path} is damaged: missing tables {sorted(missing)}')

    def _configure(self) -> None:
        c = self._conn
        mode = c.execute('PRAGMA journal_mode=WAL').fetchone()[0]
        if str(mode).lower() != 'wal':
            raise MapError(
                f'cannot put map {self.path} in WAL mode (got {mode!r}); is it on a network filesystem or read-only?'
            )
        c.execute('PRAGMA synchronous=FULL')
        c.execute('PRAGMA foreign_keys=ON')

    def _migrate(self) -> None:
        version = int(self._meta()['schema_version'])
        while version < SCHEMA_VERSION:
            step = MIGRATIONS.get(version)
            if step is None:
                raise MapError(
                    f'map {self.path} has schema version {version} and there is no migration to {version + 1}'
                )
            self._conn.execute('BEGIN IMMEDIATE')
            try:
                step(self._conn)
                self._conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(version + 1),))
                self._conn.execute('COMMIT')
            except BaseException:
                self._conn.execute('ROLLBACK')
                raise
            log.info('migrated map %s from schema %d to %d', self.path, version, version + 1)
            version += 1

    def _start_quick_check(self):
        """Run SQLite's quick_check (it reads every page of the file) on a second connection in a
        thread, and return a function that waits for it and raises MapError if it found damage.

        SQLite releases the GIL while it works, so the check overlaps _load's index building: at
        100k keyframes (2.7 GB) the check alone took ~6 s and the load ~4 s on this 2-core machine.
        The caller hands the store out only after the check passed."""
        verdict: dict = {}

        def check() -> None:
            try:
                conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None)
                try:
                    verdict['rows'] = [r[0] for r in conn.execute('PRAGMA quick_check(20)')]
                finally:
                    conn.close()
            except sqlite3.Error as e:
                verdict['error'] = e

        worker = threading.Thread(target=check, name='lln-map-quick-check', daemon=True)
        worker.start()

        def wait() -> None:
            worker.join()
            # the messages SQLiteMapStore.__init__ gives the same errors on its own connection
            if isinstance(verdict.get('error'), sqlite3.OperationalError):  # locked, read-only, I/O error
                raise MapError(f'cannot open map {self.path}: {verdict["error"]}')
            if 'error' in verdict:
                raise MapError(f'map {self.path} is corrupt or truncated: {verdict["error"]}')
            if verdict['rows'] != ['ok']:
                raise MapError(f'map {self.path} is corrupt (SQLite quick_check): ' + '; '.join(verdict['rows']))

        return wait

    def _meta(self) -> dict:
        return {k: v for k, v in self._conn.execute('SELECT key, value FROM meta')}

    def _load(self) -> None:
        """(Re)read the model record and rebuild the FAISS index from the keyframes table, in one read
        transaction: every statement sees one snapshot of the file, so keyframes another process
        commits meanwhile cannot make the keyframes and landmarks tables disagree (a reader reloading
        beside a writer process raised 'landmark index disagrees' before). WAL: it blocks no writer."""
        c = self._conn
        own = not c.in_transaction
        if own:
            c.execute('BEGIN')  # deferred: the snapshot starts at the first read
        try:
            self._load_snapshot()
        finally:
            if own and c.in_transaction:
                c.execute('COMMIT')

    def _load_snapshot(self) -> None:
        c = self._conn
        self._data_version = c.execute('PRAGMA data_version').fetchone()[0]
        meta = self._meta()
        self._model = self._read_model_record(meta['model']) if 'model' in meta else None
        count = c.execute('SELECT count(*) FROM keyframes').fetchone()[0]
        self._ids = []
        self._index = None
        self._landmarks = None
        self._quarantined = {}
        if self._model is None:
            if count:
                raise MapError(f'map {self.path} is damaged: {count} keyframes but no model record')
            return
        dim = int(self._model['descriptor_dim'])
        self._quarantined = self._damaged(dim)
        if self._quarantined:
            log.warning(
                'map %s: %d damaged keyframe(s) quarantined (kept in the file, never answered): %s',
                self.path,
                len(self._quarantined),
                '; '.join(list(self._quarantined.values())[:10]),
            )
        # streamed into one preallocated array: a 100k map's rows as Python objects would double the peak
        x = np.empty((count, dim), np.float32)
        cursor = c.execute('SELECT id, global_descriptor FROM keyframes ORDER BY id')
        while rows := cursor.fetchmany(4096):
            for kid, blob in rows:
                if kid not in self._quarantined and len(self._ids) < count:
                    x[len(self._ids)] = np.frombuffer(blob, '<f4')
                    self._ids.append(int(kid))
        self._index = GlobalIndex(dim, self.conf)
        self._index.build(x[: len(self._ids)], np.asarray(self._ids, np.int64))
        problems = self._faiss_problems()
        if problems:
            raise MapError(f'map {self.path}: in-memory index disagrees with the file: {"; ".join(problems)}')
        self._load_landmarks()

    def _damaged(self, dim: int) -> dict:
        """{id: problem} of keyframes whose stored sizes do not fit their n and D (a missing landmarks
        row, a blob of the wrong length, a bad grid or stamp). One SQL scan using length(), which
        reads a blob's size from its record header without reading the blob: 0.87 s at 100k
        keyframes against 4.1 s for quick_check (bench/bench_integrity.py, warm cache, loaded)."""
        rows = self._conn.execute(
            'SELECT k.id, k.n, k.grid_rows, k.grid_cols, k.stamp_sec, k.stamp_nanosec, length(k.global_descriptor), '
            'length(l.cells), length(l.centers), length(l.scores), length(l.descriptors), l.keyframe_id IS NULL '
            'FROM keyframes k LEFT JOIN landmarks l ON l.keyframe_id = k.id WHERE l.keyframe_id IS NULL '
            'OR k.n < 1 OR k.grid_rows < 1 OR k.grid_cols < 1 OR k.stamp_nanosec < 0 '
            'OR k.stamp_nanosec >= 1000000000 OR k.stamp_sec < -2147483648 OR k.stamp_sec > 2147483647 '
            'OR length(k.global_descriptor) IS NOT 4 * :d '
            'OR length(l.cells) IS NOT 4 * k.n OR length(l.centers) IS NOT 8 * k.n '
            'OR length(l.scores) IS NOT 4 * k.n OR length(l.descriptors) IS NOT 2 * k.n * :d ORDER BY k.id',
            {'d': int(dim)},
        )
        out = {}
        for kid, n, rows_, cols_, sec, nsec, lg, lc, lce, ls, ld, orphan in rows:
            if orphan:
                out[kid] = f'keyframe {kid} has no landmarks row'
                continue
            want = (4 * dim, 4 * n, 8 * n, 4 * n, 2 * n * dim)
            if (lg, lc, lce, ls, ld) != want or n < 1:
                out[kid] = (
                    f'keyframe {kid}: blob sizes (global, cells, centers, scores, descriptors) '
                    f'{(lg, lc, lce, ls, ld)} do not fit n={n}, D={dim} (expected {want})'
                )
            else:
                # a stamp an older version stored unchecked (issue 25) would fail every answer
                stamp = stamp_problem(sec, nsec)
                out[kid] = f'keyframe {kid}: ' + (stamp or f'bad grid {rows_}x{cols_}')
        return out

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
                if (
                    meta.get('descriptor_dim') != str(dim)
                    or meta.get('descriptor_space') != self._model['descriptor_space']
                ):
                    problems.append('meta descriptor_space/descriptor_dim disagree with the model record')
                # the same scan the open runs (the node quarantines exactly these keyframes)
                add(self._damaged(dim).values(), lambda p: f'{p} (quarantined: never answered)')
                orphans = [
                    r[0]
                    for r in c.execute(
                        'SELECT keyframe_id FROM landmarks WHERE keyframe_id NOT IN (SELECT id FROM keyframes)'
                    )
                ]
                add(orphans, lambda i: f'landmarks row {i} has no keyframe')
                problems.extend(self._faiss_problems())
                problems.extend(self._landmark_problems(self._stored_counts()))
            except sqlite3.DatabaseError as e:
                problems.append(f'SQLite error while checking: {e}')
        return problems

    def add_keypoints(self, keyframe_id: int, uv: np.ndarray, descriptors: np.ndarray) -> None:
        """Store a keyframe's keypoints: uv (N, 2) float32 original pixels, binary descriptors
        (N, B) uint8, as float32 / uint8 blobs (8 + B bytes per keypoint). Replaces earlier ones."""
        uv = np.ascontiguousarray(uv, '<f4').reshape(-1, 2)
        desc = np.ascontiguousarray(descriptors)
        if desc.dtype != np.uint8 or desc.ndim != 2 or len(desc) != len(uv):
            raise DescriptorError(
                f'keypoints need (N, B) uint8 descriptors for N={len(uv)} points, got {desc.dtype} {desc.shape}'
            )
        with self._lock:
            self._ready()
            if int(keyframe_id) not in set(self._ids):
                raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
            self._write(
                lambda c: (
                    c.execute(self._KEYPOINTS_TABLE),
                    c.execute(
                        'INSERT OR REPLACE INTO keypoints (keyframe_id, n, uv, descriptors) VALUES (?, ?, ?, ?)',
                        (int(keyframe_id), len(uv), uv.tobytes(), desc.tobytes()),
                    ),
                )
            )

    def keypoints(self, keyframe_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(uv (N, 2) float32, descriptors (N, B) uint8) of a keyframe, or None when none were stored."""
        with self._lock:
            self._ready()
            with self._read_errors():
                if not self._conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'keypoints'").fetchone():
                    return None
                row = self._conn.execute(
                    'SELECT n, uv, descriptors FROM keypoints WHERE keyframe_id = ?', (int(keyframe_id),)
                ).fetchone()
        if row is None:
            return None
        n, uv, desc = row
        if len(uv) != 8 * n or (n and len(desc) % n) or (not n and desc):
            raise MapError(
                f'map {self.path} is corrupt: keyframe {keyframe_id} keypoints are {len(uv)} + '
                f'{len(desc)} bytes for n={n}'
            )
        return (
            np.frombuffer(uv, '<f4').reshape(n, 2).copy(),
            np.frombuffer(desc, np.uint8).reshape(n, len(desc) // n if n else 32).copy(),
        )
