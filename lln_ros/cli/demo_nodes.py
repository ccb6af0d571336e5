"""lln-demo's online run: the two traverses as bags, the extractors and the matcher started as
`ros2 run` would, the map traverse played (keyframes), then the query traverse (answers), and every
message collected by the probe (lln_ros.ros.probe). lln_ros.cli.demo is the pipeline around it.

Playback: paced by the extractor (the probe publishes the next frame once the previous frame's
landmarks are out), or `lln-bag play` at --fps frames/s; see lln_ros.cli.demo's doc.
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

from ..eval.online import stored_stamps
from ..ros import topics
from ..ros.probe import HANDSHAKE_WAIT, ProbeTimeout, free_domain_probe
from ..ros.supervisor import NodeProcess, localhost_discovery, ros_env, stop_all
from .common import RunError

PROG = 'lln-demo'
BAG_TOPIC = '/camera/image_raw'
MAP_IMAGE = '/lln_demo/map/image_raw'
QUERY_IMAGE = '/lln_demo/query/image_raw'
NOMINAL_HZ = 10.0  # bag stamps in paced mode (the pace itself comes from the extractor)
DAY_NS = 86_400 * 1_000_000_000  # the query bag starts a day after the map bag: stamps never collide


MATCHER = '/lln_matcher'
STALL_S = 60.0  # a backlog that has not moved for this long is written off (its frames count as lost)


class Backlog:
    """What the next node has not taken yet, sent() - done() - written off, for the paced playback
    to wait on. done() comes from /diagnostics (every diagnostics_period). A node can stall for a
    while (the matcher trains its IVF-PQ landmark index once, at 20k landmarks: tens of seconds on
    a loaded machine), so only when done() has not moved for `stall` s is the outstanding count
    written off: a message lost on the way must not stop the playback, and the frames after it are
    again limited to MAX_IN_FLIGHT. Written-off frames that arrive after all are taken back."""

    def __init__(self, sent, done, stall: float = STALL_S):
        self.sent, self.done, self.stall = sent, done, stall
        self.last, self.since, self.written_off = None, time.monotonic(), 0

    def __call__(self) -> int:
        sent, done = self.sent(), self.done()
        now = time.monotonic()
        if done != self.last:
            self.last, self.since = done, now
        self.written_off = min(self.written_off, max(0, sent - done))  # late arrivals are not lost
        pending = sent - done - self.written_off
        if pending > 0 and now - self.since > self.stall:
            self.written_off += pending
            self.since = now
            return 0
        return max(0, pending)


def run_online(ds, args, out: Path, exes: dict, log) -> dict:
    """Bags into out/, the nodes up, both traverses played; everything the probe collected (stamps,
    landmarks, candidates, matches, /diagnostics, the map's stamps) and the timing of each step.
    Every node started is stopped, also on an error."""
    from tqdm import tqdm

    from ..ros import bag
    from ..ros.bag import DEFAULT_START_NS

    timing = {}
    t = time.monotonic()
    hz = args.fps or NOMINAL_HZ
    log(
        f'{PROG}: writing {out / "map_bag"} ({len(ds.ref_paths)} frames) and {out / "query_bag"} '
        f'({len(ds.query_paths)} frames)'
    )
    ref_stamps = bag.write_image_bag(ds.ref_paths, out / 'map_bag', BAG_TOPIC, rate=hz, start_ns=DEFAULT_START_NS)
    query_stamps = bag.write_image_bag(
        ds.query_paths, out / 'query_bag', BAG_TOPIC, rate=hz, start_ns=DEFAULT_START_NS + DAY_NS
    )
    timing['write_bags'] = time.monotonic() - t

    k = min(args.prefilter_k or len(ds.ref_paths), len(ds.ref_paths))
    ext_method = 'lln' if args.method == 'holistic' else args.method
    logs = out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    t = time.monotonic()
    localhost_discovery()
    graph = free_domain_probe(args.domain_id, 'lln_demo')
    procs: list[NodeProcess] = []
    result: dict = {}
    try:
        env = ros_env(graph.domain, out / 'logs' / 'ros', args.threads)
        log(f'{PROG}: starting the nodes on ROS_DOMAIN_ID={graph.domain} (localhost only); logs in {logs}')
        common = ['-p', 'diagnostics_period:=0.5']
        extractor_params = [
            '-p',
            'reliability:=reliable',
            '-p',
            f'num_threads:={args.threads}',
            '-p',
            f'method:={ext_method}',
            '-p',
            f'top_n:={args.top_n}',
            *common,
        ]
        if args.weights:
            extractor_params += ['-p', f'weights:={Path(args.weights).expanduser().resolve()}']
        if args.runtime:
            extractor_params += ['-p', f'runtime:={args.runtime}']
        procs.append(
            NodeProcess(
                exes['matcher'],
                [
                    '-p',
                    f'map_path:={(out / "map.db").resolve()}',
                    '-p',
                    'mode:=localization',
                    '-p',
                    f'prefilter:={args.prefilter}',
                    '-p',
                    f'prefilter_k:={args.prefilter_k}',
                    '-p',
                    f'k:={k}',
                    '-p',
                    f'method:={"holistic" if args.method == "holistic" else "lln"}',
                    '-p',
                    'min_score:=-1.0e9',
                    *common,
                ],
                env,
                logs / 'matcher.log',
                'matcher',
                out,
                new_session=True,
            )
        )
        # one extractor per traverse, wired by remaps as a user would (the matcher stores /keyframes and
        # answers /query)
        for role, image, landmarks in (
            ('map', MAP_IMAGE, '/' + topics.KEYFRAMES),
            ('query', QUERY_IMAGE, '/' + topics.QUERY),
        ):
            remaps = [
                '-r',
                f'__node:=lln_extractor_{role}',
                '-r',
                f'image:={image}',
                '-r',
                f'{topics.LANDMARKS}:={landmarks}',
            ]
            procs.append(
                NodeProcess(
                    exes['extractor'],
                    [*remaps, *extractor_params],
                    env,
                    logs / f'extractor_{role}.log',
                    f'extractor ({role})',
                    out,
                    new_session=True,
                )
            )
        graph.watch = procs
        graph.collect_answers()
        graph.collect_diagnostics()
        map_pub = graph.image_publisher(MAP_IMAGE) if not args.fps else None
        query_pub = graph.image_publisher(QUERY_IMAGE) if not args.fps else None

        node = graph.node

        def ready() -> bool:
            return (
                node.count_subscribers(MAP_IMAGE) >= 1
                and node.count_subscribers(QUERY_IMAGE) >= 1
                and node.count_publishers('/' + topics.KEYFRAMES) >= 1
                and node.count_publishers('/' + topics.QUERY) >= 1
                and node.count_subscribers('/' + topics.KEYFRAMES) >= 2
                and node.count_subscribers('/' + topics.QUERY) >= 2
                and node.count_publishers('/' + topics.CANDIDATES) >= 1
            )

        graph.spin_until(ready, args.timeout, 'the extractors and the matcher to come up')
        info = {}

        def model_known() -> bool:
            info.update(graph.matcher_info(args.timeout))
            return bool(info.get('model')) or graph.spin_for(0.3)

        graph.spin_until(model_known, args.timeout, "the matcher to learn the extractors' model")
        if info.get('keyframes'):
            raise RunError(f'the map {info.get("path")} is not empty ({info["keyframes"]} keyframes)')
        # let the endpoints match: seeing every endpoint in the graph does not mean the extractors' writers
        # have matched the matcher's readers. Paced playback also checks the first frame of each phase;
        # lln-bag play (--fps) cannot, so it gets a longer head start.
        graph.spin_for(3.0 if args.fps else 1.0)
        timing['start_nodes'] = time.monotonic() - t
        model = info['model']
        log(
            f'{PROG}: nodes up in {timing["start_nodes"]:.1f} s; model {model.get("descriptor_space")}, '
            f'head {model.get("head", "?")}{"" if model.get("head_trained", True) else " (UNTRAINED)"}'
        )

        mode = 'paced' if not args.fps else f'{args.fps:g} Hz'
        tick = 0.1 if sys.stderr.isatty() else 10.0  # progress lines in a log file: one per 10 s

        def play(phase: str, stamps: list, topic: str, kind: str, publisher, confirm, backlog=None) -> dict:
            """One traverse through its extractor: paced by the probe, or `lln-bag play` at --fps."""
            log(f'{PROG}: {phase}: playing {len(stamps)} frames ({mode}) -> lln_extractor_{phase} -> {kind}')
            bar = tqdm(
                total=len(stamps), desc=phase, unit='frame', disable=args.quiet, file=sys.stderr, mininterval=tick
            )
            try:
                if args.fps:
                    return graph.play_fixed(
                        exes['lln-bag'],
                        out / f'{phase}_bag',
                        topic,
                        hz,
                        kind,
                        stamps,
                        env,
                        out,
                        args.timeout,
                        logs / f'play_{phase}.log',
                        bar,
                    )
                return graph.play_paced(
                    out / f'{phase}_bag',
                    publisher,
                    kind,
                    stamps,
                    args.timeout,
                    f'/lln_extractor_{phase}',
                    confirm,
                    bar,
                    backlog,
                )
            finally:
                bar.close()

        # ---- phase 1: the map traverse -> keyframes
        def map_has_it(_stamp) -> bool:
            return graph.wait_quietly(
                lambda: graph.matcher_info(args.timeout).get('keyframes', 0) >= 1 or graph.spin_for(0.2), HANDSHAKE_WAIT
            )

        # keyframes wait too while the matcher has MAX_IN_FLIGHT not yet taken off its queue: storing
        # one (SQLite, the global and the landmark index) can be slower than extracting it, and a
        # full subscription queue loses keyframes (434 of 1073 on a loaded machine without this)
        map_backlog = Backlog(
            lambda: len(graph.landmarks['keyframes']), lambda: graph.counter(MATCHER, 'keyframes_received')
        )
        play_map = play('map', ref_stamps, MAP_IMAGE, 'keyframes', map_pub, map_has_it, backlog=map_backlog)
        expected = len(graph.landmarks['keyframes'])

        def stored() -> int:
            info.update(graph.matcher_info(args.timeout))
            return int(info.get('keyframes', 0))

        try:
            graph.spin_until(
                lambda: stored() >= expected or graph.spin_for(0.3),
                min(args.timeout, 30.0),
                f'the matcher to store {expected} keyframes',
                progress=lambda: info.get('keyframes'),
            )
        except ProbeTimeout as e:
            graph.check_nodes()
            log(f'{PROG}: warning: {str(e).splitlines()[0]}; the missing keyframes are counted as lost')
        map_info = dict(info)
        log(f'{PROG}: map: {map_info["keyframes"]} keyframes stored in {play_map["seconds"]:.1f} s')

        # ---- phase 2: the query traverse -> query -> candidates
        play_query = play(
            'query',
            query_stamps,
            QUERY_IMAGE,
            'query',
            query_pub,
            lambda stamp: graph.wait_quietly(lambda: stamp in graph.candidates, HANDSHAKE_WAIT),
            backlog=lambda: len(graph.landmarks['query']) - len(graph.candidates),
        )
        sent = set(graph.landmarks['query'])
        try:
            graph.spin_until(
                lambda: sent <= set(graph.candidates),
                min(args.timeout, 30.0),
                'the answers to every query',
                progress=lambda: len(graph.candidates),
            )
        except ProbeTimeout as e:
            graph.check_nodes()
            log(f'{PROG}: warning: {str(e).splitlines()[0]}; the queries without an answer are counted as lost')

        # final counters: wait for a /diagnostics round that has seen everything
        names = ('/lln_extractor_map', '/lln_extractor_query', '/lln_matcher')
        try:
            graph.spin_until(
                lambda: (
                    graph.counter('/lln_extractor_map', 'received') >= len(ref_stamps)
                    and graph.counter('/lln_extractor_query', 'received') >= len(query_stamps)
                    and graph.counter('/lln_matcher', 'queries_answered') >= len(graph.candidates)
                ),
                5.0,
                'final /diagnostics',
            )
        except ProbeTimeout:
            pass
        graph.spin_for(1.2)  # one more round (period 0.5 s): counters of the last frame are in
        final_info = graph.matcher_info(args.timeout)
        timing['map_phase'] = play_map['seconds']
        timing['query_phase'] = play_query['seconds']
        result = {
            'ref_stamps': ref_stamps,
            'query_stamps': query_stamps,
            'landmarks': graph.landmarks,
            'candidates': dict(graph.candidates),
            'matches': dict(graph.matches),
            'diagnostics': {n: dict(graph.diag.get(n, {})) for n in names},
            'map_info': map_info,
            'final_info': final_info,
            'model': model,
            'duplicates': dict(graph.duplicates),
            'bad_messages': list(graph.bad_messages),
            'play': {'map': play_map, 'query': play_query, 'mode': mode},
            'domain_id': graph.domain,
            'k': k,
            'timing': timing,
            'commands': {p.name: ' '.join(shlex.quote(c) for c in p.command) for p in procs},
        }
    finally:
        t = time.monotonic()
        try:
            result['exit_status'] = stop_all(procs)
        finally:
            graph.close()
        timing['stop_nodes'] = time.monotonic() - t
    result['stored_stamps'] = stored_stamps(out / 'map.db')
    return result
