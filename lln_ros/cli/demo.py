"""lln-demo: build a map from one traverse and query it with another through the ROS 2 nodes.

    lln-demo --out DIR [--dataset SPEC] [--range START:END] [--download] [--rate HZ]
             [--method lln|act|rand|all|holistic] [--top-n 50] [--prefilter landmarks|holistic|exhaustive]
             [--prefilter-k 100]
             [--offline | --no-offline] [--check]

Without --dataset: the Nordland test split (summer = map, winter = queries, +-1 frame, the last 30%
of the route, `--range 0.7:1`) when ../shared/data is next to the repository; otherwise Gardens
Point Walking (day_right = map, night_right = queries) from --download-dir, fetched there with
--download; otherwise it asks for --dataset. SPEC: aligned:DIR_REF,DIR_QUERY[,TOL] |
vprbench:DIR | gardenspoint:DIR[,REF,QUERY] (the map traverse is the reference one).

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
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PROG = 'lln-demo'
NORDLAND_RANGE = (0.7, 1.0)
BAG_TOPIC = '/camera/image_raw'
MAP_IMAGE = '/lln_demo/map/image_raw'
QUERY_IMAGE = '/lln_demo/query/image_raw'
NOMINAL_HZ = 10.0                      # bag stamps in paced mode (the pace itself comes from the extractor)
DAY_NS = 86_400 * 1_000_000_000        # the query bag starts a day after the map bag: stamps never collide
METHODS = ('lln', 'act', 'rand', 'all', 'holistic')
METRICS = (('p_at_100r', 'P@100%R'), ('r_at_100p', 'R@100%P'), ('auc_pr', 'AUC-PR'),
           ('r_at_1', 'R@1'), ('r_at_5', 'R@5'), ('r_at_10', 'R@10'))
# what one run writes into DIR (removed at the start of a run, so a rerun is clean)
OUTPUTS = ('map_bag', 'query_bag', 'map.db', 'map.db-wal', 'map.db-shm', 'results_online.json',
           'results_online.md', 'answers_online.csv', 'rankings.npz', 'pr_online.png', 'offline', 'logs')
DEFAULT_DOWNLOAD_DIR = '~/.cache/lln_ros/gardens_point'
HANDSHAKE_TRIES = 5    # sends of a phase's first frame until it is seen downstream
HANDSHAKE_WAIT = 3.0   # seconds to wait for that, after the extractor published it
MAX_IN_FLIGHT = 10     # paced queries the matcher may have unanswered (its queue holds queue_depth 100)


class UsageError(Exception):
    """Bad command-line values (one line, exit 2)."""


class DemoError(Exception):
    """The online run failed (a node died, a timeout): exit 1."""


class Terminated(KeyboardInterrupt):
    """SIGTERM / SIGHUP: cleaned up like Ctrl-C."""


# ------------------------------------------------------------------------------------------ inputs

def repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path | None:
    """../shared/data beside the repository root (or beside the current folder), if present."""
    for base in (repo_root(), Path.cwd()):
        d = base.parent / 'shared' / 'data'
        if (d / 'nordland_trimmed' / 'summer').is_dir() and (d / 'nordland_trimmed' / 'winter').is_dir():
            return d
    return None


def nordland_spec(data: Path) -> str:
    root = data / 'nordland_trimmed'
    return f'aligned:{root / "summer"},{root / "winter"},1'


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'must be a number, got {text!r}') from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f'must be positive, got {text}')
    return value


def build_parser() -> argparse.ArgumentParser:
    lines = __doc__.strip().splitlines()
    p = argparse.ArgumentParser(prog=PROG, description=lines[0], epilog='\n'.join(lines[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', required=True, metavar='DIR', help='output folder (bags, map, results, plots, logs)')
    p.add_argument('--dataset', metavar='SPEC', help='default: the Nordland test split, else Gardens Point')
    p.add_argument('--range', metavar='START:END',
                   help='fractions of an aligned dataset (default 0.7:1 for the default Nordland split)')
    p.add_argument('--download', action='store_true',
                   help='fetch Gardens Point Walking when it is the dataset and is not there yet')
    p.add_argument('--download-dir', default=DEFAULT_DOWNLOAD_DIR,
                   help=f'where the default Gardens Point dataset lives (default {DEFAULT_DOWNLOAD_DIR})')
    p.add_argument('--download-url', default=None, help='where --download fetches from (default: the public archive)')
    p.add_argument('--rate', type=positive_float, metavar='HZ',
                   help='play the bags at HZ frames/s with lln-bag play (default: paced by the extractor)')
    p.add_argument('--method', default='lln', choices=METHODS,
                   help='landmark selection of the extractor (lln, act, rand, all) or holistic (the matcher '
                        'ranks by the global descriptor alone); default lln')
    p.add_argument('--top-n', type=int, default=50, help='landmarks per image (default 50)')
    from ..landmark_index import PREFILTERS
    from ..retrieval import default_conf as retrieval_conf
    p.add_argument('--prefilter', default=retrieval_conf['prefilter'], choices=PREFILTERS,
                   help=f"first stage of the matcher and the offline run (default {retrieval_conf['prefilter']})")
    p.add_argument('--prefilter-k', type=int, default=retrieval_conf['prefilter_k'],
                   help=f"first-stage candidates reranked (default {retrieval_conf['prefilter_k']}; 0 = every map frame)")
    p.add_argument('--weights', default='', help="LLN head checkpoint (default '': the shipped head)")
    p.add_argument('--threads', type=int, default=1,
                   help='torch threads per extractor and offline, BLAS threads per node (default 1)')
    p.add_argument('--offline', action=argparse.BooleanOptionalAction, default=True,
                   help='also run the offline evaluator and compare (default on)')
    p.add_argument('--cache', metavar='DIR', help='offline feature cache (default DIR/cache/features)')
    p.add_argument('--examples', type=int, default=2, help='success and failure match pictures (default 2 each)')
    p.add_argument('--timeout', type=positive_float, default=120.0,
                   help='seconds to wait for a node (start, one frame, the last answers) (default 120)')
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
    from ..datasets import parse_range
    frac = parse_range(args.range)  # DatasetError (exit 2) on a bad --range
    if args.dataset:
        return args.dataset, frac, 'given with --dataset'
    data = shared_data_dir()
    if data is not None:
        return nordland_spec(data), frac or NORDLAND_RANGE, f'the Nordland test split in {data}'
    gp = Path(args.download_dir).expanduser()
    if (gp / 'day_right').is_dir() and (gp / 'night_right').is_dir():
        return f'gardenspoint:{gp}', frac, f'Gardens Point Walking in {gp}'
    if args.download:
        return f'gardenspoint:{gp}', frac, f'Gardens Point Walking, downloaded into {gp}'
    raise UsageError(f'no dataset: ../shared/data is not beside {repo_root()} and Gardens Point is not in {gp}; '
                     'give --dataset SPEC (e.g. aligned:MAP_DIR,QUERY_DIR,2), or add --download to fetch '
                     'Gardens Point Walking')


def load_dataset(spec: str, frac, args, log):
    """The checked Dataset (every image decoded); Gardens Point fetched when needed and allowed."""
    from .. import datasets
    from ..errors import DatasetError
    from .eval import load_dataset as eval_load
    from .eval import UsageError as EvalUsage
    kind = spec.partition(':')[0]
    if kind == 'loop':
        raise UsageError('loop: datasets are one sequence (mapping mode); lln-demo needs two traverses '
                         '(aligned:, vprbench: or gardenspoint:)')
    if frac is not None and kind != 'aligned':
        raise UsageError(f'--range applies to aligned: datasets only, not {kind}:')
    try:
        ds, _ = eval_load(spec, frac, args.download)
    except EvalUsage as e:
        raise UsageError(str(e)) from None
    if ds is None:  # gardenspoint:DIR without its folders, --download given
        from ..evaluation import GARDENS_POINT_URL, fetch_gardenspoint
        root = spec.partition(':')[2].split(',')[0]
        url = args.download_url or GARDENS_POINT_URL
        log(f'{PROG}: {root} lacks the Gardens Point folders; downloading {url}')
        fetch_gardenspoint(root, url, progress=not args.quiet)
        ds = datasets.parse_spec(spec)
    if ds.candidates is not None:
        raise DatasetError(f'{spec} is a loop dataset; lln-demo needs two traverses')
    return ds


# ----------------------------------------------------------------------------------- executables

def find_executables() -> tuple[dict, str]:
    """{'extractor', 'matcher', 'lln-bag'} -> command list, and where they were found.

    What `ros2 run lln_ros X` starts: <prefix>/lib/lln_ros/X of the ament prefix of lln_ros (a
    sourced colcon install or ROS workspace); else the console scripts beside this Python (the
    .venv of a pip install)."""
    names = ('extractor', 'matcher', 'lln-bag')
    try:
        from ament_index_python.packages import get_package_prefix
        prefix = Path(get_package_prefix('lln_ros'))
        lib = prefix / 'lib' / 'lln_ros'
        if all(os.access(lib / n, os.X_OK) for n in names[:2]):
            found = {n: [str(lib / n)] for n in names if os.access(lib / n, os.X_OK)}
            return fill_bag_player(found), f'ament prefix {prefix}'
    except Exception:  # noqa: BLE001  no AMENT_PREFIX_PATH, or lln_ros not in it
        pass
    bindir = Path(sys.executable).parent
    found = {n: [str(bindir / n)] for n in names if os.access(bindir / n, os.X_OK)}
    missing = [n for n in names[:2] if n not in found]
    if missing:
        raise DemoError(f'cannot find the node executables {", ".join(missing)}: no ament prefix of lln_ros '
                        f'and not in {bindir}; install the package (bash scripts/setup.sh) or source a '
                        'colcon install')
    return fill_bag_player(found), f'console scripts in {bindir}'


def fill_bag_player(found: dict) -> dict:
    found.setdefault('lln-bag', [sys.executable, '-m', 'lln_ros.cli.bag'])
    return found


# ------------------------------------------------------------------------------------ processes

class NodeProcess:
    """One node executable started as `ros2 run lln_ros <exe> --ros-args ...` starts it, in its own
    session (a Ctrl-C in the terminal reaches the demo, which stops the nodes in order)."""

    def __init__(self, name: str, command: list, ros_args: list, env: dict, log: Path, cwd: Path):
        self.name = name
        self.command = list(command) + ['--ros-args', *ros_args]
        self.log_path = log
        self._log = open(log, 'w')
        try:
            self.proc = subprocess.Popen(self.command, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, cwd=cwd, start_new_session=True)
        except OSError as e:
            self._log.close()
            raise DemoError(f'cannot start {self.command[0]}: {e}') from e

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 15) -> str:
        try:
            if not self._log.closed:
                self._log.flush()
            text = self.log_path.read_text(errors='replace').rstrip().splitlines()
        except OSError:
            return ''
        return '\n'.join(f'    {line}' for line in text[-lines:])

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if not self._log.closed:
            self._log.close()


def stop_all(procs: list, timeout: float = 10.0) -> dict:
    """SIGINT to every node at once (as Ctrl-C would), SIGKILL to those still running after `timeout`.
    Every node is gone when this returns, even when a second Ctrl-C arrives meanwhile (it is re-raised
    after the SIGKILLs). Returns {name: exit status}."""
    try:
        for p in procs:
            if p.alive():
                p.proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for p in procs:
            try:
                p.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    finally:
        for p in procs:
            p.kill()
    return {p.name: p.proc.returncode for p in procs}


def child_env(domain: int, out: Path, threads: int) -> dict:
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('ROS_STATIC_PEERS', None)
    env['ROS_LOG_DIR'] = str(out / 'logs' / 'ros')
    env['PYTHONUNBUFFERED'] = '1'
    for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        env.setdefault(var, str(threads))  # two nodes on a shared CPU: spinning BLAS threads contend
    return env


# ---------------------------------------------------------------------------------- the ROS side

class Graph:
    """The demo's own node (its own rclpy Context on the private domain): publishes the bags' frames,
    collects the extractors' landmarks, the matcher's candidates and matches, /diagnostics, and calls
    the matcher's ~/info."""

    def __init__(self, domain: int):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.rclpy = rclpy
        self.domain = domain
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('lln_demo', context=self.context, start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.watch: list[NodeProcess] = []
        self.landmarks = {'keyframes': {}, 'query': {}}   # stamp -> (centers (n, 2), cell (w, h))
        self.duplicates = {'keyframes': 0, 'query': 0, 'candidates': 0}
        self.candidates: dict = {}                          # query stamp -> structured array
        self.matches: dict = {}                             # query stamp -> structured array
        self.bad_messages: list[str] = []
        self.diag: dict = {}                                # node name -> {key: value}
        self._info_client = None

    def close(self) -> None:
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        finally:
            self.rclpy.try_shutdown(context=self.context)

    # --------------------------------------------------------------- domain

    def foreign_nodes(self, seconds: float) -> list[str]:
        """Nodes of other processes on this domain (another lln-demo's `lln_demo` too)."""
        self.spin_for(seconds)
        names = [f'{ns.rstrip("/")}/{n}' for n, ns in self.node.get_node_names_and_namespaces()]
        if self.node.get_fully_qualified_name() in names:
            names.remove(self.node.get_fully_qualified_name())
        return names

    # --------------------------------------------------------------- collecting

    def collect(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        for kind in ('keyframes', 'query'):
            self.node.create_subscription(PointCloud2, f'/{kind}', lambda m, k=kind: self._on_landmarks(k, m),
                                          reliable)
        self.node.create_subscription(PointCloud2, '/candidates', self._on_candidates, reliable)
        self.node.create_subscription(PointCloud2, '/matches', self._on_matches, reliable)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_landmarks(self, kind: str, msg) -> None:
        from .. import msgs
        stamp = msgs.stamp_to_ns(msg.header)
        try:
            rows = msgs.cloud_to_array(msg, msgs.LANDMARK_FIELDS[:4], f'{kind} cloud')
        except Exception as e:  # noqa: BLE001  one bad message is reported, never fatal here
            self.bad_messages.append(f'{kind} @ {stamp}: {e}')
            rows = None
        seen = self.landmarks[kind]
        if stamp in seen:
            self.duplicates[kind] += 1
            return
        if rows is None or len(rows) < 2:
            seen[stamp] = (None, None)
            return
        seen[stamp] = (np.stack([rows['u'][1:], rows['v'][1:]], axis=1).astype(np.float32),
                       (float(rows['w'][1]), float(rows['h'][1])))

    def _on_candidates(self, msg) -> None:
        from .. import msgs
        stamp = msgs.stamp_to_ns(msg.header)
        if stamp in self.candidates:
            self.duplicates['candidates'] += 1
            return
        try:
            self.candidates[stamp] = msgs.cloud_to_candidates(msg)
        except Exception as e:  # noqa: BLE001
            self.bad_messages.append(f'candidates @ {stamp}: {e}')
            self.candidates[stamp] = None

    def _on_matches(self, msg) -> None:
        from .. import msgs
        stamp = msgs.stamp_to_ns(msg.header)
        try:
            self.matches.setdefault(stamp, msgs.cloud_to_matches(msg))
        except Exception as e:  # noqa: BLE001
            self.bad_messages.append(f'matches @ {stamp}: {e}')

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            self.diag[status.name] = {kv.key: kv.value for kv in status.values}

    def counter(self, node: str, key: str) -> int:
        try:
            return int(self.diag.get(node, {}).get(key, 0))
        except ValueError:
            return 0

    # --------------------------------------------------------------- spinning

    def check_nodes(self) -> None:
        for p in self.watch:
            if not p.alive():
                raise DemoError(f'node {p.name} exited with status {p.proc.returncode}; the end of '
                                f'{p.log_path}:\n{p.tail()}')

    def spin_until(self, done, timeout: float, what: str, progress=None) -> None:
        """Spin until done(); DemoError on timeout or when a watched node dies. `progress()` returning
        a changing value restarts the timeout (a long run that keeps moving never times out)."""
        last = progress() if progress else None
        deadline = time.monotonic() + timeout
        next_check = 0.0
        while not done():
            now = time.monotonic()
            if now >= next_check:
                self.check_nodes()
                next_check = now + 0.5
                if progress is not None:
                    value = progress()
                    if value != last:
                        last, deadline = value, now + timeout
            if now > deadline:
                raise DemoError(f'timed out after {timeout:g} s waiting for {what}' + self._state() + self._tails())
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def _state(self) -> str:
        seen = {k: len(v) for k, v in self.landmarks.items()}
        return (f'\n  seen so far: landmarks {seen}, answers {len(self.candidates)}; node counters '
                f'{json.dumps(self.diag, sort_keys=True)}')

    def _tails(self) -> str:
        return ''.join(f'\n  the end of {p.log_path}:\n{p.tail(8)}' for p in self.watch)

    # --------------------------------------------------------------- services

    def info(self, timeout: float) -> dict:
        from std_srvs.srv import Trigger
        if self._info_client is None:
            self._info_client = self.node.create_client(Trigger, '/lln_matcher/info')
        self.spin_until(self._info_client.service_is_ready, timeout, 'the matcher service /lln_matcher/info')
        future = self._info_client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout, 'an answer from /lln_matcher/info')
        response = future.result()
        if not response.success:
            raise DemoError(f'/lln_matcher/info failed: {response.message}')
        return json.loads(response.message)

    # --------------------------------------------------------------- playing

    def image_publisher(self, topic: str):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image
        return self.node.create_publisher(Image, topic, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def play_paced(self, bag_path: Path, publisher, out_kind: str, stamps: list, timeout: float,
                   extractor: str, confirm, bar=None, backlog=None) -> dict:
        """Publish the bag's frames (the recorded CDR bytes, as a bag player does), each once the
        extractor has published the previous frame's landmarks on `out_kind`: its one-frame mailbox
        never holds two frames, so none is dropped. backlog: a count of what the next node has not
        finished (unanswered queries); frames wait while it is MAX_IN_FLIGHT or more, so a matcher
        slower than the extractor (prefilter_k 0 on a large map) never overflows its queue.

        Frame 0 is a handshake: seeing every endpoint in the graph does not mean the extractor's
        writer has matched the matcher's reader yet (discovery is not symmetric in time), and a
        volatile sample published before that is lost for good. So once the extractor has published
        frame 0, `confirm(stamp)` checks that it arrived downstream (the map counts a keyframe / the
        query is answered); if not, frame 0 is sent again (HANDSHAKE_TRIES times at most). Returns
        timing and the number of frames sent again."""
        from .. import bag
        seen = self.landmarks[out_kind]
        self.spin_until(lambda: publisher.get_subscription_count() > 0, timeout,
                        f'a subscriber on {publisher.topic_name}')
        t0 = time.monotonic()
        waits, resent = [], 0
        for i, (_topic, _type, stamp, raw) in enumerate(bag.read_raw(bag_path, [BAG_TOPIC])):
            if stamp != stamps[i]:
                raise DemoError(f'{bag_path}: frame {i} has stamp {stamp}, expected {stamps[i]}')
            t = time.monotonic()
            if i == 0:
                for attempt in range(HANDSHAKE_TRIES):
                    published = self.counter(extractor, 'published')
                    publisher.publish(bytes(raw))
                    self.spin_until(lambda s=stamp, n=published: s in seen or self.counter(extractor, 'published') > n,
                                    timeout, f'the landmarks of the first frame of {bag_path.name} on /{out_kind}')
                    if confirm(stamp):
                        break
                    resent += 1
                else:
                    raise DemoError(f'the first frame of {bag_path.name} never reached the matcher through '
                                    f'/{out_kind} ({HANDSHAKE_TRIES} tries)' + self._state() + self._tails())
                try:  # our own reader may match a little later than the matcher's
                    self.spin_until(lambda s=stamp: s in seen, HANDSHAKE_WAIT, 'our copy of the first landmarks')
                except DemoError:
                    pass
            else:
                if backlog is not None:
                    self.spin_until(lambda: backlog() < MAX_IN_FLIGHT, timeout, f'the matcher to catch up ({i})')
                publisher.publish(bytes(raw))
                self.spin_until(lambda s=stamp: s in seen, timeout,
                                f'the landmarks of frame {i} of {bag_path.name} on /{out_kind}')
            waits.append(time.monotonic() - t)
            if bar is not None:
                bar.update(1)
        total = time.monotonic() - t0
        return {'seconds': total, 'frames': len(waits), 'frames_per_s': len(waits) / total if total else None,
                'median_frame_ms': 1e3 * float(np.median(waits)) if waits else None, 'resent': resent}

    def wait_quietly(self, done, seconds: float) -> bool:
        try:
            self.spin_until(done, seconds, 'a confirmation')
            return True
        except DemoError:
            return False

    def play_fixed(self, player: list, bag_path: Path, topic: str, hz: float, out_kind: str, stamps: list,
                   env: dict, cwd: Path, timeout: float, log_path: Path, bar=None) -> dict:
        """`lln-bag play BAG --topic-remap /camera/image_raw:=TOPIC` at the recorded rate (HZ) in its own
        process, as `ros2 bag play` would; then wait for the extractor to publish what it got."""
        seen = self.landmarks[out_kind]
        cmd = player + ['play', str(bag_path), '--rate', '1', '--topic-remap', f'{BAG_TOPIC}:={topic}',
                        '--wait-subscribers', '1', '--wait-timeout', f'{timeout:g}']
        t0 = time.monotonic()
        with open(log_path, 'w') as log:
            proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=log, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True)
            try:
                shown = 0
                while proc.poll() is None:
                    self.check_nodes()
                    self.spin_for(0.1)
                    if bar is not None and len(seen) > shown:
                        bar.update(len(seen) - shown)
                        shown = len(seen)
            finally:
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
                    try:
                        proc.wait(5)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
        played = Path(log_path).read_text(errors='replace')
        if proc.returncode != 0:
            raise DemoError(f'lln-bag play {bag_path.name} failed (status {proc.returncode}):\n{played[-2000:]}')
        # the extractor may still be working on its last frame; stop when every frame is in or nothing moves
        wanted = set(stamps)
        try:
            self.spin_until(lambda: wanted <= set(seen), min(timeout, 15.0), 'the last landmarks',
                            progress=lambda: len(seen))
        except DemoError:
            pass  # frames the extractor dropped never come: counted by the caller
        if bar is not None:
            bar.update(len(seen) - bar.n)
        total = time.monotonic() - t0
        return {'seconds': total, 'frames': len(stamps), 'frames_per_s': len(stamps) / total if total else None,
                'rate_hz': hz}


# ------------------------------------------------------------------------------------ the online run

def pick_domain(requested: int | None, log) -> 'Graph':
    """A Graph on a domain where no other node is running on this host (unless one is requested)."""
    if requested is not None:
        return Graph(requested)
    start = (os.getpid() * 7919 + int(time.time())) % 100
    tried = []
    for step in range(8):
        domain = 1 + (start + step * 37) % 100
        graph = Graph(domain)
        others = graph.foreign_nodes(1.0)
        if not others:
            return graph
        tried.append(f'{domain} ({len(others)} nodes)')
        graph.close()
    raise DemoError(f'no free ROS_DOMAIN_ID found (busy: {", ".join(tried)}); pass --domain-id')


def run_online(ds, args, out: Path, exes: dict, log) -> dict:
    from .. import bag
    from ..bag import DEFAULT_START_NS
    from tqdm import tqdm

    timing = {}
    t = time.monotonic()
    hz = args.rate or NOMINAL_HZ
    log(f'{PROG}: writing {out / "map_bag"} ({len(ds.ref_paths)} frames) and {out / "query_bag"} '
        f'({len(ds.query_paths)} frames)')
    ref_stamps = bag.write_image_bag(ds.ref_paths, out / 'map_bag', BAG_TOPIC, rate=hz, start_ns=DEFAULT_START_NS)
    query_stamps = bag.write_image_bag(ds.query_paths, out / 'query_bag', BAG_TOPIC, rate=hz,
                                       start_ns=DEFAULT_START_NS + DAY_NS)
    timing['write_bags'] = time.monotonic() - t

    k = min(args.prefilter_k or len(ds.ref_paths), len(ds.ref_paths))
    ext_method = 'lln' if args.method == 'holistic' else args.method
    logs = out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    t = time.monotonic()
    # this process's own participant: the same discovery scope as the nodes (read by rmw at init)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    for var in ('ROS_LOCALHOST_ONLY', 'ROS_STATIC_PEERS'):
        os.environ.pop(var, None)
    graph = pick_domain(args.domain_id, log)
    procs: list[NodeProcess] = []
    result: dict = {}
    try:
        env = child_env(graph.domain, out, args.threads)
        log(f'{PROG}: starting the nodes on ROS_DOMAIN_ID={graph.domain} (localhost only); logs in {logs}')
        common = ['-p', 'diagnostics_period:=0.5']
        extractor_params = ['-p', 'reliability:=reliable', '-p', f'num_threads:={args.threads}',
                            '-p', f'method:={ext_method}', '-p', f'top_n:={args.top_n}', *common]
        if args.weights:
            extractor_params += ['-p', f'weights:={Path(args.weights).expanduser().resolve()}']
        procs.append(NodeProcess('matcher', exes['matcher'], [
            '-p', f'map_path:={(out / "map.db").resolve()}', '-p', 'mode:=localization',
            '-p', f'prefilter:={args.prefilter}', '-p', f'prefilter_k:={args.prefilter_k}', '-p', f'k:={k}',
            '-p', f'method:={"holistic" if args.method == "holistic" else "lln"}',
            '-p', 'min_score:=-1.0e9', *common], env, logs / 'matcher.log', out))
        procs.append(NodeProcess('extractor (map)', exes['extractor'], [
            '-r', '__node:=lln_extractor_map', '-r', f'image:={MAP_IMAGE}', '-r', 'landmarks:=/keyframes',
            *extractor_params], env, logs / 'extractor_map.log', out))
        procs.append(NodeProcess('extractor (query)', exes['extractor'], [
            '-r', '__node:=lln_extractor_query', '-r', f'image:={QUERY_IMAGE}', '-r', 'landmarks:=/query',
            *extractor_params], env, logs / 'extractor_query.log', out))
        graph.watch = procs
        graph.collect()
        map_pub = graph.image_publisher(MAP_IMAGE) if not args.rate else None
        query_pub = graph.image_publisher(QUERY_IMAGE) if not args.rate else None

        node = graph.node

        def ready() -> bool:
            return (node.count_subscribers(MAP_IMAGE) >= 1 and node.count_subscribers(QUERY_IMAGE) >= 1
                    and node.count_publishers('/keyframes') >= 1 and node.count_publishers('/query') >= 1
                    and node.count_subscribers('/keyframes') >= 2 and node.count_subscribers('/query') >= 2
                    and node.count_publishers('/candidates') >= 1)
        graph.spin_until(ready, args.timeout, 'the extractors and the matcher to come up')
        info = {}

        def model_known() -> bool:
            info.update(graph.info(args.timeout))
            return bool(info.get('model')) or graph.spin_for(0.3)
        graph.spin_until(model_known, args.timeout, "the matcher to learn the extractors' model")
        if info.get('keyframes'):
            raise DemoError(f'the map {info.get("path")} is not empty ({info["keyframes"]} keyframes)')
        # let the endpoints match: seeing every endpoint in the graph does not mean the extractors' writers
        # have matched the matcher's readers. Paced playback also checks the first frame of each phase;
        # lln-bag play (--rate) cannot, so it gets a longer head start.
        graph.spin_for(3.0 if args.rate else 1.0)
        timing['start_nodes'] = time.monotonic() - t
        model = info['model']
        log(f'{PROG}: nodes up in {timing["start_nodes"]:.1f} s; model {model.get("descriptor_space")}, '
            f'head {model.get("head", "?")}{"" if model.get("head_trained", True) else " (UNTRAINED)"}')

        # ---- phase 1: the map traverse -> keyframes
        mode = 'paced' if not args.rate else f'{args.rate:g} Hz'
        tick = 0.1 if sys.stderr.isatty() else 10.0  # progress lines in a log file: one per 10 s
        log(f'{PROG}: map: playing {len(ref_stamps)} frames ({mode}) -> lln_extractor_map -> keyframes')
        bar = tqdm(total=len(ref_stamps), desc='map', unit='frame', disable=args.quiet, file=sys.stderr,
                   mininterval=tick)
        try:
            if args.rate:
                play_map = graph.play_fixed(exes['lln-bag'], out / 'map_bag', MAP_IMAGE, hz, 'keyframes',
                                            ref_stamps, env, out, args.timeout, logs / 'play_map.log', bar)
            else:
                def map_has_it(_stamp) -> bool:
                    return graph.wait_quietly(lambda: graph.info(args.timeout).get('keyframes', 0) >= 1
                                              or graph.spin_for(0.2), HANDSHAKE_WAIT)
                play_map = graph.play_paced(out / 'map_bag', map_pub, 'keyframes', ref_stamps, args.timeout,
                                            '/lln_extractor_map', map_has_it, bar)
        finally:
            bar.close()
        expected = len(graph.landmarks['keyframes'])

        def stored() -> int:
            info.update(graph.info(args.timeout))
            return int(info.get('keyframes', 0))
        try:
            graph.spin_until(lambda: stored() >= expected or graph.spin_for(0.3), min(args.timeout, 30.0),
                             f'the matcher to store {expected} keyframes', progress=lambda: info.get('keyframes'))
        except DemoError as e:
            graph.check_nodes()
            log(f'{PROG}: warning: {str(e).splitlines()[0]}; the missing keyframes are counted as lost')
        map_info = dict(info)
        log(f'{PROG}: map: {map_info["keyframes"]} keyframes stored in {play_map["seconds"]:.1f} s')

        # ---- phase 2: the query traverse -> query -> candidates
        log(f'{PROG}: queries: playing {len(query_stamps)} frames ({mode}) -> lln_extractor_query -> query')
        bar = tqdm(total=len(query_stamps), desc='query', unit='frame', disable=args.quiet, file=sys.stderr,
                   mininterval=tick)
        try:
            if args.rate:
                play_query = graph.play_fixed(exes['lln-bag'], out / 'query_bag', QUERY_IMAGE, hz, 'query',
                                              query_stamps, env, out, args.timeout, logs / 'play_query.log', bar)
            else:
                play_query = graph.play_paced(
                    out / 'query_bag', query_pub, 'query', query_stamps, args.timeout, '/lln_extractor_query',
                    lambda stamp: graph.wait_quietly(lambda: stamp in graph.candidates, HANDSHAKE_WAIT), bar,
                    backlog=lambda: len(graph.landmarks['query']) - len(graph.candidates))
        finally:
            bar.close()
        sent = set(graph.landmarks['query'])
        try:
            graph.spin_until(lambda: sent <= set(graph.candidates), min(args.timeout, 30.0),
                             'the answers to every query', progress=lambda: len(graph.candidates))
        except DemoError as e:
            graph.check_nodes()
            log(f'{PROG}: warning: {str(e).splitlines()[0]}; the queries without an answer are counted as lost')

        # final counters: wait for a /diagnostics round that has seen everything
        names = ('/lln_extractor_map', '/lln_extractor_query', '/lln_matcher')
        try:
            graph.spin_until(lambda: graph.counter('/lln_extractor_map', 'received') >= len(ref_stamps)
                             and graph.counter('/lln_extractor_query', 'received') >= len(query_stamps)
                             and graph.counter('/lln_matcher', 'queries_answered') >= len(graph.candidates),
                             5.0, 'final /diagnostics')
        except DemoError:
            pass
        graph.spin_for(1.2)  # one more round (period 0.5 s): counters of the last frame are in
        final_info = graph.info(args.timeout)
        timing['map_phase'] = play_map['seconds']
        timing['query_phase'] = play_query['seconds']
        result = {
            'ref_stamps': ref_stamps, 'query_stamps': query_stamps,
            'landmarks': graph.landmarks, 'candidates': dict(graph.candidates), 'matches': dict(graph.matches),
            'diagnostics': {n: dict(graph.diag.get(n, {})) for n in names},
            'map_info': map_info, 'final_info': final_info, 'model': model,
            'duplicates': dict(graph.duplicates), 'bad_messages': list(graph.bad_messages),
            'play': {'map': play_map, 'query': play_query, 'mode': mode},
            'domain_id': graph.domain, 'k': k, 'timing': timing,
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


def stored_stamps(path: Path) -> list[int]:
    """Stamps (ns) of every keyframe in the map file, in storage order (read after the matcher stopped)."""
    from ..mapstore import MapStore
    with MapStore.open(str(path), create=False) as store:
        out = []
        for kid in store.ids():
            sec, nsec = store.get(kid).meta['stamp']
            out.append(int(sec) * 1_000_000_000 + int(nsec))
    return out


# ----------------------------------------------------------------------------------------- scoring

def score_online(ds, run: dict) -> dict:
    """Rankings (Q, k) and scores from the collected candidates, by stamps; transport accounting."""
    from .. import metrics
    ref_of = {s: i for i, s in enumerate(run['ref_stamps'])}
    query_of = {s: i for i, s in enumerate(run['query_stamps'])}
    q_count, k = len(run['query_stamps']), int(run['k'])
    ranked = np.full((q_count, k), -1, np.int64)
    scores = np.full((q_count, k), -np.inf, np.float32)
    holistic = np.full((q_count, k), np.nan, np.float32)
    unknown_keyframes, unknown_queries = 0, 0
    for stamp, cands in run['candidates'].items():
        q = query_of.get(stamp)
        if q is None:
            unknown_queries += 1
            continue
        if cands is None:
            continue
        n = min(len(cands), k)
        for j in range(n):
            r = ref_of.get(int(cands['stamp_sec'][j]) * 1_000_000_000 + int(cands['stamp_nanosec'][j]), -1)
            unknown_keyframes += r < 0
            ranked[q, j] = r
        scores[q, :n] = cands['score'][:n]
        holistic[q, :n] = cands['holistic_score'][:n]
    summary = metrics.summary(ranked, scores[:, 0], ds.gt)
    answered = int(sum(1 for s in run['query_stamps'] if run['candidates'].get(s) is not None))
    diag = run['diagnostics']
    ext_map, ext_query, matcher = (diag.get(n, {}) for n in ('/lln_extractor_map', '/lln_extractor_query',
                                                             '/lln_matcher'))
    as_int = lambda d, key: int(d.get(key, 0) or 0)  # noqa: E731
    stored = run['stored_stamps']
    stored_set = set(stored)
    lost_refs = [i for i, s in enumerate(run['ref_stamps']) if s not in stored_set]
    lost_queries = [i for i, s in enumerate(run['query_stamps']) if run['candidates'].get(s) is None]
    transport = {
        'map': {'frames': len(run['ref_stamps']),
                'extractor_received': as_int(ext_map, 'received'),
                'extractor_published': as_int(ext_map, 'published'),
                'extractor_dropped': as_int(ext_map, 'dropped'),
                'extractor_bad_image': as_int(ext_map, 'bad_image'),
                'landmarks_seen': len(run['landmarks']['keyframes']),
                'resent': int(run['play']['map'].get('resent', 0)),
                'keyframes_stored': int(run['map_info'].get('keyframes', 0)),
                'keyframes_in_map_file': len(stored), 'duplicate_keyframes': len(stored) - len(stored_set),
                'bad_keyframe': as_int(matcher, 'bad_keyframe'),
                'lost': len(lost_refs), 'lost_indices': lost_refs[:50]},
        'query': {'frames': len(run['query_stamps']), 'resent': int(run['play']['query'].get('resent', 0)),
                  'extractor_received': as_int(ext_query, 'received'),
                  'extractor_published': as_int(ext_query, 'published'),
                  'extractor_dropped': as_int(ext_query, 'dropped'),
                  'extractor_bad_image': as_int(ext_query, 'bad_image'),
                  'landmarks_seen': len(run['landmarks']['query']),
                  'answered': answered, 'queries_answered_counter': as_int(matcher, 'queries_answered'),
                  'bad_query': as_int(matcher, 'bad_query'),
                  'lost': len(lost_queries), 'lost_indices': lost_queries[:50]},
        'keyframes_in_map_at_end': int(run['final_info'].get('keyframes', 0)),
        'duplicates': run['duplicates'], 'unknown_keyframe_stamps': int(unknown_keyframes),
        'unknown_query_stamps': int(unknown_queries), 'bad_messages': run['bad_messages'][:20],
    }
    return {'ranked': ranked, 'scores': scores, 'holistic': holistic, 'summary': summary,
            'answered': answered, 'transport': transport}


JUMP = 1e-3  # relative S difference above which a query-candidate pair is not "the same up to rounding"


def compare(online: dict, off_ranked: np.ndarray, off_scores: np.ndarray, off_summary: dict,
            transport: dict) -> dict:
    """Online vs offline: metric by metric, query by query, and candidate by candidate (online k =
    prefilter_k, so both sides score the same holistic top-K); the cause of every difference."""
    on_ranked, on_scores = online['ranked'], online['scores']
    q = len(on_ranked)
    on_top, off_top = on_ranked[:, 0], off_ranked[:, 0]
    answered = on_top >= 0
    same = on_top == off_top
    differ = np.flatnonzero(answered & ~same)
    lost = int((~answered).sum())
    metric_diff = {key: (None if online['summary'][key] is None or off_summary.get(key) is None else
                         float(online['summary'][key]) - float(off_summary[key])) for key, _ in METRICS}
    agree = all(d is not None and abs(d) < 1e-9 for d in metric_diff.values())

    def scored(ranked, scores, i):
        return {int(r): float(v) for r, v in zip(ranked[i], scores[i]) if r >= 0 and math.isfinite(v)}
    rel_all, jumps, prefilter_sets = [], 0, 0
    for i in np.flatnonzero(answered):
        on, off = scored(on_ranked, on_scores, i), scored(off_ranked, off_scores, i)
        prefilter_sets += set(on) != set(list(off)[:len(on)])  # offline holistic ranks every ref
        for r in set(on) & set(off):
            rel = abs(on[r] - off[r]) / max(abs(off[r]), 1e-6)
            rel_all.append(rel)
            jumps += rel > JUMP
    causes = []
    for i in differ:
        on, off = scored(on_ranked, on_scores, i), scored(off_ranked, off_scores, i)
        a, b = int(on_top[i]), int(off_top[i])
        if a not in off or b not in on:
            causes.append({'query': int(i), 'online': a, 'offline': b, 'cause': 'prefilter',
                           'detail': f'{"online" if a not in off else "offline"} answer outside the other '
                                     "side's holistic top-K"})
            continue
        da, db = on[a] - off[a], on[b] - off[b]
        big = max(abs(da) / max(abs(off[a]), 1e-6), abs(db) / max(abs(off[b]), 1e-6)) > JUMP
        causes.append({'query': int(i), 'online': a, 'offline': b, 'cause': 'S jump' if big else 'near-tie',
                       'S_online': [on[a], on[b]], 'S_offline': [off[a], off[b]],
                       'detail': f'S(online answer) {off[a]:.3f} -> {on[a]:.3f}, S(offline answer) '
                                 f'{off[b]:.3f} -> {on[b]:.3f} (offline -> online)'})
    rel_all = np.asarray(rel_all)
    notes = []
    if lost:
        notes.append(f'{lost} queries got no answer online (lost in transport): they count as misses')
    if transport['map']['lost']:
        notes.append(f'{transport["map"]["lost"]} map frames never became keyframes')
    if len(differ):
        n_pre = sum(c['cause'] == 'prefilter' for c in causes)
        n_jump = sum(c['cause'] == 'S jump' for c in causes)
        n_tie = sum(c['cause'] == 'near-tie' for c in causes)
        parts = []
        if n_jump:
            parts.append(f'{n_jump} because the landmark similarity S of one contender changed by a whole '
                         'mutual pair (a mutual-nearest-neighbour pair gained or lost)')
        if n_pre:
            parts.append(f'{n_pre} at the holistic prefilter boundary (one answer is outside the other '
                         "side's top-K; the global-descriptor cosines there differ in the 5th decimal)")
        if n_tie:
            parts.append(f'{n_tie} near-ties of S decided by rounding')
        notes.append(f'{len(differ)} of {q} queries have another top-1 online than offline (' + '; '.join(parts) +
                     '). Not transport: both paths round features and descriptors to float16 at the same '
                     'places, but the backbone itself runs at another batch size online (1 frame) than in '
                     'the offline feature cache (a batch), and its kernels then differ in the last bits; a '
                     'value near a float16 rounding boundary can round the other way, and S is not '
                     'continuous in the descriptors (mutual nearest neighbours, offset mode), so where '
                     'neighbouring cells are almost identical (e.g. tiny upsampled frames) that flips a pair')
    if len(rel_all) and jumps:
        notes.append(f'Over all {len(rel_all)} query-candidate pairs scored on both sides, {jumps} '
                     f'({100 * jumps / len(rel_all):.2f}%) differ in S by more than {100 * JUMP:g}%; the '
                     f'median relative difference is {np.median(rel_all):.1e}')
    if not agree and not lost and not len(differ):
        notes.append('same top-1 for every query; the threshold metrics (R@100%P, AUC-PR) differ because '
                     'the top-1 scores differ slightly and reorder queries of almost equal score')
    both = answered & same & np.isfinite(on_scores[:, 0]) & np.isfinite(off_scores[:, 0])
    rel = (np.abs(on_scores[both, 0] - off_scores[both, 0])
           / np.maximum(np.abs(off_scores[both, 0]), 1e-6)) if both.any() else np.zeros(0)
    return {'agree': bool(agree), 'metric_diff': metric_diff, 'same_top1': int((answered & same).sum()),
            'queries': q, 'lost_queries': lost, 'differing_queries': causes[:100],
            'candidate_pairs_compared': int(len(rel_all)), 'candidate_pairs_jumped': int(jumps),
            'candidate_sets_differing': int(prefilter_sets),
            'candidate_rel_diff_median': float(np.median(rel_all)) if len(rel_all) else None,
            'score_rel_diff_median': float(np.median(rel)) if len(rel) else None,
            'score_rel_diff_max': float(rel.max()) if len(rel) else None,
            'notes': notes}


# ----------------------------------------------------------------------------------------- offline

def run_offline(ds, spec: str, args, out: Path, log) -> dict:
    from ..evaluation import evaluate
    from ..extractor import Extractor
    ext_method = 'lln' if args.method == 'holistic' else args.method
    extractor = Extractor({'top_n': args.top_n, 'method': ext_method, 'num_threads': args.threads,
                           'weights': str(Path(args.weights).expanduser().resolve()) if args.weights else ''})
    conf = {'methods': [args.method], 'top_n': args.top_n, 'prefilter': args.prefilter,
            'prefilter_k': args.prefilter_k, 'scale': 1.0,
            'timing_images': 3, 'timing_queries': 5, 'timing_repeats': 1, 'examples': args.examples,
            'heatmap_images': 4, 'cache_dir': args.cache or str(out / 'cache' / 'features'),
            'plots': True, 'progress': not args.quiet}
    t = time.monotonic()
    command = (f'lln-eval --dataset {shlex.quote(spec)} --methods {args.method} --top-n {args.top_n} '
               f'--prefilter {args.prefilter} --prefilter-k {args.prefilter_k} --out {shlex.quote(str(out / "offline"))}')
    run = evaluate([ds], extractor, conf, None, out / 'offline', specs=[spec], command=command, log=log)
    name = next(iter(run.datasets))
    row = next(iter(run.datasets[name].rankings))
    ranked, scores = run.datasets[name].rankings[row]
    entry = run.results['datasets'][name]['methods'][row]
    return {'ranked': ranked, 'scores': scores, 'row': row, 'summary': {key: entry[key] for key, _ in METRICS},
            'entry': entry, 'seconds': time.monotonic() - t, 'model': extractor.model_info,
            'results': str(out / 'offline' / 'results.json')}


# ----------------------------------------------------------------------------------------- output

def pct(x) -> str:
    return '–' if x is None or (isinstance(x, float) and not math.isfinite(x)) else f'{100 * x:.1f}'


def table(online: dict, offline: dict | None, comparison: dict | None, markdown: bool = False) -> str:
    head = ['metric (%)', 'online'] + (['offline', 'online − offline'] if offline else [])
    rows = []
    for key, label in METRICS:
        row = [label, pct(online['summary'][key])]
        if offline:
            d = comparison['metric_diff'][key]
            row += [pct(offline['summary'][key]), '–' if d is None else f'{100 * d:+.1f}']
        rows.append(row)
    q = len(online['ranked'])
    row = ['queries answered', f'{online["answered"]}/{q}']
    if offline:
        row += [f'{int((offline["ranked"][:, 0] >= 0).sum())}/{q}', '']
    rows.append(row)
    if offline:
        rows.append(['same top-1', f'{comparison["same_top1"]}/{q}', '', ''])
    if markdown:
        lines = ['| ' + ' | '.join(head) + ' |', '|' + '|'.join(['---'] + ['---:'] * (len(head) - 1)) + '|']
        lines += ['| ' + ' | '.join(r) + ' |' for r in rows]
        return '\n'.join(lines)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    fmt = lambda r: '  '.join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i])  # noqa: E731
                              for i, c in enumerate(r))
    return '\n'.join([fmt(head), '  '.join('-' * w for w in widths)] + [fmt(r) for r in rows])


