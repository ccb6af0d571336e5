"""The matcher's metric side without rclpy (lln_ros.core.registration): odometry by stamp and its
refusals, keyframe gating, recent exclusion in seconds and metres, the pose fields of an answer and
the loop-closure filter passing the pose on."""

import math
import threading
import time

import numpy as np
import pytest

from lln_ros.core.counters import Counters
from lln_ros.core.loop_closure import LoopClosureFilter
from lln_ros.core.odometry import OdometryBuffer
from lln_ros.core.registration import POSE_FIELDS, OdomPose, Registration, best_raw_score, nan_fields, pose_from_parts
from lln_ros.errors import CameraError, PoseError
from lln_ros.io.camera import CameraModel

S = 1_000_000_000
CAM = CameraModel.from_camera_info({'width': 640, 'height': 480, 'k': [525, 0, 320, 0, 525, 240, 0, 0, 1]})


def odom(t_s, x=0.0, yaw_deg=0.0, frame='odom'):
    a = math.radians(yaw_deg) / 2
    return OdomPose(int(t_s * S), pose_from_parts([x, 0, 0], [0, 0, math.sin(a), math.cos(a)]), frame)


@pytest.mark.parametrize(
    'position, orientation',
    [([math.nan, 0, 0], [0, 0, 0, 1]), ([0, 0, 0], [0, 0, 0, 2]), ([0, 0, 0], [0, 0, 0, 0]), ([0, 0], [0, 0, 0, 1])],
)
def test_broken_poses_refused(position, orientation):
    with pytest.raises(PoseError):
        pose_from_parts(position, orientation)


def test_odometry_by_stamp_within_max_dt_and_frame_change():
    counters = Counters(log=lambda _: None)
    reg = Registration({'odom_max_dt': 0.05}, counters)
    assert reg.odometry_at(5 * S) is None and not counters.counts  # no odometry at all: nothing missing
    for t in (1.00, 1.01, 1.02, 0.99):  # out of order too
        reg.add_odometry(odom(t, x=t))
    assert reg.odometry_at(int(1.012 * S)).T[0, 3] == pytest.approx(1.012)  # interpolated
    assert reg.odometry_at(int(1.05 * S)).T[0, 3] == pytest.approx(1.02)  # after the newest: the nearest
    assert reg.odometry_at(int(1.2 * S)) is None and counters.counts['odometry_missing'] == 1
    reg.add_odometry(odom(2.0, frame='map'))  # another frame: the old poses cannot be compared with it
    assert reg.odometry_at(1 * S) is None and reg.odometry_at(2 * S).frame_id == 'map'


def test_odometry_interpolates_rotation_along_the_geodesic():
    buf = OdometryBuffer(10)
    buf.add(odom(1.0, x=0.0, yaw_deg=10))
    buf.add(odom(1.1, x=1.0, yaw_deg=50))
    T = buf.at(int(1.025 * S), max_dt_s=0.1).T
    assert T[0, 3] == pytest.approx(0.25)
    assert math.degrees(math.atan2(T[1, 0], T[0, 0])) == pytest.approx(20.0)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    # a gap wider than 2 x max_dt is not bridged: the nearest within max_dt, or nothing
    assert buf.at(int(1.02 * S), max_dt_s=0.03).T[0, 3] == 0.0
    assert buf.at(int(1.05 * S), max_dt_s=0.03) is None


def test_lagging_odometry_is_waited_for_a_stopped_stream_is_not():
    buf = OdometryBuffer(100)
    buf.add(odom(1.0, x=1.0))
    late = threading.Timer(0.15, lambda: buf.add(odom(1.2, x=2.0)))  # the sensor thread, behind the frames
    late.start()
    t0 = time.monotonic()
    found = buf.at(int(1.1 * S), max_dt_s=0.1, wait_s=2.0)
    assert 0.1 < time.monotonic() - t0 < 1.5 and found.T[0, 3] == pytest.approx(1.5)
    late.join()
    assert buf.at(int(1.3 * S), max_dt_s=0.1, wait_s=0.2).T[0, 3] == pytest.approx(2.0)  # waited 0.2 s: nearest
    buf._last_add -= 5.0  # the last sample arrived 5 s ago: the stream stopped, nobody waits for it
    t0 = time.monotonic()
    assert buf.at(int(9 * S), max_dt_s=0.1, wait_s=2.0) is None and time.monotonic() - t0 < 0.5


