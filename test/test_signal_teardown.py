"""SIGINT to a node in the middle of its work: run_node ends with status 0, never -11.

rclpy's own SIGINT handler raises KeyboardInterrupt in the main thread while rclpy's signal thread
still walks the list of every SIGINT guard condition to trigger them; tearing the executor down
then frees that list under the walk (CI: the matcher exited -11 at SIGINT). run_node handles the
signals itself (lln_ros.nodes.common.stop_on_signals). The node here makes the walk long (20,000
guard conditions, destroyed at close as an executor's is) and keeps the main thread in Python
bytecode (a busy timer callback): with rclpy's handler this node exited -11 in 12 of 20 runs, with
run_node's in 0 of 20."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

from ros_harness import REPO, ros_env

NODE = textwrap.dedent(
    """
    import sys
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerGuardCondition
    from lln_ros.nodes.common import run_node

    class BusyNode(Node):
        def __init__(self):
            super().__init__('signal_teardown_probe')
            self.sigint_guards = [SignalHandlerGuardCondition() for _ in range(20000)]
            self.ticks = 0
            self.create_timer(0.001, self.tick)

        def tick(self):
            self.ticks += 1
            if self.ticks == 20:
                print('spinning', flush=True)
            for _ in range(100_000):  # the main thread in Python bytecode when the signal comes
                pass

        def close(self):
            for guard in self.sigint_guards:
                guard.destroy()
            print(f'closed after {self.ticks} ticks', flush=True)

    sys.exit(run_node(BusyNode, 'signal_teardown_probe'))
    """
)


def test_sigint_while_busy_exits_cleanly(tmp_path):
    script = tmp_path / 'busy_node.py'
    script.write_text(NODE)
    env = ros_env(tmp_path, extra={'PYTHONPATH': str(REPO)})
    for run in range(8):
        proc = subprocess.Popen(
            [sys.executable, str(script)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        try:
            line = proc.stdout.readline()
            assert line.strip() == 'spinning', f'run {run}: {line!r} {proc.stderr.read()}'
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, f'run {run}: exit {proc.returncode}\n{err[-3000:]}'
        assert out.startswith('closed after'), out
