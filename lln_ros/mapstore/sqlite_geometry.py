"""A part of SQLiteMapStore (sqlite.py), as a mixin: the geometry table of schema 2 (issue 27; the
record is described in geometry_record.py) and the migration of schema 1 maps to it.

    geometry   keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE
               camera TEXT (JSON of CameraModel.to_dict, or NULL), pose BLOB (float64 LE (7,) or NULL),
               frame_id TEXT, depth BLOB (float32 LE (N,) aligned with the keypoints row, or NULL)
"""

from __future__ import annotations

import json

import numpy as np

from ..errors import MapError
from . import geometry_record

GEOMETRY_TABLE = """
CREATE TABLE geometry (
    keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
    camera      TEXT,
    pose        BLOB,
    frame_id    TEXT NOT NULL DEFAULT '',
    depth       BLOB
)
"""


def migrate_1_to_2(conn) -> None:
    """Schema 1 -> 2: the geometry table (existing keyframes have none: no rows)."""
    conn.execute(GEOMETRY_TABLE)


class SQLiteGeometry:
    """set_geometry / geometry of an SQLiteMapStore (its _lock, _ready, _write, _ids, _conn)."""

    def set_geometry(self, keyframe_id: int, fields: dict) -> None:
        """Store (or update) some geometry fields of a keyframe (geometry_record)."""
        kid = int(keyframe_id)
        where = f'map {self.path}, keyframe {kid}'
        fields = geometry_record.check(fields, where)
        cols = {
            'camera': lambda v: None if v is None else json.dumps(v),
            'pose': lambda v: None if v is None else np.asarray(v, '<f8').tobytes(),
            'frame_id': lambda v: v,
            'depth': lambda v: None if v is None else np.asarray(v, '<f4').tobytes(),
        }
        names = list(fields)
        values = [cols[n](fields[n]) for n in names]
        if not names:
            return
        sql = (
            f'INSERT INTO geometry (keyframe_id, {", ".join(names)}) VALUES (?{", ?" * len(names)}) '
            f'ON CONFLICT(keyframe_id) DO UPDATE SET {", ".join(f"{n} = excluded.{n}" for n in names)}'
        )
        with self._lock:
            self._ready()
            if kid not in set(self._ids):
                raise KeyError(f'no keyframe {kid} in map {self.path}')
            self._write(lambda c: c.execute(sql, (kid, *values)))

    def geometry(self, keyframe_id: int) -> dict | None:
        """The keyframe's geometry record (geometry_record), or None when none was stored."""
        kid = int(keyframe_id)
        with self._lock:
            self._ready()
            with self._read_errors():
                row = self._conn.execute(
                    'SELECT camera, pose, frame_id, depth FROM geometry WHERE keyframe_id = ?', (kid,)
                ).fetchone()
        if row is None:
            return None
        camera, pose, frame_id, depth = row
        where = f'map {self.path}: keyframe {kid}'
        if (pose is not None and len(pose) != 56) or (depth is not None and len(depth) % 4):
            raise MapError(f'{where} is corrupt: geometry pose {len(pose or b"")} / depth {len(depth or b"")} bytes')
        try:
            camera = None if camera is None else json.loads(camera)
        except ValueError as e:
            raise MapError(f'{where} is corrupt: geometry camera is not JSON: {e}') from None
        return {
            'camera': camera,
            'pose': None if pose is None else np.frombuffer(pose, '<f8').copy(),
            'frame_id': frame_id or '',
            'depth': None if depth is None else np.frombuffer(depth, '<f4').copy(),
        }
