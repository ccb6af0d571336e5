"""What a keyframe keeps for registration (issue 27) in both map backends, and the migration of maps
made before it: an SQLite schema 1 map and a Milvus schema 2 map, each written by this code and then
taken back to the older layout (the older layouts are these minus the geometry table / collection),
are opened, upgraded and given geometry with their keyframes intact."""

import sqlite3

import numpy as np
import pytest
from test_map_backends import BACKENDS, HAVE_MILVUS, uri_for
from test_mapstore import MODEL, make_set

from lln_ros.errors import MapError
from lln_ros.mapstore import MapStore

CAMERA = {'width': 640, 'height': 480, 'k': [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], 'd': [0.0] * 5}
POSE = np.array([1.0, 2.0, 3.0, 0.0, 0.0, np.sin(0.25), np.cos(0.25)])


@pytest.fixture(params=BACKENDS)
def uri(request, tmp_path):
    if request.param == 'milvus-server':
        return request.getfixturevalue('milvus_map')
    return uri_for(request.param, tmp_path)


def test_geometry_round_trip_and_refusals(uri):
    rng = np.random.default_rng(3)
    depth = np.array([1.5, np.nan, 2.25], np.float32)
    with MapStore.open(uri, model=MODEL) as store:
        a, b = store.add_many([make_set(rng), make_set(rng)], [(1, 0), (2, 0)])
        assert store.geometry(a) is None
        store.set_geometry(a, {'camera': CAMERA, 'pose': POSE, 'frame_id': 'odom'})
        store.set_geometry(a, {'depth': depth})  # later, with the keypoints: the other fields stay
        g = store.geometry(a)
        assert g['frame_id'] == 'odom' and g['camera']['k'] == CAMERA['k'] and g['camera']['width'] == 640
        np.testing.assert_allclose(g['pose'], POSE)
        np.testing.assert_array_equal(g['depth'], depth)
        bad = [
            {'pose': [0, 0, 0, 0, 0, 0, 2.0]},  # not a unit quaternion
            {'pose': [np.nan, 0, 0, 0, 0, 0, 1.0]},
            {'camera': {**CAMERA, 'k': [0.0] * 9}},  # uncalibrated
            {'depth': [-1.0]},
            {'colour': 1},
        ]
        for fields in bad:
            with pytest.raises(MapError):
                store.set_geometry(b, fields)
        assert store.geometry(b) is None  # nothing half-written
        with pytest.raises(KeyError):
            store.set_geometry(999, {'frame_id': 'x'})
    with MapStore.open(uri) as store:  # persistent
        np.testing.assert_allclose(store.geometry(a)['pose'], POSE)
        store.delete([a])
        assert store.geometry(a) is None


def test_sqlite_schema_1_map_is_migrated(tmp_path):
    rng = np.random.default_rng(4)
    path = str(tmp_path / 'old.db')
    sets = [make_set(rng) for _ in range(3)]
    with MapStore.open(path, model=MODEL) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(3)])
    conn = sqlite3.connect(path)  # back to schema 1: the same file without geometry, sessions, origins
    for table in ('origins', 'sessions', 'geometry'):
        conn.execute(f'DROP TABLE {table}')
    conn.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    conn.commit()
    conn.close()
    with MapStore.open(path) as store:
        assert store.info()['schema_version'] == 3 and len(store) == 3
        assert store.query(sets[1], k=1)[0].keyframe_id == ids[1]
        assert store.geometry(ids[0]) is None
        store.set_geometry(ids[0], {'pose': POSE, 'frame_id': 'map'})
    with MapStore.open(path) as store:
        assert store.geometry(ids[0])['frame_id'] == 'map'
        assert store.check() == []


@pytest.mark.skipif(not HAVE_MILVUS, reason='pymilvus / milvus-lite not installed (requirements.txt)')
def test_milvus_schema_2_map_is_migrated(tmp_path):
    rng = np.random.default_rng(5)
    uri = f'milvus-lite://{tmp_path}/old.db'
    sets = [make_set(rng) for _ in range(3)]
    with MapStore.open(uri, model=MODEL) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(3)])
        store.set_geometry(ids[0], {'frame_id': 'x'})  # creates the collection, as a schema 3 map has
        name = store._fr_c[: -len('_frames')] + '_geometry'
        store._client.drop_collection(name)  # back to schema 2
        store._put_meta({'schema_version': '2'})
    with MapStore.open(uri) as store:
        from lln_ros.mapstore.milvus_collections import SCHEMA_VERSION

        assert store.info()['schema_version'] == SCHEMA_VERSION and len(store) == 3  # migrated all the way
        assert store._client.has_collection(name)
        assert store.query(sets[2], k=1)[0].keyframe_id == ids[2]
        assert store.geometry(ids[0]) is None
        store.set_geometry(ids[0], {'camera': CAMERA})
        assert store.geometry(ids[0])['camera']['height'] == 480
