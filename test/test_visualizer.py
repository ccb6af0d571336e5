"""lln_ros.viz.drawing (ROS-free, OpenCV) and the lln_visualizer node over real DDS: the query beside its
best keyframe with the matched regions linked, and the loop-closure markers, from real extractions
of the matplotlib photograph."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from lln_ros.core.retrieval import pair_regions
from lln_ros.core.similarity import match_pair
from lln_ros.ros import msgs
from lln_ros.viz.drawing import CAPTION_HEIGHT, LEGEND_HEIGHT, draw_match_overlay, similarity_colours
from ros_harness import Probe, RosProcess, installed_env, ros_env

T0 = 1_700_000_000 * 10**9


@pytest.fixture(scope='module')
def pair(photo, extractor):
    """Two overlapping crops of the photo (RGB), their landmark sets and the matcher's match rows."""
    h, w = photo.shape[:2]
    a_img = np.ascontiguousarray(photo[: h * 3 // 4, : w * 3 // 4])
    b_img = np.ascontiguousarray(photo[h // 8 : h * 7 // 8, w // 8 : w * 7 // 8])
    a, b = extractor.extract_batch([a_img, b_img])
    result = match_pair(a, b, 1.0)
    rows = msgs.match_rows(1, pair_regions(a, b, result.pairs(0)))
    assert len(rows) >= 5, 'the crops should share landmarks'
    return a_img, b_img, a, b, float(result.scores[0]), rows


def test_overlay_layout_and_regions(pair):
    a_img, b_img, _, _, _, rows = pair
    q, k = cv2.cvtColor(a_img, cv2.COLOR_RGB2BGR), cv2.cvtColor(b_img, cv2.COLOR_RGB2BGR)
    canvas = draw_match_overlay(q, k, rows, caption=['one', 'two'], height=300, max_links=len(rows))
    wq, wk = round(q.shape[1] * 300 / q.shape[0]), round(k.shape[1] * 300 / k.shape[0])
    assert canvas.shape == (300 + 2 * CAPTION_HEIGHT + LEGEND_HEIGHT, wq + wk, 3) and canvas.dtype == np.uint8
    # every linked pair has its ends drawn in its similarity colour, on both sides
    colours = similarity_colours(rows['similarity'])
    sq, sk = 300 / q.shape[0], 300 / k.shape[0]
    top = 2 * CAPTION_HEIGHT
    hits = 0
    for row, colour in zip(rows, colours):
        for x, y in (
            (row['query_u'] * sq, top + row['query_v'] * sq),
            (wq + row['map_u'] * sk, top + row['map_v'] * sk),
        ):
            hits += np.abs(canvas[round(y), round(x)].astype(int) - colour.astype(int)).max() <= 60
    assert hits >= 0.8 * 2 * len(rows), f'{hits} of {2 * len(rows)} pair ends drawn'
    # no keyframe image: a grey panel, the query side still outlined
    blind = draw_match_overlay(q, None, rows, height=300)
    right = blind[:, wq:]
    assert right.shape[1] == 400 and (np.median(right.reshape(-1, 3), axis=0) == 64).all()
    assert (blind[30:300, :wq] != cv2.resize(q, (wq, 300))[30:]).any()  # below the panel label
    # thumbnails: coordinates of the original image land at the same canvas place
    thumb = cv2.resize(k, (k.shape[1] // 4, k.shape[0] // 4))
    from_thumb = draw_match_overlay(q, thumb, rows, height=300, original_heights=(None, k.shape[0]))
    assert from_thumb.shape[0] == canvas.shape[0] - 2 * CAPTION_HEIGHT
    assert abs(from_thumb.shape[1] - (wq + wk)) <= 2
    # the key strip: the similarity colour bar (viridis, dark blue .. yellow) and its words
    key = canvas[-LEGEND_HEIGHT:]
    bar_row = key[LEGEND_HEIGHT // 2]
    for colour in similarity_colours(np.array([0.0, 1.0])):
        assert (np.abs(bar_row.astype(int) - colour.astype(int)).max(axis=1) <= 10).any()
    assert (key > 200).all(axis=2).sum() > 200, 'white key text'
    # the panel labels: white text on a dark box in each panel's top-left corner
    for x0 in (0, wq):
        corner = canvas[top : top + 20, x0 : x0 + 40]
        assert (corner < 30).all(axis=2).mean() > 0.3 and (corner > 200).all(axis=2).any()


def test_visualizer_node_overlay_and_markers(pair, colcon_install, tmp_path):
    a_img, b_img, a, b, score, rows = pair
    env = installed_env(colcon_install, ros_env(tmp_path))
    proc = RosProcess(
        colcon_install / 'lln_ros' / 'lib' / 'lln_ros' / 'visualizer',
        ['-p', 'reliability:=reliable', '-p', 'overlay_height:=240'],
        env,
        tmp_path / 'visualizer.log',
    )
    probe = Probe(env)
    try:
        images = probe.publisher(Image, 'image')
        candidates = probe.publisher(PointCloud2, 'lln/candidates')
        matches = probe.publisher(PointCloud2, 'lln/matches')
        overlays = probe.collect(Image, 'lln/overlay')
        markers = probe.collect(MarkerArray, 'lln/markers')
        probe.spin_until(
            lambda: all(p.get_subscription_count() for p in (images, candidates, matches)) or not proc.alive(),
            60,
            'visualizer subscriptions',
        )
        assert proc.alive(), proc.log()
        keyframe_header, query_header = msgs.make_header(T0, 'camera'), msgs.make_header(T0 + 2 * 10**9, 'camera')
        images.publish(msgs.array_to_image(b_img, 'rgb8', keyframe_header))  # seen first: the keyframe
        images.publish(msgs.array_to_image(a_img, 'rgb8', query_header))
        probe.spin_for(1.0)
        row = {
            'keyframe_id': 1,
            'score': score,
            'holistic_score': float(a.global_descriptor @ b.global_descriptor),
            'stamp_sec': T0 // 10**9,
            'stamp_nanosec': 0,
        }
        matches.publish(msgs.matches_to_cloud(rows, query_header))  # either order
        candidates.publish(msgs.candidates_to_cloud([row], query_header))
        probe.spin_until(lambda: overlays and markers, 30, 'overlay and markers')
        overlay, order = msgs.image_to_array(overlays[0])
        assert overlays[0].header.stamp == query_header.stamp and overlays[0].encoding == 'bgr8'
        assert overlay.shape[0] == 240 + 2 * CAPTION_HEIGHT + LEGEND_HEIGHT
        right = overlay[2 * CAPTION_HEIGHT :, round(a_img.shape[1] * 240 / a_img.shape[0]) :]
        assert right.std() > 20, 'the keyframe panel should show the keyframe image, not the grey placeholder'
        arcs = [m for m in markers[0].markers if m.ns == 'loop_closures']
        assert len(arcs) == 1 and arcs[0].header.frame_id == 'lln_timeline'
        xs = [p.x for p in arcs[0].points]
        assert max(xs) == pytest.approx(0.0, abs=1e-6) and min(xs) == pytest.approx(-2 * 0.2, abs=1e-6)
        # a bad cloud is counted and skipped, the node lives on
        candidates.publish(PointCloud2(header=query_header, width=3))
        probe.spin_for(1.0)
        assert proc.alive(), proc.log()
    finally:
        probe.close()
        code = proc.stop()
    assert code == 0, proc.log()
    assert 'bad_candidates' in proc.log()
