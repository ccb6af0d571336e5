#!/usr/bin/env python3
"""Loop-closure constraints from a running lln_matcher, one JSON object per line (docs/slam_integration.md).

    python scripts/loop_closure_client.py --min-score 46.1 [--min-inliers 15] [--min-gap 5] [--require-pose] \
        [--out closures.jsonl] \
        [--ros-args -r candidates:=/robot1/candidates -r matches:=/robot1/matches -p use_sim_time:=true]

Subscribes the matcher's `candidates` and `matches` (they share the query's header stamp and come on
two topics in either order), keeps the best candidate when it passes the thresholds
(lln_ros.core.loop_closure.LoopClosureFilter) and writes {query_stamp_ns, keyframe_stamp_ns, keyframe_id,
score, holistic_score, inliers, regions, transform, covariance, metric} lines: what a pose-graph back
end needs to look up its two poses by stamp and add the edge. transform (4x4 T(keyframe <- query),
camera optical frames) and covariance (6x6 of [x y z roll pitch yaw]) are the matcher's accepted
pose (verify + geometry; null otherwise); --require-pose keeps only answers that have one.
On Ctrl-C it prints how many answers were accepted and why the others were not.
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ros_args = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
    own = argv[: len(argv) - len(ros_args)]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--min-score', type=float, default=0.0, help='S of the best candidate (default 0: any)')
    p.add_argument('--min-inliers', type=int, default=0, help='verify mode: RANSAC inliers (default 0: any)')
    p.add_argument(
        '--min-gap',
        type=float,
        default=0.0,
        metavar='S',
        help='seconds between query and keyframe stamps below which it is odometry, not a loop',
    )
    p.add_argument('--require-pose', action='store_true', help='only answers with an accepted pose')
    p.add_argument('--out', help='append the lines to this file instead of stdout')
    p.add_argument('--count', type=int, default=0, help='exit after this many answers (default 0: run until Ctrl-C)')
    args = p.parse_args(own)

    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import PointCloud2

    from lln_ros.core.loop_closure import LoopClosureFilter
    from lln_ros.nodes.common import stop_on_signals
    from lln_ros.ros import msgs

    select = LoopClosureFilter(
        {
            'min_score': args.min_score,
            'min_inliers': args.min_inliers,
            'min_gap_s': args.min_gap,
            'require_pose': args.require_pose,
        }
    )
    out = open(args.out, 'a') if args.out else sys.stdout
    # Ctrl-C as the nodes take it: rclpy's handler races the teardown (see stop_on_signals)
    rclpy.init(args=['loop_closure_client', *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    stop = stop_on_signals()
    node = rclpy.create_node('lln_loop_closure_client')
    pending: dict[int, dict] = {}
    state = {'answers': 0, 'accepted': 0}

    def on_answer(msg: PointCloud2, kind: str) -> None:
        stamp = msgs.stamp_to_ns(msg.header.stamp)
        decode = msgs.cloud_to_candidates if kind == 'candidates' else msgs.cloud_to_matches
        try:
            entry = pending.setdefault(stamp, {})
            entry[kind] = decode(msg)
        except Exception as e:  # noqa: BLE001  a bad cloud is reported, never fatal
            node.get_logger().warning(f'{kind} at {stamp}: {e}')
            pending.pop(stamp, None)
            return
        while len(pending) > 100:
            pending.pop(next(iter(pending)))
        if len(entry) < 2:
            return
        del pending[stamp]
        state['answers'] += 1
        closure = select(stamp, entry['candidates'], entry['matches'])
        if closure is not None:
            state['accepted'] += 1
            print(json.dumps(closure.as_dict()), file=out, flush=True)

    node.create_subscription(PointCloud2, 'lln/candidates', lambda m: on_answer(m, 'candidates'), 100)
    node.create_subscription(PointCloud2, 'lln/matches', lambda m: on_answer(m, 'matches'), 100)
    try:
        while rclpy.ok() and not stop.is_set() and not (args.count and state['answers'] >= args.count):
            rclpy.spin_once(node, timeout_sec=0.1)
    except ExternalShutdownException:  # the context was shut down elsewhere (Ctrl-C: stop_on_signals)
        pass
    finally:
        print(
            f'loop_closure_client: {state["answers"]} answers, {state["accepted"]} loop closures accepted, '
            f'rejected: {select.rejected}',
            file=sys.stderr,
        )
        node.destroy_node()
        rclpy.try_shutdown()
        if args.out:
            out.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
