"""End to end, real processes and real DDS, metric (issue 27): a stretch of TUM fr1rpy as an RGB-D
MCAP bag (colour JPEG, registered 16UC1 depth, camera_info, ground truth as nav_msgs/Odometry at
100 Hz) played into the colcon-installed extractor (publish_keypoints, depth) and matcher (verify,
geometry). Phase 1 maps (mapping mode, keyframes gated by odometry): every accepted pose in the
candidates table is checked against the ground truth, and the bad inputs mixed into the bag
(camera_info with zeros, NaN or another size; depth of another size or encoding; odometry with NaN
or a non-unit quaternion) must be refused and counted, with every stored keyframe's pose the true
one. Phase 2 relocalizes later frames in that map (localization mode): lln/pose against the truth.

Bounds: measured on this machine with the same frames through the same code offline (Localizer +
Registration on frames 0-89, step 3: accepted rotation errors p50 2.3, max 4.9 deg; translation
p50 0.035, max 0.11 m), with margin; a false fix is the issue's 10 deg / 0.5 m.
"""

import json
import math
import subprocess

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from conftest import shared_data
from lln_ros.core.geometry import invert, rotation_deg
from lln_ros.core.loop_closure import LoopClosureFilter
from lln_ros.core.registration import pose_from_parts
from lln_ros.ros import bag, msgs
from lln_ros.ros.rgbd_bag import TOPICS, rgbd_records
from ros_harness import Probe, RosProcess, installed_env, ros_env

STEP = 3  # 10 Hz of the 30 Hz sequence
MAP_FRAMES = range(0, 90)  # 9 s: phase 1
LOC_FRAMES = range(100, 130)  # 3 s later on: phase 2
BAD_CAMERA_AT, BAD_DEPTH_AT, BAD_ODOM_AT = (10, 20, 30), (15, 25), (12, 22)
FALSE_FIX_DEG, FALSE_FIX_M = 10.0, 0.5


def _bad_records(seq):
    """The refused inputs: (topic, message, stamp) beside the good ones, and the good depth images they replace."""
    import copy

    from sensor_msgs.msg import Image

    out, replace = [], set()
    good = msgs.camera_model_to_info(seq.camera)
    for n, i in enumerate(BAD_CAMERA_AT):
        st = int(round(seq.frames[i].stamp * 1e9)) + 1
        info = copy.deepcopy(good)
        info.header = msgs.make_header(st, 'camera_rgb_optical_frame')
        if n == 0:
            info.k = [0.0] * 9  # an uncalibrated camera
        elif n == 1:
            info.k = [float('nan')] + list(info.k[1:])
        else:
            info.width, info.height = 320, 240  # a valid camera, of another size than the images
        out.append((TOPICS['camera_info'], info, st))
    for n, i in enumerate(BAD_DEPTH_AT):
        st = int(round(seq.frames[i].stamp * 1e9))
        replace.add(st)
        if n == 0:
            msg = msgs.depth_to_image(np.full((240, 320), 1000, np.uint16), '16UC1', st)
        else:
            msg = Image(header=msgs.make_header(st), height=480, width=640, encoding='rgb8', step=1920)
            msg.data = bytes(640 * 480 * 3)
        out.append((TOPICS['depth'], msg, st))
    for n, i in enumerate(BAD_ODOM_AT):
        st = int(round(seq.frames[i].stamp * 1e9))  # at the frame's own stamp: the nearest, were it taken
        odom = msgs.pose_to_odometry(np.eye(4), st, 'world', 'camera_rgb_optical_frame')
        if n == 0:
            odom.pose.pose.position.x = float('nan')
        else:
            odom.pose.pose.orientation.w = 2.0
        out.append((TOPICS['odom'], odom, st))
    return out, replace


def _write_bags(seq, tmp):
    bad, replace = _bad_records(seq)
    records = [r for r in rgbd_records(seq, MAP_FRAMES) if not (r[0] == TOPICS['depth'] and r[2] in replace)]
    bag.write_bag(tmp / 'map_bag', sorted(records + bad, key=lambda r: r[2]))
    bag.write_bag(tmp / 'loc_bag', rgbd_records(seq, LOC_FRAMES))


