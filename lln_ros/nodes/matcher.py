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
from ..landmark_index import check_prefilter
from ..mapstore import MapStore
from ..retrieval import default_conf as retrieval_conf
from ..sequence import KeyframeSequence
from .common import MODEL_QOS, Health, declare, run_node, start_diagnostics, subscription_qos

PARAMETERS = {
    'map_path': ('~/.ros/lln_ros/map.db', 'map URI: SQLite file path (created if missing), '
                 'milvus-lite:///path.db or milvus://host:port[/db][?map=name]'),
    'mode': ('localization', 'localization: answer queries only | mapping: answer, then store each query'),
    'prefilter': (retrieval_conf['prefilter'], 'first stage: landmarks (every query landmark against every map '
                  'landmark, voted per keyframe) | holistic (global descriptor cosine) | exhaustive (every keyframe)'),
    'prefilter_k': (retrieval_conf['prefilter_k'], 'first-stage candidates reranked by the landmark similarity; '
                    '0 = every keyframe (exhaustive, whatever prefilter says; cost grows with the map)'),
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
}


def space_model(space: str) -> dict:
    """{'descriptor_space', 'descriptor_dim'} from a 'backbone/layer/D' string."""
    try:
        dim = int(space.rsplit('/', 1)[1])
    except (IndexError, ValueError):
        raise ValueError(f"descriptor_space must look like 'backbone/layer/D', got {space!r}") from None
    return {'descriptor_space': space, 'descriptor_dim': dim}


