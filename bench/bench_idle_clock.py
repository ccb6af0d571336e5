"""What an idle sim-time matcher costs: CPU of the matcher's executor while /clock runs at 40 Hz.

    python bench/bench_idle_clock.py [--seconds 10] [--hz 40] [--repeats 2]

Each row is a fresh process: a MatcherNode (use_sim_time, an empty SQLite map) spun by one executor
in a thread, and a publisher of its own rclpy context sending rosgraph_msgs/Clock at --hz, in a
DDS domain of its own on this host. CPU is the process's user + system time over --seconds, as a
percentage of one core (the publisher included: the same in every row). Executors:

    rclpy MultiThreadedExecutor   rclpy's, 2 threads (Jazzy 7.1.6: rclpy #1452)
    two_thread_executor           lln_ros.nodes.common's: a queued callback is submitted once

A benchmark, not a test: it prints a table; nothing asserts a figure.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lln_ros.ros.supervisor import ros_env  # noqa: E402

KINDS = {'rclpy': 'rclpy MultiThreadedExecutor', 'lln_ros': 'two_thread_executor'}

CHILD = r"""
import os, resource, sys, threading, time
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
kind, seconds, hz, map_path = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
rclpy.init()
from rclpy.executors import MultiThreadedExecutor
from lln_ros.nodes.common import two_thread_executor
from lln_ros.nodes.matcher import MatcherNode
node = MatcherNode(parameter_overrides=[
    Parameter('map_path', value=map_path), Parameter('use_sim_time', value=True),
    Parameter('descriptor_space', value='efficientnet_lite0/stage6/192')])
executor = two_thread_executor() if kind == 'lln_ros' else MultiThreadedExecutor(num_threads=2)
executor.add_node(node)
threading.Thread(target=executor.spin, daemon=True).start()
context = rclpy.Context()
rclpy.init(context=context)
clock = rclpy.create_node('bench_clock', context=context).create_publisher(
    Clock, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
time.sleep(2.0)  # discovery and the node's first rounds
msg, ns = Clock(), 1_700_000_000 * 10**9
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
while time.monotonic() - t0 < seconds:
    ns += int(1e9 / hz)
    msg.clock.sec, msg.clock.nanosec = divmod(ns, 10**9)
    clock.publish(msg)
    time.sleep(1.0 / hz)
r1, wall = resource.getrusage(resource.RUSAGE_SELF), time.monotonic() - t0
cpu = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)
print(f'{100.0 * cpu / wall:.1f}', flush=True)
os._exit(0)  # the measurement is taken; the DDS teardown is not what this bench measures
"""


def run(kind: str, seconds: float, hz: float, domain: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        env = ros_env(domain, log_dir=Path(tmp) / 'ros_log')
        out = subprocess.run(
            [sys.executable, '-c', CHILD, kind, str(seconds), str(hz), str(Path(tmp) / 'map.db')],
            env=env,
            capture_output=True,
            text=True,
            timeout=seconds + 120,
        )
    if out.returncode != 0:
        raise SystemExit(f'{kind} run failed ({out.returncode}):\n{out.stderr[-2000:]}')
    return float(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--hz', type=float, default=40.0)
    ap.add_argument('--repeats', type=int, default=2)
    args = ap.parse_args(argv)
    domain = 100 + os.getpid() % 60
    rows = []
    for repeat in range(args.repeats):
        for kind in KINDS:  # interleaved, so a change of machine load hits both kinds
            rows.append((kind, repeat, run(kind, args.seconds, args.hz, domain), os.getloadavg()[0]))
    print(f'idle matcher, use_sim_time, /clock at {args.hz:g} Hz, {args.seconds:g} s per row (CPU: % of one core)')
    print(f'{"executor":>28} {"run":>4} {"cpu %":>7} {"load":>5}')
    for kind, repeat, cpu, load in rows:
        print(f'{KINDS[kind]:>28} {repeat + 1:>4} {cpu:>7.1f} {load:>5.1f}')
    mean = {k: sum(c for kk, _, c, _ in rows if kk == k) / args.repeats for k in KINDS}
    print(
        f'mean: {KINDS["rclpy"]} {mean["rclpy"]:.1f}%, {KINDS["lln_ros"]} {mean["lln_ros"]:.1f}% '
        f'({mean["rclpy"] / max(mean["lln_ros"], 1e-9):.1f}x)'
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
