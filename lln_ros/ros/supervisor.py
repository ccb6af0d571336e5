"""A small `launch`: the node executables found as `ros2 run lln_ros X` finds them, started as it
starts them, on a private DDS domain, and stopped in order. Shared by lln-demo and the tests.

Children are started with subprocess's vfork() path: never pass preexec_fn (it forces fork(), and
fork() in a process where gRPC threads run, e.g. after pymilvus was used, can leave the child dead
before exec; test/conftest.py and test/test_harness.py say more). start_new_session is vfork-safe.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

NODE_EXECUTABLES = ('extractor', 'matcher')
BLAS_THREAD_VARS = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')


class SupervisorError(Exception):
    """A node could not be found or started, died, or did not answer in time."""


def ros_env(
    domain: int,
    log_dir: Path | None = None,
    threads: int | None = None,
    extra: dict | None = None,
    base: dict | None = None,
) -> dict:
    """Environment for child ROS processes: ROS_DOMAIN_ID `domain`, discovery on this host only
    (no ROS_LOCALHOST_ONLY / ROS_STATIC_PEERS from the caller), unbuffered output, ROS logs in
    log_dir. threads: the BLAS thread default of every child (a variable already set wins): two
    nodes on a shared CPU with spinning BLAS threads each contend badly."""
    env = dict(os.environ if base is None else base)
    env['ROS_DOMAIN_ID'] = str(int(domain))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('ROS_STATIC_PEERS', None)
    if log_dir is not None:
        env['ROS_LOG_DIR'] = str(log_dir)
    env['PYTHONUNBUFFERED'] = '1'
    if threads:
        for var in BLAS_THREAD_VARS:
            env.setdefault(var, str(threads))
    env.update(extra or {})
    return env


def localhost_discovery() -> None:
    """This process's own participants: the same discovery scope as its children (rmw reads it at
    init, so call this before the first rclpy.init)."""
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    for var in ('ROS_LOCALHOST_ONLY', 'ROS_STATIC_PEERS'):
        os.environ.pop(var, None)


def find_executables() -> tuple[dict, str]:
    """{'extractor', 'matcher', 'lln-bag'} -> command list, and where they were found.

    What `ros2 run lln_ros X` starts: <prefix>/lib/lln_ros/X of the ament prefix of lln_ros (a
    sourced colcon install or ROS workspace); else the console scripts beside this Python (the
    .venv of a pip install). lln-bag falls back to `python -m lln_ros.cli.bag`."""
    names = NODE_EXECUTABLES + ('lln-bag',)
    try:
        from ament_index_python.packages import get_package_prefix

        prefix = Path(get_package_prefix('lln_ros'))
        lib = prefix / 'lib' / 'lln_ros'
        if all(os.access(lib / n, os.X_OK) for n in NODE_EXECUTABLES):
            found = {n: [str(lib / n)] for n in names if os.access(lib / n, os.X_OK)}
            return _with_bag_player(found), f'ament prefix {prefix}'
    except Exception:  # noqa: BLE001  no AMENT_PREFIX_PATH, or lln_ros not in it
        pass
    bindir = Path(sys.executable).parent
    found = {n: [str(bindir / n)] for n in names if os.access(bindir / n, os.X_OK)}
    missing = [n for n in NODE_EXECUTABLES if n not in found]
    if missing:
        raise SupervisorError(
            f'cannot find the node executables {", ".join(missing)}: no ament prefix of lln_ros '
            f'and not in {bindir}; install the package (bash scripts/setup.sh) or source a '
            'colcon install'
        )
    return _with_bag_player(found), f'console scripts in {bindir}'


def _with_bag_player(found: dict) -> dict:
    found.setdefault('lln-bag', [sys.executable, '-m', 'lln_ros.cli.bag'])
    return found


class NodeProcess:
    """One executable started as `ros2 run lln_ros <exe> --ros-args ...` starts it, output into `log`.

    new_session: its own session, so a Ctrl-C in the terminal reaches only the supervisor, which
    stops the nodes in order (lln-demo); without it the child shares the caller's terminal (tests)."""

    def __init__(
        self,
        command: list,
        ros_args: list,
        env: dict,
        log: Path,
        name: str | None = None,
        cwd: Path | None = None,
        new_session: bool = False,
    ):
        self.command = [str(c) for c in command] + ['--ros-args', *ros_args]
        self.name = name or Path(self.command[0]).name
        self.log_path = Path(log)
        self._log = open(self.log_path, 'w')
        try:
            # no preexec_fn (module doc): subprocess keeps its vfork() path
            self.proc = subprocess.Popen(
                self.command,
                env=env,
                stdout=self._log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                cwd=cwd or self.log_path.parent,
                start_new_session=new_session,
            )
        except OSError as e:
            self._log.close()
            raise SupervisorError(f'cannot start {self.command[0]}: {e}') from e

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        """Everything the process has written so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors='replace')

    def tail(self, lines: int = 15) -> str:
        try:
            text = self.log().rstrip().splitlines()
        except OSError:
            return ''
        return '\n'.join(f'    {line}' for line in text[-lines:])

    def died(self) -> str:
        """Why it is gone, with the end of its log (for an error message)."""
        return f'node {self.name} exited with status {self.proc.returncode}; the end of {self.log_path}:\n{self.tail()}'

    def stop(self, timeout: float = 10.0) -> int:
        """Ctrl-C, as a user would; SIGKILL if it does not exit. Returns the exit status."""
        return stop_all([self], timeout)[self.name]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if not self._log.closed:
            self._log.close()

    kill9 = kill


def stop_all(procs: list[NodeProcess], timeout: float = 10.0) -> dict:
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


def run_to_end(command: list, env: dict, cwd: Path, log: Path, while_running) -> int:
    """A helper process (e.g. `lln-bag play`) in its own session, output into `log`; while_running()
    is called until it exits (and may raise: the process is then stopped with SIGINT, then SIGKILL).
    Returns its exit status."""
    with open(log, 'w') as out:
        proc = subprocess.Popen(
            command,
            env=env,
            cwd=cwd,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        try:
            while proc.poll() is None:
                while_running()
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    return proc.returncode
