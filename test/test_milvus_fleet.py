"""Many writers, one Milvus map (issue 29, part 3), on the real Milvus 2.3.5 server: writer processes
(multiprocessing, spawn) store keyframes and start sessions into one map at once. Every keyframe is
stored exactly once under an id no other keyframe has, session numbers are distinct (also for two
writers given one robot id), every writer sees the others' keyframes, and a writer killed with
SIGKILL mid-insert loses at most what it was not told was stored, and never makes a survivor reuse
an id. A map of schema 4 (one writer's next_id) migrates and takes concurrent writers.

Small id blocks (ID_BLOCK = 8, in every process of a test: the map's writers must agree on it) make
the writers claim many blocks, so block boundaries and claim contention are exercised often.
Runs only inside the loopback-only namespace (test_milvus_server.py::test_real_server_suite).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import time
from collections import Counter

import numpy as np
import pytest
from test_mapstore import MODEL, make_set

from lln_ros.mapstore import MapStore

server = pytest.mark.milvus_server
SMALL_BLOCK = 8
WAIT_S = 180  # bounds a wait for an event, never a measured time


def small_blocks() -> None:
    from lln_ros.mapstore import milvus_claims

    milvus_claims.ID_BLOCK = SMALL_BLOCK


def frames_rows(uri: str) -> list[int]:
    """Every row id of the frames collection straight from the server (Strong), duplicates kept:
    Milvus stores two rows with one primary key, and count(*) counts both."""
    from pymilvus import MilvusClient

    from lln_ros.mapstore.milvus import parse_uri

    where = parse_uri(uri)
    c = MilvusClient(uri=where['uri'], timeout=60, db_name=where['db_name'])
    try:
        name = f'{where["map"]}_frames'
        count = int(c.query(name, filter='', output_fields=['count(*)'], consistency_level='Strong')[0]['count(*)'])
        ids = c.query(name, filter='id >= 0', output_fields=['id'], limit=16384, consistency_level='Strong')
        ids = [int(r['id']) for r in ids]
        return count, ids
    finally:
        c.close()


def writer(uri, index, robot, n, sessions, start, out):
    """One writer process: `sessions` sessions of `robot`, then n keyframes (stamp = (index, i)) in
    the last one, one by one and in batches of 3, each with its origin; then waits until it sees
    every writer's keyframes. Reports through `out`."""
    try:
        _write(uri, index, robot, n, sessions, start, out)
    except BaseException as e:  # the parent fails with the reason, at once
        out.put(('error', index, f'{type(e).__name__}: {e}'))
        raise


def _write(uri, index, robot, n, sessions, start, out):
    small_blocks()
    rng = np.random.default_rng(100 + index)
    with MapStore.open(uri, model=MODEL, conf={'refresh_s': 0.2}) as store:
        start.wait(WAIT_S)  # every writer opened: they all write at once
        made = [store.start_session(robot) for _ in range(sessions)]
        session, acked, seq = made[-1], [], 0
        while seq < n:
            batch = 1 if seq % 4 else min(3, n - seq)
            ids = store.add_many([make_set(rng) for _ in range(batch)], [(index, seq + j) for j in range(batch)])
            for kid in ids:
                seq += 1
                store.set_origin(kid, session.id, seq)
            acked += ids
        out.put(('done', index, acked, [(s.id, s.robot, s.label) for s in made]))
        total, deadline = start.parties * n, time.monotonic() + WAIT_S  # every writer stores n
        while len(store) < total and time.monotonic() < deadline:
            time.sleep(0.2)
        out.put(('seen', index, store.ids(), total))


def run_writers(uri, robots, n, sessions=3):
    ctx = mp.get_context('spawn')
    start, out = ctx.Barrier(len(robots)), ctx.Queue()
    procs = [
        ctx.Process(target=writer, args=(uri, i, robot, n, sessions, start, out)) for i, robot in enumerate(robots)
    ]
    for p in procs:
        p.start()
    got = {}
    try:
        for _ in range(2 * len(procs)):
            kind, index, *rest = out.get(timeout=WAIT_S * 2)
            assert kind != 'error', f'writer {index}: {rest[0]}'
            got[(kind, index)] = rest
        for p in procs:
            p.join(WAIT_S)
            assert p.exitcode == 0, f'writer exited {p.exitcode}'
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
    return got


