"""Verify mode over real DDS: the extractor's `keypoints` topic, and the matcher storing keypoints
per keyframe and re-ranking candidates by region-constrained RANSAC inliers (issue 5)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import Image, PointCloud2, PointField
from test_nodes import EXTRACTOR, MATCHER, header, read_log, rig, same_header, start_matcher  # noqa: F401

from lln_ros.core.reloc import Relocalizer
from lln_ros.mapstore import MapStore
from lln_ros.ros import msgs


@pytest.fixture(scope='module')
def scenes(extractor, photo) -> dict:
    """Four keyframes (distinct crops of the photograph) with landmarks and ORB keypoints, and a
    query: keyframe 2 seen again, rotated 4 degrees and 10% brighter."""
    crops = [np.ascontiguousarray(photo[y : y + 288, x : x + 256]) for y, x in ((0, 0), (0, 256), (300, 0), (300, 256))]
    h, w = crops[2].shape[:2]
    A = cv2.getRotationMatrix2D((w / 2, h / 2), 4, 1.0)
    query = np.clip(cv2.warpAffine(crops[2], A, (w, h), borderMode=cv2.BORDER_REFLECT) * 1.1, 0, 255).astype(np.uint8)
    orb = Relocalizer({'max_keypoints': 500})
    images = crops + [query]
    sets = extractor.extract_batch(images)
    return {
        'sets': sets,
        'kps': [orb.detect(im) for im in images],
        'space': extractor.model_info['descriptor_space'],
        'images': images,
    }


def test_extractor_publishes_keypoints_with_the_landmarks_header(rig, scenes):
    proc = rig.extractor('-p', 'publish_keypoints:=true', '-p', 'keypoints_max:=300')
    landmarks = rig.probe.collect(PointCloud2, 'lln/landmarks')
    keypoints = rig.probe.collect(PointCloud2, 'lln/keypoints')
    pub = rig.probe.publisher(Image, 'image')
    rig.until(
        lambda: pub.get_subscription_count() > 0 and rig.probe.node.count_publishers('lln/keypoints') > 0,
        'extractor up',
        proc,
    )
    blank = np.full((240, 320, 3), 90, np.uint8)
    for i, img in enumerate([scenes['images'][0], blank]):
        pub.publish(msgs.array_to_image(img, 'rgb8', header(i)))
        rig.until(lambda: len(landmarks) > i and len(keypoints) > i, f'frame {i}', proc)
    for i in range(2):
        assert same_header(keypoints[i].header, landmarks[i].header)
    fields = {f.name: (f.datatype, f.count) for f in keypoints[0].fields}
    assert fields['descriptor'] == (PointField.UINT8, 32) and fields['octave'][0] == PointField.INT32
    kps = msgs.cloud_to_keypoints(keypoints[0], (256, 288))
    assert 100 < len(kps) <= 300 and kps.uv[:, 0].max() < 256 and kps.uv[:, 1].max() < 288
    # the keypoints are what the library detects on the same image
    ref = Relocalizer({'max_keypoints': 300}).detect(scenes['images'][0])
    np.testing.assert_allclose(kps.uv, ref.uv)
    assert len(msgs.cloud_to_keypoints(keypoints[1])) == 0  # textureless: an empty cloud, not an error
    assert rig.counter(EXTRACTOR, 'bad_image') == 0


def test_matcher_verify_reranks_by_inliers(rig, scenes, tmp_path):
    map_path = tmp_path / 'map.db'
    proc = start_matcher(rig, map_path, {'space': scenes['space']}, '-p', 'verify:=true', '-p', 'k:=4')
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    kp_pub = rig.probe.publisher(PointCloud2, 'lln/keypoints')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates')
    rig.until(lambda: kp_pub.get_subscription_count() > 0 and q_pub.get_subscription_count() > 0, 'subs', proc)
    rig.answers_reach_us(proc)
    for i in range(4):
        h = header(i, 'map')
        kp_pub.publish(msgs.keypoints_to_cloud(scenes['kps'][i], h))
        rig.probe.spin_for(0.05)
        kf_pub.publish(msgs.landmarks_to_cloud(scenes['sets'][i], h))
    rig.wait_counter(MATCHER, 'keyframes_stored', 4, proc)

    qh = header(100, 'query')
    kp_pub.publish(msgs.keypoints_to_cloud(scenes['kps'][4], qh))
    rig.probe.spin_for(0.05)
    q_pub.publish(msgs.landmarks_to_cloud(scenes['sets'][4], qh))
    rig.until(lambda: cands, 'the verified answer', proc)
    table = msgs.cloud_to_candidates(cands[0])
    assert 'inliers' in table.dtype.names and len(table) >= 2
    stored_ids = [int(k) for k in table['keyframe_id']]
    assert table['inliers'][0] >= 15 and all(table['inliers'][0] > x for x in table['inliers'][1:])
    assert list(table['inliers']) == sorted(table['inliers'], reverse=True)
    best = stored_ids[0]

    # no keypoints for this query: answered unverified, inliers NaN, counted
    q_pub.publish(msgs.landmarks_to_cloud(scenes['sets'][4], header(101, 'query')))
    rig.until(lambda: len(cands) > 1, 'the unverified answer', proc)
    assert all(math.isnan(x) for x in msgs.cloud_to_candidates(cands[1])['inliers'])
    rig.wait_counter(MATCHER, 'verify_missing_keypoints', 1, proc)
    # a malformed keypoints cloud: counted, the node lives, the query is still answered
    bad = msgs.keypoints_to_cloud(scenes['kps'][4], header(102, 'query'))
    bad.data = bad.data[:-7]
    kp_pub.publish(bad)
    rig.probe.spin_for(0.05)
    q_pub.publish(msgs.landmarks_to_cloud(scenes['sets'][4], header(102, 'query')))
    rig.until(lambda: len(cands) > 2, 'the answer after bad keypoints', proc)
    rig.wait_counter(MATCHER, 'bad_keypoints', 1, proc)
    assert proc.alive()
    assert proc.stop() == 0, read_log(proc)

    with MapStore(map_path, create=False) as store:
        for kid, kps in zip(store.ids(), scenes['kps'][:4]):
            uv, desc = store.keypoints(kid)
            np.testing.assert_array_equal(uv, kps.uv)
            np.testing.assert_array_equal(desc, kps.descriptors)
        assert store.get(best).meta['stamp'] == (int(header(2).stamp.sec), int(header(2).stamp.nanosec))
        assert store.check() == []
