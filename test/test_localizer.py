"""The matcher's decisions without rclpy (lln_ros.core.localizer.Localizer) on real SQLite maps, the
input limits (lln_ros.core.limits) and problem logging by kind (lln_ros.core.counters)."""

import json
import os
import sqlite3
import subprocess
import sys

import numpy as np
import pytest
from test_mapstore import MODEL, SPACE, make_set

from lln_ros.core.counters import Counters, problem_kind
from lln_ros.core.limits import check_landmark_set, default_conf, validate_model
from lln_ros.core.localizer import Localizer
from lln_ros.errors import MapError, ModelError
from lln_ros.mapstore import MapStore, writable_problem
from lln_ros.mapstore import open_for_matcher as open_map

T0 = 1_700_000_000 * 10**9


def stamp(i: int) -> int:
    return T0 + i * 50_000_000


class Log:
    """A logger that keeps its lines (what the node's rclpy logger would print)."""

    def __init__(self):
        self.lines = []

    def warning(self, text):
        self.lines.append(('WARN', text))

    def error(self, text):
        self.lines.append(('ERROR', text))

    def info(self, text):
        self.lines.append(('INFO', text))


def invariants(counts: dict) -> None:
    got = {
        k: counts.get(k, 0)
        for k in (
            'queries_received',
            'queries_answered',
            'queries_stale',
            'bad_query',
            'queries_failed',
            'keyframes_received',
            'keyframes_stored',
            'bad_keyframe',
            'keyframes_failed',
            'queries_stored',
        )
    }
    assert (
        got['queries_received']
        == got['queries_answered'] + got['queries_stale'] + got['bad_query'] + got['queries_failed']
    ), got
    assert (
        got['keyframes_received'] + got['queries_stored']
        == got['keyframes_stored'] + got['bad_keyframe'] + got['keyframes_failed']
    ), got


def ask(loc: Localizer, lset, i: int):
    """What the node does with one decoded query: received, answered (or not)."""
    if not loc.query_fresh(stamp(i), stamp(i)):
        return None
    answer = loc.query(lset, stamp(i))
    if answer is not None:
        loc.count('queries_answered')
    return answer


def keyframe(loc: Localizer, lset, i: int):
    loc.count('keyframes_received')
    return loc.keyframe(lset, stamp(i))


@pytest.fixture
def rng():
    return np.random.default_rng(3)


@pytest.fixture
def map_path(tmp_path):
    return tmp_path / 'map.db'


