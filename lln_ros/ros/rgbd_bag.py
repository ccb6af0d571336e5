"""An RGB-D sequence with poses (lln_ros.io.rgbd, the TUM layout) as the messages a robot's RGB-D
camera and odometry publish, for an MCAP bag (lln_ros.ros.bag.write_bag).

    records = rgbd_records(read_tum(root, {'step': 3}), range(0, 90))
    bag.write_bag(out, records)       # [(topic, msg, stamp_ns), ...] in stamp order

Topics (TOPICS, the openni/realsense driver names): the colour image as sensor_msgs/CompressedImage
(the dataset's JPEG bytes as they are), the registered depth as sensor_msgs/Image 16UC1 (mm, REP
118), the colour camera's sensor_msgs/CameraInfo with every frame, and the ground truth as
nav_msgs/Odometry at its own rate (~100 Hz) over the frames' time span (frame_id 'world', child
frame the camera's optical frame: what odometry without drift would say).
"""

from __future__ import annotations

import numpy as np

from .msgs import camera_model_to_info, depth_to_image, make_header, pose_to_odometry

TOPICS = {
    'image': '/camera/rgb/image_color/compressed',
    'depth': '/camera/depth_registered/image_raw',
    'camera_info': '/camera/rgb/camera_info',
    'odom': '/odom',
}
CAMERA_FRAME, ODOM_FRAME = 'camera_rgb_optical_frame', 'world'


def _ns(t: float) -> int:
    return int(round(float(t) * 1e9))


def rgbd_records(seq, indices, topics: dict | None = None) -> list[tuple]:
    """(topic, message, stamp_ns) for frames `indices` of an io.rgbd.RGBDSequence, in stamp order.
    A frame without a depth image (none within the reader's max_depth_dt) gets none."""
    from sensor_msgs.msg import CompressedImage

    from ..io.rgbd import pose_matrix

    t = {**TOPICS, **(topics or {})}
    indices = list(indices)
    records = []
    for i in indices:
        f = seq.frames[i]
        st = _ns(f.stamp)
        header = make_header(st, CAMERA_FRAME)
        records.append((t['image'], CompressedImage(header=header, format='jpeg', data=f.rgb.read_bytes()), st))
        info = camera_model_to_info(seq.camera, st)
        info.header.frame_id = CAMERA_FRAME
        records.append((t['camera_info'], info, st))
        depth = seq.depth_m(i)
        if depth is not None:
            mm = np.where(np.isfinite(depth), np.rint(depth * 1000.0), 0).astype(np.uint16)
            records.append((t['depth'], depth_to_image(mm, '16UC1', st, CAMERA_FRAME), st))
    gt = np.loadtxt(seq.root / 'groundtruth.txt', comments='#')
    lo, hi = seq.frames[indices[0]].stamp - 0.1, seq.frames[indices[-1]].stamp + 0.1
    for row in gt[(gt[:, 0] >= lo) & (gt[:, 0] <= hi)]:
        pose = row[1:8].copy()
        pose[3:] /= np.linalg.norm(pose[3:])
        records.append(
            (t['odom'], pose_to_odometry(pose_matrix(pose), _ns(row[0]), ODOM_FRAME, CAMERA_FRAME), _ns(row[0]))
        )
    records.sort(key=lambda r: r[2])
    return records
