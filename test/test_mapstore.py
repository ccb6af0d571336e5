"""The persistent map (lln_ros.mapstore): real SQLite files, landmark sets of realistic shapes
(n=50, D=320, a 9x12 grid at 384x288) made with numpy."""

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from lln_ros.core.landmarks import LandmarkSet
from lln_ros.core.similarity import default_conf as SIM
from lln_ros.errors import MapError
from lln_ros.mapstore import SCHEMA_VERSION, MapCandidate, MapStore

SPACE = 'efficientnet_lite0/stage7/320'
MODEL = {
    'backbone': 'efficientnet_lite0',
    'layer': 'stage7',
    'descriptor_dim': 320,
    'descriptor_space': SPACE,
    'head': 'abc123',
    'head_trained': True,
    'weights': '',
    'input_height': 288,
}
OTHER_MODEL = {
    **MODEL,
    'backbone': 'resnet101',
    'layer': 'layer3',
    'descriptor_dim': 1024,
    'descriptor_space': 'resnet101/layer3/1024',
}


def make_set(rng, n=50, dim=320, rows=9, cols=12, space=SPACE, base=None, noise=0.0):
    """Random unit descriptors with realistic shapes; `base` given: a noisy view of that set."""

    def unit(x):
        return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)

    if base is None:
        glob, desc = unit(rng.standard_normal(dim)), unit(rng.standard_normal((n, dim)))
        flat = rng.choice(rows * cols, n, replace=False)
        cells = np.stack([flat % cols, flat // cols], axis=1).astype(np.int32)
    else:
        glob = unit(base.global_descriptor + noise * rng.standard_normal(dim))
        desc = unit(base.descriptors + noise * rng.standard_normal(base.descriptors.shape))
        cells = base.cells.copy()
    cell = np.array([384 / cols, 288 / rows], np.float32)
    return LandmarkSet(
        global_descriptor=glob,
        descriptors=desc,
        cells=cells,
        centers=((cells + 0.5) * cell).astype(np.float32),
        scores=np.sort(rng.random(n).astype(np.float32))[::-1].copy(),
        cell_size=cell,
        image_size=np.array([384, 288], np.float32),
        grid=(rows, cols),
        activation=rng.random((rows, cols)).astype(np.float32),
        descriptor_space=space,
    )


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def map_path(tmp_path):
    return tmp_path / 'maps' / 'map.db'


def fill(store, rng, count, start_sec=100):
    sets = [make_set(rng) for _ in range(count)]
    ids = [store.add(s, stamp=(start_sec + i, 1000 * i)) for i, s in enumerate(sets)]
    return sets, ids


def test_add_then_query_with_itself_ranks_first(map_path, rng):
    with MapStore.open(map_path, model=MODEL) as store:
        sets, ids = fill(store, rng, 40)
        assert ids == sorted(ids) and len(set(ids)) == 40 and len(store) == 40 and store.ids() == ids
        for i in (0, 17, 39):
            res = store.query(sets[i], prefilter_k=30, k=5)
            assert 1 <= len(res) <= 5 and all(isinstance(c, MapCandidate) for c in res)
            top = res[0]
            assert top.keyframe_id == ids[i]
            assert top.stamp == (100 + i, 1000 * i)
            assert top.holistic_score == pytest.approx(1.0, abs=1e-5)
            # 50 mutual pairs, cosine ~1, weight 1, in raw S and in the whitened S the default adds
            assert top.score == pytest.approx(50.0 * (1 + SIM['fusion_weight']), abs=0.15)
            assert top.score > res[1].score + 10
            assert [c.score for c in res] == sorted((c.score for c in res), reverse=True)
            assert top.offset == (0, 0) and top.n_pairs == 50
            p = top.pairs
            assert set(p) == {
                'query_index',
                'map_index',
                'query_u',
                'query_v',
                'map_u',
                'map_v',
                'cell_w',
                'cell_h',
                'similarity',
                'weight',
            }
            assert all(len(v) == 50 for v in p.values())
            np.testing.assert_array_equal(p['query_index'], p['map_index'])
            np.testing.assert_allclose(p['query_u'], sets[i].centers[p['query_index'], 0])
            np.testing.assert_allclose(p['map_v'], sets[i].centers[p['map_index'], 1])
            np.testing.assert_allclose(p['cell_w'], 32.0)
            np.testing.assert_allclose(p['cell_h'], 32.0)
            np.testing.assert_allclose(p['similarity'], 1.0, atol=2e-3)
            np.testing.assert_allclose(p['weight'], 1.0)
            assert top.cell_size == (32.0, 32.0) and top.image_size == (384.0, 288.0)


def test_noisy_revisit_is_found(map_path, rng):
    with MapStore(map_path) as store:
        sets, ids = fill(store, rng, 30)
        revisit = make_set(rng, base=sets[12], noise=0.05)
        assert store.query(revisit)[0].keyframe_id == ids[12]


def test_k_min_score_and_holistic_only(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        sets, ids = fill(store, rng, 20)
        assert len(store.query(sets[3], k=2)) == 2
        only = store.query(sets[3], min_score=10.0)
        assert [c.keyframe_id for c in only] == [ids[3]]
        hol = store.query(sets[3], prefilter_k=10, k=10, method_rerank=False, prefilter='holistic')
        assert len(hol) == 10 and hol[0].keyframe_id == ids[3]
        assert all(c.score == c.holistic_score and c.n_pairs == 0 for c in hol)
        assert [c.score for c in hol] == sorted((c.score for c in hol), reverse=True)
        with pytest.raises(ValueError):
            store.query(sets[3], prefilter_k=-1)
        with pytest.raises(ValueError):
            store.query(sets[3], k=0)


def test_exclude_recent(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        sets, ids = fill(store, rng, 15)
        query = make_set(rng)
        # the 5 most recent keyframes are near-copies of the query: holistically the best 5
        near = [store.add(make_set(rng, base=query, noise=0.02)) for _ in range(5)]
        assert {
            c.keyframe_id for c in store.query(query, method_rerank=False, prefilter='holistic', prefilter_k=5, k=5)
        } == set(near)
        res = store.query(query, prefilter_k=3, k=3, exclude_recent=5, method_rerank=False, prefilter='holistic')
        assert len(res) == 3, 'FAISS must be asked for more than prefilter_k when recent ones are excluded'
        assert all(c.keyframe_id in ids for c in res)
        reranked = store.query(query, prefilter_k=3, k=3, exclude_recent=5)
        assert len(reranked) == 3 and not set(near) & {c.keyframe_id for c in reranked}
        # a keyframe about to be stored is not its own loop closure
        last = store.add(sets[0])
        assert store.query(sets[0])[0].keyframe_id == last
        assert store.query(sets[0], exclude_recent=1)[0].keyframe_id == ids[0]
        assert store.query(sets[0], exclude_recent=len(store)) == []


def test_get_round_trip(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        s = make_set(rng)
        kid = store.add(s, stamp=(1700000000, 999999999))
        back = store.get(kid)
        np.testing.assert_array_equal(back.global_descriptor, s.global_descriptor)
        np.testing.assert_allclose(back.descriptors, s.descriptors, atol=1e-3)  # stored as float16
        assert back.descriptors.dtype == np.float32
        np.testing.assert_array_equal(back.cells, s.cells)
        np.testing.assert_array_equal(back.centers, s.centers)
        np.testing.assert_array_equal(back.scores, s.scores)
        np.testing.assert_array_equal(back.cell_size, s.cell_size)
        np.testing.assert_array_equal(back.image_size, s.image_size)
        assert back.grid == (9, 12) and back.descriptor_space == SPACE and back.activation is None
        assert back.meta == {'keyframe_id': kid, 'stamp': (1700000000, 999999999)}
        back.validate()
        assert kid in store and kid + 1 not in store
        with pytest.raises(KeyError, match='map.db'):
            store.get(kid + 1)


def test_stamp_from_ros_time_like_object(map_path, rng):
    class Time:
        sec, nanosec = 12, 34

    with MapStore(map_path) as store:
        kid = store.add(make_set(rng), stamp=Time())
        assert store.get(kid).meta['stamp'] == (12, 34)
        with pytest.raises(ValueError, match='nanosec'):
            store.add(make_set(rng), stamp=(1, 2_000_000_000))


def test_reopen_keeps_everything(map_path, rng):
    store = MapStore.open(map_path, model=MODEL)
    sets, ids = fill(store, rng, 25)
    store.close()
    store.close()  # idempotent
    with pytest.raises(MapError, match='closed'):
        len(store)
    with MapStore.open(map_path, create=False) as again:
        assert again.ids() == ids and len(again) == 25
        assert again.model == MODEL
        for i in (0, 24):
            assert again.query(sets[i])[0].keyframe_id == ids[i]
            np.testing.assert_allclose(again.get(ids[i]).descriptors, sets[i].descriptors, atol=1e-3)
        info = again.info()
        assert info['keyframes'] == 25 and info['schema_version'] == SCHEMA_VERSION
        assert info['path'] == str(map_path) and info['descriptor_space'] == SPACE
        assert info['file_bytes'] > 25 * 34080 and info['model'] == MODEL
        assert again.check() == []
        # ids keep growing after a reopen
        assert again.add(sets[0]) > ids[-1]


def test_model_recorded_from_first_set_when_none_given(map_path, rng):
    with MapStore(map_path) as store:
        assert store.model is None and store.query(make_set(rng)) == []
        store.add(make_set(rng))
        assert store.model == {'descriptor_space': SPACE, 'descriptor_dim': 320}
    with MapStore(map_path, model=MODEL) as store:  # same space: accepted
        assert len(store) == 1


def test_model_mismatch_refused(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        store.add(make_set(rng))
        other = make_set(rng, dim=1024, space='resnet101/layer3/1024')
        with pytest.raises(MapError, match='resnet101/layer3/1024') as err:
            store.add(other)
        assert str(map_path) in str(err.value) and SPACE in str(err.value)
        with pytest.raises(MapError, match='resnet101'):
            store.query(other)
        same_dim_other_space = make_set(rng, space='efficientnet_lite0/stage6/320')
        with pytest.raises(MapError, match='stage6'):
            store.add(same_dim_other_space)
        with pytest.raises(MapError, match='descriptor_space'):
            store.add(make_set(rng, space=''))
        assert len(store) == 1
    with pytest.raises(MapError) as err:
        MapStore(map_path, model=OTHER_MODEL)
    msg = str(err.value)
    assert str(map_path) in msg and SPACE in msg and 'resnet101/layer3/1024' in msg
    with pytest.raises(MapError, match='descriptor_dim'):
        MapStore(map_path, model={'backbone': 'x'})
    with MapStore(map_path) as store:  # the refused open changed nothing
        assert store.model == MODEL and len(store) == 1 and store.check() == []


def test_random_bytes_refused(tmp_path):
    path = tmp_path / 'noise.db'
    path.write_bytes(np.random.default_rng(1).bytes(20000))
    with pytest.raises(MapError, match='noise.db'):
        MapStore(path)


def test_empty_file_refused(tmp_path):
    path = tmp_path / 'empty.db'
    path.touch()
    with pytest.raises(MapError, match='empty.db'):
        MapStore(path)
    assert path.stat().st_size == 0


@pytest.mark.parametrize('verify', [True, False])
@pytest.mark.parametrize('fraction', [0.5, 0.9])
def test_truncated_map_refused(map_path, rng, verify, fraction):
    with MapStore(map_path, model=MODEL) as store:
        fill(store, rng, 30)
    size = map_path.stat().st_size
    with open(map_path, 'r+b') as f:
        f.truncate(int(size * fraction))
    with pytest.raises(MapError, match='map.db') as err:
        MapStore(map_path, verify=verify)
    assert 'truncated' in str(err.value) or 'corrupt' in str(err.value)


def test_truncated_map_with_leftover_wal_refused(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        fill(store, rng, 30)
    with open(map_path, 'r+b') as f:
        f.truncate(map_path.stat().st_size // 2)
    (map_path.parent / 'map.db-wal').write_bytes(b'\0' * 64)  # skips the header size check
    with pytest.raises(MapError, match='map.db'):
        MapStore(map_path)


def test_foreign_sqlite_file_refused_and_untouched(tmp_path):
    path = tmp_path / 'photos.sqlite'
    con = sqlite3.connect(path)
    con.execute('CREATE TABLE photos (id INTEGER PRIMARY KEY, name TEXT)')
    con.execute("INSERT INTO photos (name) VALUES ('a')")
    con.commit()
    con.close()
    before = path.read_bytes()
    with pytest.raises(MapError, match='photos.sqlite.*not an lln_ros map'):
        MapStore(path)
    assert path.read_bytes() == before, 'a file that is not ours must not be modified'
    path2 = tmp_path / 'meta.sqlite'
    con = sqlite3.connect(path2)
    con.execute('CREATE TABLE meta (key TEXT, value TEXT)')
    con.commit()
    con.close()
    with pytest.raises(MapError, match='meta.sqlite.*not an lln_ros map'):
        MapStore(path2)


def test_missing_file_with_create_false(tmp_path):
    with pytest.raises(MapError, match='nope.db'):
        MapStore(tmp_path / 'nope.db', create=False)
    assert not (tmp_path / 'nope.db').exists()


def test_newer_schema_refused(map_path):
    MapStore(map_path).close()
    con = sqlite3.connect(map_path)
    con.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION + 1),))
    con.commit()
    con.close()
    with pytest.raises(MapError, match='schema version'):
        MapStore(map_path)


def test_clear_keeps_model_and_never_reuses_ids(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        sets, ids = fill(store, rng, 10)
        store.clear()
        assert len(store) == 0 and store.ids() == [] and store.query(sets[0]) == []
        assert store.model == MODEL and store.check() == []
        new = store.add(sets[0])
        assert new > ids[-1]
        assert store.query(sets[0])[0].keyframe_id == new
    with MapStore(map_path) as store:
        assert store.ids() == [new] and store.model == MODEL


def test_check_healthy_and_damaged(map_path, rng):
    with MapStore(map_path, model=MODEL) as store:
        assert store.check() == []
        fill(store, rng, 12)
        assert store.check() == []
        store.save()
        assert store.info()['wal_bytes'] == 0
        assert store.check() == []
    con = sqlite3.connect(map_path)
    con.execute('UPDATE landmarks SET descriptors = zeroblob(100) WHERE keyframe_id = 3')
    con.execute('DELETE FROM keyframes WHERE id = 5')
    con.commit()
    con.close()
    with MapStore(map_path) as store:
        problems = store.check()
        assert any('keyframe 3' in p and 'blob sizes' in p for p in problems), problems
        assert any('landmarks row 5' in p for p in problems), problems
        with pytest.raises(MapError, match='keyframe 3'):
            store.get(3)


def test_second_connection_sees_new_keyframes(map_path, rng):
    with MapStore(map_path, model=MODEL) as a, MapStore(map_path) as b:
        sets, ids = fill(a, rng, 5)
        assert b.ids() == ids
        assert b.query(sets[2])[0].keyframe_id == ids[2]
        a.clear()
        assert len(b) == 0 and b.check() == []


# every landmark held (landmark_index_top 0): 12 keyframes of 50 pass the threshold of 500
SMALL_IVF = {
    'landmark_index_threshold': 500,
    'landmark_ivf_lists': 8,
    'landmark_nprobe': 8,
    'landmark_pq_bits': 4,
    'landmark_index_top': 0,
}


@pytest.mark.parametrize('conf', [{}, SMALL_IVF], ids=['exact', 'compressed'])
def test_second_connection_adds_appended_keyframes_without_a_reload(map_path, rng, conf):
    """A reader beside a writer catches up by id (sqlite_catch_up.py): what the writer appended joins
    the reader's indexes without a full reload (which retrains a compressed landmark index: seconds
    per foreign commit on a fleet's map), and it answers as a map opened afresh; a delete falls back
    to the full reload, so the deleted keyframe is never answered."""
    with MapStore(map_path, model=MODEL, conf=conf) as a, MapStore(map_path, conf=conf) as b:
        sets, ids = fill(a, rng, 12)  # 600 landmarks: compressed from the start with SMALL_IVF
        assert (a.info()['landmark_index'] != 'exact') == bool(conf)
        b.query(sets[0])
        reloads = []
        full_load = b._load
        b._load = lambda: (reloads.append(len(a)), full_load())[1]
        more, more_ids = [], []
        for round_ in range(4):  # four foreign commits, each caught up at the reader's next call
            new_sets, new_ids = fill(a, rng, 5, start_sec=200 + 10 * round_)
            more, more_ids = more + new_sets, more_ids + new_ids
            assert b.query(new_sets[-1], k=1)[0].keyframe_id == new_ids[-1]
        assert reloads == [] and b.ids() == ids + more_ids and b.check() == []
        # ids below ones the reader knows: another writer's, interleaved with its own, or an import
        gap = [make_set(rng) for _ in range(2)]
        gap_ids = a.add_many(gap, [(300, 0), (301, 0)], ids=[ids[-1] + 1000, ids[-1] + 1001])
        assert b.query(gap[0], k=1)[0].keyframe_id == gap_ids[0]
        low = [make_set(rng) for _ in range(2)]
        low_ids = a.add_many(low, [(302, 0), (303, 0)], ids=[ids[-1] + 500, ids[-1] + 501])
        assert b.query(low[1], k=1)[0].keyframe_id == low_ids[1]
        more, more_ids = more + gap + low, more_ids + gap_ids + low_ids
        assert reloads == [] and b.ids() == sorted(ids + more_ids) and b.check() == []
        with MapStore(map_path, create=False, conf=conf) as fresh:
            for s in sets + more:
                got, want = b.query(s, k=3), fresh.query(s, k=3)
                assert got[0].keyframe_id == want[0].keyframe_id
                if not conf:  # exact indexes: the same answer to the last digit
                    assert [(m.keyframe_id, m.score) for m in got] == [(m.keyframe_id, m.score) for m in want]
        a.delete([more_ids[3]])
        assert more_ids[3] not in [m.keyframe_id for m in b.query(more[3], k=5)]
        assert reloads == [len(ids) + len(more_ids) - 1] and b.check() == []


def test_threads_add_and_query_concurrently(map_path, rng):
    sets = [make_set(rng) for _ in range(60)]
    errors, added = [], []
    with MapStore(map_path, model=MODEL) as store:

        def writer(chunk):
            try:
                for s in chunk:
                    added.append((store.add(s), s))
            except Exception as e:  # pragma: no cover - reported below
                errors.append(e)

        def reader():
            try:
                for s in sets[:20]:
                    store.query(s, exclude_recent=2)
                    store.info()
                store.save()
            except Exception as e:  # pragma: no cover
                errors.append(e)

        threads = [threading.Thread(target=writer, args=(sets[i::3],)) for i in range(3)]
        threads += [threading.Thread(target=reader) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert errors == []
        assert len(store) == 60 and store.check() == []
        for kid, s in added[::10]:
            assert store.query(s)[0].keyframe_id == kid


KILL_SCRIPT = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[2])
from test_mapstore import make_set
from lln_ros.mapstore import MapStore
store = MapStore(sys.argv[1], model={'descriptor_space': 'efficientnet_lite0/stage7/320', 'descriptor_dim': 320})
rng = np.random.default_rng(7)
sets = [make_set(rng) for _ in range(16)]
print('ready', flush=True)
i = 0
while True:
    kid = store.add(sets[i % 16], stamp=(i, 0))
    print(kid, flush=True)
    i += 1
"""


def test_acknowledged_keyframes_survive_kill_9(map_path, tmp_path):
    script = tmp_path / 'writer.py'
    script.write_text(KILL_SCRIPT)
    here = os.path.dirname(os.path.abspath(__file__))  # the writer imports make_set from this file
    proc = subprocess.Popen(
        [sys.executable, str(script), str(map_path), here],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        bufsize=1,
    )
    acked = []
    try:
        deadline = time.monotonic() + 120
        assert proc.stdout.readline().strip() == 'ready', proc.stderr.read()
        while len(acked) < 200 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            acked.append(int(line))
        assert proc.poll() is None, 'the writer must still be running when it is killed'
        os.kill(proc.pid, signal.SIGKILL)  # mid-stream: it is adding as fast as it can
        proc.wait(timeout=30)
        # anything acknowledged before the kill that we have not read yet counts too
        acked += [int(x) for x in proc.stdout.read().split()]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert len(acked) >= 200
    with MapStore(map_path, create=False) as store:
        ids = store.ids()
        assert set(acked) <= set(ids)
        assert len(ids) - len(acked) <= 1  # at most the one in flight, committed but not yet printed
        assert store.check() == []
        assert store.get(acked[-1]).descriptors.shape == (50, 320)


PACED_WRITER = """
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[2])
from test_mapstore import make_set
from lln_ros.mapstore import MapStore
store = MapStore(sys.argv[1], create=False)
rng = np.random.default_rng(8)
for i in range(int(sys.argv[3])):
    store.add(make_set(rng), stamp=(i, 0))
    time.sleep(0.01)
store.close()
"""


def test_reader_process_queries_beside_a_writer_process(map_path, tmp_path, rng):
    """A matcher reading a map that another process writes (issue 29's shared SQLite map): each query
    reloads what the writer committed meanwhile, and that reload must read one snapshot; before it
    did, a keyframe committed between two of its reads raised 'landmark index disagrees' or 'in-memory
    index disagrees' (found by bench/bench_milvus_writers.py; this test failed 3 of 3 runs then)."""
    count = 120
    with MapStore(map_path, model=MODEL):
        pass  # the model is recorded before either process opens the map
    script = tmp_path / 'writer.py'
    script.write_text(PACED_WRITER)
    here = os.path.dirname(os.path.abspath(__file__))
    proc = subprocess.Popen(
        [sys.executable, str(script), str(map_path), here, str(count)], stderr=subprocess.PIPE, text=True
    )
    probe = make_set(rng)
    sizes = []  # the map's size as each query saw it
    try:
        with MapStore(map_path, create=False) as reader:
            deadline = time.monotonic() + 120
            while proc.poll() is None and time.monotonic() < deadline:
                reader.query(probe, k=3)  # raises MapError on a torn reload
                sizes.append(len(reader))
            proc.wait(timeout=60)
            assert proc.returncode == 0, proc.stderr.read()
            assert len(reader) == count and reader.check() == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert len(set(sizes)) >= 10, sizes  # the writer committed between most of the queries


# ---------------------------------------------------------------- lln-map: the exit contract


def lln_map(capsys, *args):
    from lln_ros.cli.map import main

    status = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return status, out, err


def assert_bad_input(capsys, args, match):
    status, out, err = lln_map(capsys, *args)
    assert status == 2, (status, out, err)
    assert err.startswith('lln-map: error: ') and match in err and err.count('\n') == 1, err
    assert 'create=False' not in err and 'Traceback' not in err


def test_lln_map_bad_input_exits_2_with_one_line(tmp_path, rng, capsys):
    missing = tmp_path / 'missing.db'
    for command in ('info', 'check', 'compact'):
        assert_bad_input(capsys, [command, missing], f'{missing}: no such map file')
    assert_bad_input(capsys, ['export', missing, tmp_path / 'dest.db'], f'{missing}: no such map file')
    assert not (tmp_path / 'dest.db').exists()  # nothing created for a copy that cannot start
    assert_bad_input(capsys, ['import', tmp_path / 'dest.db', missing], f'{missing}: no such map file')
    (tmp_path / 'folder').mkdir()
    assert_bad_input(capsys, ['info', tmp_path / 'folder'], 'is a directory, not a map file')
    (tmp_path / 'notes.db').write_text('not a map')
    assert_bad_input(capsys, ['info', tmp_path / 'notes.db'], 'is not an lln_ros map')
    assert_bad_input(capsys, ['info', 'milvus://:bad'], 'Milvus map URI must look like')
    lite = tmp_path / 'nolite.db'
    assert_bad_input(capsys, ['info', f'milvus-lite://{lite}'], f'no such Milvus Lite map ({lite} does not exist)')
    # a copy the destination refuses: another model
    with MapStore(tmp_path / 'a.db', model=MODEL) as store:
        store.add(make_set(rng), (1, 0))
    with MapStore(tmp_path / 'b.db', model=OTHER_MODEL) as store:
        store.add(make_set(rng, dim=OTHER_MODEL['descriptor_dim'], space=OTHER_MODEL['descriptor_space']), (1, 0))
    status, _, err = lln_map(capsys, 'export', tmp_path / 'a.db', tmp_path / 'b.db')
    assert status == 2 and err.startswith('lln-map: error: ') and err.count('\n') == 1, err


def test_lln_map_check_exits_1_with_its_findings(tmp_path, capsys):
    (tmp_path / 'notes.db').write_text('not a map')
    status, out, _ = lln_map(capsys, 'check', tmp_path / 'notes.db')
    assert status == 1 and '1 problem(s)' in out and 'is not an lln_ros map' in out


def test_lln_map_info_prints_iso_times(tmp_path, rng, capsys):
    path = tmp_path / 'm.db'
    before = time.time()
    with MapStore(path, model=MODEL) as store:
        store.add(make_set(rng), (1, 0))
    status, out, _ = lln_map(capsys, 'info', path)
    assert status == 0
    created = next(line for line in out.splitlines() if line.startswith('created '))
    stamp = created.split()[1]
    assert re.fullmatch(r'\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ', stamp), created
    from datetime import datetime

    assert abs(datetime.strptime(stamp, '%Y-%m-%dT%H:%M:%S%z').timestamp() - before) < 60
    assert 'created_unix' not in out
    status, out, _ = lln_map(capsys, 'info', '--json', path)
    info = json.loads(out)
    assert info['created'] == stamp and abs(info['created_unix'] - before) < 60