def test_localizer_is_ros_free():
    """The Localizer, limits and counters import without rclpy (nodes decode; this decides)."""
    code = (
        'import sys, lln_ros.core.localizer, lln_ros.core.limits, lln_ros.core.counters; '
        'bad = [m for m in sys.modules if m.split(".")[0] in ("rclpy", "sensor_msgs", "std_msgs")]; '
        'print(bad); sys.exit(1 if bad else 0)'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_localization_and_mapping(map_path, rng):
    sets = [make_set(rng) for _ in range(6)]
    store, quarantined = open_map(map_path, 'localization', SPACE)
    with store:
        assert quarantined == {}
        loc = Localizer(store, {'k': 3})
        for i, s in enumerate(sets):
            assert keyframe(loc, s, i) == i + 1
        answer = ask(loc, sets[4], 100)
        assert answer.rows[0]['keyframe_id'] == 5 and answer.best.keyframe_id == 5
        assert (answer.rows[0]['stamp_sec'], answer.rows[0]['stamp_nanosec']) == divmod(stamp(4), 10**9)
        assert len(answer.rows) == 3 and answer.extra_fields == ('session_id',) and len(store) == 6
        invariants(loc.counters.snapshot())
    store, _ = open_map(map_path, 'mapping', SPACE)
    with store:
        loc = Localizer(store, {'mode': 'mapping', 'exclude_recent': 2, 'k': 3})
        answer = ask(loc, sets[2], 200)  # answered from the map, then stored
        assert answer.rows[0]['keyframe_id'] == 3 and len(store) == 7
        again = ask(loc, sets[2], 201)  # its own copy (keyframe 7) is too recent to answer
        assert 7 not in [r['keyframe_id'] for r in again.rows]
        invariants(loc.counters.snapshot())


def test_recent_exclusion_applies_to_this_session_only(map_path, rng):
    """Issue 29: exclude_recent keeps this session's own newest keyframes out of the answers, never
    another robot's or an earlier run's, however recent; every stored keyframe gets (session, seq)."""
    from lln_ros.mapstore.sessions import SessionLog

    sets = [make_set(rng) for _ in range(4)]
    store, _ = open_map(map_path, 'mapping', SPACE)
    with store:
        every = {'keyframe_novelty_max_score': 0.0}  # every query stored: robot_a's own copy too
        other = Localizer(store, {'mode': 'mapping', 'exclude_recent': 10, 'registration': every})
        other.session = SessionLog(store, 'robot_b')
        for i, s in enumerate(sets[:3]):
            ask(other, s, i)  # robot_b maps three places
        mine = Localizer(store, {'mode': 'mapping', 'exclude_recent': 10, 'k': 3, 'registration': every})
        mine.session = SessionLog(store, 'robot_a')
        answer = ask(mine, sets[1], 100)  # robot_b's keyframe 2 is among the newest 10, yet an answer
        assert answer.rows[0]['keyframe_id'] == 2 and answer.rows[0]['session_id'] == other.session.session.id
        again = ask(mine, sets[1], 101)  # robot_a's own copy (keyframe 4) is too recent: still robot_b's
        assert 4 not in [r['keyframe_id'] for r in again.rows] and again.rows[0]['keyframe_id'] == 2
        origins = store.origins()
        assert [(origins[k].session_id, origins[k].seq) for k in store.ids()] == [
            (other.session.session.id, 1),
            (other.session.session.id, 2),
            (other.session.session.id, 3),
            (mine.session.session.id, 1),
            (mine.session.session.id, 2),
        ]
        invariants(mine.counters.snapshot())


def test_sequence_search_follows_each_session_in_an_interleaved_map(map_path, rng):
    """Issue 29: two robots mapping at once interleave their keyframe ids; the sequence search
    orders the map by (session, seq), so each robot's keyframes are one route, and a third robot
    driving robot_a's route gets robot_a's keyframes in step, answered from the sequence."""
    from lln_ros.mapstore.sessions import SessionLog

    route_a, route_b = [make_set(rng) for _ in range(8)], [make_set(rng) for _ in range(8)]
    store, _ = open_map(map_path, 'mapping', SPACE)
    with store:
        every = {'keyframe_novelty_max_score': 0.0}
        conf = {'mode': 'mapping', 'exclude_recent': 2, 'sequence_length': 4, 'registration': every}
        a, b = Localizer(store, conf), Localizer(store, conf)
        a.session, b.session = SessionLog(store, 'robot_a'), SessionLog(store, 'robot_b')
        for i in range(8):  # ids 1, 3, 5 .. are robot_a's; 2, 4, 6 .. robot_b's
            ask(a, route_a[i], 2 * i)
            ask(b, route_b[i], 2 * i + 1)
        assert a.session.ids == list(range(1, 16, 2))
        third = Localizer(store, {'sequence_length': 4, 'k': 3})
        for i in range(8):
            answer = ask(third, route_a[i], 100 + i)
            assert answer.rows[0]['keyframe_id'] == a.session.ids[i], (i, answer.rows)
            assert answer.rows[0]['sequence_score'] > 0
        sessions = sorted([a.session.session.id, b.session.session.id])
        first = a.session.ids if sessions[0] == a.session.session.id else b.session.ids
        assert third.sequence.ids[:8].tolist() == first  # a whole session, then the other
        invariants(third.counters.snapshot())


def test_similarity_chooses_the_reranker_s(map_path, rng):
    """similarity: the rerank's S is similarity.match_pair's on the sets it names (raw, fused, ...), the
    same ranking path otherwise; an unknown name is refused."""
    from lln_ros.core.similarity import CENTERS, match_pair

    sets = [make_set(rng) for _ in range(4)]
    view = make_set(rng, base=sets[2], noise=0.5)
    with MapStore(map_path, model=MODEL) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(4)])
        got = {}
        for name in ('raw', 'fuse'):
            answer = ask(Localizer(store, {'similarity': name, 'k': 4}), view, 0)
            got[name] = {r['keyframe_id']: r['score'] for r in answer.rows}
            for kid in ids:
                expect = float(match_pair(view, store.get(kid), center=CENTERS[name]).scores[0])  # as stored
                assert np.isclose(got[name][kid], expect, rtol=1e-5), (name, kid)
        assert got['raw'] != got['fuse']
        with pytest.raises(ValueError, match='similarity must be one of'):
            Localizer(store, {'similarity': 'cosine'})


