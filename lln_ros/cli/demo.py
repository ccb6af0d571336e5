"""lln-demo: build a map from one traverse and query it with another through the ROS 2 nodes.

    lln-demo --out DIR [--dataset SPEC] [--range START:END] [--download] [--rate HZ]
             [--method lln|act|rand|all|holistic] [--top-n 50] [--prefilter landmarks|holistic|exhaustive]
             [--prefilter-k 100]
             [--offline | --no-offline] [--check]

Without --dataset: the Nordland test split (summer = map, winter = queries, +-1 frame, the last 30%
of the route, `--range 0.7:1`) when $LLN_DATA names the shared data folder (scripts/main_job.sh and
`make main` set it to ../shared/data beside the checkout); otherwise Gardens Point Walking
(day_right = map, night_right = queries) from --download-dir, fetched there with --download;
otherwise it asks for --dataset. SPEC: aligned:DIR_REF,DIR_QUERY[,TOL] | vprbench:DIR |
gardenspoint:DIR[,REF,QUERY] (the map traverse is the reference one).

What it does:
  1. reads and checks the dataset (every image decodes), then writes DIR/map_bag (the references)
     and DIR/query_bag (the queries) as MCAP bags of sensor_msgs/Image rgb8 on /camera/image_raw;
  2. starts the nodes as `ros2 run lln_ros ...` would (<prefix>/lib/lln_ros/{extractor,matcher} of
     an ament prefix of lln_ros, else the console scripts beside this Python), on a free private
     ROS_DOMAIN_ID with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: one matcher (localization mode, map
     DIR/map.db) and two extractors (reliable image QoS), lln_extractor_map with
     `-r landmarks:=keyframes` and lln_extractor_query with `-r landmarks:=query`;
  3. plays the map bag (as `ros2 bag play --remap /camera/image_raw:=...`), waits until the matcher's
     ~/info counts every keyframe, then plays the query bag and collects every `candidates` and
     `matches` message;
  4. prints the metrics (P@100%R, R@100%P, AUC-PR, R@1/5/10), writes DIR/results_online.json,
     DIR/results_online.md, DIR/answers_online.csv (top-1 per query), DIR/rankings.npz (every ranking),
     DIR/pr_online.png and DIR/matches_online_*.png;
  5. with --offline (the default) runs the offline evaluator (lln-eval's code) on the same dataset with
     the same method, top-n, prefilter and prefilter-k into DIR/offline/, and prints online vs offline.

Why two extractors: the wiring is static, exactly the `-r` remaps a user writes, and each traverse
is counted by its own extractor's /diagnostics; re-routing one extractor between the phases would mean
a restart (model load, discovery again) or a relay hop that a real system does not have.

Playback: by default each frame is published as soon as the extractor has published the previous
frame's landmarks (paced: its one-frame mailbox never holds two frames, so none is dropped, as fast
as the extractor goes), and queries also wait while the matcher has MAX_IN_FLIGHT unanswered (with
--prefilter-k 0 on a large map it is the slower node). The first frame of each phase is a handshake:
it is sent again until it has arrived downstream (a keyframe in the map / an answer), because a frame
published before the extractor's writer has matched the matcher's reader is lost even when the graph
already shows both.
--rate HZ instead plays the bags at HZ frames per second with `lln-bag play` (what `ros2 bag play`
does); frames the extractor cannot keep up with are dropped by its newest-frame policy, counted and
reported (the extractors' /diagnostics `received`/`published`/`dropped`, the stamps in the map file,
the answers).

Bad input exits 2 with one line on stderr (before anything long runs); a failure while running
exits 1 with the node logs' tails (DIR/logs/); Ctrl-C exits 130. Every node started is stopped.

The pieces: lln_ros.ros.supervisor (executables, environment, start / stop), lln_ros.ros.probe
(collecting, paced playback), lln_ros.eval.online (scoring, online vs offline), lln_ros.eval.report
and lln_ros.eval.figures (the one report stack lln-eval uses too). This module is the pipeline.
"""

# Why this module is past 500 lines: about 450 lines of pipeline; the rest is the node command lines
# and report dicts, which the formatter lays out one element per line.
from __future__ import annotations

