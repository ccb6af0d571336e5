"""The map server under load and concurrent service calls: the colcon-installed matcher against
maps of synthetic landmark sets (D=192, n=50: the default model's shapes), a probe on the test side.

- 30 Hz of queries for 60 s against a 10,000-keyframe map (marked slow): latency stays bounded,
  memory does not grow, every query is accounted for (answered, dropped as stale by the node, or
  dropped in transport), and the counts are reported (the share answered is load-dependent: the
  throughput figure is bench/bench_map.py's).
- ~/clear and ~/save during a burst of keyframes: no deadlock, no lost keyframe.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from test_mapstore import make_set
from test_nodes import MATCHER, Rig, header, stamp_of

from lln_ros.mapstore import MapStore
from lln_ros.ros import msgs

SPACE = 'efficientnet_lite0/stage6/192'


def random_set(rng):
    return make_set(rng, dim=192, space=SPACE)


def noisy_view(rng, lset):
    return make_set(rng, dim=192, base=lset, noise=0.02)  # a perturbation of norm ~0.28 per unit vector


@pytest.fixture
def rig(colcon_install, tmp_path):
    r = Rig(colcon_install, tmp_path)
    # one BLAS / OpenMP thread per query: on a shared 2-core machine spinning pool workers cost more
    # than they give (bench/bench_map.py)
    r.env.update({'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1'})
    yield r
    r.close()


def rss_mb(pid: int) -> float:
    with open(f'/proc/{pid}/status') as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith('VmRSS:'))


def start(rig, map_path, *args):
    proc = rig.matcher(map_path, '-p', f'descriptor_space:={SPACE}', *args)
    rig.until(
        lambda: (
            rig.probe.node.count_publishers('lln/candidates') > 0 and rig.probe.node.count_subscribers('lln/query') > 0
        ),
        'matcher up',
        proc,
        timeout=120,
    )
    return proc


@pytest.mark.slow
def test_matcher_30hz_for_60s_on_10k_map(rig, tmp_path, record_property):
    rng = np.random.default_rng(0)
    map_path = tmp_path / 'map10k.db'
    size, rate, seconds, max_age = 10_000, 30.0, 60.0, 1.0
    revisits = {}
    with MapStore.open(map_path, model={'descriptor_space': SPACE, 'descriptor_dim': 192}) as store:
        for start_at in range(0, size, 1000):
            sets = [random_set(rng) for _ in range(1000)]
            ids = store.add_many(sets, [(start_at + i, 0) for i in range(1000)])
            revisits.update({ids[j]: sets[j] for j in range(0, 1000, 50)})
        store.save()
    proc = start(rig, map_path, '-p', f'max_query_age:={max_age}', '-p', 'queue_depth:=10')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query', depth=10)
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'query subscription', proc)
    answers = rig.probe.collect(
        PointCloud2,
        'lln/candidates',
        lambda m: (
            msgs.stamp_to_ns(m.header),
            time.monotonic(),
            [int(r['keyframe_id']) for r in msgs.cloud_to_candidates(m)],
        ),
    )
    queries = [(kid, msgs.landmarks_to_cloud(noisy_view(rng, s))) for kid, s in revisits.items()]
    sent: dict[int, tuple[float, int]] = {}
    t0 = time.monotonic()
    rss_start = None
    i = 0
    while (now := time.monotonic()) - t0 < seconds:
        kid, cloud = queries[i % len(queries)]
        stamp = time.time_ns()
        cloud.header = msgs.make_header(stamp, 'cam')
        q_pub.publish(cloud)
        sent[stamp] = (now, kid)
        i += 1
        if rss_start is None and now - t0 > 5:  # after warm-up: the map, index and caches are in
            rss_start = rss_mb(proc.proc.pid)
        rig.probe.spin_for(max(0.0, t0 + i / rate - time.monotonic()))
    rig.probe.spin_for(3.0)  # drain
    rss_end = rss_mb(proc.proc.pid)
    counters = rig.info()['counters']
    assert proc.alive()
    latency = np.array([t - sent[s][0] for s, t, _ in answers if s in sent])
    top1 = np.mean([bool(ids) and ids[0] == sent[s][1] for s, _, ids in answers if s in sent])
    received, answered = counters.get('queries_received', 0), counters.get('queries_answered', 0)
    stale = counters.get('queries_stale', 0)
    report = {
        'sent': len(sent),
        'received': received,
        'answered': answered,
        'dropped_stale': stale,
        'dropped_transport': len(sent) - received,
        'p50_s': float(np.percentile(latency, 50)),
        'p99_s': float(np.percentile(latency, 99)),
        'max_s': float(latency.max()),
        'top1': float(top1),
        'rss_start_mb': rss_start,
        'rss_end_mb': rss_end,
    }
    print('load report:', report)
    for key, value in report.items():
        record_property(key, value)
    assert len(sent) >= 0.95 * rate * seconds  # the probe kept the rate
    assert received == answered + stale + counters.get('bad_query', 0)  # every received query accounted for
    assert len(answers) == answered and received <= len(sent)
    # How much of the stream is answered depends on the machine's load (278 of 1,791 at load 13 on
    # 2 cores, most of them at load 2): a speed figure, measured by bench/bench_map.py, not asserted.
    assert answered >= 20, report  # it does answer, all the time ...
    # ... with a bounded latency: stale queries are dropped, not queued (the margin covers one query's
    # compute on a CPU-starved machine)
    assert report['max_s'] < max_age + 3.0, report
    assert top1 >= 0.9, report  # and the answers are right
    assert rss_end - rss_start < 50, report  # no growing queue or cache
    assert proc.stop() == 0


def test_clear_and_save_during_a_burst(rig, tmp_path):
    """~/clear and ~/save called while 150 keyframes arrive: every call returns, and every stored
    keyframe is either in the map or was counted by a clear (the last clear wins, nothing else lost)."""
    rng = np.random.default_rng(1)
    map_path = tmp_path / 'map.db'
    proc = start(rig, map_path, '-p', 'queue_depth:=200')  # the whole burst fits the queue
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes', depth=200)
    rig.until(lambda: kf_pub.get_subscription_count() > 0, 'keyframes subscription', proc)
    clients = {n: rig.probe.node.create_client(Trigger, f'{MATCHER}/{n}') for n in ('clear', 'save')}
    rig.until(lambda: all(c.service_is_ready() for c in clients.values()), 'services', proc)
    burst, futures = 150, []
    for i in range(burst):
        kf_pub.publish(msgs.landmarks_to_cloud(random_set(rng), header(i)))
        if i % 25 == 10:
            futures += [clients['clear'].call_async(Trigger.Request()), clients['save'].call_async(Trigger.Request())]
        rig.probe.spin_for(0.0)
    rig.until(lambda: all(f.done() for f in futures), 'every service answer (no deadlock)', proc, timeout=60)
    try:
        rig.wait_counter(MATCHER, 'keyframes_stored', burst, proc)
    finally:
        print('matcher counters:', rig.diag.get(MATCHER))
    assert all(f.result().success for f in futures), [f.result().message for f in futures]
    cleared = sum(int(f.result().message.split()[1]) for f in futures[0::2])
    assert proc.stop() == 0
    with MapStore.open(map_path, create=False) as store:
        stamps = [store.get(k).meta['stamp'] for k in store.ids()]
        assert store.check() == []
    assert cleared + len(stamps) == burst
    assert stamps == [stamp_of(header(i)) for i in range(burst - len(stamps), burst)]


def test_stale_queries_are_dropped_and_counted(rig, tmp_path):
    """A query older than max_query_age (a backlog, a stalled link) is dropped, counted and never
    answered; a fresh one is answered."""
    rng = np.random.default_rng(2)
    map_path = tmp_path / 'map.db'
    sets = [random_set(rng) for _ in range(5)]
    with MapStore.open(map_path, model={'descriptor_space': SPACE, 'descriptor_dim': 192}) as store:
        store.add_many(sets, [(i, 0) for i in range(5)])
    proc = start(rig, map_path, '-p', 'max_query_age:=1.0')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'query subscription', proc)
    answers = rig.probe.collect(PointCloud2, 'lln/candidates', lambda m: msgs.stamp_to_ns(m.header))
    old = [time.time_ns() - 10 * 10**9 + i for i in range(4)]
    for stamp in old:
        q_pub.publish(msgs.landmarks_to_cloud(sets[1], msgs.make_header(stamp)))
    fresh = time.time_ns()
    q_pub.publish(msgs.landmarks_to_cloud(sets[1], msgs.make_header(fresh)))
    rig.until(lambda: answers, 'the fresh answer', proc)
    rig.wait_counter(MATCHER, 'queries_stale', 4, proc)
    assert answers == [fresh]
    counters = rig.info()['counters']
    assert counters['queries_received'] == 5 and counters['queries_stale'] == 4
    assert counters['queries_answered'] == 1