def test_sequence_carry_scores_where_the_route_goes_next(map_path, rng):
    """sequence_carry: the previous query's best sequence ends and the keyframes after them are reranked
    beside a first stage that keeps one candidate, so the answer rows carry their own S (a keyframe that
    is neither is 0); carry 0 scores the first stage's candidate alone."""
    route = [make_set(rng) for _ in range(12)]
    with MapStore(map_path, model=MODEL) as store:
        ids = store.add_many(route, [(i, 0) for i in range(12)])
        one = {'sequence_length': 4, 'k': 5, 'prefilter_k': 1, 'sequence_prefilter_k': 1, 'sequence_acquire_k': 0}
        plain, carried = Localizer(store, {**one, 'sequence_carry': 0}), Localizer(store, {**one, 'sequence_carry': 2})
        for i in range(2, 8):
            view = make_set(rng, base=route[i], noise=0.3)
            p, c = ask(plain, view, i), ask(carried, view, i)
            assert c.rows[0]['keyframe_id'] == ids[i], c.rows
            assert sum(r['score'] != 0 for r in p.rows) == 1, p.rows  # the first stage's one candidate
            if i > 2:  # from the second query on: the last ends and their next steps are scored too
                scored = {r['keyframe_id'] for r in c.rows if r['score'] != 0}
                assert len(scored) > 1 and ids[i + 1] in scored, c.rows
        invariants(carried.counters.snapshot())
        with pytest.raises(ValueError, match='sequence_carry must be 0'):
            Localizer(store, {'sequence_carry': -1})


def test_sequence_acquire_k_reranks_more_while_the_window_fills(map_path, rng):
    """sequence_acquire_k: the first sequence_length - 1 queries, and those after a reset (a gap), rerank
    that many candidates, so their answer rows carry more S; a full window reranks sequence_prefilter_k."""
    route = [make_set(rng) for _ in range(12)]
    with MapStore(map_path, model=MODEL) as store:
        ids = store.add_many(route, [(i, 0) for i in range(12)])
        one = {'sequence_length': 4, 'k': 5, 'prefilter_k': 1, 'sequence_prefilter_k': 1, 'sequence_carry': 0}
        loc = Localizer(store, {**one, 'sequence_acquire_k': 6})
        scored = []
        for i, at in zip(range(1, 11), [1, 2, 3, 4, 5, 6, 40, 41, 42, 43]):  # 6 -> 40: a 1.7 s gap (max 1 s)
            answer = ask(loc, make_set(rng, base=route[i], noise=0.3), at)
            scored.append(sum(r['score'] != 0 for r in answer.rows))
            if i == 1:  # one frame: the line is its best S, found among the 6
                assert answer.rows[0]['keyframe_id'] == ids[1], answer.rows
        # while filling, 6 are reranked and several answer rows carry S; a full window reranks 1
        assert [n > 1 for n in scored] == [True] * 3 + [False] * 3 + [True] * 3 + [False], scored
        assert max(scored[3:6]) == 1 and scored[9] == 1, scored
        assert loc.counters.snapshot()['sequence_reset_gap'] == 1
        with pytest.raises(ValueError, match='sequence_acquire_k must be 0'):
            Localizer(store, {'sequence_acquire_k': -1})


