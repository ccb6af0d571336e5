"""lln_visualizer: what the matcher decided, as pictures (`ros2 run lln_ros visualizer`).

Subscribes  image (sensor_msgs/Image) or, with image_transport=compressed, image/compressed (the
            camera stream the extractor sees), lln/candidates and lln/matches (the matcher's answers)
Publishes   lln/overlay (sensor_msgs/Image bgr8: the query beside its best keyframe, matched regions
            outlined and linked, as `lln-match --plot` draws them; header = the query's),
            lln/markers (visualization_msgs/MarkerArray: a loop-closure timeline in frame
            `timeline_frame`: every answered query on the x axis at its time, an arc from it to its
            best keyframe, coloured by score)

Keyframe images come from the same camera stream: the node keeps the last `history` frames as JPEG
thumbnails, keyed by header stamp, and finds a candidate's image by its stamp_sec/stamp_nanosec. A
keyframe older than that (or from a map built in another run) is drawn as a grey panel that says so.
Nothing here feeds back into the matcher; the node can start and stop at any time.
"""

from __future__ import annotations

import sys
from collections import OrderedDict

import cv2
import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ..errors import LLNError
from ..ros import msgs, topics
from ..viz.drawing import draw_match_overlay, similarity_colours
from .common import Health, guarded, run_node, subscription_qos
from .parameters import Param, declare_all

PARAMETERS = {
    'image_transport': Param(
        'raw', "raw: sensor_msgs/Image on 'image' | compressed: 'image/compressed'", choices=('raw', 'compressed')
    ),
    'reliability': Param('best_effort', 'image subscription reliability', choices=('best_effort', 'reliable')),
    'history': Param(600, 'camera frames kept (JPEG thumbnails) to draw keyframes from', range=(1, 100000)),
    'thumbnail_height': Param(240, 'height of the kept frames, pixels', range=(32, 2160)),
    'overlay_height': Param(360, 'height of each image on the overlay, pixels', dynamic=True, range=(32, 2160)),
    'max_links': Param(60, 'matched region pairs drawn per overlay (strongest first)', dynamic=True, range=(0, 1000)),
    'publish_overlay': Param(True, "publish 'overlay'", dynamic=True),
    'publish_markers': Param(True, "publish 'markers'", dynamic=True),
    'timeline_frame': Param(
        'lln_timeline', 'frame_id of the markers (set it as the fixed frame in rviz2)', dynamic=True
    ),
    'timeline_scale': Param(
        0.2, 'metres of the marker time axis per second of stamps', dynamic=True, range=(1e-6, 1e3)
    ),
    'score_scale': Param(
        20.0, 'score drawn at full colour on the markers (viridis: dark = low)', dynamic=True, range=(1e-6, 1e6)
    ),
}