class MatcherNode(Node):
    def __init__(self, **kwargs):
        super().__init__('lln_matcher', **kwargs)
        p = self.params = declare(self, PARAMETERS)
        if p['mode'] not in ('localization', 'mapping'):
            raise ValueError(f"mode must be 'localization' or 'mapping', got {p['mode']!r}")
        if p['method'] not in ('lln', 'holistic'):
            raise ValueError(f"method must be 'lln' or 'holistic', got {p['method']!r}")
        check_prefilter(p['prefilter'], p['prefilter_k'])
        if p['sequence_length'] < 0:
            raise ValueError(f"sequence_length must be 0 (off) or positive, got {p['sequence_length']}")
        self.sequence = KeyframeSequence({'length': p['sequence_length'], 'max_gap_s': p['sequence_max_gap']}) \
            if p['sequence_length'] > 0 else None
        self.store = MapStore.open(p['map_path'], model=space_model(p['descriptor_space'])
                                   if p['descriptor_space'] else None)
        self.health = Health(self)
        self.refusing = ''  # set when the extractor's model differs from the map's
        qos = subscription_qos(p['reliability'], p['queue_depth'])
        self.candidates_pub = self.create_publisher(PointCloud2, 'candidates', 10)
        self.matches_pub = self.create_publisher(PointCloud2, 'matches', 10)
        self.create_subscription(PointCloud2, 'keyframes', self.on_keyframe, qos)
        self.create_subscription(PointCloud2, 'query', self.on_query, qos)
        self.create_subscription(String, 'model_info', self.on_model_info, MODEL_QOS)
        self.reloc, self.pending_keypoints, self.unmatched_keyframes = None, {}, {}
        if p['verify']:
            from ..reloc import Relocalizer
            self.reloc = Relocalizer({'min_inliers': p['verify_min_inliers'], 'margin': p['verify_margin']})
            self.create_subscription(PointCloud2, 'keypoints', self.on_keypoints, qos)
        self.create_service(Trigger, '~/save', self.on_save)
        self.create_service(Trigger, '~/clear', self.on_clear)
        self.create_service(Trigger, '~/info', self.on_info)
        start_diagnostics(self, self.health, p['diagnostics_period'], lambda: {'keyframes': len(self.store)})
        model = self.store.model
        self.get_logger().info(
            f"map {self.store.path}: {len(self.store)} keyframes, model "
            f"{model['descriptor_space'] if model else '(none yet)'}; mode {p['mode']}")

    # ------------------------------------------------------------------ inputs

    def on_model_info(self, msg: String) -> None:
        try:
            model = json.loads(msg.data)
            self.store.use_model(model)
            self.refusing = ''
        except LLNError as e:  # before ValueError: LLNError (MapError) subclasses it
            self.refusing = str(e)
            self.get_logger().error(f'{e}; landmark input is refused until the models agree')
        except (ValueError, KeyError, TypeError) as e:
            self.health.problem('bad_model_info', f'cannot read model_info: {e}')

    def decode(self, msg: PointCloud2, kind: str):
        if self.refusing:
            self.health.problem(kind, self.refusing)
            return None
        model = self.store.model
        try:
            return msgs.cloud_to_landmarks(msg, expected_dim=model['descriptor_dim'] if model else None,
                                           descriptor_space=model['descriptor_space'] if model else '')
        except LLNError as e:
            self.health.problem(kind, str(e))
            return None

    def on_keypoints(self, msg: PointCloud2) -> None:
        """Held until the landmark set with the same stamp arrives (the newest 100 are kept); two
        topics are not ordered, so keypoints of a keyframe already stored are attached to it."""
        stamp = msgs.stamp_to_ns(msg.header.stamp)
        kid = self.unmatched_keyframes.pop(stamp, None)
        if kid is None:
            self.pending_keypoints[stamp] = msg
            _bound(self.pending_keypoints)
            return
        try:
            kps = self.decode_keypoints(msg, self.store.get(kid))
            if kps is not None:
                self.store.add_keypoints(kid, kps.uv, kps.descriptors)
        except (LLNError, KeyError) as e:
            self.health.problem('bad_keypoints', str(e))

    def take_keypoints(self, stamp, lset):
        """The keypoints sent with this landmark set (by stamp), decoded, or None."""
        msg = self.pending_keypoints.pop(msgs.stamp_to_ns(stamp), None) if self.reloc else None
        if msg is None:
            if self.reloc:
                self.health.count('verify_missing_keypoints')
            return None
        return self.decode_keypoints(msg, lset)

    def decode_keypoints(self, msg, lset):
        from ..reloc import detection_scale
        w, h = (float(v) for v in lset.image_size)
        try:
            return msgs.cloud_to_keypoints(msg, (w, h), detection_scale(h, self.reloc.conf['min_height']))
        except LLNError as e:
            self.health.problem('bad_keypoints', str(e))
            return None

    def store_keyframe(self, lset, stamp, kps) -> None:
        kid = self.store.add(lset, stamp)
        if kps is not None:
            self.store.add_keypoints(kid, kps.uv, kps.descriptors)
        elif self.reloc is not None:   # its keypoints may still come
            self.unmatched_keyframes[msgs.stamp_to_ns(stamp)] = kid
            _bound(self.unmatched_keyframes)
        self.health.count('keyframes_stored')

    def stored_keypoints(self, keyframe_id: int, image_size):
        from ..reloc import Keypoints, detection_scale
        found = self.store.keypoints(keyframe_id)
        if found is None:
            return None
        uv, desc = found
        kps = Keypoints.empty(image_size)
        kps.uv, kps.descriptors = uv, desc
        kps.scale = detection_scale(image_size[1], self.reloc.conf['min_height'])
        return kps

    def on_keyframe(self, msg: PointCloud2) -> None:
        lset = self.decode(msg, 'bad_keyframe')
        if lset is None:
            return
        try:
            self.store_keyframe(lset, msg.header.stamp, self.take_keypoints(msg.header.stamp, lset))
        except (LLNError, ValueError) as e:
            self.health.problem('bad_keyframe', str(e))
            return

    def on_query(self, msg: PointCloud2) -> None:
        self.health.count('queries_received')
        max_age = self.params['max_query_age']
        if max_age > 0:
            age = (self.get_clock().now().nanoseconds - msgs.stamp_to_ns(msg.header)) * 1e-9
            if age > max_age:
                self.health.count('queries_stale')
                return
        lset = self.decode(msg, 'bad_query')
        if lset is None:
            return
        p = self.params
        mapping = p['mode'] == 'mapping'
        kps = self.take_keypoints(msg.header.stamp, lset)
        sequence = self.sequence is not None  # the sequence search needs every reranked candidate
        try:
            found = self.store.query(lset, prefilter_k=p['prefilter_k'],
                                     k=(p['prefilter_k'] or max(len(self.store), 1)) if sequence else p['k'],
                                     min_score=None if sequence else p['min_score'],
                                     exclude_recent=p['exclude_recent'] if mapping else 0,
                                     method_rerank=p['method'] == 'lln', scale=p['offset_scale'],
                                     prefilter=p['prefilter'] if p['method'] == 'lln' else 'holistic')
            inliers = {}
            if self.reloc is not None:
                found, inliers = self.verify(lset, kps, found)
            if mapping:  # committed before the answer goes out: an answered keyframe is never lost
                self.store_keyframe(lset, msg.header.stamp, kps)
        except (LLNError, ValueError) as e:
            self.health.problem('bad_query', str(e))
            return
        rows = [{'keyframe_id': c.keyframe_id, 'score': c.score, 'holistic_score': c.holistic_score,
                 'stamp_sec': c.stamp[0], 'stamp_nanosec': c.stamp[1],
                 **({'inliers': inliers.get(c.keyframe_id, float('nan'))} if self.reloc else {})} for c in found]
        if sequence:
            rows, found = self.sequence_rows(found, msg, mapping, inliers if self.reloc else None)
        # a zero-row answer carries the same optional fields as the others
        extra = ('inliers',) * (self.reloc is not None) + ('sequence_score',) * sequence
        self.candidates_pub.publish(msgs.candidates_to_cloud(rows, msg.header, extra))
        best = found[0] if found else None
        self.matches_pub.publish(msgs.matches_to_cloud(
            msgs.match_rows(best.keyframe_id, best.pairs) if best else [], msg.header))
        self.health.count('queries_answered')

    def verify(self, lset, kps, found):
        """Candidates re-ranked by region-constrained inliers, and {keyframe_id: inliers}."""
        from ..reloc import verify_candidates
        if kps is None or not found:
            return found, {}
        ranked = verify_candidates(self.reloc, kps, lset.cell_size, found,
                                   lambda c: self.stored_keypoints(c.keyframe_id, c.image_size))
        self.health.count('queries_verified')
        return [c for c, _ in ranked], {c.keyframe_id: float(r.inliers) for c, r in ranked if r is not None}

    def sequence_rows(self, found: list, msg: PointCloud2, mapping: bool,
                      inliers: dict | None = None) -> tuple[list, list]:
        """Candidate rows ranked by sequence_score, and the MapCandidates among them (same order)
        for the matches topic. Called before a mapping-mode query's own keyframe joins the ids.
        inliers: verify mode's {keyframe_id: inliers} (rows get an `inliers` field, NaN if unknown)."""
        p = self.params
        size = len(self.store) - int(mapping)  # mapping: the query was just stored, never its own answer
        if size != len(self.sequence.ids):  # keyframes only append (or ~/clear): re-read the ids then
            self.sequence.set_map(self.store.ids()[:size])
        allowed = size - p['exclude_recent'] if mapping else None
        reason, ranked = self.sequence.update(msgs.stamp_to_ns(msg.header), {c.keyframe_id: c.score for c in found},
                                              allowed, p['k'])
        if reason:
            self.health.count(f'sequence_reset_{reason}')
        by_id = {c.keyframe_id: c for c in found}
        rows = []
        for kf, seq_score in ranked:
            if seq_score < p['min_score']:
                continue
            c = by_id.get(kf)
            stamp = c.stamp if c else self.store.get(kf).meta['stamp']
            rows.append({'keyframe_id': kf, 'score': c.score if c else 0.0,
                         'holistic_score': c.holistic_score if c else 0.0,
                         'stamp_sec': stamp[0], 'stamp_nanosec': stamp[1], 'sequence_score': seq_score,
                         **({'inliers': inliers.get(kf, float('nan'))} if inliers is not None else {})})
        first = by_id.get(rows[0]['keyframe_id']) if rows else None
        return rows, [first] if first else []

    # ------------------------------------------------------------------ services

    def on_save(self, request, response):
        def save():
            self.store.save()
            return f'saved {len(self.store)} keyframes to {self.store.path}'
        return self._service(response, save)

    def on_clear(self, request, response):
        def clear():
            removed = self.store.clear()
            if self.sequence is not None:
                self.sequence.set_map([])
            return f'cleared {removed} keyframes from {self.store.path}'
        return self._service(response, clear)

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
        self.store.close()
        return super().destroy_node()


def _bound(pending: dict, size: int = 100) -> None:
    """Keep the newest `size` entries of an insertion-ordered dict."""
    while len(pending) > size:
        pending.pop(next(iter(pending)))


def main(args=None):
    return run_node(MatcherNode, 'lln_matcher', args)


if __name__ == '__main__':
    sys.exit(main())