@server
def test_concurrent_writers_store_every_keyframe_once(milvus_map, monkeypatch):
    """Three writer processes (two of them given the same robot id) start sessions and store 40
    keyframes each into one map at once: 120 rows, 120 distinct ids, each (writer, stamp) once, each
    (session, seq) once, 9 distinct session numbers, and every writer sees all 120 keyframes."""
    monkeypatch.setattr('lln_ros.mapstore.milvus_claims.ID_BLOCK', SMALL_BLOCK)
    with MapStore.open(milvus_map, model=MODEL):
        pass  # the map exists before the writers race to open it
    robots, n = ['twin', 'twin', 'solo'], 40
    got = run_writers(milvus_map, robots, n)
    acked = {i: got[('done', i)][0] for i in range(len(robots))}
    every = [k for ids in acked.values() for k in ids]
    assert len(every) == len(set(every)) == n * len(robots), Counter(every).most_common(3)
    count, rows = frames_rows(milvus_map)
    assert count == len(rows) == n * len(robots), (count, len(rows))
    assert sorted(rows) == sorted(every)
    for i in range(len(robots)):
        seen, total = got[('seen', i)]
        assert seen == sorted(every), f'writer {i} sees {len(seen)} of {total}'
    made = {i: got[('done', i)][1] for i in range(len(robots))}
    numbers = [sid for m in made.values() for sid, _, _ in m]
    assert len(numbers) == len(set(numbers)) == 3 * len(robots), numbers
    labels = [label for m in made.values() for _, _, label in m]
    assert len(set(labels)) == len(labels)
    with MapStore.open(milvus_map, create=False) as store:
        stored = {s.id: s for s in store.sessions()}
        assert sorted(stored) == sorted(numbers)
        assert [s.robot for s in stored.values()].count('twin') == 6
        origins = store.origins()
        assert sorted(origins) == sorted(every)
        keys = Counter((o.session_id, o.seq) for o in origins.values())
        assert max(keys.values()) == 1, keys.most_common(3)
        for i, ids in acked.items():
            last_session = made[i][-1][0]
            assert {origins[k].session_id for k in ids} == {last_session}
            assert sorted(origins[k].seq for k in ids) == list(range(1, n + 1))
            stamps = Counter(store.get(k).meta['stamp'] for k in ids)
            assert set(stamps) == {(i, s) for s in range(n)} and max(stamps.values()) == 1
        assert store.check() == []
        # the two 'twin' writers are two sessions of one robot: distinct numbers, labels and seqs
        twins = [s for s in stored.values() if s.robot == 'twin']
        assert len({s.label for s in twins}) == len(twins)


def victim(uri, out):
    """A writer that stores keyframes in batches of 6 (each insert split into messages of one row)
    until it is killed, reporting each acknowledged batch."""
    small_blocks()
    rng = np.random.default_rng(7)
    with MapStore.open(uri, model=MODEL, conf={'insert_bytes': 1}) as store:
        out.put(('ready', os.getpid()))
        i = 0
        while True:
            ids = store.add_many([make_set(rng) for _ in range(6)], [(9, i + j) for j in range(6)])
            i += 6
            out.put(('acked', ids))


def survivor(uri, index, n, out, killed):
    small_blocks()
    rng = np.random.default_rng(200 + index)
    with MapStore.open(uri, model=MODEL, conf={'refresh_s': 0.2}) as store:
        out.put(('ready', os.getpid()))
        acked = []
        for i in range(n):
            acked.append(store.add(make_set(rng), (index, i)))
            if i == n // 2:  # the other half after the kill
                out.put(('half', index))
                killed.wait(WAIT_S)
        out.put(('survivor', index, acked))