class VisualizerNode(Node):
    def __init__(self, **kwargs):
        super().__init__('lln_visualizer', **kwargs)
        self.params = declare_all(self, PARAMETERS)
        p = self.params
        self.health = Health(self)
        self.frames: OrderedDict[int, tuple[bytes, int]] = OrderedDict()  # stamp ns -> (jpeg, original height)
        self.answers: dict[int, dict] = {}  # stamp ns -> {'candidates': table, 'matches': table}
        self.t0 = None
        self.marker_id = 0
        compressed = p['image_transport'] == 'compressed'
        self.create_subscription(
            CompressedImage if compressed else Image,
            topics.IMAGE + '/compressed' if compressed else topics.IMAGE,
            self.on_image,
            subscription_qos(p['reliability'], 5),
        )
        self.create_subscription(PointCloud2, topics.CANDIDATES, lambda m: self.on_answer(m, 'candidates'), 10)
        self.create_subscription(PointCloud2, topics.MATCHES, lambda m: self.on_answer(m, 'matches'), 10)
        self.overlay_pub = self.create_publisher(Image, topics.OVERLAY, 2)
        self.markers_pub = self.create_publisher(MarkerArray, topics.MARKERS, 10)

    @guarded('image callback')
    def on_image(self, msg) -> None:
        try:
            image, order = msgs.message_to_array(msg)
        except LLNError as e:
            self.health.problem('bad_image', str(e))
            return
        if image.ndim == 3 and order == 'rgb':
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        h = image.shape[0]
        th = min(h, self.params['thumbnail_height'])
        thumb = cv2.resize(image, (max(1, round(image.shape[1] * th / h)), th), interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode('.jpg', thumb, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            self.frames[msgs.stamp_to_ns(msg.header.stamp)] = (jpeg.tobytes(), h)
            while len(self.frames) > self.params['history']:
                self.frames.popitem(last=False)

    def frame(self, stamp_ns: int):
        """(BGR thumbnail, original height) of the kept frame with this stamp, or (None, None)."""
        found = self.frames.get(stamp_ns)
        if found is None:
            return None, None
        return cv2.imdecode(np.frombuffer(found[0], np.uint8), cv2.IMREAD_COLOR), found[1]

    @guarded('answer callback')
    def on_answer(self, msg: PointCloud2, kind: str) -> None:
        """candidates and matches of one query come on two topics in either order: draw when both are in."""
        stamp = msgs.stamp_to_ns(msg.header.stamp)
        try:
            table = msgs.cloud_to_candidates(msg) if kind == 'candidates' else msgs.cloud_to_matches(msg)
        except LLNError as e:
            self.health.problem(f'bad_{kind}', str(e))
            return
        entry = self.answers.setdefault(stamp, {})
        entry[kind] = table
        while len(self.answers) > 50:  # a lost half of an answer must not pile up
            self.answers.pop(next(iter(self.answers)))
        if len(entry) == 2:
            del self.answers[stamp]
            self.show(msg.header, entry['candidates'], entry['matches'])

    def show(self, header, candidates: np.ndarray, matches: np.ndarray) -> None:
        stamp = msgs.stamp_to_ns(header.stamp)
        best = candidates[0] if len(candidates) else None
        best_stamp = int(best['stamp_sec']) * 10**9 + int(best['stamp_nanosec']) if best is not None else None
        if self.params['publish_overlay']:
            query, qh = self.frame(stamp)
            if query is not None:
                keyframe, kh = self.frame(best_stamp) if best is not None else (None, None)
                caption = [f'query {stamp / 1e9:.3f}']
                if best is None:
                    caption.append('no candidate: new place (or the map is empty)')
                else:
                    inliers = (
                        f', {best["inliers"]:.0f} inliers'
                        if 'inliers' in candidates.dtype.names and np.isfinite(best['inliers'])
                        else ''
                    )
                    caption.append(
                        f'best keyframe #{int(best["keyframe_id"])} at {best_stamp / 1e9:.3f}: '
                        f'score {best["score"]:.2f}, holistic {best["holistic_score"]:.2f}{inliers}'
                    )
                canvas = draw_match_overlay(
                    query,
                    keyframe,
                    matches if best is not None else matches[:0],
                    caption,
                    max_links=self.params['max_links'],
                    height=self.params['overlay_height'],
                    original_heights=(qh, kh),
                )
                self.overlay_pub.publish(msgs.array_to_image(canvas, 'bgr8', header))
            else:
                self.health.count('overlay_without_image')
        if self.params['publish_markers']:
            self.markers_pub.publish(self.markers(stamp, best, best_stamp))

    def markers(self, stamp: int, best, best_stamp) -> MarkerArray:
        """The query as a point on the time axis; an arc to its best keyframe (if any)."""
        p = self.params
        self.t0 = stamp if self.t0 is None else self.t0
        x = lambda ns: (ns - self.t0) / 1e9 * p['timeline_scale']  # noqa: E731
        out = MarkerArray()
        point = Marker(ns='queries', id=self.marker_id, type=Marker.SPHERE, action=Marker.ADD)
        point.header.frame_id = p['timeline_frame']
        point.pose.position.x, point.pose.orientation.w = x(stamp), 1.0
        point.scale.x = point.scale.y = point.scale.z = 0.05
        point.color = ColorRGBA(r=0.8, g=0.8, b=0.8, a=1.0)
        point.lifetime = Duration()
        out.markers.append(point)
        if best is not None:
            arc = Marker(ns='loop_closures', id=self.marker_id, type=Marker.LINE_STRIP, action=Marker.ADD)
            arc.header.frame_id = p['timeline_frame']
            arc.pose.orientation.w = 1.0
            arc.scale.x = 0.02
            b, g, r = (float(c) / 255 for c in similarity_colours(np.array([best['score'] / p['score_scale']]))[0])
            arc.color = ColorRGBA(r=r, g=g, b=b, a=1.0)
            xq, xk = x(stamp), x(best_stamp)
            for t in np.linspace(0, np.pi, 24):
                arc.points.append(
                    Point(
                        x=(xq + xk) / 2 + (xq - xk) / 2 * float(np.cos(t)), y=0.0, z=abs(xq - xk) / 2 * float(np.sin(t))
                    )
                )
            out.markers.append(arc)
        self.marker_id += 1
        return out


def main(args=None):
    return run_node(VisualizerNode, 'lln_visualizer', args)


if __name__ == '__main__':
    sys.exit(main())