@pytest.mark.parametrize(
    'text, problem',
    [
        ('{"descriptor_space": "a/b/192", "descriptor_dim": 1e999}', 'must be an integer'),  # OverflowError before
        ('{"descriptor_space": "a/b/192", "descriptor_dim": -5}', 'must be in'),
        ('{"descriptor_space": "a/b/192", "descriptor_dim": 10000000000000000000000}', 'must be in'),
        ('{"descriptor_space": "a/b/192", "descriptor_dim": "192"}', 'must be an integer'),
        ('{"descriptor_space": "a/b/192", "descriptor_dim": 64}', 'ends in D=192'),
        ('{"descriptor_space": "a/b/192", "descriptor_dim": 192, "input_height": 100}', 'multiple of 32'),
        ('{"descriptor_dim": 192}', 'descriptor_space'),
        ('[1, 2]', 'JSON object'),
        ('not json', 'cannot use model_info'),
        ('[' * 100000 + ']' * 100000, 'cannot use model_info'),
    ],
)
def test_bad_model_info_changes_nothing(map_path, text, problem):
    """A model_info that fails validation is counted and logged, and neither the map (no model record
    written) nor the refusal state changes; a valid one afterwards is recorded."""
    log = Log()
    store, _ = open_map(map_path)
    with store:
        loc = Localizer(store, log=log)
        loc.model_info(text)
        assert loc.counters.snapshot() == {'model_info_received': 1, 'bad_model_info': 1}
        assert problem in log.lines[0][1], log.lines
        assert store.model is None and loc.refusing == ''
        loc.model_info(json.dumps(MODEL))
        assert store.model == MODEL
    with MapStore(map_path, create=False) as again:
        assert again.model == MODEL and again.check() == []


def test_model_conflict_refuses_until_models_agree(map_path, rng):
    log = Log()
    store, _ = open_map(map_path, descriptor_space=SPACE)
    with store:
        loc = Localizer(store, log=log)
        loc.model_info(json.dumps({**MODEL, 'descriptor_space': 'x/y/320'}))
        assert loc.refusing and [kind for kind, _ in log.lines] == ['ERROR']
        assert loc.landmark_decoding('bad_query') is None and loc.counters.snapshot()['bad_query'] == 1
        loc.model_info(json.dumps(MODEL))
        assert loc.refusing == '' and loc.landmark_decoding('bad_query')['expected_dim'] == 320


def hostile_sets(rng) -> dict:
    """Landmark sets whose declared sizes a sender controls, by the problem each one must be refused for."""
    good = make_set(rng)

    def variant(**fields):
        s = make_set(rng)
        for k, v in fields.items():
            setattr(s, k, v)
        return s

    many = make_set(rng, n=5000, rows=50, cols=128)
    many.cell_size, many.image_size = np.array([3, 5.76], np.float32), np.array([384, 288], np.float32)
    return {
        'tiny cell': variant(cell_size=np.array([1e-3, 1e-3], np.float32), grid=(288000, 384000)),
        'huge image': variant(image_size=np.array([1e9, 1e9], np.float32), grid=(9, 12)),
        '32768 px wide': variant(
            image_size=np.array([32768, 288], np.float32), cell_size=np.array([32, 32], np.float32), grid=(9, 1024)
        ),
        'rows vs input_height': variant(image_size=np.array([384, 576], np.float32), grid=(18, 12)),
        'not whole cells': variant(cell_size=np.array([33.3, 32], np.float32)),
        '5000 landmarks': many,
        'no landmarks': variant(
            descriptors=np.zeros((0, 320), np.float32),
            cells=np.zeros((0, 2), np.int32),
            centers=np.zeros((0, 2), np.float32),
            scores=np.zeros(0, np.float32),
        ),
        'good': good,
    }


