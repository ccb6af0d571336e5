"""The Milvus backend against a real Milvus 2.3.5 standalone server (PyPI `milvus`), plus what only
a server (or a Milvus schema) has: database creation, gRPC message limits, the schema 1 -> 2
migration, keypoints, two readers with one writer, a server restart under a writer, and the
matcher over DDS in mapping mode.

The server listens on every interface, so it only runs in a network namespace that has nothing but
lo: test_real_server_suite (in the normal run) re-runs every `milvus_server` test, this file's,
test_map_backends.py's and test_map_geometry.py's, in a child pytest inside such a namespace
(test/milvus_loopback.py); there the `milvus_server` fixture starts one server for the whole child
run. Outside it those tests skip.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from milvus_loopback import milvus_version, only_loopback
from test_mapstore import MODEL, make_set

from lln_ros.core import landmark_index
from lln_ros.errors import MapError
from lln_ros.mapstore import MapStore
from lln_ros.mapstore.milvus_collections import SCHEMA_VERSION as MILVUS_SCHEMA

REPO = Path(__file__).resolve().parents[1]
HAVE_LITE = all(__import__('importlib').util.find_spec(m) for m in ('pymilvus', 'milvus_lite'))
server = pytest.mark.milvus_server
BOTH = [
    pytest.param('lite', marks=pytest.mark.skipif(not HAVE_LITE, reason='pymilvus / milvus-lite not installed')),
    pytest.param('server', marks=server),
]


@pytest.fixture
def milvus_uri(request, tmp_path):
    """A fresh Milvus map: Milvus Lite in tmp_path, or a map on the real server."""
    if request.param == 'lite':
        return f'milvus-lite://{tmp_path}/m.db'
    return request.getfixturevalue('milvus_map')


def child_env() -> dict:
    return {
        **os.environ,
        'PYTHONPATH': os.pathsep.join(p for p in (str(REPO), str(REPO / 'test'), os.environ.get('PYTHONPATH')) if p),
    }


# ============================================================================================
# the normal run: every milvus_server test, in a child pytest inside a loopback-only namespace


@pytest.mark.skipif(only_loopback(), reason='already inside the loopback namespace (this is the child run)')
def test_real_server_suite(tmp_path):
    if milvus_version() is None:
        pytest.skip('the PyPI package `milvus` (a Milvus 2.3.5 standalone server) is not installed')
    cmd = [
        sys.executable,
        str(REPO / 'test' / 'milvus_loopback.py'),
        '--',
        sys.executable,
        '-m',
        'pytest',
        '-q',
        '-p',
        'no:cacheprovider',
        '-m',
        'milvus_server',
        '-o',
        'addopts=-ra',
        str(REPO / 'test' / 'test_map_backends.py'),
        str(REPO / 'test' / 'test_map_geometry.py'),
        str(REPO / 'test' / 'test_milvus_server.py'),
        str(REPO / 'test' / 'test_milvus_fleet.py'),
    ]
    t = time.monotonic()
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=child_env(), timeout=1800)
    text = out.stdout + out.stderr
    if out.returncode == 3 and 'cannot make a loopback-only network namespace' in text:
        pytest.skip(text.strip().splitlines()[-1])
    print(text[-6000:])
    print(f'real-server suite: {time.monotonic() - t:.0f} s')
    assert out.returncode == 0, text[-8000:]
    assert ' passed' in text and ' failed' not in text, text[-4000:]


# ============================================================================================
# inside the namespace


@server
def test_database_is_created_and_a_missing_one_named(milvus_server):
    uri = f'{milvus_server.uri}/lln_fresh_db?map=m'
    with pytest.raises(MapError, match="no map at .*no database 'lln_nowhere'"):
        MapStore.open(f'{milvus_server.uri}/lln_nowhere?map=m', create=False)
    try:
        with MapStore.open(uri, model=MODEL) as store:
            kid = store.add(make_set(np.random.default_rng(0)))
            assert store.ids() == [kid] and store.info()['schema_version'] == MILVUS_SCHEMA
        with MapStore.open(uri, create=False) as store:
            assert store.ids() == [kid]
    finally:
        from milvus_loopback import drop_maps

        drop_maps(milvus_server, 'lln_fresh_db', 'm_')


@server
def test_big_insert_is_batched_and_a_too_big_message_is_a_map_error(milvus_map):
    """700 keyframes of n=50, D=320 (the issue's case, ~47 MB as rows) go in messages under the
    server's 64 MB limit; forcing one message, the server's RESOURCE_EXHAUSTED becomes a MapError."""
    rng = np.random.default_rng(3)
    space = {'descriptor_space': 'efficientnet_lite2/stage6/320', 'descriptor_dim': 320}
    sets = [make_set(rng, dim=320, space=space['descriptor_space']) for _ in range(40)]
    many = [sets[i % 40] for i in range(700)]
    with MapStore.open(milvus_map, model=space) as store:
        ids = store.add_many(many, [(i, 0) for i in range(700)])
        assert len(store) == 700 and store.query(sets[7], k=1)[0].keyframe_id in ids[7::40]
    with MapStore.open(milvus_map, conf={'insert_bytes': 1 << 40}) as store:
        with pytest.raises(MapError, match='insert failed.*(RESOURCE_EXHAUSTED|larger than max|64 MB)'):
            store.add_many(many * 3, [(i, 0) for i in range(2100)])
        assert len(store) == 700


def write_schema1_map(uri: str, sets, stamps, model: dict) -> list[int]:
    """A map exactly as lln_ros wrote it before schema 2 (the code of mapstore_milvus.py at schema 1):
    {map}_keyframes (a row per keyframe) + {map}_landmarks (a row per landmark, descriptor float16
    bits as ARRAY<INT16>); scalar index STL_SORT on the server (the 2.3 server refuses INVERTED)."""
    from pymilvus import DataType, MilvusClient

    from lln_ros.mapstore import FORMAT
    from lln_ros.mapstore.milvus import parse_uri

    where = parse_uri(uri)
    c = MilvusClient(uri=where['uri'], timeout=60)
    if where['db_name']:
        if where['db_name'] not in c.list_databases():
            c.create_database(where['db_name'])
        c.close()
        c = MilvusClient(uri=where['uri'], timeout=60, db_name=where['db_name'])
    m, dim = where['map'], int(model['descriptor_dim'])

    def create(name, fields, vector, vdim, index=None, auto_id=False):
        schema = MilvusClient.create_schema(auto_id=auto_id)
        for f, kind, extra in fields:
            schema.add_field(f, getattr(DataType, kind), **extra)
        schema.add_field(vector, DataType.FLOAT_VECTOR, dim=vdim)
        params = c.prepare_index_params()
        params.add_index(vector, index_type='FLAT', metric_type='IP' if vdim > 2 else 'L2')
        if index:
            params.add_index(index, index_type='INVERTED' if where['uri'].endswith('.db') else 'STL_SORT')
        c.create_collection(name, schema=schema, index_params=params, consistency_level='Strong')

    create(
        f'{m}_meta',
        [('key', 'VARCHAR', {'is_primary': True, 'max_length': 64}), ('value', 'VARCHAR', {'max_length': 65535})],
        'unused',
        2,
    )
    create(
        f'{m}_keyframes',
        [('id', 'INT64', {'is_primary': True}), ('stamp_sec', 'INT64', {}), ('stamp_nanosec', 'INT64', {})]
        + [(f, 'FLOAT', {}) for f in ('image_w', 'image_h', 'cell_w', 'cell_h')]
        + [(f, 'INT32', {}) for f in ('grid_rows', 'grid_cols', 'n')],
        'global_descriptor',
        dim,
    )
    create(
        f'{m}_landmarks',
        [
            ('pk', 'INT64', {'is_primary': True}),
            ('keyframe_id', 'INT64', {}),
            ('rank', 'INT32', {}),
            ('col', 'INT16', {}),
            ('row', 'INT16', {}),
            ('score', 'FLOAT', {}),
            ('descriptor', 'ARRAY', {'element_type': DataType.INT16, 'max_capacity': dim}),
        ],
        'center',
        2,
        index='keyframe_id',
        auto_id=True,
    )
    ids = list(range(1, len(sets) + 1))
    meta = {
        'format': FORMAT,
        'schema_version': '1',
        'created': '0',
        'created_by': 'lln_ros (schema 1)',
        'next_id': str(len(sets) + 1),
        'model': json.dumps(model, sort_keys=True),
        'descriptor_space': model['descriptor_space'],
        'descriptor_dim': str(dim),
    }
    c.upsert(f'{m}_meta', [{'key': k, 'value': v, 'unused': [0.0, 0.0]} for k, v in meta.items()])
    kf, lm = [], []
    for kid, lset, (sec, nsec) in zip(ids, sets, stamps):
        kf.append(
            {
                'id': kid,
                'stamp_sec': sec,
                'stamp_nanosec': nsec,
                'image_w': float(lset.image_size[0]),
                'image_h': float(lset.image_size[1]),
                'cell_w': float(lset.cell_size[0]),
                'cell_h': float(lset.cell_size[1]),
                'grid_rows': int(lset.grid[0]),
                'grid_cols': int(lset.grid[1]),
                'n': len(lset),
                'global_descriptor': np.asarray(lset.global_descriptor, np.float32).tolist(),
            }
        )
        bits = np.ascontiguousarray(lset.descriptors, np.float16).view(np.int16)
        lm += [
            {
                'keyframe_id': kid,
                'rank': j,
                'col': int(lset.cells[j, 0]),
                'row': int(lset.cells[j, 1]),
                'score': float(lset.scores[j]),
                'center': lset.centers[j].astype(np.float32).tolist(),
                'descriptor': bits[j].tolist(),
            }
            for j in range(len(lset))
        ]
    c.insert(f'{m}_landmarks', lm)
    c.insert(f'{m}_keyframes', kf)
    c.close()
    return ids


@pytest.mark.parametrize('milvus_uri', BOTH, indirect=True)
def test_schema1_map_is_migrated_at_open(milvus_uri):
    """A map written in the schema 1 layout opens as the current schema (1 -> 2 -> 3) with the same keyframes, answers,
    and the old per-landmark collections are gone; a second open does nothing more."""
    rng = np.random.default_rng(5)
    sets = [make_set(rng) for _ in range(30)]
    ids = write_schema1_map(milvus_uri, sets, [(100 + i, i) for i in range(30)], MODEL)
    with MapStore.open(milvus_uri, create=False) as store:
        assert store.info()['schema_version'] == MILVUS_SCHEMA and store.ids() == ids and store.check() == []
        got = store.get(ids[4])
        np.testing.assert_allclose(got.descriptors, sets[4].descriptors, atol=2e-3)
        np.testing.assert_array_equal(got.cells, sets[4].cells)
        assert got.meta['stamp'] == (104, 4)
        assert store.query(make_set(rng, base=sets[9], noise=0.3), k=1)[0].keyframe_id == ids[9]
        new = store.add(sets[0])
        assert new > ids[-1]
        names = store._client.list_collections()
        assert not any(n.endswith(('_keyframes', '_landmarks')) and n.startswith(store._fr_c[:-7]) for n in names)
    with MapStore.open(milvus_uri, create=False) as store:
        assert store.ids() == ids + [new]


@pytest.mark.parametrize('milvus_uri', BOTH, indirect=True)
def test_keypoints_are_stored_per_keyframe(milvus_uri):
    """verify mode's keypoints in Milvus: stored, replaced, zero of them, absent, deleted with the keyframe."""
    rng = np.random.default_rng(6)
    uv = rng.uniform(0, 300, (400, 2)).astype(np.float32)
    desc = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    with MapStore.open(milvus_uri, model=MODEL) as store:
        a, b, c = store.add_many([make_set(rng) for _ in range(3)], [(i, 0) for i in range(3)])
        assert store.keypoints(a) is None
        store.add_keypoints(a, uv, desc)
        store.add_keypoints(b, uv[:0], desc[:0])
        with pytest.raises(KeyError):
            store.add_keypoints(999, uv, desc)
        store.add_keypoints(c, uv[:10], desc[:10])
        store.add_keypoints(c, uv[:20], desc[:20])  # replaces
        store.delete([c])
        assert store.check() == []
    with MapStore.open(milvus_uri, create=False) as store:
        got_uv, got_desc = store.keypoints(a)
        np.testing.assert_array_equal(got_uv, uv)
        np.testing.assert_array_equal(got_desc, desc)
        assert store.keypoints(b)[0].shape == (0, 2) and store.keypoints(c) is None


READER = r"""
import json, sys, time
import numpy as np
from lln_ros.mapstore import MapStore
from test_mapstore import make_set
uri, want = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(11)
sets = [make_set(rng) for _ in range(want)]          # the writer's sets: same seed
with MapStore.open(uri, create=False) as store:
    print(json.dumps({'opened_with': len(store)}), flush=True)
    deadline = time.monotonic() + 60
    while len(store) < want and time.monotonic() < deadline:
        time.sleep(0.2)
    ids = store.ids()
    top = [store.query(sets[i], k=1)[0].keyframe_id for i in (0, want - 6)]
    recent = store.query(sets[want - 1], k=want, exclude_recent=5)
    print(json.dumps({'ids': ids, 'top': top, 'max_allowed': max(c.keyframe_id for c in recent)}), flush=True)
"""


@server
def test_two_readers_follow_one_writer(milvus_map):
    """Two reader processes open the map while this process writes: they see the keyframes added
    after they opened (the id list refreshes), and exclude_recent counts those too."""
    rng = np.random.default_rng(11)
    sets = [make_set(rng) for _ in range(30)]
    with MapStore.open(milvus_map, model=MODEL) as writer:
        ids = writer.add_many(sets[:10], [(i, 0) for i in range(10)])
        readers = [
            subprocess.Popen(
                [sys.executable, '-c', READER, milvus_map, '30'],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=child_env(),
                cwd=REPO,
            )
            for _ in range(2)
        ]
        for r in readers:
            assert json.loads(r.stdout.readline() or '{}').get('opened_with') == 10, r.stderr.read()
        ids += [writer.add(s, (10 + i, 0)) for i, s in enumerate(sets[10:])]
        for r in readers:
            out, err = r.communicate(timeout=120)
            assert r.returncode == 0, err
            seen = json.loads(out.strip().splitlines()[-1])
            assert seen['ids'] == ids and seen['top'] == [ids[0], ids[24]]
            assert seen['max_allowed'] < ids[25]


WRITER = r"""
import sys, time
import numpy as np
from lln_ros.errors import MapError
from lln_ros.mapstore import MapStore
from test_mapstore import MODEL, make_set
uri, total = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(12)
store = MapStore.open(uri, model=MODEL, conf={'timeout': 5.0})
acked, deadline = 0, time.monotonic() + 240
while acked < total and time.monotonic() < deadline:
    try:
        kid = store.add(make_set(rng), (acked, 0))
    except MapError as e:
        print('error', str(e).replace('\n', ' ')[:300], flush=True)
        time.sleep(0.5)
        continue
    acked += 1
    print('acked', kid, flush=True)
    time.sleep(0.02)
store.close()
"""


@server
@pytest.mark.parametrize('how', ['terminate', 'kill'])
def test_server_restart_while_a_writer_runs(milvus_server, milvus_map, how):
    """The server stops (SIGTERM, or SIGKILL) and starts again while a writer adds keyframes: the
    writer gets MapErrors that say what failed, carries on once the server is back, and every
    keyframe it was told was stored is in the map afterwards."""
    proc = subprocess.Popen(
        [sys.executable, '-c', WRITER, milvus_map, '80'],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=child_env(),
        cwd=REPO,
    )
    lines, acked = [], []

    def read_until(count: int) -> None:
        while len(acked) < count:
            line = proc.stdout.readline()
            if not line:
                raise AssertionError(f'writer ended with {len(acked)} acknowledged:\n' + ''.join(lines[-30:]))
            lines.append(line)
            if line.startswith('acked'):
                acked.append(int(line.split()[1]))

    try:
        read_until(20)
        milvus_server.restart(kill=how == 'kill')
        read_until(80)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    errors = [line for line in lines if line.startswith('error')]
    assert all('map milvus://' in e and 'failed' in e for e in errors), errors[:3]
    with MapStore.open(milvus_map, create=False) as store:
        stored = set(store.ids())
        lost = sorted(set(acked) - stored)
        assert not lost, f'acknowledged but lost after a server {how}: {lost} ({len(errors)} errors)'
        assert store.check() == []
        store.get(acked[19])
    print(f'{how}: {len(acked)} acknowledged, {len(errors)} MapErrors while the server was down, none lost')


@server
def test_matcher_over_dds_in_mapping_mode(milvus_map, colcon_install, extractor, photo, tmp_path):
    """The installed matcher node, map_path = the real server: mapping mode over DDS (loopback inside
    the namespace) with landmark sets of real photo crops; revisits found, every answered keyframe stored."""
    from sensor_msgs.msg import PointCloud2
    from test_nodes import Rig, cloud, header, stamp_of, start_matcher

    from lln_ros.ros import msgs

    crops = [photo[y : y + 256, x : x + 224] for y in (0, 170, 340) for x in (0, 144, 288)]
    sets = extractor.extract_batch([np.ascontiguousarray(c) for c in crops])
    places = {
        'sets': sets,
        'space': extractor.model_info['descriptor_space'],
        'dim': extractor.model_info['descriptor_dim'],
    }
    rig = Rig(colcon_install, tmp_path)
    try:
        # novelty off: every answered query is stored, revisits included (the point of this test)
        every = ('-p', 'keyframe_novelty_max_score:=0.0')
        proc = start_matcher(rig, milvus_map, places, '-p', 'mode:=mapping', '-p', 'exclude_recent:=2', *every)
        q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
        cands = rig.probe.collect(PointCloud2, 'lln/candidates', msgs.cloud_to_candidates)
        rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
        sequence = [0, 1, 2, 3, 4, 1, 5, 3]  # frame 5 revisits place 1, frame 7 place 3
        for j, place in enumerate(sequence):
            q_pub.publish(cloud(places, place, header(j)))
            rig.until(lambda: len(cands) > j, f'answer {j}', proc)
        assert [len(c) for c in cands[:3]] == [0, 0, 0]
        for j, c in enumerate(cands):
            allowed = {stamp_of(header(i)) for i in range(j - 2)}
            assert {(int(s), int(n)) for s, n in zip(c['stamp_sec'], c['stamp_nanosec'])} <= allowed, j
        for j, first in ((5, 1), (7, 3)):
            assert (int(cands[j]['stamp_sec'][0]), int(cands[j]['stamp_nanosec'][0])) == stamp_of(header(first))
        info = rig.info()
        assert info['keyframes'] == len(sequence) and info['counters']['queries_answered'] == len(sequence)
        assert proc.stop() == 0, proc.log()
    finally:
        rig.close()
    with MapStore.open(milvus_map, create=False) as store:
        assert [store.get(k).meta['stamp'] for k in store.ids()] == [stamp_of(header(j)) for j in range(len(sequence))]
        assert store.check() == []


def damage_row(uri: str, keyframe_id: int) -> None:
    """Write one keyframe's landmark blob as 1 byte, straight through pymilvus (past lln_ros's checks),
    as a bad writer, a bad import or a bit of storage rot would leave it."""
    from pymilvus import MilvusClient

    from lln_ros.mapstore.milvus import pack, parse_uri

    where = parse_uri(uri)
    c = MilvusClient(uri=where['uri'], timeout=60, **({'db_name': where['db_name']} if where['db_name'] else {}))
    try:
        name = f'{where["map"]}_frames'
        row = c.query(name, filter=f'id == {int(keyframe_id)}', output_fields=['*'], consistency_level='Strong')[0]
        row = {**row, 'landmarks': pack(np.zeros(1, np.uint8))}
        row['global_descriptor'] = [float(v) for v in row['global_descriptor']]
        c.upsert(name, [row])
    finally:
        c.close()


@pytest.mark.parametrize('milvus_uri', BOTH, indirect=True)
def test_damaged_keyframe_is_quarantined_at_open(milvus_uri):
    """#12 item 5 for Milvus: one keyframe's landmark blob of 1 byte (its n and D declare 50 x 336
    bytes) is found by the open's integrity check, named, quarantined (never answered, left in the
    collection; the rest of the map answers); the node's open (open_map), the store's check() and
    `lln-map check` name the same keyframe."""
    from test_map_backends import run_cli

    from lln_ros.mapstore import open_for_matcher as open_map

    rng = np.random.default_rng(21)
    sets = [make_set(rng) for _ in range(6)]
    with MapStore.open(milvus_uri, model=MODEL) as store:
        ids = store.add_many(sets, [(100 + i, 0) for i in range(6)])
        assert store.check() == []
    victim = ids[2]
    damage_row(milvus_uri, victim)
    store, quarantined = open_map(milvus_uri, 'localization', MODEL['descriptor_space'])
    with store:
        assert list(quarantined) == [victim], quarantined
        assert f'keyframe {victim}: landmark blob size 1 bytes does not fit n=50' in quarantined[victim]
        assert store.ids() == [i for i in ids if i != victim] and store.info()['quarantined'] == [victim]
        with pytest.raises(KeyError):
            store.get(victim)
        for j, s in enumerate(sets):  # the damaged place itself is answered from the others, no error
            found = [c.keyframe_id for c in store.query(make_set(rng, base=s, noise=0.2), k=6)]
            assert victim not in found and (j == 2 or found[0] == ids[j]), (j, found)
        assert [c.keyframe_id for c in store.query(sets[2], k=6, prefilter='holistic')].count(victim) == 0
        problems = store.check()
        assert len(problems) == 1 and problems[0].startswith(f'keyframe {victim}:'), problems
        assert 'quarantined' in problems[0]
        new = store.add(sets[2], (999, 0))  # the map still takes keyframes
        assert store.query(sets[2], k=1)[0].keyframe_id == new
    if milvus_uri.startswith('milvus://'):  # Milvus Lite: this process's embedded server keeps the lock
        out = run_cli('check', milvus_uri, check=False)
        assert out.returncode == 1 and f'keyframe {victim}:' in out.stdout and 'quarantined' in out.stdout, out
        assert out.stdout.count('  - ') == 1, out.stdout
    with MapStore.open(milvus_uri, create=False) as store:  # still there, still quarantined
        assert store.quarantined.keys() == {victim} and len(store) == 6
        assert store.clear() == 6 and store.check() == [] and store.quarantined == {}


@pytest.mark.parametrize('milvus_uri', BOTH, indirect=True)
def test_trained_landmark_index_is_kept_between_opens(milvus_uri, tmp_path, caplog):
    """A trained (IVF-PQ) landmark index is kept in a file on this machine at close and read at the
    next open instead of training again (minutes on a loaded machine), caught up with what another
    writer added and deleted meanwhile; a file of another map (other map_uuid) is not used."""
    import logging

    rng = np.random.default_rng(22)
    # every landmark held (landmark_index_top 0, not the default's best 25): 2,000 landmarks, IVF-PQ
    conf = {'landmark_index_threshold': 1000, 'landmark_dir': str(tmp_path / 'lm'), 'landmark_index_top': 0}
    sets = [make_set(rng) for _ in range(40)]
    with MapStore.open(milvus_uri, model=MODEL, conf=conf) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(40)])
        assert store.info()['landmark_index'] in landmark_index.COMPRESSED
    files = list((tmp_path / 'lm').iterdir())
    assert len(files) == 1 and files[0].suffix == '.landmarks'
    with MapStore.open(milvus_uri, create=False, conf={**conf, 'landmark_dir': ''}) as other:
        new = other.add(make_set(rng), (99, 0))
        other.delete([ids[0]])
    caplog.set_level(logging.INFO, logger='lln_ros')
    with MapStore.open(milvus_uri, create=False, conf=conf) as store:
        assert not [r for r in caplog.records if 'training' in r.getMessage()], 'trained again'
        assert store._landmarks.keyframe_counts() == {i: 50 for i in ids[1:] + [new]}
        assert store.check() == []
        assert store.query(make_set(rng, base=sets[5], noise=0.2), k=1)[0].keyframe_id == ids[5]
    with MapStore.open(milvus_uri, create=False, conf=conf) as store:
        assert store._read_landmark_file() is not None
        store._uuid = 'another map'  # as if the map had been dropped and made again under this name
        assert store._read_landmark_file() is None
