"""A part of MatcherNode (matcher.py), as a mixin: the metric inputs and outputs of issue 27 —
camera_info (or camera_info_file), odom, lln/pose and ~/relocalize — and the two-thread executor
the sensor callbacks need. State is MatcherNode's (params, loc, health)."""

from __future__ import annotations

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import CameraInfo
from std_srvs.srv import Trigger

from ..core.sequence import KeyframeSequence
from ..errors import LLNError
from ..ros import msgs, topics
from .common import failed_response, guarded, subscription_qos, two_thread_executor


class MetricInputs:
    """camera_info / odom subscriptions on their own thread, lln/pose, ~/relocalize."""

    def start_metric(self, p: dict) -> None:
        # odometry at 100 Hz must not overflow the reader while a query is being answered: 10 s of it
        sensor_qos = subscription_qos(p['sensor_reliability'], 1000)
        # their own thread (make_executor): one take per subscription and executor round would let
        # 100 Hz odometry fall seconds behind the queries it must pose
        sensors = MutuallyExclusiveCallbackGroup()
        if p['camera_info_file']:
            from ..io.camera import CameraModel

            self.loc.reg.set_camera(CameraModel.from_camera_info(p['camera_info_file']))  # CameraError: fatal
        else:
            self.create_subscription(
                CameraInfo, topics.CAMERA_INFO, self.on_camera_info, sensor_qos, callback_group=sensors
            )
        self.create_subscription(Odometry, topics.ODOM, self.on_odometry, sensor_qos, callback_group=sensors)
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, topics.POSE, 10)
        self.create_service(Trigger, '~/relocalize', self.on_relocalize)

    def make_executor(self):
        """Two threads: the node's default group (every answer, serialised: the Localizer is used by
        one caller at a time) and the sensors group (odometry, camera_info)."""
        return two_thread_executor()

    @guarded('camera_info callback')
    def on_camera_info(self, msg: CameraInfo) -> None:
        try:
            # zeros (uncalibrated), NaN, a principal point outside the size, a size not the images': not used
            self.loc.reg.set_camera(msgs.camera_info_to_model(msg))
        except LLNError as e:
            self.loc.refuse('bad_camera_info', e)

    @guarded('odometry callback')
    def on_odometry(self, msg: Odometry) -> None:
        try:
            odom = msgs.odometry_to_pose(msg)
        except LLNError as e:  # NaN, a non-unit quaternion: never buffered, so never stored with a keyframe
            self.loc.refuse('bad_odometry', e)
            return
        self.loc.reg.add_odometry(odom)

    def publish_pose(self, pose, stamp_ns: int) -> None:
        """Localization mode: an accepted metric pose of a keyframe with an odometry pose, as the
        camera's pose in the stored poses' frame."""
        if self.params['mode'] == 'localization' and pose is not None and pose.T_map is not None:
            self.pose_pub.publish(msgs.pose_to_message(pose.T_map, pose.cov_map, stamp_ns, pose.frame_id))
            self.health.count('poses_published')

    @guarded('~/relocalize', failed_response)
    def on_relocalize(self, request, response):
        def relocalize():
            self.loc.reg.reset()
            if self.loc.sequence is not None:  # the sequence search starts afresh too
                self.loc.sequence = KeyframeSequence.of(self.loc.conf)
            return 'pose consistency state cleared: the next accepted pose starts from scratch'

        return self._service(response, relocalize)