def test_limits_refuse_declared_sizes_before_any_work(map_path, rng):
    """Every hostile class is a counted refusal (bad_query / bad_keyframe), none is stored, and the
    next good message is answered; the counter sums hold throughout."""
    sets = hostile_sets(rng)
    log = Log()
    store, _ = open_map(map_path, descriptor_space=SPACE)
    with store:
        loc = Localizer(store, log=log)
        loc.model_info(json.dumps(MODEL))  # the extractor's: input_height 288 makes a grid of 9 rows
        assert keyframe(loc, sets['good'], 0) == 1
        for i, (name, s) in enumerate(sets.items()):
            if name == 'good':
                continue
            assert keyframe(loc, s, 10 + i) is None, name
            assert ask(loc, s, 10 + i) is None, name
        counts = loc.counters.snapshot()
        assert counts['bad_keyframe'] == counts['bad_query'] == len(sets) - 1, counts
        assert len(store) == 1
        answer = ask(loc, sets['good'], 99)
        assert answer.rows[0]['keyframe_id'] == 1
        invariants(loc.counters.snapshot())
    texts = ' '.join(text for _, text in log.lines)
    for needle in ('max_grid_side', 'max_image_pixels', 'max_landmarks', 'input_height 288', 'whole number'):
        assert needle in texts, (needle, texts)


def test_check_landmark_set_accepts_the_extractors_output(extractor, photo):
    """What the real extractor publishes passes every limit at the model's input height."""
    for image in (photo, photo[:100, :600], np.ascontiguousarray(photo[::4, ::4])):
        lset = extractor(image)
        check_landmark_set(lset, extractor.model_info, default_conf)


def test_validate_model_accepts_model_info(extractor):
    assert validate_model(extractor.model_info) == extractor.model_info
    with pytest.raises(ModelError, match='max_descriptor_dim'.replace('max_descriptor_dim', 'must be in')):
        validate_model({**extractor.model_info, 'descriptor_dim': 5000, 'descriptor_space': 'x/y/5000'})


def damage(map_path, keyframe_id: int) -> None:
    con = sqlite3.connect(map_path)
    con.execute("UPDATE landmarks SET descriptors = x'00' WHERE keyframe_id = ?", (keyframe_id,))
    con.commit()
    con.close()


def test_damaged_keyframe_quarantined_not_blamed_on_the_query(map_path, rng):
    """A landmark blob of 1 byte: found at open, named, quarantined (never answered, left in the
    file); a query of that very place is answered from the others, not counted as bad_query; the
    store's check() names the same keyframe."""
    sets = [make_set(rng) for _ in range(5)]
    with MapStore(map_path, model=MODEL) as store:
        for i, s in enumerate(sets):
            store.add(s, divmod(stamp(i), 10**9))
    damage(map_path, 3)
    store, quarantined = open_map(map_path, 'localization', SPACE)
    with store:
        assert list(quarantined) == [3] and 'blob sizes' in quarantined[3]
        assert store.ids() == [1, 2, 4, 5] and store.info()['quarantined'] == [3]
        problems = store.check()
        assert len(problems) == 1 and problems[0].startswith('keyframe 3:'), problems
        loc = Localizer(store, {'prefilter_k': 0})
        answer = ask(loc, sets[2], 50)
        assert answer is not None and 3 not in [r['keyframe_id'] for r in answer.rows]
        assert 'bad_query' not in loc.counters.snapshot()
    with sqlite3.connect(map_path) as con:  # left in the file
        assert con.execute('SELECT count(*) FROM keyframes').fetchone()[0] == 5


def test_damage_after_open_is_the_maps_fault(map_path, rng):
    """Damage written by another connection while the map is open: the reload quarantines it too;
    no query is counted as bad_query."""
    sets = [make_set(rng) for _ in range(4)]
    store, _ = open_map(map_path, 'localization', SPACE)
    with store:
        loc = Localizer(store, {'prefilter_k': 0})
        for i, s in enumerate(sets):
            keyframe(loc, s, i)
        damage(map_path, 2)
        answer = ask(loc, sets[1], 40)
        assert answer is not None and 2 not in [r['keyframe_id'] for r in answer.rows]
        assert store.quarantined.keys() == {2}
        counts = loc.counters.snapshot()
        assert 'bad_query' not in counts and counts['queries_answered'] == 1
        invariants(counts)


