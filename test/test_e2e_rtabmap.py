"""End to end, real processes and real DDS: rtabmap_loop as an MCAP bag, played into the
colcon-installed extractor and matcher (mapping mode: online loop-closure detection), every
`candidates` message scored against samples_GT.bmp."""

import json
import subprocess

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import PointCloud2

from conftest import shared_data
from lln_ros.ros import bag, msgs, topics
from ros_harness import Probe, RosProcess, installed_env, ros_env

# the extractor keeps only the newest waiting frame (by design: bounded latency), so at a fixed rate a
# frame is dropped whenever one extraction stalls for two frame periods: at 4 Hz about one run in four
# on the shared 2-core CI machine, and at 2 Hz with the machine at load ~17 (82 of 84 answered). The
# player therefore paces on the extractor's output (`lln-bag play --pace lln/landmarks`): the recorded
# 2 Hz is the fastest pace, and a slow extraction delays the rest of the bag instead of losing a frame.
RATE_HZ = 2.0
GAP = 10  # a frame may be answered only with frames at least 10 older (the dataset's protocol)


def recall_at_precision(correct: np.ndarray, scores: np.ndarray, positives: int, min_precision: float):
    """Best recall over thresholds on the top-1 score whose precision is >= min_precision.
    correct / scores: per answered query; positives: queries that have a true match."""
    order = np.argsort(-scores, kind='stable')
    tp = np.cumsum(correct[order])
    precision = tp / np.arange(1, len(order) + 1)
    recall = tp / positives
    ok = precision >= min_precision
    return float(recall[ok].max()) if ok.any() else 0.0


@pytest.fixture(scope='module')
def rtabmap_run(colcon_install, tmp_path_factory):
    return play_rtabmap(colcon_install, tmp_path_factory.mktemp('e2e'), ['-p', 'k:=5'])


