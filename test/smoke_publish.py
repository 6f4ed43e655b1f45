# SPDX-License-Identifier: Apache-2.0
"""Smoke check for an installed node (used by .ci/run): publish one cloud, expect ground back.

Usage: python test/smoke_publish.py [--topic /velodyne_points] [--timeout 60]
Publishes a real KITTI frame from ../shared/data (or, if absent, a synthetic sloped scan) on
``--topic`` every second until a message arrives on /ground and on /obstacles; exits 0 then,
1 on timeout. Not a pytest module (no ``test_`` prefix).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # scenes/ of this checkout
from scenes.real_data import DATA_DIR  # noqa: E402

BAG = DATA_DIR / 'kitti00_velodyne_points'


def _cloud():
    if BAG.is_dir():
        from rclpy.serialization import deserialize_message
        from rosbags.highlevel import AnyReader
        with AnyReader([BAG]) as reader:
            for _, _, raw in reader.messages():
                return deserialize_message(raw, PointCloud2), 'KITTI frame from the shared bag'
    from gp_ground_segmentation.ros.cloud import make_cloud
    rng = np.random.default_rng(0)
    r, a = rng.uniform(3, 40, 20000), rng.uniform(-np.pi, np.pi, 20000)
    xyz = np.stack([r * np.cos(a), r * np.sin(a), -1.7 + 0.03 * r * np.cos(a)], 1)
    return make_cloud(Header(frame_id='lidar'), xyz.astype(np.float32)), 'synthetic scan'


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--topic', default='/velodyne_points')
    ap.add_argument('--timeout', type=float, default=60.0, help='seconds')
    args = ap.parse_args(argv)
    msg, what = _cloud()
    rclpy.init()
    node = rclpy.create_node('gp_smoke_publisher')
    got = {}
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(PointCloud2, '/ground', lambda m: got.setdefault('ground', m), qos)
    node.create_subscription(PointCloud2, '/obstacles',
                             lambda m: got.setdefault('obstacles', m), qos)
    pub = node.create_publisher(PointCloud2, args.topic, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    deadline = time.monotonic() + args.timeout
    next_pub = 0.0
    try:
        while time.monotonic() < deadline and len(got) < 2:
            if time.monotonic() >= next_pub and pub.get_subscription_count() > 0:
                pub.publish(msg)
                next_pub = time.monotonic() + 1.0
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if len(got) < 2:
        print(f'smoke: no ground/obstacles output within {args.timeout} s', file=sys.stderr)
        return 1
    g, o = got['ground'], got['obstacles']
    ok = g.width + o.width <= msg.width and g.header.frame_id == msg.header.frame_id
    print(f'smoke: published {what} ({msg.width} points) on {args.topic}; received ground '
          f'{g.width} + obstacles {o.width} points, frame_id {g.header.frame_id!r}')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
