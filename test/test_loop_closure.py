"""lln_ros.core.loop_closure and scripts/loop_closure_client.py: the matcher's answers turned into
loop-closure constraints (thresholds, verify-mode inliers, odometry gap), and the client over real DDS."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2

from lln_ros.core.loop_closure import LoopClosureFilter, threshold_table
from lln_ros.ros import msgs
from ros_harness import Probe, ros_env

CLIENT = Path(__file__).resolve().parents[1] / 'scripts' / 'loop_closure_client.py'
T0 = 1_700_000_000


def answer(rows, extra=()):
    """candidates and matches tables as the matcher sends them (through the real codecs)."""
    header = msgs.make_header(T0 * 10**9 + 60 * 10**9)
    cands = msgs.cloud_to_candidates(msgs.candidates_to_cloud(rows, header, extra))
    best = rows[0]['keyframe_id'] if rows else 0
    pairs = {
        'query_u': [10.0, 50.0],
        'query_v': [20.0, 60.0],
        'map_u': [12.0, 55.0],
        'map_v': [21.0, 58.0],
        'cell_w': [32.0, 32.0],
        'cell_h': [32.0, 32.0],
        'similarity': [0.9, 0.8],
        'weight': [1.0, 0.7],
    }
    matches = msgs.cloud_to_matches(msgs.matches_to_cloud(msgs.match_rows(best, pairs) if rows else [], header))
    return header, cands, matches


def row(kf, score, sec, inliers=None):
    r = {'keyframe_id': kf, 'score': score, 'holistic_score': 0.5, 'stamp_sec': sec, 'stamp_nanosec': 0}
    return r if inliers is None else {**r, 'inliers': inliers}


def test_filter_thresholds_and_evidence():
    header, cands, matches = answer([row(3, 20.0, T0), row(7, 12.0, T0 + 1)])
    stamp = msgs.stamp_to_ns(header.stamp)
    closure = LoopClosureFilter({'min_score': 15})(stamp, cands, matches)
    assert closure.keyframe_id == 3 and closure.keyframe_stamp_ns == T0 * 10**9 and closure.inliers is None
    assert closure.regions.shape == (2, 6) and closure.regions[1].tolist() == [50, 60, 55, 58, 32, 32]
    json.dumps(closure.as_dict())
    select = LoopClosureFilter({'min_score': 25})
    assert select(stamp, cands, matches) is None and select.rejected == {'low_score': 1}
    # the best candidate 59 s old is "odometry" with min_gap 61: nothing qualifies
    select = LoopClosureFilter({'min_gap_s': 61})
    assert select(stamp, cands, matches) is None and select.rejected == {'too_recent': 1}
    # verify mode: NaN inliers (no keypoints) or too few are refused when inliers are required
    header, cands, matches = answer([row(3, 20.0, T0, float('nan'))], ('inliers',))
    assert LoopClosureFilter({'min_inliers': 15})(stamp, cands, matches) is None
    header, cands, matches = answer([row(3, 20.0, T0, 40.0)], ('inliers',))
    assert LoopClosureFilter({'min_inliers': 15})(stamp, cands, matches).inliers == 40
    header, cands, matches = answer([])
    select = LoopClosureFilter()
    assert select(stamp, cands, matches) is None and select.rejected == {'no_candidate': 1}
    with pytest.raises(ValueError, match='unknown loop-closure settings'):
        LoopClosureFilter({'min_scor': 1})


def test_threshold_table():
    scores = np.array([30, 25, 20, 18, 10, 5.0])
    correct = np.array([1, 1, 0, 1, 0, 1], bool)
    table = {r['precision_target']: r for r in threshold_table(scores, correct, positives=5, precisions=(1.0, 0.75))}
    assert table[1.0]['threshold'] == 25 and table[1.0]['recall'] == pytest.approx(2 / 5)
    assert table[0.75]['threshold'] == 18 and table[0.75]['recall'] == pytest.approx(3 / 5)


def test_client_over_dds(tmp_path):
    env = ros_env(tmp_path)
    out = tmp_path / 'closures.jsonl'
    client = subprocess.Popen(
        [sys.executable, str(CLIENT), '--min-score', '15', '--count', '3', '--out', str(out)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with Probe(env) as probe:
            cpub, mpub = probe.publisher(PointCloud2, 'lln/candidates'), probe.publisher(PointCloud2, 'lln/matches')
            probe.spin_until(lambda: cpub.get_subscription_count() and mpub.get_subscription_count(), 60, 'client')
            for i, rows in enumerate(([row(3, 20.0, T0)], [row(4, 9.0, T0)], [])):
                header = msgs.make_header((T0 + 100 + i) * 10**9)
                mpub.publish(
                    msgs.matches_to_cloud(
                        msgs.match_rows(
                            rows[0]['keyframe_id'] if rows else 0,
                            {
                                'query_u': [1.0],
                                'query_v': [2.0],
                                'map_u': [3.0],
                                'map_v': [4.0],
                                'cell_w': [8.0],
                                'cell_h': [8.0],
                                'similarity': [0.9],
                                'weight': [1.0],
                            },
                        )
                        if rows
                        else [],
                        header,
                    )
                )
                cpub.publish(msgs.candidates_to_cloud(rows, header))
            probe.spin_until(lambda: client.poll() is not None, 60, 'client exit')
        _, err = client.communicate(timeout=10)
    finally:
        if client.poll() is None:
            client.kill()
    assert client.returncode == 0, err
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(lines) == 1 and lines[0]['keyframe_id'] == 3 and lines[0]['query_stamp_ns'] == (T0 + 100) * 10**9
    assert lines[0]['regions'] == [[1.0, 2.0, 3.0, 4.0, 8.0, 8.0]]
    assert "3 answers, 1 loop closures accepted, rejected: {'low_score': 1, 'no_candidate': 1}" in err
