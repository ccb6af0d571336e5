"""lln_matcher: the map server (`ros2 run lln_ros matcher`).

Subscribes  keyframes (PointCloud2 landmark sets to store), query (landmark sets to localize),
            model_info (std_msgs/String, the extractor's model, latched), keypoints (PointCloud2,
            the extractor's ORB keypoints; with verify)
Publishes   candidates (PointCloud2: keyframe_id, score, holistic_score, stamp_sec, stamp_nanosec;
            with verify also inliers, NaN where the keyframe or query had no keypoints;
            with sequence_length > 0 also sequence_score),
            matches (PointCloud2: the matched region pairs of the best candidate), /diagnostics
Services    ~/save, ~/clear, ~/info (std_srvs/Trigger; info answers JSON)

mode=localization answers queries and leaves the map alone; mode=mapping answers each query, then
stores it as a keyframe (online loop-closure detection; the newest `exclude_recent` keyframes are
never answers). A keyframe is committed to the SQLite map before its query's answer is published,
so whatever a subscriber has seen answered survives kill -9.

verify=true: keypoints are paired with landmark sets by header stamp and stored per keyframe; the
top candidates are re-ranked by region-constrained RANSAC inliers (lln_ros.reloc.verify_candidates).

sequence_length L > 0 ranks keyframes by sequence agreement over the last L queries (lln_ros.sequence,
the search lln-eval --sequence runs offline): candidates come best sequence_score first, min_score
applies to sequence_score, and `score` / `holistic_score` are this query's own (0 = the keyframe was
not among this query's prefilter_k). Out-of-order stamps and gaps longer than sequence_max_gap start a
new sequence (counted as sequence_reset_out_of_order / sequence_reset_gap).

What happens to each message is decided by lln_ros.localizer.Localizer (ROS-free, unit-tested
without rclpy); this node decodes (lln_ros.msgs), calls it and publishes. Input limits
(max_image_pixels, max_landmarks, max_descriptor_dim, max_grid_side, max_keypoints) default to
lln_ros.limits.default_conf.
"""
from __future__ import annotations

import json
import sys

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from .. import msgs
from ..errors import LLNError
from ..limits import default_conf as LIMITS
from ..localizer import Localizer, open_map
from .common import MODEL_QOS, Health, declare, run_node, start_diagnostics, subscription_qos

PARAMETERS = {
    'map_path': ('~/.ros/lln_ros/map.db', 'map URI: SQLite file path (created if missing), '
                 'milvus-lite:///path.db or milvus://host:port[/db][?map=name]'),
    'mode': ('localization', 'localization: answer queries only | mapping: answer, then store each query'),
    'prefilter_k': (30, 'holistic candidates reranked by the landmark similarity; 0 = every keyframe '
                        '(exhaustive: no holistic cap on recall, cost grows with the map)'),
    'k': (5, 'candidates published per query'),
    'min_score': (0.0, 'candidates scoring below this are not published'),
    'exclude_recent': (10, 'mapping mode: the newest N keyframes are never answers'),
    'method': ('lln', 'lln: rerank by landmark similarity S | holistic: global descriptor only'),
    'offset_scale': (1.0, 'Gaussian width of the offset weights, in grid cells'),
    'descriptor_space': ('', "expected model, e.g. efficientnet_lite0/stage6/192; '' = the map's or first seen"),
    'reliability': ('reliable', 'keyframes/query subscriptions: reliable | best_effort'),
    'queue_depth': (100, 'keyframes/query subscription queue depth'),
    'verify': (False, "re-rank candidates by keypoint inliers (needs the extractor's publish_keypoints)"),
    'verify_min_inliers': (15, 'verify: RANSAC inliers for a candidate to count as verified'),
    'verify_margin': (1.0, 'verify: matched regions grown by this many grid cells'),
    'max_query_age': (0.0, 'seconds; older queries (header stamp vs node clock) are dropped and counted '
                           'as queries_stale, so a backlog cannot grow latency; 0 = off'),
    'diagnostics_period': (1.0, 'seconds between /diagnostics messages; 0 = off'),
    'sequence_length': (0, 'queries in the sequence search (0 = off, single-frame ranking)'),
    'sequence_max_gap': (1.0, 'seconds between query stamps beyond which a new sequence starts'),
    # input limits (lln_ros.limits): a message declaring more is refused and counted, never sized from
    'max_image_pixels': (LIMITS['max_image_pixels'], 'limit: image width x height a landmark cloud may declare'),
    'max_landmarks': (LIMITS['max_landmarks'], 'limit: landmark rows per keyframe or query'),
    'max_descriptor_dim': (LIMITS['max_descriptor_dim'], 'limit: descriptor size D (clouds and model_info)'),
    'max_grid_side': (LIMITS['max_grid_side'], 'limit: grid cells a side a landmark cloud may declare '
                                               '(image size / cell size)'),
    'max_keypoints': (LIMITS['max_keypoints'], 'limit: rows per keypoints cloud (verify)'),
}


