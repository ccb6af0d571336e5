"""Camera-sized images over real DDS (issue 16): a camera stand-in process publishing 640x480 and
1280x720 bgr8 frames of a real photograph at 30 Hz with sensor-data QoS (best effort), and the
colcon-installed extractor with the configuration the package ships, in another process.

The camera process gets exactly what docs/robot_integration.md tells a usb_cam / v4l2_camera user to export
(FASTRTPS_DEFAULT_PROFILES_FILE = share/lln_ros/config/fastdds_large_data.xml). Without it, Fast DDS
sends every frame over 512 KiB as UDP fragments and most are lost (measured: 26/60 at 640x480,
11/60 at 1280x720); with it, frames go through shared memory. Arrivals are the extractor's own
`received` counter on /diagnostics; the newest-frame policy may then skip frames it cannot extract
in time, which it counts as `dropped` (received = published + dropped).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from ros_harness import Probe, RosProcess, installed_env, ros_env

HERE = Path(__file__).resolve().parent
FRAMES = 100
HZ = 30.0
EXTRACTOR = '/lln_extractor'


def camera_env(share: Path, env: dict) -> dict:
    """The camera-side setting of docs/robot_integration.md: the shipped Fast DDS profile for the publishing process."""
    profile = share / 'config' / 'fastdds_large_data.xml'
    assert profile.is_file(), f'{profile} is not installed'
    return {**env, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile), 'FASTDDS_DEFAULT_PROFILES_FILE': str(profile)}


def test_camera_sized_frames_reach_the_extractor(colcon_install, tmp_path):
    install = colcon_install / 'lln_ros'
    share = install / 'share' / 'lln_ros'
    env = installed_env(colcon_install, ros_env(tmp_path))
    diag: dict[str, str] = {}
    statuses: list[tuple[bytes, str]] = []
    extractor = RosProcess(
        install / 'lib' / 'lln_ros' / 'extractor',
        [
            '--params-file',
            str(share / 'config' / 'extractor.yaml'),
            '-p',
            'num_threads:=1',
            '-p',
            'diagnostics_period:=0.2',
        ],
        env,
        tmp_path / 'extractor.log',
    )
    probe = Probe(env)
    try:

        def on_diag(msg):
            for status in msg.status:
                if status.name == EXTRACTOR:
                    diag.clear()
                    diag.update({kv.key: kv.value for kv in status.values})
                    statuses.append((status.level, status.message))

        probe.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
        counter = lambda key: int(diag.get(key, 0))  # noqa: E731
        probe.spin_until(lambda: diag or not extractor.alive(), 180, 'extractor diagnostics')
        assert extractor.alive(), extractor.log()
        results, missing_seen = {}, {}
        for width, height in ((640, 480), (1280, 720)):
            before = counter('received')
            missing_before, dds_lost_before = counter('frames_missing'), counter('dds_lost')
            camera = subprocess.Popen(
                [sys.executable, str(HERE / 'camera_publisher.py'), str(width), str(height), str(FRAMES), str(HZ)],
                env=camera_env(share, env),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            probe.spin_until(lambda: camera.poll() is not None, 120, f'camera {width}x{height}')
            out = camera.stdout.read()
            assert camera.returncode == 0 and f'published {FRAMES}' in out, out
            # every arrival is extracted or counted as dropped; wait for the last extraction
            probe.spin_until(
                lambda: (
                    counter('published') + counter('dropped') + counter('bad_image') >= counter('received')
                    and counter('received') > before
                ),
                60,
                'the extractor to finish its backlog',
            )
            probe.spin_for(0.5)
            results[(width, height)] = counter('received') - before
            missing_seen[(width, height)] = max(
                counter('frames_missing') - missing_before, counter('dds_lost') - dds_lost_before
            )
            print(f'{width}x{height}: {results[(width, height)]} of {FRAMES} received; totals {diag}')
        assert extractor.alive(), extractor.log()
        for (width, height), received in results.items():
            # best effort through shared memory still loses a frame when the reader is descheduled past
            # its history (CI of stop 33, beside other jobs: 97 of 100 at 640x480, all 3 counted missing):
            # a loss passes only if the node saw and counted it (one at the very end leaves no gap), and
            # never more than 5%
            lost = FRAMES - received
            assert received >= 0.95 * FRAMES and lost <= max(1, missing_seen[(width, height)]), (
                f'{width}x{height}: {received} of {FRAMES} frames reached the extractor, '
                f'{missing_seen[(width, height)]} counted missing; {diag}\n{extractor.log()[-2000:]}'
            )
        assert counter('bad_image') == 0, diag
        assert counter('received') == counter('published') + counter('dropped'), diag
        if counter('dropped'):  # the newest-frame policy's skips are visible, with the reason
            assert any(lvl == DiagnosticStatus.WARN and 'newest-frame' in msg for lvl, msg in statuses), statuses

        # a camera without the profile (Fast DDS defaults): frames are lost in the middleware, and the
        # extractor says so at level WARN, from the stamp gaps and from DDS's own sample-lost events
        # (under load a run of losses at the end of the stream leaves no gap behind it: measured 27 of
        # 60 lost frames as gaps, 58 as DDS events, in a fresh-clone make test beside a CPU hog)
        before, missing, dds_lost = counter('received'), counter('frames_missing'), counter('dds_lost')
        statuses.clear()
        plain = {
            k: v for k, v in env.items() if k not in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
        }
        camera = subprocess.run(
            [
                sys.executable,
                str(HERE / 'camera_publisher.py'),
                '1280',
                '720',
                str(FRAMES),
                str(HZ),
                '--stamp-start',
                '1700001000',
            ],
            env=plain,
            capture_output=True,
            text=True,
            timeout=180,
        )
        assert camera.returncode == 0, camera.stdout + camera.stderr
        probe.spin_for(1.5)
        lost = FRAMES - (counter('received') - before)
        print(
            f'1280x720 without the profile: {FRAMES - lost} of {FRAMES} received, '
            f'{counter("frames_missing") - missing} counted missing'
        )
        if lost >= 3:  # (on an idle machine loopback UDP may deliver most of them; then there is nothing to see)
            seen = max(counter('frames_missing') - missing, counter('dds_lost') - dds_lost)
            assert seen >= lost // 2, diag
            assert any(
                lvl == DiagnosticStatus.WARN and ('missing upstream' in msg or 'samples lost' in msg)
                for lvl, msg in statuses
            ), statuses
    finally:
        probe.close()
        code = extractor.stop()
    assert code == 0, extractor.log()
    # the node applied the shipped profile to itself too (its activation images are camera-sized)
    assert 'shared-memory segment 16 MiB' in extractor.log(), extractor.log()
