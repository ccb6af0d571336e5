"""lln_extractor: camera images in, landmark sets out (`ros2 run lln_ros extractor`).

Subscribes  image (sensor_msgs/Image) or, with image_transport=compressed, image/compressed
Publishes   landmarks (sensor_msgs/PointCloud2, see lln_ros.msgs), activation (sensor_msgs/Image,
            bgr8, with publish_activation), model_info (std_msgs/String, JSON, latched),
            /diagnostics (counters)

Only the newest frame waits for the network: when extraction falls behind, an older waiting frame
is replaced and counted as dropped, so latency stays bounded by one extraction.
"""
from __future__ import annotations

import json
import sys
import threading
import time

from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import String

from .. import msgs
from ..errors import LLNError
from ..extractor import Extractor, default_conf as extractor_defaults
from ..image import check_image
from ..plotting import heatmap_bgr
from .common import MODEL_QOS, Health, declare, run_node, start_diagnostics, subscription_qos

PARAMETERS = {
    'backbone': ('efficientnet_lite0', 'backbone: efficientnet_lite0 | efficientnet_lite2 | resnet101'),
    'layer': ('', "backbone feature layer; '' = the backbone's default"),
    'backbone_weights': ('', "local backbone state dict; '' = shipped weights (resnet101 needs one)"),
    'weights': ('', "LLN head checkpoint; '' = the head shipped for the backbone"),
    'top_n': (50, 'landmarks per image'),
    'input_height': (288, 'network input height in pixels (aspect kept)'),
    'method': ('lln', 'landmark selection: lln | act | rand | all'),
    'image_transport': ('raw', "raw: sensor_msgs/Image on 'image'; compressed: 'image/compressed'"),
    'reliability': ('best_effort', 'image subscription reliability: best_effort | reliable (for bags)'),
    'publish_activation': (False, "also publish the LLN activation heatmap on 'activation'"),
    'publish_keypoints': (False, "also publish ORB keypoints on 'keypoints' (matcher verify mode)"),
    'keypoints_max': (500, 'ORB keypoints per image with publish_keypoints'),
    'num_threads': (0, 'torch intra-op threads; 0 = torch default'),
    'runtime': (extractor_defaults['runtime'], 'what runs the network: onnxruntime (falls back to torch when '
                'not installed) | torch; same landmarks, model_info says which ran'),
    'diagnostics_period': (1.0, 'seconds between /diagnostics messages; 0 = off'),
}


class NewestFrame:
    """A one-message mailbox: put() replaces what is waiting (returns True when it dropped one)."""

    def __init__(self):
        self._msg = None
        self._cond = threading.Condition()

    def put(self, msg) -> bool:
        with self._cond:
            dropped = self._msg is not None
            self._msg = msg
            self._cond.notify()
            return dropped

    def take(self, timeout: float):
        with self._cond:
            if self._msg is None:
                self._cond.wait(timeout)
            msg, self._msg = self._msg, None
            return msg


class ExtractorNode(Node):
    def __init__(self, **kwargs):
        super().__init__('lln_extractor', **kwargs)
        p = self.params = declare(self, PARAMETERS)
        self.extractor = Extractor({
            'backbone': {'name': p['backbone'], 'layer': p['layer'], 'weights_path': p['backbone_weights']},
            'weights': p['weights'], 'top_n': p['top_n'], 'input_height': p['input_height'],
            'method': p['method'], 'num_threads': p['num_threads'], 'runtime': p['runtime']})
        self.health = Health(self)
        self.landmarks_pub = self.create_publisher(PointCloud2, 'landmarks', 10)
        self.activation_pub = self.create_publisher(Image, 'activation', 2) if p['publish_activation'] else None
        self.keypoints_pub, self.orb = None, None
        if p['publish_keypoints']:
            from ..reloc import Relocalizer
            self.orb = Relocalizer({'detector': 'orb', 'max_keypoints': p['keypoints_max']})
            self.keypoints_pub = self.create_publisher(PointCloud2, 'keypoints', 10)
        model_pub = self.create_publisher(String, 'model_info', MODEL_QOS)
        model_pub.publish(String(data=json.dumps(self.extractor.model_info)))
        compressed = p['image_transport'] == 'compressed'
        if p['image_transport'] not in ('raw', 'compressed'):
            raise ValueError(f"image_transport must be 'raw' or 'compressed', got {p['image_transport']!r}")
        self.create_subscription(CompressedImage if compressed else Image,
                                 'image/compressed' if compressed else 'image', self.on_image,
                                 subscription_qos(p['reliability'], 5))
        self.mailbox = NewestFrame()
        self.latency_ms = 0.0
        self._running = True
        self.worker = threading.Thread(target=self._work, name='lln_extractor_worker', daemon=True)
        self.worker.start()
        start_diagnostics(self, self.health, p['diagnostics_period'],
                          lambda: {'last_latency_ms': f'{self.latency_ms:.1f}'})
        info = self.extractor.model_info
        self.get_logger().info(
            f"extracting {p['method']} top-{p['top_n']} landmarks with {info['descriptor_space']} "
            f"(head {info['head']}{'' if info['head_trained'] else ', UNTRAINED'}, {info['runtime']}) from "
            f"'{self.resolve_topic_name('image/compressed' if compressed else 'image')}'")

    def on_image(self, msg) -> None:
        self.health.count('received')
        if self.mailbox.put(msg):
            self.health.count('dropped')

    def _work(self) -> None:
        while self._running:
            msg = self.mailbox.take(timeout=0.2)
            if msg is None:
                continue
            try:
                self.process(msg)
            except Exception as e:  # noqa: BLE001  the worker must outlive any one frame
                self.get_logger().error(f'unexpected error on a frame (skipped): {type(e).__name__}: {e}')
                self.health.count('internal_error')

    def process(self, msg) -> None:
        start = time.perf_counter()
        try:
            image, order = msgs.message_to_array(msg)
            lset = self.extractor(image, channel_order=order)
            kps = self.orb.detect(image, order) if self.orb is not None else None
        except LLNError as e:
            self.health.problem('bad_image', str(e))
            return
        if kps is not None:  # first, so a matcher has them when the landmarks of this header arrive
            self.keypoints_pub.publish(msgs.keypoints_to_cloud(kps, msg.header))
        self.landmarks_pub.publish(msgs.landmarks_to_cloud(lset, msg.header))
        if self.activation_pub is not None:
            heat = heatmap_bgr(check_image(image, order), lset.activation)
            self.activation_pub.publish(msgs.array_to_image(heat, 'bgr8', msg.header))
        self.latency_ms = (time.perf_counter() - start) * 1e3
        self.health.count('published')

    def destroy_node(self):
        self._running = False
        self.worker.join(timeout=2.0)
        return super().destroy_node()


def main(args=None):
    return run_node(ExtractorNode, 'lln_extractor', args)


if __name__ == '__main__':
    sys.exit(main())
