"""lln-map merge and keyframe identity across maps (issue 29): two maps built apart by two robots
merge with no id conflict and no keyframe lost or duplicated, carrying geometry, keypoints and
(robot, session, seq); merging again adds nothing; maps from before schema 3 get a legacy session;
and on real Nordland images the merged map answers every query as one map built from all the
keyframes does."""

import subprocess
import sys

import numpy as np
import pytest
from test_map_backends import BACKENDS, uri_for
from test_mapstore import MODEL, OTHER_MODEL, make_set

from conftest import shared_data
from lln_ros.cli.map import merge_maps
from lln_ros.errors import MapError
from lln_ros.mapstore import MapStore
from lln_ros.mapstore.merge import digests

POSE = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0])
LOCAL = [b for b in BACKENDS if getattr(b, 'values', (b,))[0] != 'milvus-server']


def _robot_map(uri, robot, sets, first_stamp=0):
    with MapStore.open(uri, model=MODEL) as store:
        session = store.start_session(robot)
        ids = store.add_many(sets, [(first_stamp + i, 0) for i in range(len(sets))])
        for seq, kid in enumerate(ids, 1):
            store.set_origin(kid, session.id, seq)
        store.set_geometry(ids[0], {'pose': POSE, 'frame_id': robot + '/odom'})
        if hasattr(store, 'add_keypoints'):
            store.add_keypoints(ids[1], np.array([[1.0, 2.0], [3.0, 4.0]], np.float32), np.zeros((2, 32), np.uint8))
        return session, ids


def _identities(store) -> dict:
    """{content digest: (robot, label, seq)} of every keyframe."""
    sessions = {s.id: s for s in store.sessions()}
    origins = store.origins()
    by_id = {kid: d for d, kid in digests(store).items()}
    return {
        by_id[kid]: (sessions[o.session_id].robot, sessions[o.session_id].label, o.seq) for kid, o in origins.items()
    }


@pytest.mark.parametrize('kind', LOCAL)
def test_two_robots_merge_without_conflict_loss_or_duplicate(kind, tmp_path):
    rng = np.random.default_rng(7)
    a_uri, b_uri, dest = (uri_for(kind, tmp_path, n) for n in ('a', 'b', 'dest'))
    sa, a_ids = _robot_map(a_uri, 'robot_a', [make_set(rng) for _ in range(7)])
    sb, b_ids = _robot_map(b_uri, 'robot_b', [make_set(rng) for _ in range(5)], first_stamp=100)
    assert a_ids[:5] == b_ids  # ids restart at 1 in every map: `lln-map import` would refuse B
    lines = []
    totals = merge_maps([a_uri, b_uri], dest, out=lines.append)
    assert totals == {'read': 12, 'added': 12, 'present': 0, 'keyframes': 12, 'sessions': 2}, lines
    with MapStore.open(a_uri) as a, MapStore.open(b_uri) as b, MapStore.open(dest) as m:
        want = {**_identities(a), **_identities(b)}
        assert _identities(m) == want and len(want) == 12  # every keyframe once, its identity kept
        assert {(s.robot, s.label) for s in m.sessions()} == {('robot_a', sa.label), ('robot_b', sb.label)}
        by_digest = digests(m)
        a_first = next(d for d, k in digests(a).items() if k == a_ids[0])
        geom = m.geometry(by_digest[a_first])
        assert geom['frame_id'] == 'robot_a/odom' and np.allclose(geom['pose'], POSE)
        if hasattr(m, 'keypoints'):
            b_second = next(d for d, k in digests(b).items() if k == b_ids[1])
            assert m.keypoints(by_digest[b_second])[0].tolist() == [[1.0, 2.0], [3.0, 4.0]]
        # an answer names its session: a query like B's third keyframe finds it, from robot_b
        query = make_set(rng, base=b.get(b_ids[2]), noise=0.1)
        top = m.query(query, k=1)[0]
        assert {s.id: s.robot for s in m.sessions()}[top.session_id] == 'robot_b'
    # merging again (or a map with itself) adds nothing
    assert merge_maps([b_uri, a_uri, a_uri], dest, out=lines.append)['added'] == 0
    with MapStore.open(dest) as m:
        assert len(m) == 12 and len(m.sessions()) == 2


