"""lln_matcher: the map server (`ros2 run lln_ros matcher`).

Subscribes  lln/keyframes (PointCloud2 landmark sets to store), lln/query (landmark sets to localize),
            lln/model_info (std_msgs/String, the extractor's model, latched), lln/keypoints (PointCloud2,
            the extractor's ORB keypoints, with depth when it has depth; with verify),
            camera_info (sensor_msgs/CameraInfo; or the camera_info_file parameter), odom (nav_msgs/Odometry)
Publishes   lln/candidates (PointCloud2: keyframe_id, score, holistic_score, stamp_sec, stamp_nanosec;
            with verify also inliers, NaN where the keyframe or query had no keypoints;
            with sequence_length > 0 also sequence_score),
            lln/matches (PointCloud2: the matched region pairs of the best candidate), /diagnostics,
            lln/pose (geometry_msgs/PoseWithCovarianceStamped: localization mode, the camera in the
            frame of the keyframes' odometry poses, for each accepted metric pose)
Services    ~/save, ~/clear, ~/info, ~/relocalize, ~/new_session (std_srvs/Trigger; info answers
            JSON; relocalize forgets the pose-consistency state: a kidnapped robot; new_session starts
            a new mapping session of this robot)

With verify and geometry (default on), the best candidate's T(keyframe <- query) and its 6x6
covariance go in the candidates table as pose_* / tx..qw / cov_0..cov_35 fields (docs/interfaces.md;
lln_ros.core.registration). Keyframes keep the camera model, keypoint depths and the odometry pose.

mode=localization answers queries and leaves the map alone; mode=mapping answers each query, then
stores it as a keyframe (online loop-closure detection; the newest `exclude_recent` keyframes of
this session are never answers). Each stored keyframe records (robot_id, session, seq); answers
carry the keyframe's session_id (~/info lists the sessions: robot and label). A keyframe is
committed to the SQLite map before its query's answer is published, so whatever a subscriber has
seen answered survives kill -9.

verify=true: keypoints are paired with landmark sets by header stamp and stored per keyframe; the
top candidates are re-ranked by region-constrained RANSAC inliers (lln_ros.core.reloc.verify_candidates).

sequence_length L > 0 ranks keyframes by sequence agreement over the last L queries (lln_ros.core.sequence,
the search lln-eval --sequence runs offline; with sequence_score_norm zscore each query's S in
standard deviations above its lowest candidate): candidates come best sequence_score first, min_score
applies to sequence_score, and `score` / `holistic_score` are this query's own (0 = the keyframe was
not among this query's prefilter_k). Out-of-order stamps and gaps longer than sequence_max_gap start a
new sequence (counted as sequence_reset_out_of_order / sequence_reset_gap).

What happens to each message is decided by lln_ros.core.localizer.Localizer (ROS-free, unit-tested
without rclpy); this node decodes (lln_ros.ros.msgs), calls it and publishes. Input limits
(max_image_pixels, max_landmarks, max_descriptor_dim, max_grid_side, max_keypoints) default to
lln_ros.core.limits.default_conf.
"""

from __future__ import annotations

import json
import sys

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..core.landmark_index import PREFILTERS
from ..core.limits import default_conf as LIMITS
from ..core.localizer import CHOICES, Localizer
from ..core.localizer import default_conf as LOC
from ..core.sequence import KeyframeSequence
from ..errors import LLNError
from ..mapstore import open_for_matcher
from ..ros import msgs, topics
from ..ros.stream import StampGaps
from .common import (
    MODEL_QOS,
    Health,
    failed_response,
    guarded,
    loss_events,
    run_node,
    start_diagnostics,
    subscription_qos,
    worst,
)
from .matcher_fleet import FleetIdentity
from .matcher_metric import MetricInputs
from .parameters import Param, declare_all, diagnostics_period
from .registration_params import KEYS as REG_KEYS
from .registration_params import PARAMETERS as REGISTRATION_PARAMETERS
from .registration_params import registration_conf
from .sequence_params import KEYS as SEQUENCE_KEYS
from .sequence_params import PARAMETERS as SEQUENCE_PARAMETERS

