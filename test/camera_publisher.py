"""A stand-in camera driver for the tests: its own process, sensor-data QoS (best effort, keep last 5)
as usb_cam / v4l2_camera publish, bgr8 frames of a real photograph (matplotlib's grace_hopper.jpg)
resized to W x H, at HZ, on `image`. Starts once a subscriber is matched, then prints
`published N` and exits. It knows nothing about lln_ros: the environment it gets is what docs/robot_integration.md
tells a camera user to set.

    python camera_publisher.py W H COUNT HZ [--stamp-start SEC]
"""

import argparse
import sys
import time

import cv2
import matplotlib.cbook as cbook
import numpy as np
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument('width', type=int)
    p.add_argument('height', type=int)
    p.add_argument('count', type=int)
    p.add_argument('hz', type=float)
    p.add_argument('--stamp-start', type=int, default=1_700_000_000)
    p.add_argument('--wait', type=float, default=60.0, help='seconds to wait for a subscriber')
    args = p.parse_args()
    with cbook.get_sample_data('grace_hopper.jpg') as f:
        photo = cv2.imdecode(np.frombuffer(f.read(), np.uint8), cv2.IMREAD_COLOR)
    frame = cv2.resize(photo, (args.width, args.height), interpolation=cv2.INTER_AREA)
    data = frame.tobytes()
    rclpy.init()
    node = rclpy.create_node('camera_publisher')
    pub = node.create_publisher(Image, 'image', qos_profile_sensor_data)
    deadline = time.monotonic() + args.wait
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            print('no subscriber', flush=True)
            return 1
        time.sleep(0.05)
    time.sleep(1.0)  # let the subscriber's side of discovery finish too
    start = time.monotonic()
    for i in range(args.count):
        msg = Image(height=args.height, width=args.width, encoding='bgr8', step=args.width * 3, data=data)
        msg.header.frame_id = 'camera'
        stamp_ns = args.stamp_start * 10**9 + round(i * 1e9 / args.hz)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        pub.publish(msg)
        delay = start + (i + 1) / args.hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(1.0)  # best effort: destroying the writer at once can lose the last sample
    print(f'published {args.count}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
