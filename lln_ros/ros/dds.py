"""The middleware configuration lln_ros ships for camera-sized images (no rclpy import: it must run
before rclpy.init, because Fast DDS reads its profile file when the first participant is created).

Fast DDS passes a message between processes of one host through the writer's shared-memory segment
(512 KiB by default); bigger messages fall back to UDP fragments on loopback, which best-effort
readers lose (docs/robot_integration.md "Camera-sized images"). config/fastdds_large_data.xml enlarges the segment.

    note = apply_large_data_profile()   # in a process that publishes images, before rclpy.init
    exit_if_teardown_hangs('lln-bag', 10.0)  # work done: a stuck participant deletion must not hang us
"""

from __future__ import annotations

import os
import re
import sys
import threading
from pathlib import Path

PROFILE_NAME = 'fastdds_large_data.xml'
# Fast DDS 2.x (Jazzy) reads the first, Fast DDS 3.x (Kilted and later) the second
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
DEFAULT_SEGMENT_BYTES = 512 * 1024  # Fast DDS's own shared-memory segment size


def shipped_profile() -> Path | None:
    """config/fastdds_large_data.xml of the installed package (share/lln_ros/config) or of the
    source checkout (editable install); None when neither is there."""
    candidates = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            candidates.append(Path(get_package_share_directory('lln_ros')) / 'config' / PROFILE_NAME)
        except (PackageNotFoundError, ValueError, OSError):  # OSError: no AMENT_PREFIX_PATH
            pass
    except ImportError:
        pass
    candidates.append(Path(__file__).resolve().parents[2] / 'config' / PROFILE_NAME)
    return next((p for p in candidates if p.is_file()), None)


def uses_fastdds(environ=os.environ) -> bool:
    """True when the RMW is Fast DDS (RMW_IMPLEMENTATION unset means the default, rmw_fastrtps_cpp)."""
    return environ.get('RMW_IMPLEMENTATION', '').strip() in ('', 'rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')


def segment_sizes(profile: str | os.PathLike) -> list[int]:
    """The <segment_size> values (bytes) of a Fast DDS XML profile; [] when it sets none or cannot be read."""
    try:
        text = Path(profile).read_text()
    except OSError:
        return []
    return [int(v) for v in re.findall(r'<segment_size>\s*(\d+)\s*</segment_size>', text)]


def apply_large_data_profile(environ=os.environ) -> tuple[str, str]:
    """Point Fast DDS at the shipped profile unless the user chose a profile (or another RMW).

    Returns (level, message) for the node's log: 'info' when the shipped profile or a user profile
    with a segment over 512 KiB is in effect, 'warn' when images over ~512 KB that this process
    publishes would go over UDP (and be lost with best-effort readers)."""
    if not uses_fastdds(environ):
        return 'info', (
            f"RMW {environ['RMW_IMPLEMENTATION']}: lln_ros's Fast DDS profile does not apply; see "
            "docs/robot_integration.md 'Camera-sized images' for that middleware's large-message settings"
        )
    chosen = next((environ[v] for v in PROFILE_VARIABLES if environ.get(v)), None)
    if chosen is None:
        profile = shipped_profile()
        if profile is None:
            return 'warn', (
                f'{PROFILE_NAME} not found (package not installed?): messages over 512 KiB this '
                'process publishes go over UDP and best-effort readers lose most of them'
            )
        for variable in PROFILE_VARIABLES:
            environ[variable] = str(profile)
        return 'info', f'Fast DDS profile {profile} (shared-memory segment {_mib(max(segment_sizes(profile)))})'
    sizes = segment_sizes(chosen)
    if not sizes or max(sizes) <= DEFAULT_SEGMENT_BYTES:
        return 'warn', (
            f'Fast DDS profile {chosen} sets no shared-memory segment over 512 KiB: camera-sized '
            f'images this process publishes go over UDP; see {PROFILE_NAME}'
        )
    return 'info', f'Fast DDS profile {chosen} (shared-memory segment {_mib(max(sizes))})'


def _mib(n: int) -> str:
    return f'{n / 2**20:g} MiB'


def exit_if_teardown_hangs(prog: str, seconds: float, status: int = 0, done: str = 'the work is done') -> None:
    """Arm a watchdog: if this process has not exited `seconds` from now, say so and exit `status`.

    For a process whose work is finished (messages acknowledged, map closed) when only the DDS
    teardown is left: Fast DDS can deadlock deleting a participant while a peer's participant goes
    away at the same instant (seen under load in CI: a player stuck after 'published 10 messages'),
    and whoever waits on the process (a script, a launch file, a test) would hang with it."""

    def give_up():
        print(f'{prog}: warning: DDS teardown did not finish within {seconds:g} s; exiting ({done})', file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)

    timer = threading.Timer(seconds, give_up)
    timer.daemon = True
    timer.start()