# defaults come from the ROS-free confs (lln_ros.core.localizer / limits): one source each.
# dynamic=True: settable at run time (ros2 param set), applied from the next message on
PARAMETERS = {
    'map_path': Param(
        '~/.ros/lln_ros/map.db',
        'map URI: SQLite file path (created if missing), milvus-lite:///path.db or milvus://host:port[/db][?map=name]',
    ),
    'mode': Param(
        LOC['mode'],
        'localization: answer queries only | mapping: answer, then store each query',
        choices=CHOICES['mode'],
    ),
    'prefilter': Param(
        LOC['prefilter'],
        'first stage: landmarks (every query landmark against every map landmark, '
        'voted per keyframe) | holistic (global descriptor cosine) | exhaustive (every keyframe)',
        dynamic=True,
        choices=PREFILTERS,
    ),
    'prefilter_k': Param(
        LOC['prefilter_k'],
        'first-stage candidates reranked by the landmark similarity; 0 = every '
        'keyframe (exhaustive, whatever prefilter says; cost grows with the map)',
        dynamic=True,
        range=(0, 1_000_000),
    ),
    'k': Param(LOC['k'], 'candidates published per query', dynamic=True, range=(1, 10_000_000)),
    # no range: any threshold is meaningful (lln-demo passes -1e9 for "publish every candidate")
    'min_score': Param(LOC['min_score'], 'candidates scoring below this are not published', dynamic=True),
    'exclude_recent': Param(
        LOC['exclude_recent'],
        "mapping mode: this session's newest N keyframes are never answers (another robot's or run's are)",
        dynamic=True,
        range=(0, 1_000_000),
    ),
    'method': Param(
        LOC['method'],
        'lln: rerank by landmark similarity S | holistic: global descriptor only',
        dynamic=True,
        choices=CHOICES['method'],
    ),
    'similarity': Param(
        LOC['similarity'],
        "the landmark similarity S's sets: raw (the paper's) | center | whiten | fuse (raw S + 2 x whitened S); "
        'min_score is in units of the S chosen',
        dynamic=True,
        choices=CHOICES['similarity'],
    ),
    'offset_scale': Param(
        LOC['offset_scale'], 'Gaussian width of the offset weights, in grid cells', dynamic=True, range=(1e-3, 1e3)
    ),
    'descriptor_space': Param('', "expected model, e.g. efficientnet_lite0/stage6/192; '' = the map's or first seen"),
    'robot_id': Param(
        '',
        "this robot in a shared map (keyframes are stored as robot, session, seq); '' = the node's namespace, "
        'or the host name in the root namespace',
    ),
    'reliability': Param('reliable', 'keyframes/query subscriptions', choices=('reliable', 'best_effort')),
    'queue_depth': Param(100, 'keyframes/query subscription queue depth', range=(1, 100_000)),
    'verify': Param(LOC['verify'], "re-rank candidates by keypoint inliers (needs the extractor's publish_keypoints)"),
    'verify_min_inliers': Param(
        LOC['verify_min_inliers'],
        'verify: RANSAC inliers for a candidate to count as verified',
        dynamic=True,
        range=(1, 100_000),
    ),
    'verify_margin': Param(
        LOC['verify_margin'], 'verify: matched regions grown by this many grid cells', dynamic=True, range=(0.0, 100.0)
    ),
    'max_query_age': Param(
        LOC['max_query_age'],
        'seconds; older queries (header stamp vs node clock: use_sim_time '
        'for bags) are dropped and counted as queries_stale, so a backlog cannot grow '
        'latency; 0 = off',
        dynamic=True,
        range=(0.0, 1e9),
    ),
    'diagnostics_period': diagnostics_period(),
    # input limits (lln_ros.core.limits): a message declaring more is refused and counted, never sized from
    'max_image_pixels': Param(
        LIMITS['max_image_pixels'], 'limit: image width x height a landmark cloud may declare', range=(1, 2**40)
    ),
    'max_landmarks': Param(LIMITS['max_landmarks'], 'limit: landmark rows per keyframe or query', range=(1, 2**31 - 1)),
    'max_descriptor_dim': Param(
        LIMITS['max_descriptor_dim'], 'limit: descriptor size D (clouds and model_info)', range=(1, 2**31 - 1)
    ),
    'max_grid_side': Param(
        LIMITS['max_grid_side'],
        'limit: grid cells a side a landmark cloud may declare (image size / cell size)',
        range=(1, 2**31 - 1),
    ),
    'max_keypoints': Param(LIMITS['max_keypoints'], 'limit: rows per keypoints cloud (verify)', range=(1, 2**31 - 1)),
    'max_point_fields': Param(LIMITS['max_point_fields'], 'limit: PointFields per cloud', range=(1, 2**16)),
    **SEQUENCE_PARAMETERS,
    **REGISTRATION_PARAMETERS,
}
# the Localizer's own settings among them (updated in place at run time: it reads them per message)
LOCALIZER_KEYS = (
    'mode',
    'prefilter',
    'prefilter_k',
    'k',
    'min_score',
    'exclude_recent',
    'method',
    'similarity',
    'offset_scale',
    'max_query_age',
    'verify',
    'verify_min_inliers',
    'verify_margin',
    *SEQUENCE_KEYS,
)