import argparse
import shlex
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from ..eval.online import compare, run_offline, score_online, stored_stamps
from ..eval.report import METRICS, online_console, online_markdown, transport_lines, write_answers, write_json
from ..ros.probe import HANDSHAKE_TRIES, HANDSHAKE_WAIT, ProbeTimeout, free_domain_probe  # noqa: F401
from ..ros.supervisor import NodeProcess, SupervisorError, find_executables, localhost_discovery, ros_env, stop_all
from .common import (
    DATA_ENV,
    RunError,
    UsageError,
    add_prefilter_argument,
    add_runtime_argument,
    data_dir,
    download_dataset,
    parser_from_doc,
    positive_float,
    progress_log,
    read_dataset,
    run_cli,
)

PROG = 'lln-demo'
NORDLAND_RANGE = (0.7, 1.0)
BAG_TOPIC = '/camera/image_raw'
MAP_IMAGE = '/lln_demo/map/image_raw'
QUERY_IMAGE = '/lln_demo/query/image_raw'
NOMINAL_HZ = 10.0  # bag stamps in paced mode (the pace itself comes from the extractor)
DAY_NS = 86_400 * 1_000_000_000  # the query bag starts a day after the map bag: stamps never collide
METHODS = ('lln', 'act', 'rand', 'all', 'holistic')
# what one run writes into DIR (removed at the start of a run, so a rerun is clean)
OUTPUTS = (
    'map_bag',
    'query_bag',
    'map.db',
    'map.db-wal',
    'map.db-shm',
    'results_online.json',
    'results_online.md',
    'answers_online.csv',
    'rankings.npz',
    'pr_online.png',
    'offline',
    'logs',
)
DEFAULT_DOWNLOAD_DIR = '~/.cache/lln_ros/gardens_point'
__all__ = ['METRICS', 'HANDSHAKE_TRIES', 'main']


# ------------------------------------------------------------------------------------------ inputs


def nordland_spec(data: Path) -> str:
    root = data / 'nordland_trimmed'
    return f'aligned:{root / "summer"},{root / "winter"},1'


def build_parser():
    from ..core.extractor import default_conf as ext
    from ..eval.runner import default_conf as eval_defaults

    p = parser_from_doc(PROG, __doc__)
    p.add_argument('--out', required=True, metavar='DIR', help='output folder (bags, map, results, plots, logs)')
    p.add_argument('--dataset', metavar='SPEC', help='default: the Nordland test split, else Gardens Point')
    p.add_argument(
        '--range',
        metavar='START:END',
        help='fractions of an aligned dataset (default 0.7:1 for the default Nordland split)',
    )
    p.add_argument(
        '--download',
        action='store_true',
        help='fetch Gardens Point Walking when it is the dataset and is not there yet',
    )
    p.add_argument(
        '--download-dir',
        default=DEFAULT_DOWNLOAD_DIR,
        help=f'where the default Gardens Point dataset lives (default {DEFAULT_DOWNLOAD_DIR})',
    )
    p.add_argument('--download-url', default=None, help='where --download fetches from (default: the public archive)')
    p.add_argument(
        '--rate',
        type=positive_float,
        metavar='HZ',
        help='play the bags at HZ frames/s with lln-bag play (default: paced by the extractor)',
    )
    p.add_argument(
        '--method',
        default=ext['method'],
        choices=METHODS,
        help='landmark selection of the extractor (lln, act, rand, all) or holistic (the matcher '
        f'ranks by the global descriptor alone); default {ext["method"]}',
    )
    p.add_argument('--top-n', type=int, default=ext['top_n'], help=f'landmarks per image (default {ext["top_n"]})')
    add_prefilter_argument(p)
    p.add_argument('--weights', default=ext['weights'], help="LLN head checkpoint (default '': the shipped head)")
    p.add_argument(
        '--threads',
        type=int,
        default=1,
        help='torch threads per extractor and offline, BLAS threads per node (default 1)',
    )
    add_runtime_argument(p)
    p.add_argument(
        '--offline',
        action=argparse.BooleanOptionalAction,
        default=True,
        help='also run the offline evaluator and compare (default on)',
    )
    p.add_argument('--cache', metavar='DIR', help='offline feature cache (default DIR/cache/features)')
    p.add_argument(
        '--examples',
        type=int,
        default=eval_defaults['examples'],
        help=f'success and failure match pictures (default {eval_defaults["examples"]} each)',
    )
    p.add_argument(
        '--timeout',
        type=positive_float,
        default=120.0,
        help='seconds to wait for a node (start, one frame, the last answers) (default 120)',
    )
    p.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: a free one, probed)')
    p.add_argument('--check', action='store_true', help='read and check the inputs, print the plan, stop')
    p.add_argument('--quiet', action='store_true', help='no progress output')
    return p


