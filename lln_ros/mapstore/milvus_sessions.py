"""A part of MilvusMapStore (milvus.py), as a mixin: the {map}_sessions and {map}_origins
collections of schema 4 (issue 29; what they mean: sessions.py) and the migration of schema 3 maps.

    {map}_sessions   id INT64 primary (the map's session number), data VARCHAR: JSON robot, label,
                     started_ns; unused FLOAT_VECTOR(2)
    {map}_origins    keyframe_id INT64 primary, session_id INT64, seq INT64; unused FLOAT_VECTOR(2)

A session number is claimed (milvus_claims.py) above every stored session, so two processes starting
sessions at once get different numbers, and two writers given one robot id get a session each (the
label's random suffix tells them apart too). Two processes starting a session of the same robot
and the same given label at once (two imports of one session) may each make one. Milvus has no
transactions: a keyframe stored by a process killed before its origin row is written has no
origin (it reads as session 0, unknown), never a wrong one.
"""

from __future__ import annotations

import json
import time

from ..errors import MapError
from .milvus_claims import KIND_SESSION
from .sessions import Origin, Session, check_label, check_robot_id, new_label


def _names(store) -> tuple[str, str]:
    base = store._fr_c[: -len('_frames')]
    return base + '_sessions', base + '_origins'


def create_sessions(store) -> None:
    sessions, origins = _names(store)
    if not store._client.has_collection(sessions):
        store._create(
            sessions, [('id', 'INT64', {'is_primary': True}), ('data', 'VARCHAR', {'max_length': 1024})], 'unused', 2
        )
    if not store._client.has_collection(origins):
        fields = [('keyframe_id', 'INT64', {'is_primary': True}), ('session_id', 'INT64', {}), ('seq', 'INT64', {})]
        store._create(origins, fields, 'unused', 2)
    store._load_ready(sessions)
    store._load_ready(origins)


def migrate_3_to_4(store, meta: dict) -> None:
    """Schema 3 -> 4: the sessions and origins collections (existing keyframes have no origin)."""
    create_sessions(store)


class MilvusSessions:
    """start_session / sessions / set_origin / origins of a MilvusMapStore (its _lock, _errors,
    _ready, _ids, _client)."""

    def _sessions_ready(self) -> tuple[str, str]:
        client = self._client
        if getattr(self, '_sessions_client', None) is not client:  # a new client (open, reconnect): load them
            create_sessions(self)
            self._sessions_client = client
        return _names(self)

    def start_session(self, robot: str, label: str | None = None, started_ns: int | None = None) -> Session:
        """A new session of `robot`, or the map's session of that robot and label when it has one."""
        robot = check_robot_id(robot)
        label = check_label(new_label(started_ns) if label is None else label)
        started_ns = time.time_ns() if started_ns is None else int(started_ns)
        with self._lock:
            known = self.sessions()
            for s in known:
                if (s.robot, s.label) == (robot, label):
                    return s
            data = json.dumps({'robot': robot, 'label': label, 'started_ns': started_ns})
            with self._errors('starting a session'):
                # above every session stored, also those of before schema 5 (read Strong: all of them)
                stored = self._client.query(
                    self._sessions_ready()[0],
                    filter='id >= 0',
                    output_fields=['id'],
                    limit=16384,
                    consistency_level='Strong',
                )
                sid = self._claim(KIND_SESSION, max((int(r['id']) for r in stored), default=0) + 1)
                self._client.upsert(self._sessions_ready()[0], [{'id': sid, 'data': data, 'unused': [0.0, 0.0]}])
            return Session(sid, robot, label, started_ns)

    def sessions(self) -> list[Session]:
        with self._lock, self._errors('reading sessions'):
            self._ready()
            rows = self._client.query(
                self._sessions_ready()[0], filter='id >= 0', output_fields=['id', 'data'], limit=16384
            )
        out = []
        for r in rows:
            try:
                d = json.loads(r['data'])
                out.append(Session(int(r['id']), str(d['robot']), str(d['label']), int(d['started_ns'])))
            except (ValueError, KeyError, TypeError) as e:
                raise MapError(f'map {self.path}: session {r.get("id")} is corrupt: {e}') from None
        return sorted(out, key=lambda s: s.id)

    def set_origin(self, keyframe_id: int, session_id: int, seq: int) -> None:
        kid, sid, seq = int(keyframe_id), int(session_id), int(seq)
        if seq < 1:
            raise ValueError(f'seq must be >= 1, got {seq}')
        with self._lock:
            if sid not in {s.id for s in self.sessions()}:
                raise MapError(f'map {self.path}: origin of keyframe {kid} refused: no session {sid}')
            with self._errors('storing an origin'):
                self._ready()
                if kid not in set(self._ids):
                    raise KeyError(f'no keyframe {kid} in map {self.path}')
                name = self._sessions_ready()[1]
                taken = self._client.query(
                    name, filter=f'session_id == {sid} and seq == {seq}', output_fields=['keyframe_id'], limit=2
                )
                if any(int(r['keyframe_id']) != kid for r in taken):  # what SQLite's UNIQUE (session_id, seq) says
                    raise MapError(f'map {self.path}: origin of keyframe {kid} refused: session {sid} has a seq {seq}')
                row = {'keyframe_id': kid, 'session_id': sid, 'seq': seq, 'unused': [0.0, 0.0]}
                self._client.upsert(name, [row])

    def origins(self, keyframe_ids=None) -> dict[int, Origin]:
        with self._lock, self._errors('reading origins'):
            self._ready()
            name = self._sessions_ready()[1]
            fields = ['keyframe_id', 'session_id', 'seq']
            ids = list(self._ids) if keyframe_ids is None else [int(i) for i in keyframe_ids]
            # the whole map's origins (lln-map merge copies them) are read Strong: read at the collection's
            # consistency just after a server restart, they came back empty once in
            # bench_milvus_writers.py's soak (stored, as a Strong count and a later read showed); the
            # few of an answer's candidates stay at the collection's consistency (a Strong read waits ~0.4 s)
            level = {'consistency_level': 'Strong'} if keyframe_ids is None else {}
            rows = []
            for start in range(0, len(ids), 1000):  # a query returns at most 16,384 rows
                chunk = ids[start : start + 1000]
                rows += self._client.query(
                    name, filter=f'keyframe_id in {chunk}', output_fields=fields, limit=len(chunk), **level
                )
            deleted = self._deleted
        return {
            int(r['keyframe_id']): Origin(int(r['session_id']), int(r['seq']))
            for r in rows
            if r['keyframe_id'] not in deleted
        }

    def _delete_origins(self, ids: list[int]) -> None:
        if ids:
            self._client.delete(self._sessions_ready()[1], filter=f'keyframe_id in {ids}')