def test_gating_and_recent_exclusion():
    reg = Registration({'keyframe_min_distance': 0.1, 'keyframe_min_angle': 10.0, 'exclude_recent_s': 1.0})
    assert reg.gate(0, odom(0))  # the first frame
    reg.stored(0, odom(0))
    assert not reg.gate(S // 2, odom(0.5, x=0.05, yaw_deg=5))  # still here
    assert reg.gate(S // 2, odom(0.5, x=0.12))  # moved (and now the gate's last keyframe)
    assert reg.gate(S // 2, odom(0.5, x=0.12, yaw_deg=11))  # turned
    for t in (1, 2, 3):
        reg.stored(t * S, odom(t, x=0.2 * t))
    assert reg.recent(int(3.5 * S), odom(3.5, x=0.6)) == 1  # only the keyframe at 3 s is under 1 s old
    reg.update({'exclude_recent_s': 0.0, 'exclude_recent_m': 0.5})
    # path back from x=0.75: 0.15 to the keyframe at 3 s, 0.35 to 2 s, 0.55 to 1 s (not under 0.5)
    assert reg.recent(int(3.5 * S), odom(3.5, x=0.75)) == 2
    assert reg.recent(int(3.5 * S), None) == 0  # metres need odometry
    reg.forget()
    assert reg.recent(4 * S, odom(4)) == 0


def test_camera_of_another_size_refused_once_images_are_seen():
    counters = Counters(log=lambda _: None)
    reg = Registration(None, counters)
    reg.set_camera(CAM)
    assert reg.camera_for((640, 480)) is CAM
    small = CameraModel.from_camera_info({'width': 320, 'height': 240, 'k': [262, 0, 160, 0, 262, 120, 0, 0, 1]})
    with pytest.raises(CameraError):
        reg.set_camera(small)
    assert reg.camera is CAM
    assert reg.camera_for((1280, 960)) is None and counters.counts['camera_size_mismatch'] == 1


def test_keyframe_geometry_is_the_camera_pose():
    b2c = (0.1, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0)
    reg = Registration({'base_to_camera': b2c})
    reg.set_camera(CAM)
    g = reg.keyframe_geometry((640, 480), odom(1, x=1.0))
    assert g['frame_id'] == 'odom' and g['camera']['width'] == 640
    np.testing.assert_allclose(g['pose'], [1.1, 0, 0.2, 0, 0, 0, 1], atol=1e-12)
    with pytest.raises(ValueError):
        Registration({'base_to_camera': (0, 0, 0, 0, 0, 0, 3.0)})


def test_loop_closure_filter_passes_the_pose_on():
    T = pose_from_parts([0.1, -0.2, 0.3], [0, 0, math.sin(0.1), math.cos(0.1)])
    row = {'keyframe_id': 7, 'score': 20.0, 'holistic_score': 0.5, 'stamp_sec': 1, 'stamp_nanosec': 0}
    fields = nan_fields()
    fields.update({'pose_accepted': 1.0, 'pose_metric': 1.0, 'pose_inliers': 80.0, 'pose_reproj_px': 0.8})
    fields.update(dict(zip(('tx', 'ty', 'tz'), T[:3, 3])))
    q = [0, 0, math.sin(0.1), math.cos(0.1)]
    fields.update(dict(zip(('qx', 'qy', 'qz', 'qw'), q)))
    fields.update({f'cov_{i}': float(np.eye(6).ravel()[i] * 1e-4) for i in range(36)})
    dtype = [('keyframe_id', '<u4'), ('score', '<f4'), ('holistic_score', '<f4'), ('stamp_sec', '<i4')]
    dtype += [('stamp_nanosec', '<u4'), ('session_id', '<f4')] + [(k, '<f4') for k in POSE_FIELDS]
    table = np.array([tuple({**row, **fields, 'session_id': 3.0}[n] for n, _ in dtype)], dtype)
    closure = LoopClosureFilter({'require_pose': True})(5 * S, table)
    assert closure.metric and closure.as_dict()['keyframe_session_id'] == 3  # which robot's keyframe
    np.testing.assert_allclose(closure.transform, T, atol=1e-6)
    assert closure.as_dict()['covariance'][0] == pytest.approx(1e-4)
    table['pose_accepted'] = 0.0
    f = LoopClosureFilter({'require_pose': True})
    assert f(5 * S, table) is None and f.rejected == {'no_pose': 1}


def test_pose_graph_example_closes_the_loop():
    """docs/slam_integration.md's plain-numpy pose graph: one loop closure takes a drifting square back."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / 'scripts' / 'pose_graph.py'
    out = subprocess.run([sys.executable, str(script), '--demo'], capture_output=True, text=True, check=True).stdout
    before, after = (float(v) for v in re.findall(r'([\d.]+) m', out))
    assert before > 0.3 and after < 0.02, out


def test_novelty_gating_without_odometry():
    """core.gating.KeyframeGate's novelty rule: without odometry a query is stored only when its best
    S is below keyframe_novelty_max_score (nothing alike in the map)."""
    reg = Registration({'keyframe_novelty_max_score': 15.0})
    assert reg.gate(0, None, None)  # the first frame
    assert not reg.gate(S, None, 20.0)  # seen before
    assert reg.gate(2 * S, None, 5.0) and reg.gate(3 * S, None, None)  # new, or nothing answered


def still_camera(tmp_path, conf: dict):
    """(rng, the view's landmark set, a real SQLite map, a mapping-mode Localizer with conf on it)
    for a camera that sees one view: feed it make_set(rng, base=view, noise=...) frames."""
    import json

    from test_mapstore import MODEL, make_set

    from lln_ros.core.localizer import Localizer
    from lln_ros.mapstore import open_for_matcher

    rng = np.random.default_rng(7)
    base = make_set(rng)
    store, _ = open_for_matcher(str(tmp_path / 'still.db'), 'mapping', '')
    loc = Localizer(store, {'mode': 'mapping', **conf})
    loc.model_info(json.dumps({**MODEL, 'input_height': 288}))
    return rng, base, store, loc


@pytest.mark.parametrize('exclusion, loops', [({'exclude_recent_m': 0.5}, False), ({'exclude_recent_s': 1.0}, True)])
def test_a_camera_standing_still_closes_no_loop_with_itself(tmp_path, exclusion, loops):
    """The Localizer in mapping mode on a real SQLite map, fed 4 s of one view with sensor noise at
    10 Hz and constant odometry: the gate stores one keyframe, and exclude_recent_m keeps it from
    answering however old it gets (exclude_recent in frames or seconds alone would let it answer)."""
    from test_mapstore import make_set

    rng, base, store, loc = still_camera(tmp_path, {'exclude_recent': 0, 'registration': exclusion})
    answers = []
    for i in range(40):
        t = 10 * S + i * S // 10
        loc.reg.add_odometry(OdomPose(t, pose_from_parts([1.0, 2.0, 0.0], [0, 0, 0, 1]), 'odom'))
        answers.append(loc.query(make_set(rng, base=base, noise=0.05), t))
    assert len(store) == 1 and loc.counters.counts['queries_not_stored'] == 39
    assert all(a is not None for a in answers)
    # seconds alone: the one keyframe answers once it is 1 s old; metres of path: never while still
    assert any(a.rows for a in answers) == loops
    assert not any(a.rows for a in answers[:10])
    store.close()


@pytest.mark.parametrize('novelty, keyframes, loops', [(0.0, 40, True), (15.0, 1, False)])
def test_a_still_camera_without_odometry_closes_no_loop_with_novelty_gating(tmp_path, novelty, keyframes, loops):
    """Without odometry, at the default exclude_recent (10 keyframes): storing every frame (novelty
    off) lets the view answer itself once ten twins are stored; novelty gating judges each frame
    against the last keyframe too (always among the excluded recent ones), so one keyframe is
    stored and never answers while the camera stands still."""
    from test_mapstore import make_set

    rng, base, store, loc = still_camera(tmp_path, {'registration': {'keyframe_novelty_max_score': novelty}})
    answers = [loc.query(make_set(rng, base=base, noise=0.05), 10 * S + i * S // 10) for i in range(40)]
    assert len(store) == keyframes and all(a is not None for a in answers)
    assert any(a.rows for a in answers) == loops
    assert not any(a.rows for a in answers[:10])
    # a new view is still a keyframe: the gate does not freeze the map
    assert loc.query(make_set(rng), 20 * S) is not None and len(store) == keyframes + 1
    store.close()


def test_the_novelty_gate_reads_raw_s_whatever_s_ranked():
    """best_raw_score: the sum of weight x cosine over a candidate's reported pairs (raw S's, also
    under the fused S, whose score is about 3x), the best over the candidates; the score of one
    without pairs; None for none. keyframe_novelty_max_score (25) is in raw S."""
    from types import SimpleNamespace

    fused = SimpleNamespace(score=140.0, pairs={'weight': np.array([1.0, 0.5]), 'similarity': np.array([0.8, 0.6])})
    plain = SimpleNamespace(score=0.9, pairs={})
    assert best_raw_score([fused]) == pytest.approx(1.1)
    assert best_raw_score([fused, plain]) == pytest.approx(1.1)
    assert best_raw_score([]) is None