def check_args(args) -> None:
    if args.top_n < 1:
        raise UsageError(f'--top-n must be at least 1, got {args.top_n}')
    if args.prefilter_k < 0:
        raise UsageError(f'--prefilter-k must be at least 0 (0 = every map frame), got {args.prefilter_k}')
    if args.threads < 1:
        raise UsageError(f'--threads must be at least 1, got {args.threads}')
    if args.examples < 0:
        raise UsageError(f'--examples must be 0 or more, got {args.examples}')
    if args.domain_id is not None and not 0 <= args.domain_id <= 101:
        raise UsageError(f'--domain-id must be 0..101, got {args.domain_id}')
    if args.weights and not Path(args.weights).expanduser().is_file():
        raise UsageError(f'--weights: no such file {args.weights}')
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f'--out {out} exists and is not a folder')
    parent = out.resolve().parent
    if not out.exists() and not parent.is_dir():
        raise UsageError(f'--out {out}: folder {parent} does not exist')


def choose_dataset(args) -> tuple[str, tuple | None, str]:
    """(spec, range, why) from --dataset / --range or the defaults."""
    from ..io.datasets import parse_range

    frac = parse_range(args.range)  # DatasetError (exit 2) on a bad --range
    if args.dataset:
        return args.dataset, frac, 'given with --dataset'
    data = data_dir()
    if data is not None:
        return nordland_spec(data), frac or NORDLAND_RANGE, f'the Nordland test split in {data}'
    gp = Path(args.download_dir).expanduser()
    if (gp / 'day_right').is_dir() and (gp / 'night_right').is_dir():
        return f'gardenspoint:{gp}', frac, f'Gardens Point Walking in {gp}'
    if args.download:
        return f'gardenspoint:{gp}', frac, f'Gardens Point Walking, downloaded into {gp}'
    raise UsageError(
        f'no dataset: ${DATA_ENV} does not name a folder with nordland_trimmed/ and Gardens Point is '
        f'not in {gp}; give --dataset SPEC (e.g. aligned:MAP_DIR,QUERY_DIR,2), set {DATA_ENV}, or add '
        '--download to fetch Gardens Point Walking'
    )


def load_dataset(spec: str, frac, args, log):
    """The checked Dataset (every image decoded); Gardens Point fetched when needed and allowed."""
    from ..errors import DatasetError

    kind = spec.partition(':')[0]
    if kind == 'loop':
        raise UsageError(
            'loop: datasets are one sequence (mapping mode); lln-demo needs two traverses '
            '(aligned:, vprbench: or gardenspoint:)'
        )
    if frac is not None and kind != 'aligned':
        raise UsageError(f'--range applies to aligned: datasets only, not {kind}:')
    ds, _ = read_dataset(spec, frac, args.download)
    if ds is None:  # gardenspoint:DIR without its folders, --download given
        ds = download_dataset(PROG, spec, args.download_url, args.quiet, log)
    if ds.candidates is not None:
        raise DatasetError(f'{spec} is a loop dataset; lln-demo needs two traverses')
    return ds


# ------------------------------------------------------------------------------------ the online run


