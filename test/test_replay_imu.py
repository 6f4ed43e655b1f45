# SPDX-License-Identifier: Apache-2.0
"""``replay --imu-topic``: a bag's sensor_msgs/Imu samples level its clouds as the node does.

A real KITTI scan (the shipped sample's first frame, so no ../shared is needed) is tilted by
10 degrees, as a LiDAR on a tilted base would see it, and written to a bag (rosbags Writer) with
the IMU samples a tilted IMU would give, in shuffled bag order (replay sorts them by stamp): its
orientation, or only its acceleration from an IMU mounted at 90 degrees of yaw to the LiDAR
(``imu_lidar_yaw_rad`` from --params). The labelled output must be that of the level scan
(>= 99.5 % equal; without the IMU < 98 %). A frame without an IMU sample within imu_max_age_s
keeps the static pose, is counted in the summary and WARNs in /diagnostics; bad IMU input is
one line with nothing written.
"""

import math

import numpy as np
import pytest
from conftest import REPO, quaternion_of, status_values
from test_bag import read_bag
from test_node_imu import G, _cloud, _imu, _level_labels

from gp_ground_segmentation.core.sensor_frame import SensorPose
from gp_ground_segmentation.labels import GROUND_FIELD
from gp_ground_segmentation.ros.cloud import read_cloud
from gp_ground_segmentation.ros.imu import rotation_from_rpy
from gp_ground_segmentation.tools.cli import main

SAMPLE = REPO / 'data' / 'kitti00_sample'
CLOUDS, IMU = '/velodyne_points', '/imu/data'
DEG = math.pi / 180.0


@pytest.fixture(scope='module')
def scan():
    (_, first), = read_bag(SAMPLE, CLOUDS)[CLOUDS][:1]
    return read_cloud(first).copy()


def _stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _write_bag(path, clouds, imus):
    """A ROS 2 bag of ``clouds`` on CLOUDS and ``imus`` on IMU; the IMU messages in shuffled
    bag order (bag time != stamp order), the clouds at their stamps."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    order = np.random.default_rng(0).permutation(len(imus))
    with Writer(path, version=9) as writer:
        cloud_conn = writer.add_connection(CLOUDS, 'sensor_msgs/msg/PointCloud2',
                                           typestore=typestore)
        imu_conn = writer.add_connection(IMU, 'sensor_msgs/msg/Imu', typestore=typestore)
        entries = [(_stamp_ns(m), cloud_conn, m) for m in clouds]
        entries += [(_stamp_ns(imus[k]) + 7_000_000 * (k % 3), imu_conn, imus[j])
                    for k, j in enumerate(order)]
        for bag_ns, conn, msg in sorted(entries, key=lambda e: e[0]):
            writer.write(conn, bag_ns, serialize_message(msg))


def _agreement(labeled_msg, level):
    return float(np.mean((read_cloud(labeled_msg)[GROUND_FIELD] == 1) == level))


def test_tilted_clouds_with_the_bags_imu_get_the_level_labels(scan, tmp_path, capsys):
    tilt = (10 * DEG, 0.0)
    level = SensorPose(roll=tilt[0], pitch=tilt[1]).rotation()
    imus = [_imu(100.0 + 0.01 * k, quaternion_of(rotation_from_rpy(0.0, 0.0, 0.7) @ level))
            for k in range(25)]
    stamps = (100.033, 100.133, 105.0)  # the last one 4.76 s after the last IMU sample
    bag, out = tmp_path / 'in', tmp_path / 'out'
    _write_bag(bag, [_cloud(scan, s, tilt) for s in stamps], imus)
    assert main(['replay', str(bag), str(out), '--imu-topic', 'imu/data', '--labeled']) == 0
    captured = capsys.readouterr()
    assert ('imu           /imu/data (25 samples): 2 frame(s) levelled by it, 1 with the '
            'static pose') in captured.out
    assert 'frame 2: nearest IMU sample is 4.760 s from the cloud stamp' in captured.out
    assert '1 frame(s) without an IMU sample near their stamp' in captured.err
    topics = read_bag(out)
    labeled = [m for _, m in topics[f'{CLOUDS}/labeled']]
    level_labels = _level_labels(scan, 100.033)
    agreement = [_agreement(m, level_labels) for m in labeled]
    print(f'labels equal to the level scan\'s: {agreement}')
    assert min(agreement[:2]) >= 0.995, agreement
    assert agreement[2] < 0.98, agreement  # the static pose (level) on a tilted cloud
    statuses = [arr.status[0] for _, arr in topics['/diagnostics']]
    assert [status_values(s)['frame_index'] for s in statuses] == ['0', '1', '2']
    assert 'IMU' not in statuses[1].message
    assert statuses[2].level == b'\x01' and 'nearest IMU sample is 4.760 s' in \
        statuses[2].message


def test_acceleration_only_imu_at_90_degrees_of_yaw(scan, tmp_path, capsys):
    tilt = (4 * DEG, -9.17 * DEG)
    level = SensorPose(roll=tilt[0], pitch=tilt[1]).rotation()
    force = rotation_from_rpy(0.0, 0.0, math.pi / 2) @ level.T @ np.array([0.0, 0.0, G])
    imus = [_imu(100.0 + 0.01 * k, None, force) for k in range(8)]
    params = tmp_path / 'params.yaml'
    params.write_text(f'/**:\n  ros__parameters:\n    imu_lidar_yaw_rad: {math.pi / 2!r}\n')
    bag, out = tmp_path / 'in', tmp_path / 'out'
    _write_bag(bag, [_cloud(scan, 100.033, tilt)], imus)
    assert main(['replay', str(bag), str(out), '--imu-topic', IMU, '--labeled', '--params',
                 str(params)]) == 0
    assert '1 frame(s) levelled by it, 0 with the static pose' in capsys.readouterr().out
    ((_, labeled),) = read_bag(out, f'{CLOUDS}/labeled')[f'{CLOUDS}/labeled']
    assert _agreement(labeled, _level_labels(scan, 100.033)) >= 0.995


@pytest.mark.parametrize('case, words', [
    ('missing', 'not in bag'), ('wrong type', 'not sensor_msgs/msg/Imu'),
    ('point files', 'needs a bag input')])
def test_bad_imu_input_is_one_line_and_writes_nothing(scan, tmp_path, capsys, case, words):
    bag, out = tmp_path / 'in', tmp_path / 'out'
    _write_bag(bag, [_cloud(scan, 100.0)], [_imu(100.0, (0.0, 0.0, 0.0, 1.0))])
    source, topic = str(bag), {'missing': '/imu/other', 'wrong type': CLOUDS}.get(case, IMU)
    if case == 'point files':
        source = tmp_path / 'scan.bin'
        source.write_bytes(np.stack([scan[c] for c in ('x', 'y', 'z', 'intensity')], axis=1)
                           .astype('<f4').tobytes())
    assert main(['replay', str(source), str(out), '--imu-topic', topic]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not out.exists()