@server
def test_writer_killed_mid_insert_never_makes_a_duplicate(milvus_map, monkeypatch):
    """A writer is SIGKILLed while it inserts (batches of 6 rows sent as 6 messages) next to two
    writers that keep going: every keyframe it was told was stored is in the map, nothing is stored
    twice, the survivors' ids are all distinct from each other's and from every row the killed
    writer left (acknowledged or not), and a writer opened afterwards takes ids no row has."""
    monkeypatch.setattr('lln_ros.mapstore.milvus_claims.ID_BLOCK', SMALL_BLOCK)
    with MapStore.open(milvus_map, model=MODEL):
        pass
    ctx = mp.get_context('spawn')
    # the killed writer has a queue of its own: killed while it sends, it may leave that one unusable
    vq, sq, killed = ctx.Queue(), ctx.Queue(), ctx.Event()
    kill_me = ctx.Process(target=victim, args=(milvus_map, vq))
    others = [ctx.Process(target=survivor, args=(milvus_map, i, 40, sq, killed)) for i in range(2)]
    victim_acked, survivors, halves = [], {}, set()

    def take(q, deadline):
        assert time.monotonic() < deadline, f'no kill after {WAIT_S} s: {len(victim_acked)} acked, {halves} halfway'
        try:
            return q.get(timeout=0.2)
        except queue.Empty:
            return None

    try:
        for p in [kill_me, *others]:
            p.start()
        deadline = time.monotonic() + WAIT_S
        # kill it once it has 4 acknowledged batches and both survivors are halfway (and waiting)
        while len(victim_acked) < 24 or len(halves) < 2:
            for msg in (take(vq, deadline), take(sq, deadline)):
                if msg and msg[0] == 'acked':
                    victim_acked += msg[1]
                elif msg and msg[0] == 'half':
                    halves.add(msg[1])
            assert kill_me.is_alive() and all(p.is_alive() for p in others)
        os.kill(kill_me.pid, signal.SIGKILL)
        kill_me.join(WAIT_S)
        assert kill_me.exitcode == -signal.SIGKILL
        killed.set()
        while len(survivors) < 2:
            msg = sq.get(timeout=WAIT_S)
            if msg[0] == 'survivor':
                survivors[msg[1]] = msg[2]
        for p in others:
            p.join(WAIT_S)
            assert p.exitcode == 0
    finally:
        for p in [kill_me, *others]:
            if p.is_alive():
                p.kill()
    count, rows = frames_rows(milvus_map)
    assert count == len(rows) == len(set(rows)), (count, len(rows), Counter(rows).most_common(3))
    assert set(victim_acked) <= set(rows), sorted(set(victim_acked) - set(rows))
    mine = [k for ids in survivors.values() for k in ids]
    assert len(mine) == len(set(mine)) == 80 and set(mine) <= set(rows)
    left = set(rows) - set(mine)  # everything the killed writer stored, acknowledged or not
    assert left >= set(victim_acked) and not left & set(mine)
    with MapStore.open(milvus_map, create=False) as store:
        assert store.check() == []
        stamps = Counter(store.get(k).meta['stamp'] for k in rows)
        assert max(stamps.values()) == 1, stamps.most_common(3)
        new = store.add_many([make_set(np.random.default_rng(9)) for _ in range(SMALL_BLOCK + 2)], [(8, 0)] * 10)
        assert not set(new) & set(rows) and len(set(new)) == len(new)
    print(f'killed writer: {len(victim_acked)} acknowledged, {len(left) - len(victim_acked)} stored unacknowledged')


@server
def test_schema4_map_migrates_and_takes_two_writers(milvus_map):
    """A map as schema 4 left it (no claims; meta next_id = what its one writer had reserved, 2000
    here) opens as schema 5; two stores writing into it in turn take distinct ids, none below the old
    next_id, and distinct session numbers above the old sessions'."""
    from pymilvus import MilvusClient

    from lln_ros.mapstore.milvus import parse_uri
    from lln_ros.mapstore.milvus_collections import SCHEMA_VERSION

    rng = np.random.default_rng(4)
    with MapStore.open(milvus_map, model=MODEL) as store:
        old = store.add_many([make_set(rng) for _ in range(5)], [(1, i) for i in range(5)])
        old_session = store.start_session('old')
    where = parse_uri(milvus_map)
    c = MilvusClient(uri=where['uri'], timeout=60, db_name=where['db_name'])
    try:  # back to schema 4: no claims collection, the one writer's next_id
        c.drop_collection(f'{where["map"]}_claims')
        c.upsert(
            f'{where["map"]}_meta',
            [{'key': k, 'value': v, 'unused': [0.0, 0.0]} for k, v in (('schema_version', '4'), ('next_id', '2000'))],
        )
    finally:
        c.close()
    a = MapStore.open(milvus_map, create=False)
    b = MapStore.open(milvus_map, create=False)
    try:
        assert a.info()['schema_version'] == SCHEMA_VERSION == 5
        sa, sb = a.start_session('a'), b.start_session('b')
        assert len({sa.id, sb.id, old_session.id}) == 3 and min(sa.id, sb.id) > old_session.id
        ids = []
        for i in range(6):  # in turn: each store reserved its block before the other wrote
            ids.append(a.add(make_set(rng), (2, i)))
            ids.append(b.add(make_set(rng), (3, i)))
        assert len(set(ids)) == len(ids) and min(ids) >= 2000, ids
    finally:
        a.close()
        b.close()
    count, rows = frames_rows(milvus_map)
    assert count == len(rows) == 17 and sorted(rows) == sorted(old + ids)


