"""Camera-sized images into the extractor over real DDS, with and without the shipped Fast DDS profile.

    .venv/bin/python bench/bench_large_images.py [--frames 100] [--hz 30]

A camera stand-in process (test/camera_publisher.py: sensor-data QoS, bgr8 frames of a real photo)
streams each size at --hz into `.venv/bin/extractor` (the packaged extractor.yaml, best effort),
once with the camera's environment as it comes (Fast DDS defaults: 512 KiB shared-memory segment)
and once with FASTRTPS_DEFAULT_PROFILES_FILE = config/fastdds_large_data.xml, as docs/robot_integration.md tells a
camera user to set. Prints frames received by the extractor's subscription (its /diagnostics
`received`) and how many of those it extracted / skipped under its newest-frame policy.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402

from ros_harness import Probe, RosProcess, ros_env  # noqa: E402

SIZES = ((480, 360), (640, 480), (1280, 720))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--frames', type=int, default=100)
    p.add_argument('--hz', type=float, default=30.0)
    args = p.parse_args()
    profile = REPO / 'config' / 'fastdds_large_data.xml'
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        env = ros_env(tmp)
        for var in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
            env.pop(var, None)
        exe = Path(sys.executable).parent / 'extractor'
        extractor = RosProcess(
            exe,
            [
                '--params-file',
                str(REPO / 'config' / 'extractor.yaml'),
                '-p',
                'num_threads:=1',
                '-p',
                'diagnostics_period:=0.2',
            ],
            env,
            tmp / 'extractor.log',
        )
        diag = {}

        def on_diag(msg):
            for s in msg.status:
                if s.name == '/lln_extractor':
                    diag.update({kv.key: kv.value for kv in s.values})

        probe = Probe(env)
        probe.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
        try:
            probe.spin_until(lambda: diag, 180, 'extractor diagnostics')
            count = lambda k: int(diag.get(k, 0))  # noqa: E731
            for camera_profile in (None, profile):
                for w, h in SIZES:
                    before = {k: count(k) for k in ('received', 'published', 'dropped')}
                    cam_env = dict(env)
                    if camera_profile:
                        cam_env['FASTRTPS_DEFAULT_PROFILES_FILE'] = cam_env['FASTDDS_DEFAULT_PROFILES_FILE'] = str(
                            camera_profile
                        )
                    cam = subprocess.run(
                        [
                            sys.executable,
                            str(REPO / 'test' / 'camera_publisher.py'),
                            str(w),
                            str(h),
                            str(args.frames),
                            str(args.hz),
                        ],
                        env=cam_env,
                        capture_output=True,
                        text=True,
                        timeout=300,
                    )
                    assert cam.returncode == 0, cam.stdout + cam.stderr
                    t_end = time.monotonic() + 30
                    probe.spin_until(
                        lambda: count('published') + count('dropped') >= count('received') or time.monotonic() > t_end,
                        60,
                        'backlog',
                    )
                    probe.spin_for(0.5)
                    d = {k: count(k) - before[k] for k in before}
                    rows.append(
                        (
                            f'{w}x{h}',
                            w * h * 3 / 1024,
                            'shipped profile' if camera_profile else 'Fast DDS default',
                            d['received'],
                            d['published'],
                            d['dropped'],
                        )
                    )
                    print(*rows[-1], flush=True)
        finally:
            probe.close()
            extractor.stop()
    load = os.getloadavg()
    print(
        f'\n{args.frames} frames per row at {args.hz:g} Hz, bgr8, sensor-data QoS; load average '
        f'{load[0]:.1f} on {os.cpu_count()} cores'
    )
    print('| frame | KiB | camera process | received by the extractor | extracted | skipped (newest-frame) |')
    print('|---|---|---|---|---|---|')
    for name, kib, mode, rec, pub, drop in rows:
        print(f'| {name} | {kib:.0f} | {mode} | {rec} / {args.frames} | {pub} | {drop} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
