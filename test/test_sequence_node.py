"""The matcher's online sequence search over real DDS (sequence_length > 0): the published
sequence_score ranking equals the offline search over the same map and stream, and out-of-order
stamps, gaps and a jump to an unmapped area behave as documented."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2
from test_nodes import MATCHER, cloud, header, places, read_log, rig, stamp_of, start_matcher  # noqa: F401 (fixtures)

from lln_ros.core.sequence import KeyframeSequence
from lln_ros.mapstore import MapStore
from lln_ros.ros import msgs

MAPPED = 10  # places 0..9 are in the map; 10..13 are not (the unmapped area)


def test_matcher_sequence_online_equals_offline(rig, places, tmp_path):
    map_path = tmp_path / 'map.db'
    with MapStore(map_path, model=places['model']) as store:
        for i in range(MAPPED):
            store.add(places['sets'][i], stamp=stamp_of(header(i, 'map')))
    proc = start_matcher(rig, map_path, places, '-p', 'sequence_length:=4', '-p', 'k:=3', '-p', 'sequence_max_gap:=1.0')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates', msgs.cloud_to_candidates)
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
    rig.answers_reach_us(proc)
    # the route through places 2..7, then an out-of-order stamp, a 5 s gap, then unmapped places
    stream = [(p, 100 + j) for j, p in enumerate(range(2, 8))]  # 50 ms apart
    stream += [(8, 101)]  # older than the last: reset
    stream += [(8, 200), (9, 201)]  # 5 s later: reset (gap)
    stream += [(p, 202 + j) for j, p in enumerate(range(MAPPED, 14))]  # the unmapped area
    for j, (place, t) in enumerate(stream):
        q_pub.publish(cloud(places, place, header(t, 'query')))
        rig.until(lambda: len(cands) > j, f'answer {j}', proc)
    counters = rig.info()['counters']
    assert counters['sequence_reset_out_of_order'] == 1 and counters['sequence_reset_gap'] == 1, counters
    assert proc.stop() == 0, read_log(proc)

    # offline: the same map, the same single-frame scores, the same search
    seq = KeyframeSequence({'length': 4, 'max_gap_s': 1.0})
    with MapStore(map_path, create=False) as store:
        seq.set_map(store.ids())
        ids = store.ids()
        for (place, t), table in zip(stream, cands):
            found = store.query(places['sets'][place], prefilter_k=30, k=30)
            _, ranked = seq.update(msgs.stamp_to_ns(header(t)), {c.keyframe_id: c.score for c in found}, k=3)
            assert 'sequence_score' in table.dtype.names
            assert table['keyframe_id'].tolist() == [kf for kf, _ in ranked], (place, t)
            np.testing.assert_allclose(table['sequence_score'], [s for _, s in ranked], rtol=1e-5)
    route = cands[:6]
    # on the route the answer is the place itself (keyframe ids follow insertion: place p = ids[p])
    assert [int(c['keyframe_id'][0]) for c in route] == [ids[p] for p in range(2, 8)]
    # after the jump the sequence score falls below anything seen on the route
    on_route = min(float(c['sequence_score'][0]) for c in route)
    lost = float(cands[-1]['sequence_score'][0])
    assert lost < on_route, (lost, on_route)


def test_matcher_refuses_bad_sequence_parameters(rig, tmp_path):
    """A negative sequence_length or a non-positive sequence_max_gap: exit at start, one FATAL line."""
    import time

    # the descriptor ranges (issue 16) refuse these at declaration, naming the parameter and its range
    for args, text in (
        (('sequence_length:=-1',), 'parameter sequence_length: Parameter sequence_length out of range'),
        (('prefilter_k:=-1',), 'parameter prefilter_k: Parameter prefilter_k out of range'),
        (
            ('sequence_length:=10', 'sequence_max_gap:=0.0'),
            'parameter sequence_max_gap: Parameter sequence_max_gap out of range',
        ),
    ):
        proc = rig.matcher(tmp_path / 'map.db', *[a for arg in args for a in ('-p', arg)])
        deadline = time.monotonic() + 60
        while proc.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
        log = read_log(proc)
        assert not proc.alive() and proc.proc.returncode == 1, log
        assert text in log and 'FATAL' in log and 'Traceback' not in log, log


def test_matcher_sequence_in_mapping_mode(rig, places, tmp_path):
    """mode=mapping with sequence_length: the route 0..5 is stored as it is driven, the revisit 1, 2, 3
    is answered by the sequence (the same places, in order); the newest exclude_recent keyframes never
    end a line, so the first queries get zero rows. prefilter_k 0: every allowed keyframe is scored."""
    proc = start_matcher(
        rig,
        tmp_path / 'map.db',
        places,
        '-p',
        'mode:=mapping',
        '-p',
        'exclude_recent:=2',
        '-p',
        'sequence_length:=3',
        '-p',
        'k:=2',
        '-p',
        'prefilter_k:=0',
        '-p',
        'keyframe_novelty_max_score:=0.0',  # the route and the revisit are stored as driven
    )
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates', msgs.cloud_to_candidates)
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
    rig.answers_reach_us(proc)
    route = [0, 1, 2, 3, 4, 5, 1, 2, 3]
    for j, place in enumerate(route):
        q_pub.publish(cloud(places, place, header(j)))
        rig.until(lambda: len(cands) > j, f'answer {j}', proc)
    assert [len(c) for c in cands[:3]] == [0, 0, 0]
    for j, c in enumerate(cands):
        allowed = {stamp_of(header(i)) for i in range(j - 2)}
        assert {(int(s), int(n)) for s, n in zip(c['stamp_sec'], c['stamp_nanosec'])} <= allowed, j
    # keyframe j holds query j: the revisit of places 1, 2, 3 ends at keyframes of queries 1, 2, 3
    revisit = [(int(c['stamp_sec'][0]), int(c['stamp_nanosec'][0])) for c in cands[6:]]
    assert revisit == [stamp_of(header(i)) for i in (1, 2, 3)], revisit
    assert all('sequence_score' in c.dtype.names for c in cands)  # zero-row answers too
    assert proc.stop() == 0, read_log(proc)