def test_store_failure_is_counted_as_failed(map_path, rng):
    """A map that fails under a query (closed here) is queries_failed / keyframes_failed: the message
    is not blamed, and nothing escapes to the caller."""
    sets = [make_set(rng) for _ in range(2)]
    store, _ = open_map(map_path, 'localization', SPACE)
    loc = Localizer(store)
    keyframe(loc, sets[0], 0)
    store.close()
    assert ask(loc, sets[1], 1) is None and keyframe(loc, sets[1], 2) is None
    counts = loc.counters.snapshot()
    assert counts['queries_failed'] == 1 and counts['keyframes_failed'] == 1 and 'bad_query' not in counts
    invariants(counts)


def chattr(path, flag: str) -> bool:
    out = subprocess.run(['chattr', flag, str(path)], capture_output=True)
    return out.returncode == 0


def test_mapping_mode_refuses_a_read_only_map(map_path, rng):
    """A map mapping mode cannot write: MapError naming the file and why, before SQLite opens it,
    so no -wal/-shm appear; localization mode still serves it."""
    with MapStore(map_path, model=MODEL) as store:
        store.add(make_set(rng), (1, 2))
    if not chattr(map_path, '+i'):
        if os.geteuid() == 0:
            pytest.skip('chattr +i is not permitted here, and root can write a chmod 444 file')
        map_path.chmod(0o444)
    try:
        problem = writable_problem(map_path)
        assert str(map_path) in problem and 'not writable' in problem
        with pytest.raises(MapError, match='mode mapping') as err:
            open_map(map_path, 'mapping', SPACE)
        assert str(map_path) in str(err.value)
        assert sorted(p.name for p in map_path.parent.iterdir()) == ['map.db']
    finally:
        chattr(map_path, '-i')
        map_path.chmod(0o644)


def test_map_path_under_a_regular_file_names_the_map(tmp_path):
    (tmp_path / 'afile').write_text('x')
    path = tmp_path / 'afile' / 'map.db'
    with pytest.raises(MapError) as err:
        open_map(path, 'mapping')
    assert str(path) in str(err.value) and 'afile' in str(err.value)


def test_bad_model_record_is_explained(map_path, rng):
    """A model record that is not a valid model (written by an old version or by hand): opening names
    the record and the problem, as do lln-map info (exit 2) and check (exit 1), no traceback."""
    with MapStore(map_path, model=MODEL) as store:
        store.add(make_set(rng), (1, 2))
    with sqlite3.connect(map_path) as con:
        con.execute("UPDATE meta SET value = ? WHERE key = 'model'", (json.dumps({**MODEL, 'descriptor_dim': -7}),))
    with pytest.raises(MapError, match='bad model record') as err:
        MapStore(map_path, create=False)
    assert 'descriptor_dim' in str(err.value) and str(map_path) in str(err.value)
    for command in ('info', 'check'):
        out = subprocess.run(
            [sys.executable, '-m', 'lln_ros.cli.map', command, str(map_path)], capture_output=True, text=True
        )
        # info: bad input, exit 2; check: its finding, exit 1 (the lln-map exit contract)
        assert out.returncode == (2 if command == 'info' else 1) and 'Traceback' not in out.stderr + out.stdout, out
        assert 'bad model record' in out.stderr + out.stdout and 'descriptor_dim' in out.stderr + out.stdout


def test_keypoints_paired_by_stamp_either_order(map_path, rng):
    """verify: keypoints that come before their landmark set wait for it; ones that come after are
    attached to the stored keyframe."""
    from lln_ros.core.reloc import Keypoints

    sets = [make_set(rng) for _ in range(2)]

    def kps(n):
        k = Keypoints.empty((384, 288))
        k.uv = rng.random((n, 2)).astype(np.float32) * 200
        k.descriptors = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        return k

    store, _ = open_map(map_path, 'localization', SPACE)
    with store:
        loc = Localizer(store, {'verify': True})
        loc.keypoints(kps(30), stamp(0))  # before
        keyframe(loc, sets[0], 0)
        keyframe(loc, sets[1], 1)
        loc.keypoints(kps(40), stamp(1))  # after
        assert store.keypoints(1)[0].shape == (30, 2) and store.keypoints(2)[0].shape == (40, 2)
        assert loc.counters.snapshot()['verify_missing_keypoints'] == 1


