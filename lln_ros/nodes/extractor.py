"""lln_extractor: camera images in, landmark sets out (`ros2 run lln_ros extractor`).

Subscribes  image (sensor_msgs/Image) or, with image_transport=compressed, image/compressed;
            with depth, depth/image (sensor_msgs/Image, REP 118 16UC1 mm / 32FC1 m, registered to the
            colour camera, paired with the colour image by stamp within depth_max_dt)
Publishes   lln/landmarks (sensor_msgs/PointCloud2, see lln_ros.ros.msgs), lln/activation (sensor_msgs/Image,
            bgr8, with publish_activation), lln/model_info (std_msgs/String, JSON, latched),
            /diagnostics (counters)

Only the newest frame waits for the network: when extraction falls behind, an older waiting frame
is replaced and counted as dropped, so latency stays bounded by one extraction.

Counters: received = published + dropped + bad_image + internal_error (+ the frames waiting, at
most frame_queue, and one in flight). With depth and publish_keypoints, each keypoints cloud gets a
depth field (metres, NaN = none); a frame without a depth image within depth_max_dt counts
depth_missing, a depth image of another size or encoding bad_depth (its keypoints get NaN depths:
the frame itself is still published). Every property of an input (encoding, size, a PNG/JPEG header
above max_image_pixels, undecodable data) is bad_image; internal_error counts only faults of this code.
"""

from __future__ import annotations

import json
import sys
import threading
import time

from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import String

from ..core.backbones import BACKBONES
from ..core.backbones import default_conf as BACKBONE
from ..core.extractor import Extractor
from ..core.extractor import default_conf as EXTRACTOR
from ..core.geometry import keypoint_depth
from ..core.landmarks import METHODS
from ..core.limits import default_conf as LIMITS
from ..core.runtime import RUNTIMES
from ..errors import LLNError
from ..io.image import check_image, heatmap_bgr
from ..io.rgbd import default_conf as RGBD
from ..ros import msgs, topics
from ..ros.stream import StampGaps
from .common import MODEL_QOS, Health, guarded, loss_events, run_node, start_diagnostics, subscription_qos, worst
from .parameters import Param, declare_all, diagnostics_period

# defaults come from the ROS-free confs (lln_ros.core.extractor / backbones / limits): one source each
PARAMETERS = {
    'backbone': Param(BACKBONE['name'], 'backbone', choices=tuple(BACKBONES)),
    'layer': Param(BACKBONE['layer'], "backbone feature layer; '' = the backbone's default"),
    'backbone_weights': Param(
        BACKBONE['weights_path'], "local backbone state dict; '' = shipped weights (resnet101 needs one)"
    ),
    'weights': Param(EXTRACTOR['weights'], "LLN head checkpoint; '' = the head shipped for the backbone"),
    'top_n': Param(EXTRACTOR['top_n'], 'landmarks per image', range=(1, 100_000)),
    'input_height': Param(EXTRACTOR['input_height'], 'network input height in pixels (aspect kept)', range=(32, 4096)),
    'method': Param(EXTRACTOR['method'], 'landmark selection', choices=METHODS),
    'image_transport': Param(
        'raw', "raw: sensor_msgs/Image on 'image'; compressed: 'image/compressed'", choices=('raw', 'compressed')
    ),
    'reliability': Param(
        'best_effort', 'image subscription reliability (reliable: for bags)', choices=('best_effort', 'reliable')
    ),
    'frame_queue': Param(
        1,
        'frames waiting for extraction: 1 = the newest only (live cameras, latency one '
        'extraction); e.g. 100 for bag replays, so no frame is skipped while the backlog fits',
        range=(1, 10_000),
    ),
    'publish_activation': Param(False, "also publish the LLN activation heatmap on 'activation'", dynamic=True),
    'publish_keypoints': Param(False, "also publish ORB keypoints on 'keypoints' (matcher verify mode)"),
    'keypoints_max': Param(500, 'ORB keypoints per image with publish_keypoints', range=(1, LIMITS['max_keypoints'])),
    'depth': Param(
        False,
        "subscribe 'depth/image' (REP 118, registered to the colour camera) and add each keypoint's "
        'depth (metres) to the keypoints cloud (with publish_keypoints)',
    ),
    'depth_max_dt': Param(
        RGBD['max_depth_dt'],
        'seconds: a depth image further in time from the colour image is not its pair',
        range=(0.0, 1.0),
    ),
    'num_threads': Param(
        EXTRACTOR['num_threads'],
        'inference threads (torch intra-op / ONNX Runtime intra-op); 0 = the runtime default',
        range=(0, 1024),
    ),
    'runtime': Param(
        EXTRACTOR['runtime'],
        'what runs the network: onnxruntime (falls back to torch when not '
        'installed) | torch (same landmarks) | onnxruntime-int8 (the backbone in int8: ~2x faster, '
        'close landmarks); model_info says which ran',
        choices=RUNTIMES,
    ),
    'diagnostics_period': diagnostics_period(),
    'max_image_pixels': Param(
        LIMITS['max_image_pixels'],
        'limit: width x height of an image, raw or decoded '
        '(checked from the PNG/JPEG header before decoding); more is bad_image',
        range=(1, 2**40),
    ),
}


