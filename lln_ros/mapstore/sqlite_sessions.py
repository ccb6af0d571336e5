"""A part of SQLiteMapStore (sqlite.py), as a mixin: the sessions and origins tables of schema 3
(issue 29; what they mean: sessions.py) and the migration of schema 2 maps to them.

    sessions   id INTEGER PRIMARY KEY (the map's session number), robot TEXT, label TEXT,
               started_ns INTEGER, UNIQUE (robot, label)
    origins    keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
               session_id INTEGER REFERENCES sessions(id), seq INTEGER, UNIQUE (session_id, seq)
"""

from __future__ import annotations

import sqlite3
import time

from ..errors import MapError
from .sessions import Origin, Session, check_label, check_robot_id, new_label

SESSION_TABLES = """
CREATE TABLE sessions (
    id         INTEGER PRIMARY KEY AUTOINCREMENT,
    robot      TEXT    NOT NULL,
    label      TEXT    NOT NULL,
    started_ns INTEGER NOT NULL,
    UNIQUE (robot, label)
);
CREATE TABLE origins (
    keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
    session_id  INTEGER NOT NULL REFERENCES sessions(id),
    seq         INTEGER NOT NULL,
    UNIQUE (session_id, seq)
)
"""


def migrate_2_to_3(conn) -> None:
    """Schema 2 -> 3: the sessions and origins tables (existing keyframes have no origin: no rows)."""
    for statement in SESSION_TABLES.split(';'):
        if statement.strip():
            conn.execute(statement)


class SQLiteSessions:
    """start_session / sessions / set_origin / origins of an SQLiteMapStore (its _lock, _ready,
    _write, _ids, _conn, _read_errors)."""

    def start_session(self, robot: str, label: str | None = None, started_ns: int | None = None) -> Session:
        """A new session of `robot` (label: sessions.new_label), or the map's session of that robot
        and label when it has one (lln-map merge brings a session in once)."""
        robot = check_robot_id(robot)
        label = check_label(new_label(started_ns) if label is None else label)
        started_ns = time.time_ns() if started_ns is None else int(started_ns)

        def insert(c):
            sql = 'SELECT id, started_ns FROM sessions WHERE robot = ? AND label = ?'
            found = c.execute(sql, (robot, label)).fetchone()
            if found is None:
                c.execute(
                    'INSERT INTO sessions (robot, label, started_ns) VALUES (?, ?, ?)', (robot, label, started_ns)
                )
                found = c.execute(sql, (robot, label)).fetchone()
            return found

        with self._lock:
            self._ready()
            sid, started = self._write(insert)
        return Session(int(sid), robot, label, int(started))

    def sessions(self) -> list[Session]:
        with self._lock:
            self._ready()
            with self._read_errors():
                rows = self._conn.execute('SELECT id, robot, label, started_ns FROM sessions ORDER BY id').fetchall()
        return [Session(int(i), r, lb, int(t)) for i, r, lb, t in rows]

    def set_origin(self, keyframe_id: int, session_id: int, seq: int) -> None:
        """Record where a stored keyframe came from; MapError when its session is not in the map or
        the session already has a keyframe of that seq."""
        kid, sid, seq = int(keyframe_id), int(session_id), int(seq)
        if seq < 1:
            raise ValueError(f'seq must be >= 1, got {seq}')

        def insert(c):
            try:  # inside the transaction: _write reads any other DatabaseError as a corrupt file
                c.execute(
                    'INSERT INTO origins (keyframe_id, session_id, seq) VALUES (?, ?, ?) ON CONFLICT(keyframe_id) '
                    'DO UPDATE SET session_id = excluded.session_id, seq = excluded.seq',
                    (kid, sid, seq),
                )
            except sqlite3.IntegrityError as e:  # no such session, or its seq is taken
                return str(e)
            return None

        with self._lock:
            self._ready()
            if kid not in set(self._ids):
                raise KeyError(f'no keyframe {kid} in map {self.path}')
            problem = self._write(insert)
        if problem:
            raise MapError(f'map {self.path}: origin of keyframe {kid} (session {sid}, seq {seq}) refused: {problem}')

    def origins(self, keyframe_ids=None) -> dict[int, Origin]:
        """{keyframe_id: Origin} of these keyframes (all when None); keyframes without one are absent."""
        with self._lock:
            self._ready()
            with self._read_errors():
                if keyframe_ids is None:
                    rows = self._conn.execute('SELECT keyframe_id, session_id, seq FROM origins').fetchall()
                else:
                    rows = []
                    ids = [int(i) for i in keyframe_ids]
                    for start in range(0, len(ids), 900):
                        chunk = ids[start : start + 900]
                        rows += self._conn.execute(
                            'SELECT keyframe_id, session_id, seq FROM origins WHERE keyframe_id IN '
                            f'({", ".join("?" * len(chunk))})',
                            chunk,
                        ).fetchall()
        return {int(k): Origin(int(s), int(q)) for k, s, q in rows}