def test_problems_are_logged_by_kind_rate_limited():
    """300 messages differing only in byte counts are one kind: one line, then one summary line per
    period with the number of repeats; a different kind gets its own first line."""
    lines, now = [], [0.0]
    c = Counters(log=lines.append, period_s=60, clock=lambda: now[0])
    for i in range(300):
        c.problem('bad_query', f'landmarks cloud: data is truncated: {1000 + i} bytes, expected {2000 + i}')
    assert len(lines) == 1 and c.snapshot() == {'bad_query': 300}
    c.problem('bad_query', "landmarks cloud: required field 'score' is missing")
    assert len(lines) == 2
    now[0] = 61.0
    c.problem('bad_query', 'landmarks cloud: data is truncated: 5 bytes, expected 9')
    assert len(lines) == 3 and '299 more of this kind' in lines[-1]
    assert problem_kind('D=64, expected D=192') == problem_kind('D=8, expected D=1e+30')
    for i in range(500):  # endless distinct texts share one '<other>' kind after max_kinds
        c.problem('bad_keyframe', f'kind{chr(65 + i % 26)}{chr(65 + i // 26)}')
    assert len(lines) == 3 + 64 + 1


def test_a_poisoned_keyframe_from_an_older_map_costs_little(map_path, rng):
    """A keyframe that an older version stored (a 32,768 px wide image: a 9 x 1024 grid, which passes
    the int16 cell check) made every later query take 0.5-10 s and 2.1 GB: offset_mode now counts only
    occupied bins when the dense array would be large, so a query against it allocates megabytes."""
    import tracemalloc

    poisoned = make_set(rng, rows=9, cols=1024)
    poisoned.cell_size = np.array([32, 32], np.float32)
    poisoned.image_size = np.array([32768, 288], np.float32)
    poisoned.centers = ((poisoned.cells + 0.5) * 32).astype(np.float32)
    poisoned.cells[0] = (1023, 8)  # offsets up to ~1,000 cells from any query's
    with MapStore(map_path, model=MODEL) as store:
        store.add(poisoned, (1, 0))
        store.add(make_set(rng), (2, 0))
    store, _ = open_map(map_path, 'localization', SPACE)
    with store:
        loc = Localizer(store, {'prefilter_k': 0})
        tracemalloc.start()
        answer = ask(loc, make_set(rng), 10)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert answer is not None and len(answer.rows) == 2
    assert peak < 64 * 2**20, f'{peak / 2**20:.0f} MB traced for one query'


def test_a_query_runs_its_arithmetic_on_one_thread_and_restores_the_pools(map_path, rng):
    """core.threads.one_thread around Localizer.query: inside the map's query every BLAS library
    and FAISS run one thread (two only waited, and spun on the extractor's core); after it, the
    process's pools are as they were."""
    import faiss
    from threadpoolctl import threadpool_info

    def pools():
        return {
            (p['internal_api'], p['filepath']): p['num_threads'] for p in threadpool_info()
        }, faiss.omp_get_max_threads()

    seen = []
    store, _ = open_map(map_path, 'localization', SPACE)
    with store:
        inner = store.query

        def query(*args, **kwargs):
            seen.append(pools())
            return inner(*args, **kwargs)

        store.query = query
        loc = Localizer(store, {'k': 3})
        sets = [make_set(rng) for _ in range(3)]
        for i, s in enumerate(sets):
            keyframe(loc, s, i)
        faiss.omp_set_num_threads(2)
        before = pools()
        assert ask(loc, sets[1], 100).rows[0]['keyframe_id'] == 2
        assert pools() == before
    blas, omp = seen[0]
    assert omp == 1 and blas and all(n == 1 for (api, _), n in blas.items() if api != 'openmp'), blas