def _play(lib, path, env):
    out = subprocess.run(
        [str(lib / 'lln-bag'), 'play', str(path), '--wait-subscribers', '1', '--wait-timeout', '60'],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout + out.stderr


@pytest.fixture(scope='module')
def rgbd_run(colcon_install, tmp_path_factory):
    from lln_ros.io.rgbd import read_tum

    root = shared_data('tum_fr1rpy')
    if not (root / 'depth.txt').is_file():
        pytest.skip(f'{root} has no depth.txt: the RGB-D version of the data set is not here')
    tmp = tmp_path_factory.mktemp('e2e_rgbd')
    seq = read_tum(root, {'step': STEP})
    _write_bags(seq, tmp)
    env = installed_env(colcon_install, ros_env(tmp))
    lib = colcon_install / 'lln_ros' / 'lib' / 'lln_ros'
    sensors = ['-r', f'camera_info:={TOPICS["camera_info"]}', '-r', f'odom:={TOPICS["odom"]}']
    common = ['-p', f'map_path:={tmp / "map.db"}', '-p', 'verify:=true', '-p', 'sensor_reliability:=reliable']
    common += ['-p', 'queue_depth:=300', '-r', 'lln/query:=lln/landmarks', *sensors]
    extractor = RosProcess(
        lib / 'extractor',
        [
            *('-p', 'reliability:=reliable', '-p', 'num_threads:=1', '-p', 'image_transport:=compressed'),
            *('-p', 'publish_keypoints:=true', '-p', 'depth:=true', '-p', 'frame_queue:=200'),
            *('-r', f'image/compressed:={TOPICS["image"]}', '-r', f'depth/image:={TOPICS["depth"]}'),
        ],
        env,
        tmp / 'extractor.log',
    )
    run = {'seq': seq}
    matcher = None
    try:
        with Probe(env) as probe:
            diag = {}
            probe.node.create_subscription(
                DiagnosticArray,
                '/diagnostics',
                lambda m: diag.update({st.name: {kv.key: kv.value for kv in st.values} for st in m.status}),
                50,
            )
            for phase, mode, path, frames in (
                ('map', 'mapping', 'map_bag', MAP_FRAMES),
                ('loc', 'localization', 'loc_bag', LOC_FRAMES),
            ):
                matcher = RosProcess(
                    lib / 'matcher',
                    [*common, '-p', f'mode:={mode}', '-p', 'exclude_recent_s:=1.0'],
                    env,
                    tmp / f'matcher_{phase}.log',
                )
                got = probe.collect(
                    PointCloud2, 'lln/candidates', lambda m: (msgs.stamp_to_ns(m.header), msgs.cloud_to_candidates(m))
                )
                poses = probe.collect(PoseWithCovarianceStamped, 'lln/pose')
                probe.spin_until(
                    lambda: (
                        probe.node.count_publishers('lln/candidates') > 0
                        and probe.node.count_subscribers('lln/landmarks') > 0
                        and probe.node.count_subscribers(TOPICS['odom']) > 0
                        and probe.node.count_subscribers(TOPICS['depth']) > 0
                    ),
                    300,
                    'both nodes up',
                )
                probe.spin_for(2.0)  # let endpoint matching settle (see test_e2e_rtabmap)
                run[f'{phase}_played'] = _play(lib, tmp / path, env)
                probe.spin_until(lambda: len(got) >= len(frames), 300, f'{phase}: an answer for every frame')
                probe.spin_for(1.0)
                if phase == 'loc':
                    run['relocalize'] = probe.call(Trigger, '/lln_matcher/relocalize')
                run[f'{phase}_info'] = json.loads(probe.call(Trigger, '/lln_matcher/info').message)
                run[f'{phase}_answers'], run[f'{phase}_poses'] = list(got), list(poses)
                assert matcher.alive() and extractor.alive()
                run[f'{phase}_log'] = matcher.log()
                matcher.stop()
                matcher = None
            probe.spin_for(1.5)  # one more diagnostics period of the extractor
            run['extractor_counters'] = next(v for k, v in diag.items() if k.endswith('lln_extractor'))
    finally:
        run['extractor_log'] = extractor.log()
        if matcher is not None:
            matcher.stop()
        extractor.stop()
    run['map'] = tmp / 'map.db'
    return run


def _truth(seq):
    """stamp_ns -> T(world <- camera) of the frames (the reader's nearest ground-truth pose)."""
    return {int(round(f.stamp * 1e9)): seq.T_world_cam(i) for i, f in enumerate(seq.frames)}


def _errors(T_est, T_true):
    return rotation_deg(T_true[:3, :3].T @ T_est[:3, :3]), float(np.linalg.norm(T_true[:3, 3] - T_est[:3, 3]))


def test_bad_inputs_refused_and_counted(rgbd_run):
    run = rgbd_run
    counters = run['map_info']['counters']
    assert counters.get('bad_camera_info') == len(BAD_CAMERA_AT), counters
    assert counters.get('bad_odometry') == len(BAD_ODOM_AT), counters
    ex = run['extractor_counters']
    assert int(ex.get('bad_depth', 0)) == len(BAD_DEPTH_AT), ex
    assert int(ex.get('internal_error', 0)) == 0 and counters.get('queries_failed', 0) == 0
    assert len(run['map_answers']) == len(MAP_FRAMES), 'every frame answered, bad inputs or not'


def test_stored_keyframes_have_true_poses_and_gating(rgbd_run):
    from lln_ros.mapstore import MapStore

    run = rgbd_run
    truth = _truth(run['seq'])
    with MapStore.open(run['map']) as store:
        ids = store.ids()
        stored = [(store.get(k), store.geometry(k)) for k in ids]
    n = len(ids)
    print(f'\nphase 1: {n} keyframes stored of {len(MAP_FRAMES)} frames (odometry gating, default 0.05 m / 10 deg)')
    assert n * 2 <= len(MAP_FRAMES), 'gating keeps at most one frame in two on this slow traverse'
    bad_depth = {int(round(run['seq'].frames[i].stamp * 1e9)) for i in BAD_DEPTH_AT}
    without_pose = 0
    for (lset, geom), k in zip(stored, ids):
        assert geom is not None and geom['camera']['width'] == 640
        pose = geom['pose']
        if pose is None:  # no odometry within odom_max_dt of the frame had arrived when it was answered
            without_pose += 1
            assert geom['frame_id'] == ''
        else:
            assert geom['frame_id'] == 'world'
            assert np.isfinite(pose).all() and abs(np.linalg.norm(pose[3:]) - 1) < 1e-6
        sec, nsec = lset.meta['stamp']
        stamp = int(sec) * 10**9 + int(nsec)
        T_true = truth[stamp]
        finite = int(np.isfinite(geom['depth']).sum())
        if stamp in bad_depth:  # its depth image was refused: its keypoints have none, not a wrong one
            assert finite == 0
        else:
            assert finite > 50, (k, finite)
        if pose is not None:  # the true pose: never the NaN or non-unit odometry at this very stamp
            assert np.allclose(pose[:3], T_true[:3, 3], atol=0.02), (k, pose, T_true)
    # a keyframe without a pose is counted, and rare (a race of DDS topics, seen on 2 of 34 keyframes once)
    assert without_pose <= run['map_info']['counters'].get('odometry_missing', 0)
    assert without_pose <= n // 10


def test_loop_closure_transforms_against_ground_truth(rgbd_run):
    run = rgbd_run
    truth = _truth(run['seq'])
    rot, trans, essential, answered = [], [], [], 0
    for stamp, cands in run['map_answers']:
        acc = cands[cands['pose_accepted'] == 1] if len(cands) else cands
        if not len(acc):
            continue
        row = acc[0]
        kf = int(row['stamp_sec']) * 10**9 + int(row['stamp_nanosec'])
        assert (stamp - kf) * 1e-9 >= 1.0, 'exclude_recent_s 1.0: never a keyframe younger than 1 s'
        T = pose_from_parts([row['tx'], row['ty'], row['tz']], [row['qx'], row['qy'], row['qz'], row['qw']], 1e-5)
        cov = np.array([row[f'cov_{i}'] for i in range(36)], np.float64).reshape(6, 6)
        assert np.allclose(cov, cov.T, atol=1e-9 * max(1.0, np.abs(cov).max())) and np.all(np.diag(cov) > 0)
        assert row['pose_inliers'] >= 20
        T_true = invert(truth[kf]) @ truth[stamp]
        r, t = _errors(T, T_true)
        answered += 1
        if row['pose_metric'] != 1:  # a keyframe without depth (its depth image was refused): the essential matrix
            assert row['pose_metric'] == 0 and abs(np.linalg.norm(T[:3, 3]) - 1) < 1e-3
            direction = math.degrees(
                math.acos(np.clip(T[:3, 3] @ T_true[:3, 3] / np.linalg.norm(T_true[:3, 3]), -1, 1))
            )
            essential.append((r, direction))
            continue
        rot.append(r)
        trans.append(t)
    rot, trans = np.array(rot), np.array(trans)
    print('\nmatcher counters', run['map_info']['counters'])
    print(f'\nphase 1: essential-matrix poses (rotation, direction error, deg): {np.round(essential, 2).tolist()}')
    assert all(r < FALSE_FIX_DEG for r, _ in essential)
    print(
        f'\nphase 1: {answered} accepted poses of {len(run["map_answers"])} answers ({len(rot)} metric); '
        'rotation error p50 '
        f'{np.median(rot):.2f} max {rot.max():.2f} deg, translation p50 {np.median(trans):.3f} max {trans.max():.3f} m'
    )
    assert answered >= 10
    # the client's filter (scripts/loop_closure_client.py) on the same answers passes the pose on
    select = LoopClosureFilter({'require_pose': True, 'min_gap_s': 1.0})
    closures = [c for c in (select(stamp, cands) for stamp, cands in run['map_answers']) if c is not None]
    assert len(closures) == answered and all(c.transform is not None for c in closures)
    line = closures[0].as_dict()
    line['regions'], line['covariance'] = line['regions'][:1], line['covariance'][:3]
    line['transform'] = [[round(v, 3) for v in r] for r in line['transform'][:2]]
    print('\nfirst closure (regions, covariance and transform cut):', json.dumps(line))
    assert np.median(rot) <= 4.0 and np.median(trans) <= 0.07
    assert rot.max() < FALSE_FIX_DEG and trans.max() < FALSE_FIX_M, 'no false fix'


def test_relocalized_pose_in_the_map_frame(rgbd_run):
    run = rgbd_run
    truth = _truth(run['seq'])
    poses = run['loc_poses']
    assert run['relocalize'].success, run['relocalize'].message
    assert run['loc_info']['keyframes'] == run['map_info']['keyframes'], 'localization leaves the map alone'
    rot, trans = [], []
    for m in poses:
        assert m.header.frame_id == 'world'
        p, q = m.pose.pose.position, m.pose.pose.orientation
        T = pose_from_parts([p.x, p.y, p.z], [q.x, q.y, q.z, q.w], 1e-5)
        cov = np.array(m.pose.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(0.5 * (cov + cov.T)) > -1e-12)
        r, t = _errors(T, truth[msgs.stamp_to_ns(m.header)])
        rot.append(r)
        trans.append(t)
    print(
        f'\nphase 2: {len(poses)} poses on lln/pose for {len(LOC_FRAMES)} frames; rotation error p50 '
        f'{np.median(rot) if rot else math.nan:.2f} max {max(rot, default=math.nan):.2f} deg, translation p50 '
        f'{np.median(trans) if trans else math.nan:.3f} max {max(trans, default=math.nan):.3f} m'
    )
    assert len(poses) >= 5
    assert max(rot) < FALSE_FIX_DEG and max(trans) < FALSE_FIX_M
    assert np.median(rot) <= 4.0 and np.median(trans) <= 0.07
