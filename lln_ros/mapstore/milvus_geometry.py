"""A part of MilvusMapStore (milvus.py), as a mixin: the {map}_geometry collection of schema 3
(issue 27; the record is described in geometry_record.py) and the migration of schema 2 maps.

    {map}_geometry   keyframe_id INT64 primary, data VARCHAR(65535): geometry_record.to_json
                     (camera, pose, frame_id, keypoint depths as base64 float32), unused FLOAT_VECTOR(2)

65,535 characters hold the depths of ~12,000 keypoints (4 bytes each, base64): more is refused
(MapError) rather than cut.
"""

from __future__ import annotations

from ..errors import MapError
from . import geometry_record

MAX_CHARS = 65535


def geometry_collection(store) -> str:
    return store._fr_c[: -len('_frames')] + '_geometry'


def create_geometry(store) -> None:
    name = geometry_collection(store)
    if not store._client.has_collection(name):
        store._create(
            name,
            [('keyframe_id', 'INT64', {'is_primary': True}), ('data', 'VARCHAR', {'max_length': MAX_CHARS})],
            'unused',
            2,
        )
    store._load_ready(name)


def migrate_2_to_3(store, meta: dict) -> None:
    """Schema 2 -> 3: the geometry collection (existing keyframes have none: no rows)."""
    create_geometry(store)


class MilvusGeometry:
    """set_geometry / geometry of a MilvusMapStore (its _lock, _errors, _ready, _ids, _client)."""

    def _geometry_ready(self) -> str:
        name = geometry_collection(self)
        client = self._client
        if getattr(self, '_geometry_client', None) is not client:  # a new client (open, reconnect): load it
            create_geometry(self)
            self._geometry_client = client
        return name

    def set_geometry(self, keyframe_id: int, fields: dict) -> None:
        """Store (or update) some geometry fields of a keyframe (geometry_record)."""
        kid = int(keyframe_id)
        fields = geometry_record.check(fields, f'map {self.path}, keyframe {kid}')
        with self._lock:
            old = self.geometry(kid) or geometry_record.empty()
            text = geometry_record.to_json({**old, **fields})
            if len(text) > MAX_CHARS:
                raise MapError(
                    f'map {self.path}: keyframe {kid} geometry is {len(text)} characters, at most {MAX_CHARS} '
                    '(fewer keypoints)'
                )
            with self._errors('storing geometry'):
                self._ready()
                if kid not in set(self._ids):
                    raise KeyError(f'no keyframe {kid} in map {self.path}')
                self._client.upsert(self._geometry_ready(), [{'keyframe_id': kid, 'data': text, 'unused': [0.0, 0.0]}])

    def geometry(self, keyframe_id: int) -> dict | None:
        kid = int(keyframe_id)
        with self._lock, self._errors('reading geometry'):
            self._ready()
            if kid in self._deleted:  # Session consistency: a query may still see a deleted row for a while
                return None
            rows = self._client.query(self._geometry_ready(), filter=f'keyframe_id == {kid}', output_fields=['data'])
        if not rows:
            return None
        return geometry_record.from_json(rows[0]['data'], f'map {self.path}: keyframe {kid}')

    def _delete_geometry(self, ids: list[int]) -> None:
        if ids:
            self._client.delete(self._geometry_ready(), filter=f'keyframe_id in {ids}')