def transport_lines(tr: dict) -> list[str]:
    m, q = tr['map'], tr['query']
    again = lambda t: (f' (+{t["resent"]} first frame sent again: it was published before the '  # noqa: E731
                       'extractor and the matcher had matched)' if t.get('resent') else '')
    dup = f', {m["duplicate_keyframes"]} DUPLICATES' if m.get('duplicate_keyframes') else ''
    return [f'map:   {m["frames"]} frames played{again(m)}; extractor received {m["extractor_received"]}, published '
            f'{m["extractor_published"]}, dropped {m["extractor_dropped"]}; landmarks seen {m["landmarks_seen"]}; '
            f'keyframes stored {m["keyframes_in_map_file"]} (refused {m["bad_keyframe"]}{dup})',
            f'query: {q["frames"]} frames played{again(q)}; extractor received {q["extractor_received"]}, published '
            f'{q["extractor_published"]}, dropped {q["extractor_dropped"]}; answered {q["answered"]} '
            f'(refused {q["bad_query"]})',
            f'lost in transport: {m["lost"]} map frames, {q["lost"]} queries']


def plot_pr(ds, online: dict, offline: dict | None, path: Path, title: str) -> None:
    from .. import metrics
    from ..evaluation import _pyplot
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5), dpi=110)
    curves = [('online (nodes)', online, '-', 'tab:blue')]
    if offline:
        curves.append(('offline (lln-eval)', offline, '--', 'tab:orange'))
    for label, res, style, colour in curves:
        prec, rec, _ = metrics.pr_curve(res['ranked'], res['scores'][:, 0], ds.gt)
        s = res['summary']
        ax.plot(np.r_[0.0, rec], np.r_[prec[:1] if len(prec) else [1.0], prec], style, color=colour, lw=1.6,
                label=f'{label}: P@100%R {pct(s["p_at_100r"])}%, AUC {pct(s["auc_pr"])}%')
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel('recall')
    ax.set_ylabel('precision')
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc='lower left')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_examples(ds, run: dict, online: dict, out: Path, count: int) -> list[dict]:
    """Query / keyframe pictures with the `matches` regions of the best candidate drawn (the
    landmarks outlined come from the extractors' clouds): the most confident successes and failures."""
    from types import SimpleNamespace
    from .. import metrics
    from ..image import load_image
    from ..plotting import plot_matches
    if count <= 0:
        return []
    ranked, scores = online['ranked'], online['scores']
    correct = metrics.top1_correct(ranked, ds.gt)
    order = np.argsort(-np.nan_to_num(scores[:, 0], neginf=-1e30), kind='stable')
    answered = ranked[:, 0] >= 0
    wins = [int(i) for i in order if correct[i]][:count]
    fails = [int(i) for i in order if answered[i] and not correct[i] and ds.gt[i].any()][:count]
    out_list = []
    for kind, queries in (('success', wins), ('failure', fails)):
        for j, q in enumerate(queries, 1):
            r = int(ranked[q, 0])
            qstamp, rstamp = run['query_stamps'][q], run['ref_stamps'][r]
            m = run['matches'].get(qstamp)
            if m is None:
                continue
            qc, qcell = run['landmarks']['query'].get(qstamp, (None, None))
            rc, rcell = run['landmarks']['keyframes'].get(rstamp, (None, None))
            qpts = np.stack([m['query_u'], m['query_v']], 1).astype(np.float32)
            rpts = np.stack([m['map_u'], m['map_v']], 1).astype(np.float32)
            if qc is None:
                qc, qcell = qpts, (float(m['cell_w'][0]) if len(m) else 1.0, float(m['cell_h'][0]) if len(m) else 1.0)
            if rc is None:
                rc, rcell = rpts, (float(m['cell_w'][0]) if len(m) else 1.0, float(m['cell_h'][0]) if len(m) else 1.0)

            def index_of(points, centers):
                if not len(points):
                    return np.zeros(0, np.int64)
                d = ((points[:, None, :] - centers[None, :, :]) ** 2).sum(-1)
                return d.argmin(1)
            pairs = {'query_index': index_of(qpts, qc), 'map_index': index_of(rpts, rc),
                     'similarity': np.asarray(m['similarity'], np.float32),
                     'weight': np.asarray(m['weight'], np.float32)}
            qset = SimpleNamespace(centers=qc, cell_size=np.array(qcell, np.float32), activation=None)
            rset = SimpleNamespace(centers=rc, cell_size=np.array(rcell, np.float32), activation=None)
            truth = np.flatnonzero(ds.gt[q])
            verdict = 'correct' if kind == 'success' else f'WRONG (true: {", ".join(map(str, truth[:5]))})'
            title = (f'online: query {q} ({Path(ds.query_paths[q]).name}) -> keyframe of ref {r} '
                     f'({Path(ds.ref_paths[r]).name}), {verdict}\nS = {scores[q, 0]:.2f}, {len(m)} matched region '
                     f'pairs from /matches (line opacity = offset weight)')
            name = f'matches_online_{kind}{j}_q{q}.png'
            plot_matches(load_image(str(ds.query_paths[q])), load_image(str(ds.ref_paths[r])), qset, rset, pairs,
                         str(out / name), title=title)
            out_list.append({'kind': kind, 'file': name, 'query': q, 'answer': r, 'score': float(scores[q, 0]),
                             'pairs': int(len(m))})
    return out_list


