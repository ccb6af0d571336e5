"""Does the extractor node keep up with a 30 Hz camera? A real node process, a real DDS stream.

    python bench/bench_node_rate.py [--seconds 60] [--hz 30] [--runtime onnxruntime|torch]
                                    [--threads 0] [--reliable] [--json]

Starts `extractor` (the installed console script, as `ros2 run lln_ros extractor` would, in a DDS
domain of its own on this host; test/ros_harness.py) with the packaged YAML and the default runtime
(unless --runtime), then publishes 384x288 rgb8 images (real frames: rtabmap_loop from ../shared/data,
else views of a photograph shipped in matplotlib) at --hz for --seconds, and counts:

    sent        images this script published
    received    images the node took in (its /diagnostics counter; best-effort DDS may lose some)
    published   landmark sets the node published, and dropped = frames replaced while it was busy
    kept up     published / received: 1.0 = every frame that arrived was extracted

plus the end-to-end latency (image stamp -> landmarks here) and the load average during the run.
A benchmark, not a test: it prints a table (or --json); nothing asserts a rate.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))
sys.path.insert(0, str(REPO / 'bench'))

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import Image, PointCloud2  # noqa: E402

from lln_ros.ros import msgs  # noqa: E402
from ros_harness import VENV_BIN, Probe, RosProcess, ros_env  # noqa: E402

NODE = '/lln_extractor'


def frames(width: int = 384, height: int = 288) -> tuple[list[np.ndarray], str]:
    import cv2

    root = REPO.parent / 'shared' / 'data' / 'rtabmap_loop'
    if root.is_dir():
        from lln_ros.io.image import load_image

        images = [
            cv2.resize(load_image(str(root / f'{i}.jpg')), (width, height), interpolation=cv2.INTER_AREA)
            for i in range(1, 85)
        ]
        return images, f'rtabmap_loop (84 frames, 512x384 resized to {width}x{height})'
    from bench_core import photo_views

    return photo_views(30, width, height), f'30 views of grace_hopper.jpg at {width}x{height}'


def run(seconds: float, hz: float, runtime: str | None, threads: int, reliable: bool) -> dict:
    images, source = frames()
    tmp = Path(tempfile.mkdtemp(prefix='lln_rate_'))
    env = ros_env(tmp)
    args = [
        '--params-file',
        str(REPO / 'config' / 'extractor.yaml'),
        '-p',
        f'num_threads:={threads}',
        '-p',
        'diagnostics_period:=0.5',
        '-p',
        f'reliability:={"reliable" if reliable else "best_effort"}',
    ]
    if runtime:
        args += ['-p', f'runtime:={runtime}']
    node = RosProcess(VENV_BIN / 'extractor', args, env, tmp / 'extractor.log')
    probe = Probe(env, 'rate_probe')
    diag: dict = {}
    model: list = []
    arrivals: list = []

    def on_diag(msg):
        for s in msg.status:
            if s.name == NODE:
                diag.update({kv.key: kv.value for kv in s.values})

    def on_landmarks(msg):
        arrivals.append((time.time_ns(), msgs.stamp_to_ns(msg.header)))

    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    probe.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    probe.node.create_subscription(PointCloud2, 'lln/landmarks', on_landmarks, 100)
    probe.node.create_subscription(
        String,
        'lln/model_info',
        lambda m: model.append(json.loads(m.data)),
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL),
    )
    pub = probe.node.create_publisher(
        Image,
        'image',
        QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT),
    )
    try:
        t0 = time.monotonic()
        probe.spin_until(
            lambda: not node.alive() or (pub.get_subscription_count() > 0 and model and diag), 300, 'the extractor node'
        )
        if not node.alive():
            raise RuntimeError(f'the extractor died:\n{node.log()}')
        startup = time.monotonic() - t0
        # warm-up: a second of frames that are not counted, so the first extraction is not timed
        base = {}
        for phase, length in (('warmup', 1.0), ('run', seconds)):
            if phase == 'run':
                probe.spin_for(1.0)
                base = {k: int(diag.get(k, 0)) for k in ('received', 'published', 'dropped')}
                arrivals.clear()
                load_start = os.getloadavg()
            sent, start = 0, time.monotonic()
            while time.monotonic() - start < length:
                due = start + sent / hz
                if time.monotonic() >= due:
                    img = images[sent % len(images)]
                    pub.publish(msgs.array_to_image(img, 'rgb8', msgs.make_header(time.time_ns(), 'camera')))
                    sent += 1
                else:
                    probe.executor.spin_once(timeout_sec=max(0.0, min(0.005, due - time.monotonic())))
            wall = time.monotonic() - start
        probe.spin_for(3.0)  # the last frames and the last /diagnostics
        counts = {k: int(diag.get(k, 0)) - base.get(k, 0) for k in ('received', 'published', 'dropped')}
        lat = np.array([(a - s) / 1e6 for a, s in arrivals]) if arrivals else np.zeros(1)
        return {
            'seconds': wall,
            'hz': hz,
            'source': source,
            'sent': sent,
            'sent_hz': sent / wall,
            **counts,
            'landmarks_here': len(arrivals),
            'kept_up': counts['published'] / max(counts['received'], 1),
            'published_hz': counts['published'] / wall,
            'latency_ms_p50': float(np.median(lat)),
            'latency_ms_p90': float(np.percentile(lat, 90)),
            'runtime': model[0].get('runtime') if model else None,
            'threads': threads,
            'reliable': reliable,
            'startup_s': startup,
            'load_average_start': list(load_start),
            'load_average_end': list(os.getloadavg()),
        }
    finally:
        probe.close()
        node.stop()


def table(r: dict) -> str:
    rows = [
        ('runtime (from model_info)', f'{r["runtime"]}, num_threads {r["threads"]}'),
        ('frames', r['source']),
        ('stream', f'{r["seconds"]:.1f} s at {r["hz"]:g} Hz, {"reliable" if r["reliable"] else "best effort"}'),
        ('sent', f'{r["sent"]} ({r["sent_hz"]:.1f} Hz)'),
        ('received by the node', str(r['received'])),
        ('published by the node', f'{r["published"]} ({r["published_hz"]:.1f} Hz)'),
        ('dropped (newest-frame mailbox)', str(r['dropped'])),
        ('kept up (published / received)', f'{r["kept_up"]:.3f}'),
        ('latency image -> landmarks, p50 / p90', f'{r["latency_ms_p50"]:.1f} / {r["latency_ms_p90"]:.1f} ms'),
        ('load average (1/5/15 min) at start', ', '.join(f'{v:.1f}' for v in r['load_average_start'])),
        ('load average at end', ', '.join(f'{v:.1f}' for v in r['load_average_end'])),
    ]
    w = max(len(a) for a, _ in rows)
    return '\n'.join(
        [f'| {"what":<{w}} | extractor node |', f'|{"-" * (w + 2)}|---|'] + [f'| {a:<{w}} | {b} |' for a, b in rows]
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--seconds', type=float, default=60.0, help='length of the stream (default 60)')
    p.add_argument('--hz', type=float, default=30.0, help='camera rate (default 30)')
    p.add_argument('--runtime', default=None, help="extractor runtime (default: the node's default)")
    p.add_argument('--threads', type=int, default=0, help='num_threads parameter (default 0 = the default)')
    p.add_argument('--reliable', action='store_true', help='reliable DDS for the images (default best effort)')
    p.add_argument('--json', action='store_true')
    args = p.parse_args(argv)
    r = run(args.seconds, args.hz, args.runtime, args.threads, args.reliable)
    print(json.dumps(r) if args.json else table(r))
    return 0


if __name__ == '__main__':
    sys.exit(main())
