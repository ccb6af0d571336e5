"""lln-demo: build a map from one traverse and query it with another through the ROS 2 nodes.

    lln-demo --out DIR [--dataset SPEC] [--range START:END] [--download] [--fps HZ]
             [--method lln|act|rand|all|holistic] [--top-n 50] [--prefilter landmarks|holistic|exhaustive]
             [--prefilter-k 30]
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
     A worker process does it beside the online run from step 2 on (lln_ros.eval.demo_offline): the
     backbone features into the feature cache (--cache), then the evaluation; what is left when the
     nodes are done is shared from both ends of the list. On two cores the comparison then costs
     little more time than the online run itself. An --fps run leaves the CPU to the nodes and runs
     the offline side after them.

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
--fps HZ instead plays the bags at HZ frames per second with `lln-bag play` (what `ros2 bag play`
does); frames the extractor cannot keep up with are dropped by its newest-frame policy, counted and
reported (the extractors' /diagnostics `received`/`published`/`dropped`, the stamps in the map file,
the answers).

Bad input exits 2 with one line on stderr (before anything long runs); a failure while running
exits 1 with the node logs' tails (DIR/logs/); Ctrl-C exits 130. Every node started is stopped.

The pieces: lln_ros.cli.demo_nodes (the online run: bags, nodes, playback), lln_ros.ros.supervisor
(executables, environment, start / stop), lln_ros.ros.probe (collecting, paced playback),
lln_ros.eval.online (scoring, online vs offline), lln_ros.eval.demo_offline (the offline side,
beside the online run), lln_ros.eval.report and lln_ros.eval.figures (the one report stack lln-eval uses too).
This module is the pipeline.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from ..eval.demo_offline import OfflineRun, cache_dir, run_offline
from ..eval.online import compare, score_online
from ..eval.report import METRICS, online_console, online_markdown, transport_lines, write_answers, write_json
from ..ros.probe import HANDSHAKE_TRIES
from ..ros.supervisor import SupervisorError, find_executables
from .bag import DeprecatedAlias
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
from .demo_nodes import run_online

PROG = 'lln-demo'
NORDLAND_RANGE = (0.7, 1.0)
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
__all__ = ['METRICS', 'HANDSHAKE_TRIES', 'main']  # test_demo reads both constants


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
        '--fps',
        type=positive_float,
        metavar='HZ',
        help='play the bags at HZ frames/s with lln-bag play (default: paced by the extractor)',
    )
    p.add_argument(
        '--rate', dest='fps', type=positive_float, action=DeprecatedAlias, new='--fps', help='deprecated: --fps'
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

    # the offline side's backbone features, computed beside the online run (not with --fps: a fixed
    # rate is a promise the extractors must keep, so they get the CPU to themselves)
    job = None
    if args.offline and not args.fps:
        job = OfflineRun(ds, spec, args, out)
        log(
            f'{PROG}: offline: a worker process computes the features into {cache_dir(args, out)} and then '
            'evaluates, beside the online run'
        )
    try:
        online_run = run_online(ds, args, out, exes, log)
    except BaseException:
        if job is not None:
            job.stop()
        raise
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
            (f'--fps {args.fps:g} is faster than extraction{advice}, or omit --fps to pace the bags by the extractor')
            if args.fps
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
            offline = run_offline(ds, spec, args, out, log, job)
        except (KeyboardInterrupt, MemoryError):
            raise
        except Exception as e:  # noqa: BLE001  the online results are still written
            offline_error = f'{type(e).__name__}: {e}'
            print(f'{PROG}: error: the offline evaluation failed: {offline_error}', file=sys.stderr)
        else:
            timing['offline_after_online'] = offline['seconds']
            timing['offline_evaluate'] = offline['evaluate_seconds']
            if offline['cache_fill']:
                timing['offline_features_after_online'] = offline['cache_fill']['tail_seconds']
            comparison = compare(
                online,
                offline['ranked'],
                offline['scores'],
                offline['summary'],
                tr,
                models=(online_run['model'], offline['model']),
                prefilter=args.prefilter,
            )
        finally:
            if job is not None:
                job.stop()  # the worker is done unless the evaluation failed

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
                'feature_cache_fill': offline['cache_fill'],
                'evaluate_seconds': offline['evaluate_seconds'],
                'evaluation_done_before_online_end_s': offline.get('evaluation_done_before_online_end_s'),
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
