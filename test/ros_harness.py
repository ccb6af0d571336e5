"""Real ROS 2 processes for the tests, through the same supervisor and probe lln-demo uses
(lln_ros.ros.supervisor, lln_ros.ros.probe): the installed executables, a DDS domain per test, and an
in-process probe node (its own rclpy Context) that publishes, collects and calls services.

What is test-only stays here: a colcon build of the working tree, and the environment a sourced
install gives. Children start without preexec_fn (vfork, see lln_ros/ros/supervisor.py, conftest.py)."""

from __future__ import annotations

import fcntl
import itertools
import os
import shutil
import subprocess
import sys
from pathlib import Path

from lln_ros.ros import supervisor
from lln_ros.ros.probe import Probe as _Probe
from lln_ros.ros.supervisor import NodeProcess

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
_domains = itertools.count()

# Concurrent test runs on one host (two checkouts' suites, a helper's tests beside CI) must never share a
# DDS domain, or one run's nodes answer the other's probes. Each pytest process holds one of SLOTS
# lock files for its lifetime and cycles through its own DOMAINS_PER_SLOT domains (a new one per
# ros_env, so a test never meets a late-dying node of the one before).
SLOTS, DOMAINS_PER_SLOT = 8, 25  # domains 1..200 (Fast DDS maps domain ids up to 232 to UDP ports)
_slot_lock = None


def _slot() -> int | None:
    """This process's slot (held until it exits), or None when all are taken (then ids may collide)."""
    global _slot_lock
    if _slot_lock is None:
        folder = Path(os.environ.get('TMPDIR', '/tmp')) / 'lln_ros_test_domains'
        folder.mkdir(exist_ok=True)
        for slot in range(SLOTS):
            f = open(folder / f'slot{slot}.lock', 'w')
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                f.close()
                continue
            _slot_lock = (slot, f)
            break
        else:
            return None
    return _slot_lock[0]


__all__ = ['Probe', 'RosProcess', 'colcon_build', 'installed_env', 'ros_env']


def ros_env(tmp_path: Path, extra: dict | None = None) -> dict:
    """Environment for child ROS processes: a domain of our own, discovery on this host only."""
    slot = _slot()
    if slot is None:
        domain = 1 + (os.getpid() * 7 + next(_domains)) % (SLOTS * DOMAINS_PER_SLOT)
    else:
        domain = 1 + slot * DOMAINS_PER_SLOT + next(_domains) % DOMAINS_PER_SLOT
    return supervisor.ros_env(domain, log_dir=tmp_path / 'ros_log', extra=extra)


def colcon_build(ws: Path) -> Path:
    """colcon build a clean copy of the tracked (and untracked, not ignored) sources; returns install/."""
    colcon = VENV_BIN / 'colcon'
    if not colcon.exists():
        raise RuntimeError('colcon is not installed in the test environment (scripts/setup.sh installs it)')
    src = ws / 'src' / 'lln_ros'
    files = subprocess.run(
        ['git', 'ls-files', '--cached', '--others', '--exclude-standard'],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    for f in files:
        if (REPO / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / f, src / f)
    out = subprocess.run(
        [
            str(colcon),
            '--log-base',
            str(ws / 'log'),
            'build',
            '--base-paths',
            str(ws / 'src'),
            '--build-base',
            str(ws / 'build'),
            '--install-base',
            str(ws / 'install'),
        ],
        cwd=ws,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if out.returncode:
        raise RuntimeError(f'colcon build failed:\n{out.stdout}\n{out.stderr}')
    return ws / 'install'


def installed_env(install: Path, env: dict) -> dict:
    """What sourcing install/setup.bash does in a real ROS install (no hook sets it here)."""
    prefix = install / 'lln_ros'
    env = dict(env)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(p for p in (str(prefix), env.get('AMENT_PREFIX_PATH', '')) if p)
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(prefix / 'lib' / 'python3.11' / 'site-packages'), env.get('PYTHONPATH', '')) if p
    )
    return env


class RosProcess(NodeProcess):
    """An executable started as `ros2 run lln_ros <exe> --ros-args ...` would start it; its output in
    `log`, its working folder log's folder, in the test's session (Ctrl-C reaches it)."""

    def __init__(self, exe: Path, ros_args: list[str], env: dict, log: Path):
        super().__init__([exe], ros_args, env, log)


class Probe(_Probe):
    """The probe on the domain of a ros_env() environment."""

    def __init__(self, env: dict, name: str = 'test_probe'):
        super().__init__(env, name)