def write_answers(ds, run: dict, online: dict, offline: dict | None, path: Path) -> None:
    from .. import metrics
    correct = metrics.top1_correct(online['ranked'], ds.gt)
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['query', 'query_file', 'stamp_ns', 'top1_ref', 'top1_file', 'score', 'holistic_score',
                    'correct', 'true_refs'] + (['offline_top1_ref', 'offline_score'] if offline else []))
        for q, path_q in enumerate(ds.query_paths):
            r = int(online['ranked'][q, 0])
            truth = ' '.join(map(str, np.flatnonzero(ds.gt[q])[:10]))
            row = [q, Path(path_q).name, run['query_stamps'][q], r if r >= 0 else '',
                   Path(ds.ref_paths[r]).name if r >= 0 else '',
                   f'{online["scores"][q, 0]:.6g}' if r >= 0 else '',
                   f'{online["holistic"][q, 0]:.6g}' if r >= 0 else '', int(correct[q]), truth]
            if offline:
                ro = int(offline['ranked'][q, 0])
                row += [ro if ro >= 0 else '', f'{offline["scores"][q, 0]:.6g}' if ro >= 0 else '']
            w.writerow(row)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, Path):
        return str(x)
    return x


def markdown_report(report: dict, online: dict, offline: dict | None, comparison: dict | None) -> str:
    d, p, tr, t = report['dataset'], report['parameters'], report['transport'], report['timing_s']
    lines = ['# lln-demo results', '', 'Regenerate with:', '', '```bash', report['command'], '```', '',
             f'Dataset **{d["name"]}** (`{d["spec"]}`{", range " + d["range"] if d.get("range") else ""}): '
             f'{d["refs"]} map frames (keyframes), {d["queries"]} queries ({d["queries_with_match"]} with a '
             f'true match).', '',
             f'Through the nodes ({p["executables"]}): two extractors (method `{p["method"]}`, top-n '
             f'{p["top_n"]}, reliable image QoS) and the matcher in localization mode (prefilter '
             f'{p.get("prefilter", "holistic")}, prefilter_k {p["prefilter_k"]}, k {p["k"]}), ROS_DOMAIN_ID {p["domain_id"]} on localhost; playback '
             f'{p["playback"]}.', '',
             table(online, offline, comparison, markdown=True), '']
    if comparison:
        lines += [('**Online and offline agree on every metric.**' if comparison['agree'] else
                   '**Online and offline differ.**') + ' ' + ' '.join(n + '.' for n in comparison['notes']), '']
        if comparison['differing_queries']:
            lines += ['| query | online top-1 | offline top-1 | cause | detail |', '|---:|---:|---:|---|---|']
            lines += [f'| {c["query"]} | {c["online"]} | {c["offline"]} | {c["cause"]} | {c["detail"]} |'
                      for c in comparison['differing_queries'][:30]]
            lines += ['']
        if comparison['score_rel_diff_median'] is not None:
            lines += [f'Top-1 score, online vs offline, where the top-1 agrees: median relative difference '
                      f'{comparison["score_rel_diff_median"]:.2e}, max {comparison["score_rel_diff_max"]:.2e}.', '']
    lines += ['## Transport', ''] + [f'- {line}' for line in transport_lines(tr)] + ['']
    lines += ['## Timing', '', '| step | seconds |', '|---|---:|']
    lines += [f'| {k} | {v:.1f} |' for k, v in t.items() if v is not None]
    lines += ['']
    figs = report['figures']
    lines += ['## Figures', '', f'![PR curve]({figs["pr"]})', '']
    for ex in figs['examples']:
        lines.append(f'- {ex["kind"]}: [{ex["file"]}]({ex["file"]}) query {ex["query"]} -> ref {ex["answer"]}, '
                     f'S = {ex["score"]:.2f}, {ex["pairs"]} matched regions')
    if offline:
        lines += ['', 'Offline results and figures: [offline/results.md](offline/results.md).']
    return '\n'.join(lines) + '\n'


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
    log(f'{PROG}: dataset {name} ({why}): {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries '
        f'({ds.queries_with_match} with a true match); {spec}' + (f' --range {rng}' if rng else ''))
    if len(ds.query_paths) == 0:
        raise UsageError(f'{spec}: no queries left (every query frame is blank?)')
    log(f'{PROG}: nodes: {where}')
    if args.check:
        print(f'{PROG}: OK: {name}: {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries; '
              f'nodes from {where}; would write {args.out}')
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
        ms = [float(online_run['diagnostics'].get(n, {}).get('last_latency_ms', 0) or 0)
              for n in ('/lln_extractor_map', '/lln_extractor_query')]
        advice = f' (last extraction {max(ms):.0f} ms: play at most {800 / max(ms):.1f} Hz)' if max(ms) > 0 else ''
        why = (f'--rate {args.rate:g} is faster than extraction{advice}, or omit --rate to pace the bags by '
               'the extractor') if args.rate else 'this should not happen with paced playback'
        print(f'{PROG}: warning: the extractors dropped {dropped} frames: {why}', file=sys.stderr)

    offline, comparison, offline_error = None, None, None
    if args.offline:
        log(f'{PROG}: offline: the same dataset through lln_ros.evaluation (method {args.method}, top-n '
            f'{args.top_n}, prefilter-k {args.prefilter_k}) into {out / "offline"}')
        try:
            offline = run_offline(ds, spec, args, out, log)
        except (KeyboardInterrupt, MemoryError):
            raise
        except Exception as e:  # noqa: BLE001  the online results are still written
            offline_error = f'{type(e).__name__}: {e}'
            print(f'{PROG}: error: the offline evaluation failed: {offline_error}', file=sys.stderr)
        else:
            timing['offline'] = offline['seconds']
            comparison = compare(online, offline['ranked'], offline['scores'], offline['summary'], tr)
            for key in ('descriptor_space', 'head'):
                if offline['model'].get(key) != online_run['model'].get(key):
                    comparison['notes'].append(f'the offline {key} {offline["model"].get(key)} is not the '
                                               f'nodes\' {online_run["model"].get(key)}')
                    comparison['agree'] = False

    title = f'{name}: precision-recall (threshold on the top-1 score), method {args.method}'
    plot_pr(ds, online, offline, out / 'pr_online.png', title)
    examples = plot_examples(ds, online_run, online, out, args.examples)
    write_answers(ds, online_run, online, offline, out / 'answers_online.csv')
    arrays = {'online_ranked': online['ranked'], 'online_scores': online['scores'],
              'online_holistic': online['holistic'], 'gt': ds.gt}
    if offline:
        arrays.update(offline_ranked=offline['ranked'], offline_scores=offline['scores'])
    np.savez_compressed(out / 'rankings.npz', **arrays)
    timing['total'] = time.monotonic() - t0

    report = {
        'command': f'{PROG} ' + ' '.join(shlex.quote(a) for a in argv),
        'dataset': {'name': name, 'spec': spec, 'range': rng, 'chosen': why, 'refs': len(ds.ref_paths),
                    'queries': len(ds.query_paths), 'queries_with_match': ds.queries_with_match,
                    'info': {k: v for k, v in ds.info.items() if not k.endswith('_sizes')}},
        'parameters': {'method': args.method, 'top_n': args.top_n, 'prefilter': args.prefilter,
                       'prefilter_k': args.prefilter_k,
                       'k': online_run['k'], 'threads': args.threads, 'weights': args.weights,
                       'playback': online_run['play']['mode'], 'domain_id': online_run['domain_id'],
                       'executables': where, 'node_commands': online_run['commands'],
                       'model': online_run['model']},
        'online': {**online['summary'], 'answered': online['answered'], 'queries': len(ds.query_paths)},
        'transport': tr,
        'playback': online_run['play'],
        'offline': ({**offline['summary'], 'row': offline['row'], 'results': offline['results'],
                     'extract_ms': offline['entry'].get('extract_ms'),
                     'match_ms_per_pair': offline['entry'].get('match_ms_per_pair')} if offline else None),
        'comparison': comparison,
        'offline_error': offline_error,
        'node_exit_status': online_run['exit_status'],
        'timing_s': timing,
        'figures': {'pr': 'pr_online.png', 'examples': examples},
    }
    (out / 'results_online.json').write_text(json.dumps(_jsonable(report), indent=1, allow_nan=False) + '\n')
    (out / 'results_online.md').write_text(markdown_report(report, online, offline, comparison))

    print(f'\n{name}: {len(ds.ref_paths)} map frames, {len(ds.query_paths)} queries, method {args.method} '
          f'(top-n {args.top_n}, prefilter-k {args.prefilter_k}), playback {online_run["play"]["mode"]}')
    print(table(online, offline, comparison))
    print('\n'.join(transport_lines(tr)))
    if comparison is not None:
        print(('online and offline AGREE on every metric' if comparison['agree'] else
               'online and offline DIFFER') + ''.join(f'\n  - {n}' for n in comparison['notes']))
        for c in comparison['differing_queries'][:10]:
            print(f'    query {c["query"]}: online top-1 ref {c["online"]}, offline ref {c["offline"]}: '
                  f'{c["cause"]}: {c["detail"]}')
    print(f'wrote {out / "results_online.json"}, {out / "results_online.md"}, {out / "pr_online.png"}, '
          f'{len(examples)} match pictures' + (f', {out / "offline"}/' if offline else '') +
          f' in {timing["total"]:.0f} s')
    return 1 if offline_error else 0


def main(argv=None) -> int:
    from ..errors import LLNError
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))

    def terminate(signum, _frame):
        raise Terminated(f'signal {signum}')
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        try:
            previous[sig] = signal.signal(sig, terminate)
        except (ValueError, OSError):  # not the main thread
            pass
    try:
        return run(args, argv, log)
    except (UsageError, LLNError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return 2
    except DemoError as e:
        print(f'{PROG}: failed: {e}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted; the nodes were stopped', file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == '__main__':
    sys.exit(main())