@server
def test_recent_exclusion_names_this_sessions_keyframes_when_blocks_interleave(milvus_map):
    """Two mapping Localizers write one map through two stores (two writers: A's id block below B's).
    exclude_recent keeps A's own newest keyframes out of A's answers although B's ids are higher
    (an exclusion of the highest ids would let A answer its own keyframe of a moment ago), and B's
    newest keyframes, however recent, are A's answers."""
    from test_localizer import ask

    from lln_ros.core.localizer import Localizer
    from lln_ros.mapstore import open_for_matcher as open_map
    from lln_ros.mapstore.sessions import SessionLog

    rng = np.random.default_rng(31)
    sets = [make_set(rng) for _ in range(6)]
    store_a, _ = open_map(milvus_map, 'mapping', MODEL['descriptor_space'], conf={'refresh_s': 0.0})
    store_b, _ = open_map(milvus_map, 'mapping', MODEL['descriptor_space'], conf={'refresh_s': 0.0})
    with store_a, store_b:
        a = Localizer(store_a, {'mode': 'mapping', 'exclude_recent': 3, 'k': 3, 'min_score': 0.0})
        a.session = SessionLog(store_a, 'robot_a')
        b = Localizer(store_b, {'mode': 'mapping', 'exclude_recent': 3, 'k': 3, 'min_score': 0.0})
        b.session = SessionLog(store_b, 'robot_b')
        for i, s in enumerate(sets[:3]):
            ask(a, s, i)  # A claims the first block: ids 1, 2, 3
        for i, s in enumerate(sets[3:]):
            ask(b, s, 10 + i)  # B the next one: higher ids
        a_ids, b_ids = (
            sorted(k for k, o in store_b.origins().items() if o.session_id == x.session.session.id) for x in (a, b)
        )
        assert len(a_ids) == len(b_ids) == 3 and max(a_ids) < min(b_ids), (a_ids, b_ids)
        deadline = time.monotonic() + WAIT_S  # B's keyframes reach A (another client's writes)
        while not set(b_ids) <= set(store_a.ids()) and time.monotonic() < deadline:
            time.sleep(0.1)
        mine = set(a_ids)
        answer = ask(a, make_set(rng, base=sets[2], noise=0.1), 20)  # a view of A's newest place
        got = {r['keyframe_id'] for r in answer.rows}
        assert got and got <= set(b_ids), (mine, answer.rows)
        answer = ask(a, make_set(rng, base=sets[5], noise=0.1), 21)  # B's newest: a valid answer
        assert answer.rows[0]['keyframe_id'] == b_ids[-1], answer.rows
        assert answer.rows[0]['session_id'] == b.session.session.id


@server
def test_a_writer_opening_while_another_creates_the_map_waits_for_it(milvus_map, monkeypatch):
    """Fleet matchers started together on a new map: one finds the meta collection another writer
    has just created but not yet filled. It waits for the creator's rows instead of refusing the map
    as 'not an lln_ros map' (what stopped robot B's matcher in bench_fleet on the real server)."""
    import threading

    from lln_ros.mapstore.milvus import MilvusMapStore

    created, opened = threading.Event(), []
    put_meta = MilvusMapStore._put_meta

    def slow_first_meta(self, values):  # the creator stalls between its collection and its rows
        if 'format' in values and not created.is_set():
            created.set()
            time.sleep(2.0)
        return put_meta(self, values)

    monkeypatch.setattr(MilvusMapStore, '_put_meta', slow_first_meta)
    creator = threading.Thread(target=lambda: opened.append(MapStore.open(milvus_map, model=MODEL)))
    creator.start()
    assert created.wait(WAIT_S)
    try:
        with MapStore.open(milvus_map, model=MODEL, conf={'refresh_s': 0.0}) as second:
            creator.join(WAIT_S)
            assert len(opened) == 1
            first = opened[0]
            kid = first.add(make_set(np.random.default_rng(5)), stamp=(1, 0))
            deadline = time.monotonic() + WAIT_S
            while kid not in second.ids() and time.monotonic() < deadline:
                time.sleep(0.1)
            assert second.ids() == [kid] and second.info()['descriptor_space'] == MODEL['descriptor_space']
    finally:
        creator.join(WAIT_S)
        for store in opened:
            store.close()


@server
def test_a_writer_whose_database_another_creates_meanwhile_opens(milvus_map, monkeypatch):
    """The database of the map URI appears between a writer's look and its create (another fleet
    matcher made it): the server's 'database already exist' is not a failure to open."""
    from pymilvus import MilvusClient

    with MapStore.open(milvus_map, model=MODEL):
        pass  # the database exists now
    listed = MilvusClient.list_databases
    looks = []

    def stale_first_look(self, *args, **kwargs):  # the first look predates the other's create
        names = listed(self, *args, **kwargs)
        looks.append(names)
        return [n for n in names if n != 'lln_test'] if len(looks) == 1 else names

    monkeypatch.setattr(MilvusClient, 'list_databases', stale_first_look)
    with MapStore.open(milvus_map, model=MODEL) as store:
        assert len(store) == 0 and len(looks) == 2 and 'lln_test' in looks[0]
