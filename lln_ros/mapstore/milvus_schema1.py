"""The Milvus backend's schema 1 reader, kept for the migration to schema 2 until no schema 1 map
is left: schema 1 stored a row per landmark ({map}_keyframes + {map}_landmarks, a landmark's
descriptor as the float16 bits in an ARRAY<INT16>); schema 2 stores a row per keyframe (milvus.py)."""

from __future__ import annotations

import numpy as np

from ..core.landmarks import LandmarkSet
from ..errors import MapError
from .base import MapStore
from .milvus_claims import migrate_4_to_5
from .milvus_geometry import migrate_2_to_3
from .milvus_rows import scan_ids
from .milvus_sessions import migrate_3_to_4

# `store` below is a MilvusMapStore, annotated by its base: milvus.py imports this module, so
# importing milvus.py here would make an import circle.

_FETCH_IDS = 256  # keyframes per fetch-by-id query: a reply of ~9 MB at n=50, D=320


def _v1_rows_to_sets(store: MapStore, kf_rows: list, lm_rows: list) -> list[tuple]:
    """Schema 1 rows (a keyframe row + one row per landmark) -> [(id, LandmarkSet, (sec, nsec))]."""
    by_kf: dict[int, list] = {}
    for r in lm_rows:
        by_kf.setdefault(int(r['keyframe_id']), []).append(r)
    out = []
    for k in kf_rows:
        kid, n = int(k['id']), int(k['n'])
        lms = sorted(by_kf.get(kid, []), key=lambda r: r['rank'])
        if len(lms) != n:
            raise MapError(
                f'map {store.path} (schema 1) is damaged: keyframe {kid} has {len(lms)} landmarks, '
                f'expected {n}; not migrated'
            )
        out.append(
            (
                kid,
                LandmarkSet(
                    global_descriptor=np.asarray(k['global_descriptor'], np.float32),
                    descriptors=np.array([r['descriptor'] for r in lms], np.int16).view(np.float16).astype(np.float32),
                    cells=np.array([[r['col'], r['row']] for r in lms], np.int32),
                    centers=np.array([r['center'] for r in lms], np.float32),
                    scores=np.array([r['score'] for r in lms], np.float32),
                    cell_size=np.array([k['cell_w'], k['cell_h']], np.float32),
                    image_size=np.array([k['image_w'], k['image_h']], np.float32),
                    grid=(int(k['grid_rows']), int(k['grid_cols'])),
                    activation=None,
                    descriptor_space=store._model['descriptor_space'],
                ),
                (int(k['stamp_sec']), int(k['stamp_nanosec'])),
            )
        )
    return out


def _migrate_1_to_2(store: MapStore, meta: dict) -> None:
    """Schema 1 (a row per landmark in {map}_landmarks) -> 2 (a row per keyframe in {map}_frames).
    Copies every keyframe, checks the count, then the caller records schema 2 and the old
    collections are dropped. Stopped half-way, it starts again from the schema 1 collections."""
    c, (kf_c, lm_c) = store._client, store._v1
    if 'model' not in meta or not c.has_collection(kf_c):
        return
    store._model = store._read_model_record(meta['model'])
    if c.has_collection(store._fr_c):
        c.drop_collection(store._fr_c)  # from a migration that stopped half-way
    store._create_frames(int(store._model['descriptor_dim']))
    for name in (kf_c, lm_c):
        c.load_collection(name)
    ids = scan_ids(c, kf_c, consistency_level='Strong')
    for start in range(0, len(ids), _FETCH_IDS):
        chunk = ids[start : start + _FETCH_IDS]
        kf_rows = c.query(kf_c, filter=f'id in {chunk}', output_fields=['*'], limit=len(chunk))
        lm_rows = []
        for i in range(0, len(kf_rows), 64):  # <= 64 keyframes of <= 256 landmarks: under 16,384 rows
            part = [int(k['id']) for k in kf_rows[i : i + 64]]
            lm_rows += c.query(
                lm_c,
                filter=f'keyframe_id in {part}',
                limit=sum(int(k['n']) for k in kf_rows[i : i + 64]),
                output_fields=['keyframe_id', 'rank', 'col', 'row', 'score', 'center', 'descriptor'],
            )
        rows = [
            store._frame_row(kid, lset, sec, nsec)
            for kid, lset, (sec, nsec) in _v1_rows_to_sets(store, kf_rows, lm_rows)
        ]
        c.insert(store._fr_c, rows)
    copied = int(c.query(store._fr_c, filter='', output_fields=['count(*)'], consistency_level='Strong')[0]['count(*)'])
    if copied != len(ids):
        raise MapError(
            f'migrating map {store.path} to schema 2: copied {copied} of {len(ids)} keyframes; '
            f'the schema 1 collections are kept, opening again retries'
        )


# schema version v -> function(store, meta) that upgrades a v map to v + 1
MIGRATIONS = {1: _migrate_1_to_2, 2: migrate_2_to_3, 3: migrate_3_to_4, 4: migrate_4_to_5}