NO_DATA_S = 5.0  # publishers present and no image for this long: diagnostics WARN


class NewestFrame:
    """A mailbox of `capacity` messages: put() appends, dropping the oldest waiting one when full
    (returns True when it dropped one). capacity 1 = only the newest frame waits (live cameras:
    latency stays one extraction); more = a bag replay keeps every frame while the backlog fits."""

    def __init__(self, capacity: int = 1):
        from collections import deque

        self._msgs = deque()
        self.capacity = int(capacity)
        self._cond = threading.Condition()

    def put(self, msg) -> bool:
        with self._cond:
            dropped = len(self._msgs) >= self.capacity
            if dropped:
                self._msgs.popleft()
            self._msgs.append(msg)
            self._cond.notify()
            return dropped

    def take(self, timeout: float):
        with self._cond:
            if not self._msgs:
                self._cond.wait(timeout)
            return self._msgs.popleft() if self._msgs else None


class DepthBuffer:
    """The newest depth images (sensor_msgs/Image, undecoded), for pairing with colour images by
    stamp. take() waits up to WAIT_S for a depth image as new as the colour image: the two topics
    are not ordered, and the depth of this frame may still be on its way. It does not wait when no
    depth image came for LIVE_S (no depth publisher: frames must not be slowed down for nothing)."""

    WAIT_S, LIVE_S = 0.15, 1.0

    def __init__(self, max_dt_s: float, size: int):
        from collections import deque

        self.max_dt_ns = int(float(max_dt_s) * 1e9)
        self._msgs = deque(maxlen=int(size))
        self._cond = threading.Condition()
        self.last_put = -1e9  # time.monotonic() of the newest depth image

    def put(self, msg) -> None:
        with self._cond:
            self._msgs.append(msg)
            self.last_put = time.monotonic()
            self._cond.notify_all()

    def take(self, stamp_ns: int):
        deadline = time.monotonic() + self.WAIT_S
        with self._cond:
            while True:
                stamps = [msgs.stamp_to_ns(m.header.stamp) for m in self._msgs]
                near = [i for i, st in enumerate(stamps) if abs(st - stamp_ns) <= self.max_dt_ns]
                if near:
                    return self._msgs[min(near, key=lambda i: abs(stamps[i] - stamp_ns))]
                left = deadline - time.monotonic()
                stale = time.monotonic() - self.last_put > self.LIVE_S
                if (stamps and max(stamps) > stamp_ns + self.max_dt_ns) or left <= 0 or stale:
                    return None
                self._cond.wait(left)


