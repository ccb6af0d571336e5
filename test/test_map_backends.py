"""One suite, both map backends: the embedded SQLite + FAISS map and Milvus, on Milvus Lite and on a
real Milvus 2.3.5 server (the `milvus-server` cases run inside a loopback-only network namespace, see
test_milvus_server.py). Small maps of synthetic landmark sets."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from test_mapstore import MODEL, OTHER_MODEL, make_set

from lln_ros.core.similarity import default_conf as SIM
from lln_ros.errors import MapError
from lln_ros.mapstore import MapStore, SQLiteMapStore, backend_for
from lln_ros.mapstore.sessions import Origin

HAVE_MILVUS = importlib.util.find_spec('pymilvus') is not None and importlib.util.find_spec('milvus_lite') is not None
BACKENDS = [
    'sqlite',
    pytest.param(
        'milvus',
        marks=pytest.mark.skipif(not HAVE_MILVUS, reason='pymilvus / milvus-lite not installed (requirements.txt)'),
    ),
    pytest.param('milvus-server', marks=pytest.mark.milvus_server),
]


def uri_for(kind, tmp_path, name='map'):
    # in a folder that does not exist yet: both backends create it
    return str(tmp_path / 'maps' / f'{name}.db') if kind == 'sqlite' else f'milvus-lite://{tmp_path}/maps/{name}.db'


@pytest.fixture
def rng():
    return np.random.default_rng(1)


@pytest.fixture(params=BACKENDS)
def uri(request, tmp_path):
    if request.param == 'milvus-server':
        return request.getfixturevalue('milvus_map')
    return uri_for(request.param, tmp_path)


def test_uri_picks_backend(tmp_path):
    assert backend_for(tmp_path / 'a.db') == ('sqlite', str(tmp_path / 'a.db'))
    assert backend_for('sqlite:///x/a.db') == ('sqlite', '/x/a.db')
    assert backend_for('milvus://host:19530/db?map=city')[0] == 'milvus'
    assert backend_for('milvus-lite:///x/a.db')[0] == 'milvus'
    assert type(MapStore(tmp_path / 'b.db')) is SQLiteMapStore


def test_exhaustive_query_scores_every_allowed_keyframe(uri, rng):
    """prefilter_k 0 bypasses the index: every allowed keyframe is reranked, the same as a holistic
    top-K with K = the map size; negative prefilter_k is refused."""
    with MapStore.open(uri, model=MODEL) as store:
        sets = [make_set(rng) for _ in range(12)]
        ids = store.add_many(sets, [(i, 0) for i in range(12)])
        query = make_set(rng, base=sets[4], noise=0.5)
        every = store.query(query, prefilter_k=0, k=12)
        assert sorted(c.keyframe_id for c in every) == ids
        assert [c.score for c in every] == sorted((c.score for c in every), reverse=True)
        # the same ranking and scores; float32 sums of S may differ in the last bits with the batch
        # (seen on an AVX-only CPU, where BLAS picks other kernels: 0.44473436 against 0.44473442)
        top12 = store.query(query, prefilter_k=12, k=12)
        assert [c.keyframe_id for c in every] == [c.keyframe_id for c in top12]
        assert [c.score for c in every] == pytest.approx([c.score for c in top12], rel=1e-5)
        assert [c.keyframe_id for c in store.query(query, prefilter_k=0, k=3)] == [c.keyframe_id for c in every[:3]]
        allowed = store.query(query, prefilter_k=0, k=12, exclude_recent=5)
        assert sorted(c.keyframe_id for c in allowed) == ids[:7]
        assert store.query(query, prefilter_k=0, k=5, exclude_recent=12) == []
        with pytest.raises(ValueError, match='prefilter_k >= 0'):
            store.query(query, prefilter_k=-1)


def test_exclude_ids_are_never_answers(uri, rng):
    """exclude_ids (a session's own newest keyframes, which need not be the highest ids when several
    processes write one Milvus map) drops exactly those keyframes from every first stage, and the
    others still fill the k answers."""
    sets = [make_set(rng) for _ in range(6)]
    with MapStore.open(uri, model=MODEL) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(6)])
        view = make_set(rng, base=sets[1], noise=0.1)
        for prefilter in ('landmarks', 'holistic', 'exhaustive'):
            assert store.query(view, k=1, prefilter=prefilter)[0].keyframe_id == ids[1]
            found = [c.keyframe_id for c in store.query(view, k=4, prefilter=prefilter, exclude_ids=ids[:2])]
            assert len(found) == 4 and not set(found) & set(ids[:2]), (prefilter, found)


def test_include_ids_are_reranked_beside_the_first_stage(uri, rng):
    """include_ids (the sequence search's next places) joins the first stage's candidates: scored by S
    like them, once; an excluded or unknown id is left out, whatever the first stage."""
    sets = [make_set(rng) for _ in range(8)]
    with MapStore.open(uri, model=MODEL) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(8)])
        view = make_set(rng, base=sets[1], noise=0.1)
        for prefilter in ('landmarks', 'holistic'):
            alone = [c.keyframe_id for c in store.query(view, k=8, prefilter=prefilter, prefilter_k=1)]
            assert alone == [ids[1]], prefilter
            both = store.query(view, k=8, prefilter=prefilter, prefilter_k=1, include_ids=[ids[5], ids[1], ids[5]])
            assert sorted(c.keyframe_id for c in both) == sorted([ids[1], ids[5]]), prefilter
            scored = {c.keyframe_id: c.score for c in store.query(view, k=8, prefilter=prefilter, prefilter_k=8)}
            assert all(np.isclose(c.score, scored[c.keyframe_id]) for c in both)  # the same S as a candidate
            kept = store.query(
                view,
                k=8,
                prefilter=prefilter,
                prefilter_k=1,
                exclude_recent=2,
                exclude_ids=[ids[3]],
                include_ids=[ids[3], ids[4], ids[7], max(ids) + 100],
            )
            assert sorted(c.keyframe_id for c in kept) == sorted([ids[1], ids[4]]), prefilter


def test_insert_query_get(uri, rng):
    with MapStore.open(uri, model=MODEL) as store:
        sets = [make_set(rng) for _ in range(25)]
        ids = store.add_many(sets[:20], [(100 + i, i) for i in range(20)])
        ids += [store.add(s, stamp=(120 + i, 7)) for i, s in enumerate(sets[20:])]
        assert ids == sorted(ids) and len(set(ids)) == 25 and len(store) == 25 and store.ids() == ids
        for i in (0, 13, 24):
            top = store.query(sets[i], prefilter_k=10, k=3)
            assert len(top) == 3 and top[0].keyframe_id == ids[i]
            assert top[0].holistic_score == pytest.approx(1.0, abs=1e-5)
            assert top[0].score == pytest.approx(50.0 * (1 + SIM['fusion_weight']), abs=0.15) and top[0].n_pairs == 50
        noisy = make_set(rng, base=sets[5], noise=0.3)
        assert store.query(noisy, prefilter_k=10, k=1)[0].keyframe_id == ids[5]
        assert [c.keyframe_id for c in store.query(sets[24], k=5, exclude_recent=1)] and ids[24] not in [
            c.keyframe_id for c in store.query(sets[24], k=25, exclude_recent=1)
        ]
        assert store.query(sets[0], k=5, exclude_recent=25) == []
        got = store.get(ids[3])
        np.testing.assert_allclose(got.descriptors, sets[3].descriptors, atol=2e-3)
        np.testing.assert_array_equal(got.cells, sets[3].cells)
        np.testing.assert_allclose(got.centers, sets[3].centers)
        np.testing.assert_allclose(got.global_descriptor, sets[3].global_descriptor, atol=1e-6)
        assert got.meta['stamp'] == (103, 3) and got.grid == (9, 12)
        with pytest.raises(KeyError):
            store.get(10_000)
        assert store.check() == []


def test_delete_and_clear_never_reuse_ids(uri, rng):
    with MapStore.open(uri, model=MODEL) as store:
        sets = [make_set(rng) for _ in range(10)]
        ids = store.add_many(sets, [(i, 0) for i in range(10)])
        assert store.delete([ids[2], ids[7], 999_999]) == 2
        assert len(store) == 8 and ids[2] not in store and ids[3] in store
        assert all(c.keyframe_id != ids[2] for c in store.query(sets[2], prefilter_k=10, k=10))
        assert store.check() == []
        store.clear()
        assert (
            len(store) == 0
            and store.query(sets[0]) == []
            and store.model['descriptor_space'] == MODEL['descriptor_space']
        )
        assert store.add(sets[0]) > max(ids)


def test_save_reload(uri, rng):
    sets = [make_set(rng) for _ in range(12)]
    with MapStore.open(uri, model=MODEL) as store:
        ids = store.add_many(sets, [(50 + i, 9) for i in range(12)])
        store.delete([ids[0]])
        store.save()
    with MapStore.open(uri, create=False) as store:
        assert store.ids() == ids[1:] and store.model['descriptor_space'] == MODEL['descriptor_space']
        top = store.query(sets[4], k=1)[0]
        assert top.keyframe_id == ids[4] and top.stamp == (54, 9)
        assert store.check() == []
        assert store.info()['keyframes'] == 11


def test_model_mismatch(uri, rng):
    with MapStore.open(uri, model=MODEL) as store:
        store.add(make_set(rng))
    with pytest.raises(MapError, match='resnet101'):
        MapStore.open(uri, model=OTHER_MODEL)
    with MapStore.open(uri) as store:
        other = make_set(rng, dim=1024, space=OTHER_MODEL['descriptor_space'])
        with pytest.raises(MapError, match='different models'):
            store.add(other)
        with pytest.raises(MapError, match='different models'):
            store.query(other)
        assert len(store) == 1


def test_missing_map_with_create_false(uri):
    with pytest.raises(MapError, match='no map'):
        MapStore.open(uri, create=False)


def test_sqlite_ivf_above_threshold(tmp_path, rng):
    """Past index_threshold the global index turns IVF (while adding, and when reopened) and still
    finds each keyframe for itself; FAISS and SQLite agree."""
    conf = {'index_threshold': 60, 'ivf_lists': 8, 'ivf_nprobe': 8}
    path = tmp_path / 'ivf.db'
    sets = [make_set(rng) for _ in range(100)]
    with MapStore.open(path, model=MODEL, conf=conf) as store:
        ids = store.add_many(sets[:50], [(i, 0) for i in range(50)])
        assert store.info()['index'] == 'exact'
        ids += store.add_many(sets[50:], [(i, 0) for i in range(50, 100)])
        assert store.info()['index'] == 'ivf'
        assert store.delete([ids[10]]) == 1 and store.check() == []
    with MapStore.open(path, conf=conf) as store:
        assert store.info()['index'] == 'ivf' and store.check() == []
        for i in (0, 55, 99):
            assert store.query(sets[i], k=1)[0].keyframe_id == ids[i]
        assert all(c.keyframe_id < ids[95] for c in store.query(sets[99], k=30, exclude_recent=5))
        # exhaustive queries bypass the approximate index: every keyframe, whatever nprobe misses
        assert len(store.query(sets[7], prefilter_k=0, k=200)) == 99


def run_cli(*args, check=True):
    env = {
        **os.environ,
        'PYTHONPATH': os.pathsep.join(
            p for p in (os.path.dirname(os.path.dirname(os.path.abspath(__file__))), os.environ.get('PYTHONPATH')) if p
        ),
    }
    out = subprocess.run(
        [sys.executable, '-m', 'lln_ros.cli.map', *args], capture_output=True, text=True, env=env, timeout=300
    )
    if check and out.returncode:
        raise AssertionError(f'lln-map {args} exited {out.returncode}:\n{out.stdout}\n{out.stderr}')
    return out


@pytest.mark.skipif(not HAVE_MILVUS, reason='pymilvus / milvus-lite not installed (requirements.txt)')
@pytest.mark.parametrize('target', ['lite', pytest.param('server', marks=pytest.mark.milvus_server)])
def test_cli_export_import_between_backends(tmp_path, rng, request, target):
    src = tmp_path / 'src.db'
    sets = [make_set(rng) for _ in range(15)]
    with MapStore.open(src, model=MODEL) as store:
        ids = store.add_many(sets, [(10 + i, i) for i in range(15)])
        store.delete([ids[1]])
    milvus = f'milvus-lite://{tmp_path}/fleet.db' if target == 'lite' else request.getfixturevalue('milvus_map')
    out = run_cli('export', str(src), milvus)
    assert '14 keyframes' in out.stdout
    back = tmp_path / 'back.db'
    run_cli('import', str(back), milvus)
    with MapStore.open(back, create=False) as store:
        assert store.ids() == ids[:1] + ids[2:]
        assert store.query(sets[7], k=1)[0].keyframe_id == ids[7]
        np.testing.assert_allclose(store.get(ids[9]).descriptors, sets[9].descriptors, atol=2e-3)
    info = json.loads(run_cli('info', '--json', milvus).stdout)
    assert info['keyframes'] == 14 and info['backend'] == 'milvus'
    assert 'healthy' in run_cli('check', milvus).stdout
    # again: every keyframe is there already (by content), so nothing is copied twice
    assert 'copied 0 keyframes' in run_cli('export', str(src), milvus).stdout
    other = tmp_path / 'other.db'  # another map whose ids are taken by different keyframes: refused (bad input)
    with MapStore.open(other, model=MODEL) as store:
        store.add_many([make_set(rng) for _ in range(3)], [(i, 0) for i in range(3)])
    assert run_cli('export', str(other), milvus, check=False).returncode == 2
    # the keyframe's identity and geometry come along (lln_ros.mapstore.merge)
    with MapStore.open(src) as store:
        session = store.start_session('robot_x')
        kid = store.add(make_set(rng), (99, 0))
        store.set_origin(kid, session.id, 1)
        store.set_geometry(kid, {'frame_id': 'robot_x/odom'})
    assert 'copied 1 keyframes' in run_cli('export', str(src), milvus).stdout
    with MapStore.open(milvus) as store:
        robots = {s.robot: s for s in store.sessions()}  # src's first 14 had no origin: a legacy session 'src'
        assert robots.keys() == {'src', 'robot_x'} and robots['robot_x'].label == session.label
        assert store.origins([kid])[kid] == Origin(robots['robot_x'].id, 1)
        assert store.geometry(kid)['frame_id'] == 'robot_x/odom'


def test_cli_info_check_compact(tmp_path, rng):
    path = tmp_path / 'm.db'
    with MapStore.open(path, model=MODEL) as store:
        ids = store.add_many([make_set(rng) for _ in range(30)], [(i, 0) for i in range(30)])
        store.delete(ids[:20])
    info = json.loads(run_cli('info', '--json', str(path)).stdout)
    assert info['keyframes'] == 10 and info['backend'] == 'sqlite' and info['index'] == 'exact'
    out = run_cli('compact', str(path)).stdout
    assert 'bytes' in out
    assert 'healthy' in run_cli('check', str(path)).stdout


@pytest.mark.parametrize('damage', ['truncate', 'garbage', 'bad_blob'])
def test_cli_check_explains_a_damaged_map(tmp_path, rng, damage):
    path = tmp_path / 'm.db'
    with MapStore.open(path, model=MODEL) as store:
        store.add_many([make_set(rng) for _ in range(40)], [(i, 0) for i in range(40)])
    if damage == 'truncate':
        with open(path, 'r+b') as f:
            f.truncate(os.path.getsize(path) // 2)
    elif damage == 'garbage':
        with open(path, 'r+b') as f:
            f.seek(0)
            f.write(b'\x00' * 512)
    else:
        import sqlite3

        con = sqlite3.connect(path)
        con.execute('UPDATE landmarks SET descriptors = zeroblob(10) WHERE keyframe_id = 5')
        con.commit()
        con.close()
    out = run_cli('check', str(path), check=False)
    assert out.returncode == 1, out.stdout + out.stderr
    assert str(path) in out.stdout + out.stderr
    text = out.stdout + out.stderr
    assert {'truncate': 'truncated', 'garbage': 'not an lln_ros map', 'bad_blob': 'keyframe 5'}[damage] in text
    with pytest.raises(MapError, match=str(path) if damage != 'bad_blob' else 'keyframe 5'):
        with MapStore.open(path, create=False) as store:  # never a silent empty map
            store.get(5)


def test_sqlite_migration_runs_once_in_a_transaction(tmp_path, rng, monkeypatch):
    """A map at an older schema version is upgraded at open by MIGRATIONS[v], once; a failing
    migration leaves the file at its old version."""
    import sqlite3

    from lln_ros import mapstore

    path = tmp_path / 'old.db'
    with MapStore.open(path, model=MODEL) as store:
        kid = store.add(make_set(rng))
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(mapstore.SCHEMA_VERSION - 1),))
    con.commit()
    con.close()
    calls = []

    def broken(conn):
        conn.execute('CREATE TABLE half_done (x)')
        raise RuntimeError('migration failed')

    monkeypatch.setitem(mapstore.MIGRATIONS, mapstore.SCHEMA_VERSION - 1, broken)
    with pytest.raises(RuntimeError):
        MapStore.open(path)
    con = sqlite3.connect(path)
    assert con.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == str(
        mapstore.SCHEMA_VERSION - 1
    )
    assert not con.execute("SELECT name FROM sqlite_master WHERE name = 'half_done'").fetchall()
    con.close()
    monkeypatch.setitem(mapstore.MIGRATIONS, mapstore.SCHEMA_VERSION - 1, calls.append)
    with MapStore.open(path) as store:
        assert store.info()['schema_version'] == mapstore.SCHEMA_VERSION and store.ids() == [kid]
    with MapStore.open(path) as store:
        assert len(calls) == 1 and store.check() == []


def test_sessions_and_origins_identify_keyframes(uri, rng):
    """Keyframe identity (issue 29): a session per robot run, each keyframe's (session, seq), kept
    across a reopen, carried by the answers (session_id), and forgotten with the keyframe."""
    with MapStore.open(uri, model=MODEL) as store:
        a = store.start_session('robot_a')
        b = store.start_session('fleet/robot_b', label='20261203T120000Z-abcdef', started_ns=5)
        assert (a.id, b.id) != (0, 0) and a.id != b.id and a.label != b.label
        assert store.start_session('fleet/robot_b', label=b.label).id == b.id  # brought in once
        sets = [make_set(rng) for _ in range(6)]
        ids = store.add_many(sets, [(i, 0) for i in range(6)])
        for n, kid in enumerate(ids):
            store.set_origin(kid, (a, b)[n % 2].id, n // 2 + 1)
        with pytest.raises(MapError, match='refused'):
            store.set_origin(ids[0], b.id, 1)  # session b already has a keyframe 1
        with pytest.raises(MapError, match='refused'):
            store.set_origin(ids[0], 999, 1)  # no such session
        for bad in ('', '/robot', 'a b', 'x' * 65):
            with pytest.raises(ValueError):
                store.start_session(bad)
        found = store.query(make_set(rng, base=sets[3], noise=0.1), k=2)
        assert found[0].keyframe_id == ids[3] and found[0].session_id == b.id
    with MapStore.open(uri, model=MODEL) as store:
        assert [(s.robot, s.label) for s in store.sessions()] == [(a.robot, a.label), (b.robot, b.label)]
        origins = store.origins()
        assert {k: (o.session_id, o.seq) for k, o in origins.items()} == {
            kid: ((a, b)[n % 2].id, n // 2 + 1) for n, kid in enumerate(ids)
        }
        store.delete([ids[0]])
        assert ids[0] not in store.origins() and store.origins([ids[1]])[ids[1]].session_id == b.id
