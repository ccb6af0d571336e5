"""The ROS 2 package contract: colcon builds it, the ament index finds it, and the executables
that `ros2 run lln_ros <exe>` would start exist in <prefix>/lib/lln_ros and run."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

VENV_BIN = Path(sys.executable).parent


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    colcon = VENV_BIN / 'colcon'
    if not colcon.exists():
        pytest.fail('colcon is not installed in the test environment (scripts/setup.sh installs it)')
    ws = tmp_path_factory.mktemp('ws')
    src = ws / 'src' / 'lln_ros'
    # a clean copy of the tracked sources, as a user's workspace would hold them
    files = subprocess.run(['git', 'ls-files', '--cached', '--others', '--exclude-standard'], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        if (REPO / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / f, src / f)
    out = subprocess.run([str(colcon), '--log-base', str(ws / 'log'), 'build', '--base-paths', str(ws / 'src'),
                          '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install')],
                         cwd=ws, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    return ws / 'install'


def ros_env(install):
    prefix = install / 'lln_ros'
    env = dict(os.environ)
    # what sourcing install/setup.bash does in a real ROS install (no hook sets it here)
    env['AMENT_PREFIX_PATH'] = f'{prefix}{os.pathsep}{env.get("AMENT_PREFIX_PATH", "")}'.rstrip(os.pathsep)
    env['PYTHONPATH'] = f'{prefix / "lib" / "python3.11" / "site-packages"}{os.pathsep}{env.get("PYTHONPATH", "")}'
    return env


def test_ament_index_and_executables(colcon_install, tmp_path):
    env = ros_env(colcon_install)
    code = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory;"
            "print(get_package_prefix('lln_ros')); print(get_package_share_directory('lln_ros'))")
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    prefix, share = out.stdout.split()
    assert Path(prefix) == colcon_install / 'lln_ros'
    assert (Path(share) / 'package.xml').is_file()
    exe = Path(prefix) / 'lib' / 'lln_ros' / 'lln-match'
    assert exe.is_file() and os.access(exe, os.X_OK)
    # the installed copy runs (not the editable source tree): cwd elsewhere, PYTHONPATH to the install
    out = subprocess.run([str(exe), '--help'], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and 'lln-match' in out.stdout, out.stderr
    out = subprocess.run([sys.executable, '-c', 'import lln_ros; print(lln_ros.__file__)'], env=env,
                         capture_output=True, text=True, cwd=tmp_path)
    assert str(colcon_install) in out.stdout
