"""The ROS 2 package contract: colcon builds it, the ament index finds it, and the executables
that `ros2 run lln_ros <exe>` would start exist in <prefix>/lib/lln_ros and run."""

import os
import subprocess
import sys
from pathlib import Path

from ros_harness import installed_env


def test_ament_index_and_executables(colcon_install, tmp_path):
    env = installed_env(colcon_install, dict(os.environ))
    code = (
        'from ament_index_python.packages import get_package_prefix, get_package_share_directory;'
        "print(get_package_prefix('lln_ros')); print(get_package_share_directory('lln_ros'))"
    )
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    prefix, share = out.stdout.split()
    assert Path(prefix) == colcon_install / 'lln_ros'
    assert (Path(share) / 'package.xml').is_file()
    assert (Path(share) / 'config' / 'extractor.yaml').is_file() and (Path(share) / 'config' / 'matcher.yaml').is_file()
    for name in ('extractor', 'matcher', 'lln-match', 'lln-bag'):
        exe = Path(prefix) / 'lib' / 'lln_ros' / name
        assert exe.is_file() and os.access(exe, os.X_OK), f'ros2 run lln_ros {name} would not find {exe}'
    # the installed copy runs (not the editable source tree): cwd elsewhere, PYTHONPATH to the install
    exe = Path(prefix) / 'lib' / 'lln_ros' / 'lln-match'
    out = subprocess.run([str(exe), '--help'], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and 'lln-match' in out.stdout, out.stderr
    out = subprocess.run(
        [sys.executable, '-c', 'import lln_ros; print(lln_ros.__file__)'],
        env=env,
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert str(colcon_install) in out.stdout