class MatcherNode(Node):
    def __init__(self, **kwargs):
        super().__init__('lln_matcher', **kwargs)
        p = self.params = declare(self, PARAMETERS)
        self.health = Health(self)
        conf = {name: p[name] for name in ('mode', 'prefilter_k', 'k', 'min_score', 'exclude_recent', 'method',
                                           'offset_scale', 'max_query_age', 'verify', 'verify_min_inliers',
                                           'verify_margin', 'sequence_length', 'sequence_max_gap')}
        conf['limits'] = {name: p[name] for name in LIMITS}
        Localizer.check_conf(conf)   # a bad parameter ends the node before the map is touched
        self.store, quarantined = open_map(p['map_path'], p['mode'], p['descriptor_space'])
        self.loc = Localizer(self.store, conf, self.health, self.get_logger(), msgs.cloud_to_keypoints)
        qos = subscription_qos(p['reliability'], p['queue_depth'])
        self.candidates_pub = self.create_publisher(PointCloud2, 'candidates', 10)
        self.matches_pub = self.create_publisher(PointCloud2, 'matches', 10)
        self.create_subscription(PointCloud2, 'keyframes', self.on_keyframe, qos)
        self.create_subscription(PointCloud2, 'query', self.on_query, qos)
        self.create_subscription(String, 'model_info', self.on_model_info, MODEL_QOS)
        if p['verify']:
            self.create_subscription(PointCloud2, 'keypoints', self.on_keypoints, qos)
        self.create_service(Trigger, '~/save', self.on_save)
        self.create_service(Trigger, '~/clear', self.on_clear)
        self.create_service(Trigger, '~/info', self.on_info)
        start_diagnostics(self, self.health, p['diagnostics_period'], lambda: {'keyframes': len(self.store)})
        if quarantined:
            self.get_logger().error(
                f'map {self.store.path}: {len(quarantined)} damaged keyframe(s) quarantined: never answered, '
                f'left in the file (lln-map check lists them): {"; ".join(list(quarantined.values())[:10])}')
        model = self.store.model
        self.get_logger().info(
            f"map {self.store.path}: {len(self.store)} keyframes, model "
            f"{model['descriptor_space'] if model else '(none yet)'}; mode {p['mode']}")

    # ------------------------------------------------------------------ inputs

    def on_model_info(self, msg: String) -> None:
        self.loc.model_info(msg.data)

    def decode(self, msg: PointCloud2, counter: str):
        args = self.loc.landmark_decoding(counter)
        if args is None:
            return None
        try:
            return msgs.cloud_to_landmarks(msg, **args)
        except LLNError as e:
            self.loc.refuse(counter, e)
            return None

    def on_keypoints(self, msg: PointCloud2) -> None:
        self.loc.keypoints(msg, msgs.stamp_to_ns(msg.header.stamp))

    def on_keyframe(self, msg: PointCloud2) -> None:
        self.loc.count('keyframes_received')
        lset = self.decode(msg, 'bad_keyframe')
        if lset is not None:
            self.loc.keyframe(lset, msgs.stamp_to_ns(msg.header.stamp))

    def on_query(self, msg: PointCloud2) -> None:
        stamp = msgs.stamp_to_ns(msg.header)
        if not self.loc.query_fresh(stamp, self.get_clock().now().nanoseconds):
            return
        lset = self.decode(msg, 'bad_query')
        answer = self.loc.query(lset, stamp) if lset is not None else None
        if answer is None:
            return
        self.candidates_pub.publish(msgs.candidates_to_cloud(answer.rows, msg.header, answer.extra_fields))
        best = answer.best
        self.matches_pub.publish(msgs.matches_to_cloud(
            msgs.match_rows(best.keyframe_id, best.pairs) if best else [], msg.header))
        self.health.count('queries_answered')

    # ------------------------------------------------------------------ services

    def on_save(self, request, response):
        def save():
            self.store.save()
            return f'saved {len(self.store)} keyframes to {self.store.path}'
        return self._service(response, save)

    def on_clear(self, request, response):
        return self._service(response, lambda: f'cleared {self.loc.clear()} keyframes from {self.store.path}')

    def on_info(self, request, response):
        return self._service(response, lambda: json.dumps(
            {**self.store.info(), 'mode': self.params['mode'], 'counters': self.health.snapshot()}))

    def _service(self, response, action):
        try:
            response.message = action()
            response.success = True
        except (LLNError, OSError) as e:
            response.success, response.message = False, str(e)
            self.get_logger().error(str(e))
        return response

    def destroy_node(self):
        if getattr(self, 'store', None) is not None:
            self.store.close()
        return super().destroy_node()


def main(args=None):
    return run_node(MatcherNode, 'lln_matcher', args)


if __name__ == '__main__':
    sys.exit(main())