def test_legacy_map_gets_a_session_and_a_refused_merge_leaves_no_dest(tmp_path):
    import sqlite3

    rng = np.random.default_rng(8)
    old = tmp_path / 'old.db'
    with MapStore.open(old, model=MODEL) as store:
        store.add_many([make_set(rng) for _ in range(3)], [(i, 0) for i in range(3)])
    conn = sqlite3.connect(old)  # back to schema 2: no sessions, no origins
    for table in ('origins', 'sessions'):
        conn.execute(f'DROP TABLE {table}')
    conn.execute("UPDATE meta SET value = '2' WHERE key = 'schema_version'")
    conn.commit()
    conn.close()
    dest = tmp_path / 'dest.db'
    assert merge_maps([str(old)], str(dest), out=lambda _: None)['added'] == 3
    with MapStore.open(dest) as m:
        (s,) = m.sessions()
        assert s.robot == 'old' and s.label.startswith('legacy-')
        assert sorted(o.seq for o in m.origins().values()) == [1, 2, 3]  # the old ids
    # another model: refused, exit 2, and the DEST it would have created is not left behind
    other = tmp_path / 'other.db'
    with MapStore.open(other, model=OTHER_MODEL) as store:
        store.add(make_set(rng, dim=OTHER_MODEL['descriptor_dim'], space=OTHER_MODEL['descriptor_space']))
    fresh = tmp_path / 'fresh.db'
    with pytest.raises(MapError):
        merge_maps([str(old), str(other)], str(fresh), out=lambda _: None)
    assert not fresh.exists()
    out = subprocess.run(
        [sys.executable, '-m', 'lln_ros.cli.map', 'merge', str(old), str(other), str(fresh)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2 and 'model' in out.stderr and not fresh.exists(), out.stderr


def test_merged_nordland_map_answers_as_one_map_does(extractor, tmp_path):
    """Real images: Nordland summer frames of the test part as two robots' maps (first and second
    half of the stretch), merged; every winter frame's top-1 in the merged map is the top-1 of one
    map built from all the same keyframes (by content, so ids need not agree)."""
    from lln_ros.io.image import load_image

    root = shared_data('nordland_trimmed')
    names = sorted(p.name for p in (root / 'summer').iterdir())[2600:2680:2]  # 40 places of the test part
    summer = extractor.extract_batch([load_image(root / 'summer' / n) for n in names])
    winter = extractor.extract_batch([load_image(root / 'winter' / n) for n in names])
    for lset in summer:
        lset.descriptor_space = extractor.model_info['descriptor_space']
    model = extractor.model_info
    half = len(summer) // 2
    maps = {}
    for name, sets, first in (('a', summer[:half], 0), ('b', summer[half:], half), ('one', summer, 0)):
        maps[name] = str(tmp_path / f'{name}.db')
        with MapStore.open(maps[name], model=model) as store:
            session = store.start_session(f'robot_{name}')
            for seq, kid in enumerate(store.add_many(sets, [(first + i, 0) for i in range(len(sets))]), 1):
                store.set_origin(kid, session.id, seq)
    merge_maps([maps['a'], maps['b']], str(tmp_path / 'merged.db'), out=lambda _: None)
    with MapStore.open(maps['one']) as one, MapStore.open(tmp_path / 'merged.db') as merged:
        assert len(merged) == len(one) == len(summer)
        one_d = {k: d for d, k in digests(one).items()}
        merged_d = {k: d for d, k in digests(merged).items()}
        robots = {s.id: s.robot for s in merged.sessions()}
        same = correct = 0
        for i, q in enumerate(winter):
            a, b = one.query(q, k=1)[0], merged.query(q, k=1)[0]
            same += one_d[a.keyframe_id] == merged_d[b.keyframe_id] and a.score == pytest.approx(b.score, abs=1e-5)
            place = merged.get(b.keyframe_id).meta['stamp'][0]
            correct += place == i
            assert robots[b.session_id] == ('robot_a' if place < half else 'robot_b')
        print(f'\nmerged vs one map: {same}/{len(winter)} top-1 identical; {correct} correct places')
        assert same == len(winter)
