"""Two robots on one map through the nodes: Nordland summer as robot A, winter as robot B (issue 29).

    python bench/bench_fleet.py [--data ../shared/data] [--range 0.7:1] [--map URI] [--lag 20]
                                [--exclude-recent 10,1000000] [-p NAME:=VALUE ...] [--out out/bench_fleet]

Each robot is a pipeline in its own namespace, started as `ros2 run` starts them: /robot_a and
/robot_b each run an extractor and a matcher in mapping mode (robot_id robot_a / robot_b), both
matchers writing into ONE map (--map: an SQLite file, default OUT/fleet.db; a Milvus URI; or
`--map milvus` under test/milvus_loopback.py --server, a new collection per run on that real
server). Both traverses play at once: frame i of A, then frame i - lag of B, each paced by its
own extractor (the next frame once the previous frame's landmarks are out, at most MAX_IN_FLIGHT
unanswered), so B passes each place `lag` frames after A mapped it, and A's keyframe reaches B's
matcher through the map (refresh_s).

Scored: robot B's answers (top-1 = its first candidate) against the Nordland ground truth of the
split (+-1 frame), the same P@100%R / R@k as lln-demo's single-map run (summer map, winter
queries, `make main`), and which robot each top-1 names. Every matcher setting is the shipped
default except min_score (-1e9) and k (prefilter_k: every reranked candidate published, as lln-demo
does), what -p sets for both robots, and B's exclude_recent, one run per --exclude-recent value: 10
(the default; B's own older keyframes are answers too) and 1000000 (none of B's own keyframes of this session
is an answer: inter-robot closures only, the way a fleet asks the map server for them).

Skips (exit 0, message) when the data is absent.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lln_ros.core import metrics  # noqa: E402
from lln_ros.core.localizer import default_conf as LOCALIZER  # noqa: E402
from lln_ros.io.datasets import parse_range, parse_spec  # noqa: E402
from lln_ros.ros import bag, msgs, topics  # noqa: E402
from lln_ros.ros.probe import MAX_IN_FLIGHT, free_domain_probe  # noqa: E402
from lln_ros.ros.supervisor import NodeProcess, find_executables, localhost_discovery, ros_env, stop_all  # noqa: E402

ROBOTS = ('robot_a', 'robot_b')
K = LOCALIZER['prefilter_k']  # candidates published: every one the rerank ranked
HZ = 10.0  # bag stamps; B's start half a frame after A's, so every stamp in the map is distinct
TIMEOUT = 180.0


class Pipeline:
    """One robot: its extractor and mapping matcher (namespace /robot), our image writer and readers."""

    def __init__(self, ns: str, probe, exes: dict, env: dict, map_uri: str, matcher_params: list, logs: Path):
        from sensor_msgs.msg import Image, PointCloud2

        self.ns, self.probe = ns, probe
        ros_ns = ['-r', f'__ns:=/{ns}']
        self.procs = [
            NodeProcess(
                exes['extractor'],
                [*ros_ns, '-p', 'reliability:=reliable', '-p', 'num_threads:=1', '-p', 'diagnostics_period:=0.5'],
                env,
                logs / f'{ns}_extractor.log',
                f'{ns} extractor',
                logs,
                new_session=True,
            ),
            NodeProcess(
                exes['matcher'],
                [
                    *ros_ns,
                    '-r',
                    f'{topics.QUERY}:={topics.LANDMARKS}',  # mapping mode: every frame is a query, then a keyframe
                    '-p',
                    f'map_path:={map_uri}',
                    '-p',
                    'mode:=mapping',
                    '-p',
                    f'robot_id:={ns}',
                    '-p',
                    f'k:={K}',
                    '-p',
                    'min_score:=-1.0e9',
                    '-p',
                    'diagnostics_period:=0.5',
                    *matcher_params,
                ],
                env,
                logs / f'{ns}_matcher.log',
                f'{ns} matcher',
                logs,
                new_session=True,
            ),
        ]
        self.images = probe.publisher(Image, f'/{ns}/{topics.IMAGE}')
        self.landmarks = probe.collect(PointCloud2, f'/{ns}/{topics.LANDMARKS}', lambda m: msgs.stamp_to_ns(m.header))
        self.answers: dict = {}
        probe.node.create_subscription(
            PointCloud2,
            f'/{ns}/{topics.CANDIDATES}',
            lambda m: self.answers.setdefault(msgs.stamp_to_ns(m.header), msgs.cloud_to_candidates(m)),
            _reliable(),
        )
        self.sent = 0

    def info(self) -> dict:
        return self.probe.matcher_info(TIMEOUT, f'/{self.ns}/lln_matcher/info')

    def linked(self) -> bool:
        """Every hop matched at both ends (us -> extractor -> matcher -> us): a volatile frame sent
        before that is lost."""
        info = self.info()
        return (
            self.images.get_subscription_count() == 1
            and info['publishers']['query'] == 1
            and info['subscriptions']['candidates'] >= 1
            and self.probe.matched_writers(f'/{self.ns}/{topics.LANDMARKS}') == 1
        )

    def send(self, raw: bytes, stamp: int) -> None:
        """One frame, once the matcher has fewer than MAX_IN_FLIGHT unanswered; returns when the
        extractor has published its landmarks (so its one-frame mailbox never holds two)."""
        p = self.probe
        p.spin_until(lambda: self.sent - len(self.answers) < MAX_IN_FLIGHT, TIMEOUT, f'{self.ns} matcher to catch up')
        self.images.publish(raw)
        self.sent += 1
        p.spin_until(lambda: stamp in self.landmarks, TIMEOUT, f'{self.ns} landmarks of {stamp}')


def _reliable():
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def run_once(ds, exes: dict, out: Path, map_uri: str, exclude_recent: int, lag: int, params: list) -> dict:
    """Both robots' traverses through their nodes at once; B's answers and what the map holds."""
    bags = {}
    for ns, paths, start in (('robot_a', ds.ref_paths, bag.DEFAULT_START_NS), ('robot_b', ds.query_paths, None)):
        start = bag.DEFAULT_START_NS + int(0.5e9 / HZ) if start is None else start
        shutil.rmtree(out / f'{ns}_bag', ignore_errors=True)  # a rerun replaces its bags
        stamps = bag.write_image_bag(paths, out / f'{ns}_bag', bag.DEFAULT_TOPIC, rate=HZ, start_ns=start)
        bags[ns] = (stamps, [raw for *_, raw in bag.read_raw(out / f'{ns}_bag', [bag.DEFAULT_TOPIC])])
    logs = out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    localhost_discovery()
    probe = free_domain_probe(None, 'lln_bench_fleet')
    pipes: dict = {}
    try:
        env = ros_env(probe.domain, logs / 'ros', 1)
        for ns in ROBOTS:
            excl = exclude_recent if ns == 'robot_b' else 10
            pipes[ns] = Pipeline(ns, probe, exes, env, map_uri, [*params, '-p', f'exclude_recent:={excl}'], logs)
        probe.watch = [p for pipe in pipes.values() for p in pipe.procs]
        probe.spin_until(lambda: all(p.linked() for p in pipes.values()), TIMEOUT, 'both pipelines linked')
        probe.spin_for(1.0)
        t0 = time.monotonic()
        n_a, n_b = len(bags['robot_a'][0]), len(bags['robot_b'][0])
        for step in range(max(n_a, n_b + lag)):
            for ns, i in (('robot_a', step), ('robot_b', step - lag)):
                stamps, raws = bags[ns]
                if 0 <= i < len(stamps):
                    pipes[ns].send(bytes(raws[i]), stamps[i])
            if step % 100 == 0:
                got = {ns: len(pipe.answers) for ns, pipe in pipes.items()}
                print(f'  step {step}: answered {got}', flush=True)
        for ns, pipe in pipes.items():
            want = set(bags[ns][0])
            probe.spin_until(lambda pipe=pipe, want=want: want <= set(pipe.answers), TIMEOUT, f'{ns} last answers')
        seconds = time.monotonic() - t0
        infos = {ns: pipe.info() for ns, pipe in pipes.items()}
    finally:
        status = stop_all([p for pipe in pipes.values() for p in pipe.procs])
        probe.close()
    return {
        'stamps': {ns: bags[ns][0] for ns in ROBOTS},
        'answers_b': pipes['robot_b'].answers,
        'info': infos,
        'seconds': seconds,
        'exit_status': status,
    }


def map_origins(map_uri: str) -> dict:
    """{stamp ns: robot} of every keyframe in the map, read after the matchers stopped."""
    from lln_ros.mapstore import MapStore

    with MapStore.open(map_uri, create=False) as store:
        robot_of = {s.id: s.robot for s in store.sessions()}
        origins = store.origins()
        out = {}
        for kid in store.ids():
            sec, nsec = store.get(kid).meta['stamp']
            sid = origins[kid].session_id if kid in origins else 0
            out[int(sec) * 10**9 + int(nsec)] = robot_of.get(sid, '?')
    return out


def score(ds, run: dict, origins: dict) -> dict:
    """Metrics of B's answers two ways: 'answer' = its candidates as ranked (-1 where a candidate is
    B's own keyframe: never a reference), 'inter' = only the candidates that are robot A's keyframes,
    in the answer's order (the inter-robot closure a fleet back end takes from the same answer)."""
    ref_of = {s: i for i, s in enumerate(run['stamps']['robot_a'])}
    q_stamps = run['stamps']['robot_b']
    ranked = {way: np.full((len(q_stamps), K), -1, np.int64) for way in ('answer', 'inter')}
    top = {way: np.full(len(q_stamps), -np.inf, np.float32) for way in ('answer', 'inter')}
    top_robot = {'robot_a': 0, 'robot_b': 0, 'none': 0}
    for q, stamp in enumerate(q_stamps):
        cands = run['answers_b'].get(stamp)
        if cands is None or not len(cands):
            top_robot['none'] += 1
            continue
        kf = [int(s) * 10**9 + int(n) for s, n in zip(cands['stamp_sec'][:K], cands['stamp_nanosec'][:K])]
        refs = [ref_of.get(s, -1) for s in kf]
        ranked['answer'][q, : len(refs)] = refs
        top['answer'][q] = cands['score'][0]
        theirs = [j for j, r in enumerate(refs) if r >= 0]
        ranked['inter'][q, : len(theirs)] = [refs[j] for j in theirs]
        if theirs:
            top['inter'][q] = cands['score'][theirs[0]]
        robot = origins.get(kf[0], '?')
        top_robot[robot] = top_robot.get(robot, 0) + 1
    return {
        **{way: {k: 100 * v for k, v in metrics.summary(ranked[way], top[way], ds.gt).items()} for way in ranked},
        'top1_robot': top_robot,
        'stored': {ns: sum(1 for r in origins.values() if r == ns) for ns in ROBOTS},
        'answered_b': sum(1 for s in q_stamps if s in run['answers_b']),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' / 'data'))
    ap.add_argument('--range', default='0.7:1', help='fractions of the aligned Nordland route (the test split)')
    ap.add_argument(
        '--map',
        default='',
        help="the shared map: '' = OUT/fleet.db (SQLite), a Milvus URI, or milvus = $LLN_MILVUS_URI/lln "
        '(test/milvus_loopback.py --server sets it)',
    )
    ap.add_argument('--lag', type=int, default=20, help='frames robot B runs behind robot A')
    ap.add_argument('--exclude-recent', default='10,1000000', help="robot B's exclude_recent, one run each")
    ap.add_argument(
        '-p',
        '--param',
        action='append',
        default=[],
        metavar='NAME:=VALUE',
        help='a matcher parameter for both robots (repeatable), e.g. keyframe_novelty_max_score:=0',
    )
    ap.add_argument('--out', default='out/bench_fleet')
    args = ap.parse_args(argv)
    # a SIGTERM (timeout, kill) unwinds like Ctrl-C, so run_once's finally stops every node it started
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    root = Path(args.data) / 'nordland_trimmed'
    if not (root / 'summer').is_dir():
        print(f'bench_fleet: skipped: no Nordland data at {root}')
        return 0
    ds = parse_spec(f'aligned:{root / "summer"},{root / "winter"},1', parse_range(args.range))
    exes, where = find_executables()
    out = Path(args.out)
    if args.map == 'milvus':
        if not os.environ.get('LLN_MILVUS_URI'):
            ap.error('--map milvus needs LLN_MILVUS_URI: run under test/milvus_loopback.py --server')
        args.map = os.environ['LLN_MILVUS_URI'].rstrip('/') + '/lln'
    rows = []
    for excl in (int(x) for x in args.exclude_recent.split(',')):
        run_dir = out / f'exclude_{excl}'
        run_dir.mkdir(parents=True, exist_ok=True)
        if args.map:
            # a fresh collection per run on the server (its name: the URI's map= option)
            map_uri = f'{args.map}{"&" if "?" in args.map else "?"}map=fleet_{excl}_{int(time.time())}'
        else:
            map_uri = str((run_dir / 'fleet.db').resolve())
            Path(map_uri).unlink(missing_ok=True)
        n_a, n_b = len(ds.ref_paths), len(ds.query_paths)
        print(f'bench_fleet: exclude_recent {excl}: {n_a} A frames, {n_b} B frames, map {map_uri}', flush=True)
        params = [a for p in args.param for a in ('-p', p)]
        run = run_once(ds, exes, run_dir, map_uri, excl, args.lag, params)
        with open(run_dir / 'run.pkl', 'wb') as f:  # every answer, to score again without a rerun
            pickle.dump(run, f)
        res = score(ds, run, map_origins(map_uri))
        res.update(exclude_recent=excl, lag=args.lag, params=args.param, seconds=run['seconds'])
        res.update(exit_status=run['exit_status'], map=map_uri)
        (run_dir / 'result.json').write_text(json.dumps(res, indent=1, default=str))
        rows.append(res)
    print(
        f'\nNordland {args.range}: robot A = summer, robot B = winter {args.lag} frames behind, both mapping '
        f'into one map{"; " + " ".join(args.param) if args.param else ""}; nodes from {where}'
    )
    print(
        f'{"B exclude_recent":>16} {"P@100%R":>8} {"R@5":>6} {"inter P@100%R":>13} {"inter R@5":>9} '
        f'{"top-1 = A":>9} {"= B own":>8} {"A stored":>9} {"B stored":>9} {"answered":>9} {"s":>6}'
    )
    for r in rows:
        a, x = r['answer'], r['inter']
        print(
            f'{r["exclude_recent"]:>16} {a["p_at_100r"]:>8.1f} {a["r_at_5"]:>6.1f} {x["p_at_100r"]:>13.1f} '
            f'{x["r_at_5"]:>9.1f} {r["top1_robot"].get("robot_a", 0):>9} {r["top1_robot"].get("robot_b", 0):>8} '
            f'{r["stored"]["robot_a"]:>9} {r["stored"]["robot_b"]:>9} {r["answered_b"]:>9} {r["seconds"]:>6.0f}'
        )
    print(
        "P@100%R / R@5: B's answer as ranked; inter: only robot A's keyframes in it, in its order. "
        "top-1 = A / = B own: whose keyframe B's best candidate is."
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