class ExtractorNode(Node):
    def __init__(self, **kwargs):
        super().__init__('lln_extractor', **kwargs)
        p = self.params = declare_all(self, PARAMETERS, self.on_parameters)
        self.extractor = Extractor(
            {
                'backbone': {'name': p['backbone'], 'layer': p['layer'], 'weights_path': p['backbone_weights']},
                'weights': p['weights'],
                'top_n': p['top_n'],
                'input_height': p['input_height'],
                'method': p['method'],
                'num_threads': p['num_threads'],
                'runtime': p['runtime'],
            }
        )
        self.health = Health(self)
        self.landmarks_pub = self.create_publisher(PointCloud2, topics.LANDMARKS, 10)
        self.activation_pub, self.activation_on = None, False
        self.set_activation(p['publish_activation'])
        self.keypoints_pub, self.orb = None, None
        if p['publish_keypoints']:
            from ..core.reloc import Relocalizer

            self.orb = Relocalizer({'detector': 'orb', 'max_keypoints': p['keypoints_max']})
            self.keypoints_pub = self.create_publisher(PointCloud2, topics.KEYPOINTS, 10)
        model_pub = self.create_publisher(String, topics.MODEL_INFO, MODEL_QOS)
        model_pub.publish(String(data=json.dumps(self.extractor.model_info)))
        compressed = p['image_transport'] == 'compressed'
        image_topic = topics.IMAGE + '/compressed' if compressed else topics.IMAGE
        self.image_topic = self.resolve_topic_name(image_topic)
        self.image_sub = self.create_subscription(
            CompressedImage if compressed else Image,
            image_topic,
            self.on_image,
            # a reader history shorter than the queue would overwrite a burst before we see it
            subscription_qos(p['reliability'], max(5, p['frame_queue'])),
            event_callbacks=loss_events(self.health, f'image subscription {self.image_topic}'),
        )
        # as many depth images as colour frames may wait (+ a margin for depth arriving first)
        self.depths = DepthBuffer(p['depth_max_dt'], p['frame_queue'] + 10)
        if p['depth']:
            self.create_subscription(
                Image, topics.DEPTH, self.on_depth, subscription_qos(p['reliability'], max(5, p['frame_queue']))
            )
        self.gaps = StampGaps()
        self.last_image_at, self.publishers_since = 0.0, None
        self.mailbox = NewestFrame(p['frame_queue'])
        self.latency_ms = 0.0
        self._running = True
        self.worker = threading.Thread(target=self._work, name='lln_extractor_worker', daemon=True)
        self.worker.start()
        self.diagnostics = start_diagnostics(
            self,
            self.health,
            p['diagnostics_period'],
            # image_publishers: the writers our reader has matched (the graph can list a publisher
            # before that; a volatile reader never sees what was written before its match)
            lambda: {
                'last_latency_ms': f'{self.latency_ms:.1f}',
                'image_publishers': str(self.image_sub.get_publisher_count()),
                'landmark_subscribers': str(self.landmarks_pub.get_subscription_count()),
            },
            self.status,
        )
        info = self.extractor.model_info
        self.get_logger().info(
            f'extracting {p["method"]} top-{p["top_n"]} landmarks with {info["descriptor_space"]} '
            f'(head {info["head"]}{"" if info["head_trained"] else ", UNTRAINED"}, {info["runtime"]}) from '
            f"'{self.image_topic}'"
        )

    def set_activation(self, on: bool) -> None:
        """publish_activation gates publishing; the publisher, once made, is kept. Destroying it
        while the worker thread publishes (toggling during a stream) lost frames to internal_error
        (InvalidHandle, issue 25); an idle publisher costs nothing."""
        if on and self.activation_pub is None:
            self.activation_pub = self.create_publisher(Image, topics.ACTIVATION, 2)
        self.activation_on = bool(on)

    def on_parameters(self, changes: dict) -> None:
        """Run-time changes (already range-checked): only the dynamic parameters get here."""
        if 'publish_activation' in changes:
            self.set_activation(changes['publish_activation'])
        if 'diagnostics_period' in changes:
            self.diagnostics.set_period(changes['diagnostics_period'])

    def status(self, delta: dict) -> tuple:
        """/diagnostics level and message from the last period's counter increases."""
        from diagnostic_msgs.msg import DiagnosticStatus as S

        problems = []
        if delta.get('dropped'):
            problems.append(
                (
                    S.WARN,
                    f'skipped {delta["dropped"]} of {delta.get("received", 0)} frames (newest-frame '
                    f'policy, frame_queue {self.params["frame_queue"]}: extraction takes '
                    f'{self.latency_ms:.0f} ms; lower the input rate, replay slower, or raise '
                    f'frame_queue for a bag to keep every frame)',
                )
            )
        if delta.get('frames_missing'):
            problems.append(
                (
                    S.WARN,
                    f'{delta["frames_missing"]} frames missing upstream (gaps in the image stamps: '
                    f"lost by DDS or the driver; docs/robot_integration.md 'Camera-sized images')",
                )
            )
        if delta.get('dds_lost'):
            problems.append((S.WARN, f'DDS reports {delta["dds_lost"]} image samples lost'))
        for key in ('bad_image', 'internal_error'):  # quiet: logged by kind as they happen
            if delta.get(key):
                problems.append((S.WARN, f'{delta[key]} frames refused ({key})', True))
        if delta.get('qos_incompatible'):
            problems.append(
                (
                    S.WARN,
                    f'a publisher of {self.image_topic} has an incompatible QoS (try '
                    f'reliability {"reliable" if self.params["reliability"] == "best_effort" else "best_effort"})',
                    True,
                )
            )
        publishers, now = self.count_publishers(self.image_topic), time.monotonic()
        self.publishers_since = (self.publishers_since or now) if publishers else None
        idle = now - max(self.last_image_at, self.publishers_since or now)
        if publishers and idle >= NO_DATA_S:  # an idle publisher for a moment is normal; for seconds, not
            problems.append(
                (
                    S.WARN,
                    f'{publishers} publisher(s) on {self.image_topic} ({self.image_sub.get_publisher_count()} '
                    f'matched by our reader) but no image for {idle:.0f} s (QoS mismatch, '
                    f'or frames too large for the middleware: '
                    f"docs/robot_integration.md 'Camera-sized images')",
                )
            )
        return worst(problems)

    @guarded('image callback')
    def on_image(self, msg) -> None:
        self.health.count('received')
        self.last_image_at = time.monotonic()
        missing = self.gaps.add(msgs.stamp_to_ns(msg.header.stamp))
        if missing:
            self.health.count('frames_missing', missing)
        if self.mailbox.put(msg):
            self.health.count('dropped')

    @guarded('depth callback')
    def on_depth(self, msg) -> None:
        # held undecoded until its colour frame comes: bounded in count (DepthBuffer) and here in size
        if len(msg.data) > 4 * self.params['max_image_pixels']:
            self.health.problem('bad_depth', f'depth image of {len(msg.data)} bytes: more than max_image_pixels allows')
            return
        self.depths.put(msg)

    def _work(self) -> None:
        while self._running:
            msg = self.mailbox.take(timeout=0.2)
            if msg is not None:
                self.process(msg)  # guarded: the worker outlives any one frame

    @guarded('frame')
    def process(self, msg) -> None:
        start = time.perf_counter()
        try:
            msgs.header_stamp_ns(msg.header, 'image')  # copied to every output: refused here, first
            image, order = msgs.message_to_array(msg, self.params['max_image_pixels'])
            lset = self.extractor(image, channel_order=order)
            kps = self.orb.detect(image, order) if self.orb is not None else None
        except LLNError as e:
            self.health.problem('bad_image', str(e))
            return
        if kps is not None and self.params['depth']:
            kps.depth = self.keypoint_depths(msg, image, kps)
        if kps is not None:  # first, so a matcher has them when the landmarks of this header arrive
            self.keypoints_pub.publish(msgs.keypoints_to_cloud(kps, msg.header))
        self.landmarks_pub.publish(msgs.landmarks_to_cloud(lset, msg.header))
        activation_pub = self.activation_pub  # publish_activation may change meanwhile (executor thread)
        if activation_pub is not None and self.activation_on:
            heat = heatmap_bgr(check_image(image, order), lset.activation)
            activation_pub.publish(msgs.array_to_image(heat, 'bgr8', msg.header))
        self.latency_ms = (time.perf_counter() - start) * 1e3
        self.health.count('published')

    def keypoint_depths(self, msg, image, kps):
        """(N,) float32 metres of the keypoints from the paired depth image; NaN when there is none
        (depth_missing) or it is refused (bad_depth: another size or encoding)."""
        import numpy as np

        z = np.full(len(kps.uv), np.nan, np.float32)
        depth = self.depths.take(msgs.stamp_to_ns(msg.header.stamp))
        if depth is None:
            self.health.count('depth_missing')
            return z
        try:
            metres = msgs.depth_image_to_metres(
                depth, (image.shape[1], image.shape[0]), self.params['max_image_pixels']
            )
        except LLNError as e:
            self.health.problem('bad_depth', str(e))
            return z
        return keypoint_depth(metres, kps.uv).astype(np.float32) if len(kps.uv) else z

    def close(self) -> None:
        """Stop the extraction worker; run_node calls it before the DDS teardown."""
        self._running = False
        self.worker.join(timeout=2.0)

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    return run_node(ExtractorNode, 'lln_extractor', args)


if __name__ == '__main__':
    sys.exit(main())