class MatcherNode(MetricInputs, FleetIdentity, Node):
    def __init__(self, **kwargs):
        super().__init__('lln_matcher', **kwargs)
        p = self.params = declare_all(self, PARAMETERS, self.on_parameters)
        self.health = Health(self)
        conf = {name: p[name] for name in LOCALIZER_KEYS}
        conf['limits'] = {name: p[name] for name in LIMITS}
        conf['registration'] = registration_conf(p)
        Localizer.check_conf(conf)  # a bad parameter ends the node before the map is touched
        self.store, quarantined = open_for_matcher(p['map_path'], p['mode'], p['descriptor_space'])
        self.loc = Localizer(self.store, conf, self.health, self.get_logger(), msgs.cloud_to_keypoints)
        qos = subscription_qos(p['reliability'], p['queue_depth'])
        self.candidates_pub = self.create_publisher(PointCloud2, topics.CANDIDATES, 10)
        self.matches_pub = self.create_publisher(PointCloud2, topics.MATCHES, 10)
        self.query_topic = self.resolve_topic_name(topics.QUERY)
        if p['verify']:  # before the landmark subscriptions: a round of the executor takes it first
            self.create_subscription(PointCloud2, topics.KEYPOINTS, self.on_keypoints, qos)
        self.keyframes_sub = self.create_subscription(
            PointCloud2,
            topics.KEYFRAMES,
            self.on_keyframe,
            qos,
            event_callbacks=loss_events(self.health, 'keyframes subscription'),
        )
        self.query_sub = self.create_subscription(
            PointCloud2,
            topics.QUERY,
            self.on_query,
            qos,
            event_callbacks=loss_events(self.health, f'query subscription {self.query_topic}'),
        )
        self.gaps = StampGaps()
        self.last_query_age = None  # seconds, header stamp vs node clock (sim time with use_sim_time)
        self.create_subscription(String, topics.MODEL_INFO, self.on_model_info, MODEL_QOS)
        self.start_metric(p)  # camera_info, odom, lln/pose, ~/relocalize (matcher_metric.MetricInputs)
        self.start_session(p)  # robot_id, the mapping session, ~/new_session (matcher_fleet.FleetIdentity)
        self.create_service(Trigger, '~/save', self.on_save)
        self.create_service(Trigger, '~/clear', self.on_clear)
        self.create_service(Trigger, '~/info', self.on_info)
        self.diagnostics = start_diagnostics(
            self, self.health, p['diagnostics_period'], self.diagnostic_values, self.status
        )
        if quarantined:
            self.get_logger().error(
                f'map {self.store.path}: {len(quarantined)} damaged keyframe(s) quarantined: never answered, '
                f'left in the file (lln-map check lists them): {"; ".join(list(quarantined.values())[:10])}'
            )
        model = self.store.model
        self.get_logger().info(
            f'map {self.store.path}: {len(self.store)} keyframes, model '
            f'{model["descriptor_space"] if model else "(none yet)"}; mode {p["mode"]}'
        )

    # ------------------------------------------------------------------ parameters and health

    def on_parameters(self, changes: dict) -> None:
        """Run-time changes (range-checked by rclpy, choices by parameters.declare_all); a ValueError
        refuses the whole set with its reason."""
        conf = {**self.loc.conf, **{k: v for k, v in changes.items() if k in LOCALIZER_KEYS}}
        Localizer.check_conf(conf)
        self.loc.conf.update({k: v for k, v in changes.items() if k in LOCALIZER_KEYS})
        if self.loc.reloc is not None:
            self.loc.reloc.conf.update({'min_inliers': conf['verify_min_inliers'], 'margin': conf['verify_margin']})
        if {'sequence_length', 'sequence_max_gap', 'sequence_score_norm'} & set(changes):  # a new sequence
            self.loc.sequence = KeyframeSequence.of(conf)
        reg = {k: v for k, v in changes.items() if k in REG_KEYS}
        if reg:
            self.loc.reg.update(reg)
        if 'diagnostics_period' in changes:
            self.diagnostics.set_period(changes['diagnostics_period'])

    def diagnostic_values(self) -> dict:
        values = {'keyframes': len(self.store)}
        if self.last_query_age is not None:
            values['last_query_age_s'] = f'{self.last_query_age:.3f}'
        return values

    def status(self, delta: dict) -> tuple:
        """/diagnostics level and message: ERROR while every landmark input is refused (model
        mismatch), WARN for losses and refused messages of the last period."""
        from diagnostic_msgs.msg import DiagnosticStatus as S

        problems = []
        if self.loc.refusing:  # quiet: the Localizer logged the refusal as an ERROR line
            problems.append((S.ERROR, f'refusing all landmark input: {self.loc.refusing}', True))
        if delta.get('queries_stale'):
            age = self.last_query_age or 0.0
            hint = (
                ' (stamps are days old: a replayed bag? play it with --clock and start the nodes with '
                'use_sim_time:=true)'
                if age > 86400 and not self.get_parameter('use_sim_time').value
                else ''
            )
            problems.append(
                (
                    S.WARN,
                    f'dropped {delta["queries_stale"]} queries older than max_query_age '
                    f'{self.params["max_query_age"]:g} s (last {age:.3f} s old){hint}',
                )
            )
        if delta.get('queries_missing'):
            problems.append(
                (
                    S.WARN,
                    f'{delta["queries_missing"]} queries missing (gaps in the query stamps: frames '
                    f"lost before the matcher, see the extractor's diagnostics)",
                )
            )
        if delta.get('dds_lost'):
            problems.append((S.WARN, f'DDS reports {delta["dds_lost"]} landmark samples lost'))
        for key in (
            'bad_query',
            'bad_keyframe',
            'bad_keypoints',
            'bad_model_info',
            'bad_camera_info',
            'bad_odometry',
            'queries_failed',
            'keyframes_failed',
            'bad_stored_stamp',
            'internal_error',
        ):
            if delta.get(key) and not (self.loc.refusing and key in ('bad_query', 'bad_keyframe')):
                problems.append((S.WARN, f'{delta[key]} messages refused ({key})', True))  # logged by kind already
        if delta.get('qos_incompatible'):
            problems.append(
                (
                    S.WARN,
                    'a landmark publisher has an incompatible QoS (reliability: the extractor publishes reliable)',
                    True,
                )
            )
        return worst(problems)

    # ------------------------------------------------------------------ inputs

    # every callback below runs under common.guarded: a fault of this code is internal_error, counted
    # and logged by kind, never the end of the process; each header stamp is checked at the door
    # (msgs.header_stamp_ns), so nothing unrepresentable reaches the map or an answer

    @guarded('model_info callback')
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

    def stamp(self, msg, counter: str, what: str) -> int | None:
        try:
            return msgs.header_stamp_ns(msg.header, what)
        except LLNError as e:
            self.loc.refuse(counter, e)
            return None

    @guarded('keypoints callback')
    def on_keypoints(self, msg: PointCloud2) -> None:
        stamp = self.stamp(msg, 'bad_keypoints', 'keypoints cloud')
        if stamp is not None:
            self.loc.keypoints(msg, stamp, len(msg.data))

    @guarded('keyframes callback')
    def on_keyframe(self, msg: PointCloud2) -> None:
        self.loc.count('keyframes_received')
        stamp = self.stamp(msg, 'bad_keyframe', 'keyframes cloud')
        lset = self.decode(msg, 'bad_keyframe') if stamp is not None else None
        if lset is not None:
            self.loc.keyframe(lset, stamp)

    @guarded('query callback')
    def on_query(self, msg: PointCloud2) -> None:
        stamp = self.stamp(msg, 'bad_query', 'query cloud')
        if stamp is None:
            self.loc.count('queries_received')
            return
        now = self.get_clock().now().nanoseconds
        self.last_query_age = (now - stamp) * 1e-9
        missing = self.gaps.add(stamp)
        if missing:
            self.health.count('queries_missing', missing)
        if not self.loc.query_fresh(stamp, now):
            return
        lset = self.decode(msg, 'bad_query')
        answer = self.loc.query(lset, stamp) if lset is not None else None
        if answer is None:
            return
        self.candidates_pub.publish(msgs.candidates_to_cloud(answer.rows, msg.header, answer.extra_fields))
        best = answer.best
        self.matches_pub.publish(
            msgs.matches_to_cloud(msgs.match_rows(best.keyframe_id, best.pairs) if best else [], msg.header)
        )
        self.publish_pose(answer.pose, stamp)
        self.health.count('queries_answered')

    # ------------------------------------------------------------------ services

    @guarded('~/save', failed_response)
    def on_save(self, request, response):
        def save():
            self.store.save()
            return f'saved {len(self.store)} keyframes to {self.store.path}'

        return self._service(response, save)

    @guarded('~/clear', failed_response)
    def on_clear(self, request, response):
        return self._service(response, lambda: f'cleared {self.loc.clear()} keyframes from {self.store.path}')

    @guarded('~/info', failed_response)
    def on_info(self, request, response):
        return self._service(
            response,
            lambda: json.dumps(
                {
                    **self.store.info(),
                    'mode': self.params['mode'],
                    **self.session_info(),
                    'counters': self.health.snapshot(),
                    # readers matched by the answer publishers: a client can wait until its own
                    # subscriptions are among them before it asks (answers are volatile)
                    'subscriptions': {
                        'candidates': self.candidates_pub.get_subscription_count(),
                        'matches': self.matches_pub.get_subscription_count(),
                    },
                    # writers the landmark subscriptions have matched: an extractor's first
                    # landmarks reach us only once it is counted here
                    'publishers': {
                        'keyframes': self.keyframes_sub.get_publisher_count(),
                        'query': self.query_sub.get_publisher_count(),
                    },
                }
            ),
        )

    def _service(self, response, action):
        try:
            response.message = action()
            response.success = True
        except (LLNError, OSError) as e:
            response.success, response.message = False, str(e)
            self.get_logger().error(str(e))
        return response

    def close(self) -> None:
        """Close the map (idempotent); run_node calls it before the DDS teardown."""
        if getattr(self, 'store', None) is not None:
            self.store.close()
            self.store = None

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    return run_node(MatcherNode, 'lln_matcher', args)


if __name__ == '__main__':
    sys.exit(main())