def play_rtabmap(colcon_install, tmp, matcher_params: list, frames: list | None = None) -> dict:
    """The rtabmap_loop bag (or a bag of `frames`, image paths) through the installed nodes, the
    matcher in mapping mode with exclude_recent GAP - 1 plus `matcher_params`; every `candidates`
    answer (stamp, table)."""
    if frames is None:
        frames = bag.list_images(shared_data('rtabmap_loop'), '*.jpg')
        assert len(frames) == 84
    stamps = bag.write_image_bag(frames, tmp / 'rtabmap_bag', topic='/camera/image_raw', rate=RATE_HZ)
    env = installed_env(colcon_install, ros_env(tmp))
    lib = colcon_install / 'lln_ros' / 'lib' / 'lln_ros'
    matcher = RosProcess(
        lib / 'matcher',
        [
            '-p',
            f'map_path:={tmp / "map.db"}',
            '-p',
            'mode:=mapping',
            '-p',
            f'exclude_recent:={GAP - 1}',
            *matcher_params,
            '-r',
            'lln/query:=lln/landmarks',
        ],
        env,
        tmp / 'matcher.log',
    )
    extractor = RosProcess(
        lib / 'extractor',
        ['-p', 'reliability:=reliable', '-p', 'num_threads:=1', '-r', 'image:=/camera/image_raw'],
        env,
        tmp / 'extractor.log',
    )
    try:
        with Probe(env) as probe:
            got = probe.collect(
                PointCloud2, 'lln/candidates', lambda m: (msgs.stamp_to_ns(m.header), msgs.cloud_to_candidates(m))
            )
            diag = {}  # the nodes' latest counters, to say where a missing answer was lost
            probe.node.create_subscription(
                DiagnosticArray,
                '/diagnostics',
                lambda m: diag.update({st.name: {kv.key: kv.value for kv in st.values} for st in m.status}),
                50,
            )
            probe.spin_until(
                lambda: (
                    probe.node.count_publishers('lln/candidates') > 0
                    and probe.node.count_subscribers('/camera/image_raw') > 0
                    and probe.node.count_subscribers('lln/landmarks') > 0
                ),
                300,
                'both nodes up',
            )
            # the graph shows the matcher's subscription before the extractor's publisher has matched
            # it; a frame published in between would be lost, so let endpoint matching settle
            probe.spin_for(2.0)
            # played by a separate process, as `ros2 bag play` would be
            play = subprocess.Popen(
                [
                    str(lib / 'lln-bag'),
                    'play',
                    str(tmp / 'rtabmap_bag'),
                    '--wait-subscribers',
                    '1',
                    '--wait-timeout',
                    '30',
                    '--pace',
                    topics.LANDMARKS,
                    '--pace-timeout',
                    '60',
                ],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            try:
                probe.spin_until(
                    lambda: len(got) >= len(frames) or play.poll() not in (None, 0), 600, 'an answer for every frame'
                )
            except TimeoutError as e:
                answered = {t for t, _ in got}
                missing = [i for i, t in enumerate(stamps) if t not in answered]
                raise TimeoutError(
                    f'{e}: {len(got)} answers of {len(frames)}, frames {missing[:10]} unanswered; '
                    f'player: {play.poll()}; counters {diag}\nmatcher log:\n{matcher.log()}'
                    f'\nextractor log:\n{extractor.log()}'
                ) from None
            played = play.communicate(timeout=30)[0]
            assert play.returncode == 0, played
            probe.spin_for(1.0)
            from std_srvs.srv import Trigger

            info = json.loads(probe.call(Trigger, '/lln_matcher/info').message)
        assert matcher.alive() and extractor.alive()
    finally:
        logs = {'matcher': matcher.log(), 'extractor': extractor.log()}
        matcher.stop()
        extractor.stop()
    return {'stamps': stamps, 'answers': got, 'played': played, 'info': info, 'logs': logs}


def test_every_frame_answered_and_the_novel_ones_stored(rtabmap_run):
    """Every frame is answered; at the shipped keyframe_novelty_max_score (no odometry) the frames
    too alike to what is stored are not stored, and each of the 84 is one or the other."""
    run = rtabmap_run
    assert 'published 84 messages' in run['played'], run['played']
    assert len(run['answers']) == 84, run['logs']
    assert [t for t, _ in run['answers']] == run['stamps'], 'answers carry the query header, in order'
    counters = run['info']['counters']
    assert counters.get('bad_query', 0) == 0
    assert run['info']['keyframes'] + counters.get('queries_not_stored', 0) == 84, counters
    assert 40 <= run['info']['keyframes'] < 84, run['info']  # the first lap is new; some of the second is not


def test_a_still_camera_closes_no_loop_with_itself(colcon_install, tmp_path):
    """Issue 27: a camera standing still (one rtabmap_loop frame, fresh sensor noise per frame)
    through the real nodes at the shipped defaults, no odometry: one keyframe is stored and no answer
    names a keyframe, so nothing downstream sees a loop closure. Storing every frame
    (keyframe_novelty_max_score 0) answers with the camera's own frames once exclude_recent are stored."""
    first = bag.list_images(shared_data('rtabmap_loop'), '*.jpg')[0]
    image, rng = cv2.imread(str(first)), np.random.default_rng(0)
    still = tmp_path / 'still'
    still.mkdir()
    frames = []
    for i in range(40):  # 4 times exclude_recent: with every frame stored, 30 would answer with a twin
        noisy = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        frames.append(still / f'{i:03d}.png')
        cv2.imwrite(str(frames[-1]), noisy)
    run = play_rtabmap(colcon_install, tmp_path, [], frames)
    assert len(run['answers']) == 40, run['logs']
    closures = [t for t, cands in run['answers'] if len(cands)]
    assert closures == [], f'{len(closures)} of 40 frames answered with a keyframe: {run["info"]["counters"]}'
    assert run['info']['keyframes'] == 1 and run['info']['counters']['queries_not_stored'] == 39


def test_loop_detection_against_ground_truth(rtabmap_run):
    root = shared_data('rtabmap_loop')
    gt = cv2.imread(str(root / 'samples_GT.bmp'), cv2.IMREAD_GRAYSCALE) > 0
    index_of = {s: i for i, s in enumerate(rtabmap_run['stamps'])}
    correct, scores, rows = [], [], []
    for stamp, cands in rtabmap_run['answers']:
        r = index_of[stamp]
        if len(cands) == 0:
            continue
        # keyframe stamps identify frames; no answer may be younger than the gap
        answers = [index_of[int(s) * 10**9 + int(n)] for s, n in zip(cands['stamp_sec'], cands['stamp_nanosec'])]
        assert max(answers) <= r - GAP, (r, answers)
        assert list(cands['score']) == sorted(cands['score'], reverse=True)
        rows.append(r)
        correct.append(bool(gt[r, answers[0]]))
        scores.append(float(cands['score'][0]))
    correct, scores = np.array(correct), np.array(scores)
    positives = int(gt[40:84].any(axis=1).sum())
    loop_rows = np.array(rows) >= 40
    top1 = correct[loop_rows].sum() / positives
    recall = recall_at_precision(correct, scores, positives, 0.95)
    print(
        f'\nrtabmap_loop online: top-1 correct on loop rows {correct[loop_rows].sum()}/{positives} '
        f'({top1:.3f}); recall {recall:.3f} at precision >= 0.95 over all {len(rows)} answered queries'
    )
    # issue 4's target, with the shipped (trained) head and single-frame matching: recall >= 0.85
    # at precision >= 0.95, counting answers to the 40 loop-free rows as false detections
    assert top1 >= 0.85
    assert recall >= 0.85
