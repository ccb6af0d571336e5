"""Real ROS 2 processes for the tests: the colcon-installed executables, a DDS domain per test,
and an in-process probe node (its own rclpy Context) that publishes, collects and calls services."""
from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
_domains = itertools.count()


def ros_env(tmp_path: Path, extra: dict | None = None) -> dict:
    """Environment for child ROS processes: a domain of our own, discovery on this host only."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(1 + (os.getpid() * 7 + next(_domains)) % 100)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_LOG_DIR'] = str(tmp_path / 'ros_log')
    env['PYTHONUNBUFFERED'] = '1'
    env.update(extra or {})
    return env


def colcon_build(ws: Path) -> Path:
    """colcon build a clean copy of the tracked (and untracked, not ignored) sources; returns install/."""
    colcon = VENV_BIN / 'colcon'
    if not colcon.exists():
        raise RuntimeError('colcon is not installed in the test environment (scripts/setup.sh installs it)')
    src = ws / 'src' / 'lln_ros'
    files = subprocess.run(['git', 'ls-files', '--cached', '--others', '--exclude-standard'], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        if (REPO / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / f, src / f)
    out = subprocess.run([str(colcon), '--log-base', str(ws / 'log'), 'build', '--base-paths', str(ws / 'src'),
                          '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install')],
                         cwd=ws, capture_output=True, text=True, timeout=600)
    if out.returncode:
        raise RuntimeError(f'colcon build failed:\n{out.stdout}\n{out.stderr}')
    return ws / 'install'


def installed_env(install: Path, env: dict) -> dict:
    """What sourcing install/setup.bash does in a real ROS install (no hook sets it here)."""
    prefix = install / 'lln_ros'
    env = dict(env)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(p for p in (str(prefix), env.get('AMENT_PREFIX_PATH', '')) if p)
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(prefix / 'lib' / 'python3.11' / 'site-packages'), env.get('PYTHONPATH', '')) if p)
    return env


class RosProcess:
    """An executable started as `ros2 run lln_ros <exe> --ros-args ...` would start it."""

    def __init__(self, exe: Path, ros_args: list[str], env: dict, log: Path):
        self.log_path = log
        self._log = open(log, 'w')
        # No preexec_fn: it forces fork() instead of vfork(), and fork() in a process where gRPC
        # (pymilvus) has live threads can leave the child dead before exec (conftest.py says more).
        self.proc = subprocess.Popen([str(exe), '--ros-args', *ros_args], env=env, stdout=self._log,
                                     stderr=subprocess.STDOUT, cwd=log.parent)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def stop(self, timeout: float = 10.0) -> int:
        """Ctrl-C, as a user would; SIGKILL if it does not exit."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def kill9(self) -> None:
        self.proc.kill()
        self.proc.wait()
        self._log.close()


class Probe:
    """A test-side node in its own Context on the test's domain."""

    def __init__(self, env: dict, name: str = 'test_probe'):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=int(env['ROS_DOMAIN_ID']))
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def publisher(self, msg_type, topic: str, depth: int = 100):
        return self.node.create_publisher(msg_type, topic, QoSProfile(depth=depth,
                                                                      reliability=ReliabilityPolicy.RELIABLE))

    def collect(self, msg_type, topic: str, decode=lambda m: m, depth: int = 1000) -> list:
        """Everything that arrives on `topic`, decoded, in arrival order."""
        got: list = []
        self.node.create_subscription(msg_type, topic, lambda m: got.append(decode(m)),
                                      QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))
        return got

    def spin_until(self, done, timeout: float, what: str = 'condition') -> None:
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.05)

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def wait_for_peers(self, publisher, topics: list[str] = (), timeout: float = 60.0) -> None:
        """Until `publisher` has a subscriber and every topic in `topics` has a publisher."""
        self.spin_until(lambda: (publisher is None or publisher.get_subscription_count() > 0)
                        and all(self.node.count_publishers(t) > 0 for t in topics), timeout, 'peers')

    def call(self, srv_type, name: str, timeout: float = 30.0):
        client = self.node.create_client(srv_type, name)
        self.spin_until(client.service_is_ready, timeout, f'service {name}')
        future = client.call_async(srv_type.Request())
        self.spin_until(future.done, timeout, f'answer from {name}')
        return future.result()
