"""run_node's teardown (lln_ros.nodes.common.join_executor): no callback of a MultiThreadedExecutor
may still run when the node is closed and destroyed (a segfault: rclpy #255/#663).
A real rclpy executor and node in their own Context; a timer's callback stands in for a query being
answered when SIGINT arrives."""

from __future__ import annotations

import threading
import time

import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from lln_ros.nodes.common import join_executor
from ros_harness import ros_env


def test_join_executor_waits_for_the_running_callback(tmp_path):
    ctx = rclpy.Context()
    rclpy.init(
        context=ctx, domain_id=int(ros_env(tmp_path)['ROS_DOMAIN_ID']), signal_handler_options=SignalHandlerOptions.NO
    )
    started, finished = threading.Event(), threading.Event()

    def slow_callback():
        if started.is_set():
            return
        started.set()
        time.sleep(0.5)  # a query being answered
        finished.set()

    node = rclpy.create_node('teardown_probe', context=ctx)
    try:
        node.create_timer(0.01, slow_callback)
        executor = MultiThreadedExecutor(num_threads=2, context=ctx)
        executor.add_node(node)
        stop = threading.Event()

        def spin():
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.05)

        spinner = threading.Thread(target=spin, daemon=True)
        spinner.start()
        assert started.wait(10), 'the timer never fired'
        stop.set()  # what SIGINT does to rclpy.spin: the main loop ends while the callback runs
        spinner.join(5)
        assert not finished.is_set(), 'the callback ended before the teardown began: the test shows nothing'
        assert join_executor(executor, 10.0)
        assert finished.is_set(), 'join_executor returned while a callback still ran'
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