def run_online(ds, args, out: Path, exes: dict, log) -> dict:
    from tqdm import tqdm

    from ..io import bag
    from ..io.bag import DEFAULT_START_NS

    timing = {}
    t = time.monotonic()
    hz = args.rate or NOMINAL_HZ
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
        for role, image, landmarks in (('map', MAP_IMAGE, '/keyframes'), ('query', QUERY_IMAGE, '/query')):
            remaps = ['-r', f'__node:=lln_extractor_{role}', '-r', f'image:={image}', '-r', f'landmarks:={landmarks}']
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
        map_pub = graph.image_publisher(MAP_IMAGE) if not args.rate else None
        query_pub = graph.image_publisher(QUERY_IMAGE) if not args.rate else None

        node = graph.node

        def ready() -> bool:
            return (
                node.count_subscribers(MAP_IMAGE) >= 1
                and node.count_subscribers(QUERY_IMAGE) >= 1
                and node.count_publishers('/keyframes') >= 1
                and node.count_publishers('/query') >= 1
                and node.count_subscribers('/keyframes') >= 2
                and node.count_subscribers('/query') >= 2
                and node.count_publishers('/candidates') >= 1
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
        # lln-bag play (--rate) cannot, so it gets a longer head start.
        graph.spin_for(3.0 if args.rate else 1.0)
        timing['start_nodes'] = time.monotonic() - t
        model = info['model']
        log(
            f'{PROG}: nodes up in {timing["start_nodes"]:.1f} s; model {model.get("descriptor_space")}, '
            f'head {model.get("head", "?")}{"" if model.get("head_trained", True) else " (UNTRAINED)"}'
        )

        mode = 'paced' if not args.rate else f'{args.rate:g} Hz'
        tick = 0.1 if sys.stderr.isatty() else 10.0  # progress lines in a log file: one per 10 s

        def play(phase: str, stamps: list, topic: str, kind: str, publisher, confirm, backlog=None) -> dict:
            """One traverse through its extractor: paced by the probe, or `lln-bag play` at --rate."""
            log(f'{PROG}: {phase}: playing {len(stamps)} frames ({mode}) -> lln_extractor_{phase} -> {kind}')
            bar = tqdm(
                total=len(stamps), desc=phase, unit='frame', disable=args.quiet, file=sys.stderr, mininterval=tick
            )
            try:
                if args.rate:
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

        play_map = play('map', ref_stamps, MAP_IMAGE, 'keyframes', map_pub, map_has_it)
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


# ------------------------------------------------------------------------------------------- main


def prepare_out(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in OUTPUTS:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
    for p in out.glob('matches_online_*.png'):
        p.unlink()


def run(args, argv, log) -> int:
    check_args(args)
    spec, frac, why = choose_dataset(args)
    exes, where = find_executables()
    # 1. read and check the dataset (every image decodes) before anything long
    t0 = time.monotonic()
    ds = load_dataset(spec, frac, args, log)
    name = ds.name
    rng = f'{frac[0]:g}:{frac[1]:g}' if frac else None
    log(
        f'{PROG}: dataset {name} ({why}): {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries '
        f'({ds.queries_with_match} with a true match); {spec}' + (f' --range {rng}' if rng else '')
    )
    if len(ds.query_paths) == 0:
        raise UsageError(f'{spec}: no queries left (every query frame is blank?)')
    log(f'{PROG}: nodes: {where}')
    if args.check:
        print(
            f'{PROG}: OK: {name}: {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries; '
            f'nodes from {where}; would write {args.out}'
        )
        return 0
    out = Path(args.out).resolve()  # absolute: the nodes run with DIR as their working folder
    prepare_out(out)
    timing = {'read_dataset': time.monotonic() - t0}

    online_run = run_online(ds, args, out, exes, log)
    timing.update(online_run['timing'])
    online = score_online(ds, online_run)
    tr = online['transport']
    for line in transport_lines(tr):
        log(f'{PROG}: {line}')
    dropped = tr['map']['extractor_dropped'] + tr['query']['extractor_dropped']
    if dropped:
        ms = [
            float(online_run['diagnostics'].get(n, {}).get('last_latency_ms', 0) or 0)
            for n in ('/lln_extractor_map', '/lln_extractor_query')
        ]
        advice = f' (last extraction {max(ms):.0f} ms: play at most {800 / max(ms):.1f} Hz)' if max(ms) > 0 else ''
        why = (
            (
                f'--rate {args.rate:g} is faster than extraction{advice}, or omit --rate to pace the bags by '
                'the extractor'
            )
            if args.rate
            else 'this should not happen with paced playback'
        )
        print(f'{PROG}: warning: the extractors dropped {dropped} frames: {why}', file=sys.stderr)

    offline, comparison, offline_error = None, None, None
    if args.offline:
        log(
            f'{PROG}: offline: the same dataset through lln_ros.eval (method {args.method}, top-n '
            f'{args.top_n}, prefilter {args.prefilter}, prefilter-k {args.prefilter_k}) into {out / "offline"}'
        )
        try:
            offline = run_offline(ds, spec, args, out, log)
        except (KeyboardInterrupt, MemoryError):
            raise
        except Exception as e:  # noqa: BLE001  the online results are still written
            offline_error = f'{type(e).__name__}: {e}'
            print(f'{PROG}: error: the offline evaluation failed: {offline_error}', file=sys.stderr)
        else:
            timing['offline'] = offline['seconds']
            comparison = compare(
                online,
                offline['ranked'],
                offline['scores'],
                offline['summary'],
                tr,
                models=(online_run['model'], offline['model']),
            )

    from ..eval.figures import online_curves, plot_online_examples, plot_pr

    title = f'{name}: precision-recall (threshold on the top-1 score), method {args.method}'
    plot_pr(online_curves(online, offline), ds.gt, out / 'pr_online.png', title)
    examples = plot_online_examples(ds, online_run, online, out, args.examples)
    write_answers(ds, online_run, online, offline, out / 'answers_online.csv')
    arrays = {
        'online_ranked': online['ranked'],
        'online_scores': online['scores'],
        'online_holistic': online['holistic'],
        'gt': ds.gt,
    }
    if offline:
        arrays.update(offline_ranked=offline['ranked'], offline_scores=offline['scores'])
    np.savez_compressed(out / 'rankings.npz', **arrays)
    timing['total'] = time.monotonic() - t0

    report = {
        'command': f'{PROG} ' + ' '.join(shlex.quote(a) for a in argv),
        'dataset': {
            'name': name,
            'spec': spec,
            'range': rng,
            'chosen': why,
            'refs': len(ds.ref_paths),
            'queries': len(ds.query_paths),
            'queries_with_match': ds.queries_with_match,
            'info': {k: v for k, v in ds.info.items() if not k.endswith('_sizes')},
        },
        'parameters': {
            'method': args.method,
            'top_n': args.top_n,
            'prefilter': args.prefilter,
            'prefilter_k': args.prefilter_k,
            'k': online_run['k'],
            'threads': args.threads,
            'weights': args.weights,
            'playback': online_run['play']['mode'],
            'domain_id': online_run['domain_id'],
            'executables': where,
            'node_commands': online_run['commands'],
            'model': online_run['model'],
        },
        'online': {**online['summary'], 'answered': online['answered'], 'queries': len(ds.query_paths)},
        'transport': tr,
        'playback': online_run['play'],
        'offline': (
            {
                **offline['summary'],
                'row': offline['row'],
                'results': offline['results'],
                'extract_ms': offline['entry'].get('extract_ms'),
                'match_ms_per_pair': offline['entry'].get('match_ms_per_pair'),
            }
            if offline
            else None
        ),
        'comparison': comparison,
        'offline_error': offline_error,
        'node_exit_status': online_run['exit_status'],
        'timing_s': timing,
        'figures': {'pr': 'pr_online.png', 'examples': examples},
    }
    write_json(report, out / 'results_online.json')
    (out / 'results_online.md').write_text(online_markdown(report, online, offline, comparison))

    print(
        f'\n{name}: {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries, method {args.method} '
        f'(top-n {args.top_n}, prefilter {args.prefilter}, prefilter-k {args.prefilter_k}), '
        f'playback {online_run["play"]["mode"]}'
    )
    print(online_console(online, offline, comparison))
    print(
        f'wrote {out / "results_online.json"}, {out / "results_online.md"}, {out / "pr_online.png"}, '
        f'{len(examples)} match pictures'
        + (f', {out / "offline"}/' if offline else '')
        + f' in {timing["total"]:.0f} s'
    )
    return 1 if offline_error else 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)

    def go() -> int:
        try:
            return run(args, argv, progress_log(args.quiet))
        except SupervisorError as e:  # a node died or timed out: the run failed, the input was fine
            raise RunError(str(e)) from e

    return run_cli(PROG, go, interrupted='interrupted; the nodes were stopped', catch_signals=True)


if __name__ == '__main__':
    sys.exit(main())
