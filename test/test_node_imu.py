# SPDX-License-Identifier: Apache-2.0
"""Gravity from an IMU in the node, over real rclpy pub/sub (imu_topic).

A real labelled KITTI scan (SemanticKITTI 00/000000) is tilted by 10 degrees, as a LiDAR on a
tilted base would see it, and published with the IMU samples that a tilted IMU would give: its
orientation, or (orientation_covariance[0] == -1) only its acceleration, from an IMU mounted
at 90 degrees of yaw to the LiDAR (imu_lidar_yaw_rad). The labels must be those of the level
scan (>= 99.5 % of the points equal; without the IMU about 97 % are). A stale or missing IMU falls
back to the static pose (sensor_roll_rad/sensor_pitch_rad) without losing a frame, and
diagnostics say WARN with the age.
"""

import math

import numpy as np
import pytest
from conftest import DATA, quaternion_of, status_values, wait_for

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core.sensor_frame import SensorPose
from gp_ground_segmentation.labels import GROUND_FIELD
from gp_ground_segmentation.ros.cloud import make_cloud, read_cloud
from gp_ground_segmentation.ros.imu import rotation_from_rpy
from gp_ground_segmentation.ros.pipeline import process_cloud

SCAN = DATA / 'labeled' / 'semantickitti_seq00_000000.bin'
TOPIC = 'imu/data'
DEG = math.pi / 180.0
G = 9.80665  # m/s^2


@pytest.fixture(scope='module')
def scan():
    if not SCAN.exists():
        pytest.skip(f'real data not found: {SCAN}')
    from gp_ground_segmentation.tools.io import read_points_file
    return read_points_file(SCAN)


def _cloud(points, sec, tilt=None):
    """PointCloud2 of the scan (x, y, z, intensity float32), stamped ``sec`` s, its x, y, z
    seen from a frame tilted by ``tilt`` = (roll, pitch) rad: p_T = R^T p, R = R_y R_x."""
    from std_msgs.msg import Header
    pts = points.copy()
    if tilt is not None:
        rotation = SensorPose(roll=tilt[0], pitch=tilt[1]).rotation()
        xyz = np.stack([pts['x'], pts['y'], pts['z']], axis=1).astype(np.float64) @ rotation
        pts['x'], pts['y'], pts['z'] = xyz.T
    header = Header(frame_id='velodyne')
    header.stamp.sec, header.stamp.nanosec = int(sec), int(round((sec % 1) * 1e9))
    return make_cloud(header, pts)


def _imu(sec, orientation=None, acceleration=(0.0, 0.0, G)):
    """sensor_msgs/Imu at ``sec`` s: an orientation (x, y, z, w), or none
    (orientation_covariance[0] = -1), and a linear acceleration (m/s^2)."""
    from sensor_msgs.msg import Imu
    msg = Imu()
    msg.header.frame_id = 'imu'
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(sec), int(round((sec % 1) * 1e9))
    if orientation is None:
        msg.orientation_covariance[0] = -1.0
    else:
        msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = orientation
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = (
        float(v) for v in acceleration)
    return msg


def _overrides(**values):
    from rclpy.parameter import Parameter
    return {'parameter_overrides': [Parameter('diagnostics_period_s', value=0.2)]
            + [Parameter(k, value=v) for k, v in values.items()]}


def _publish_imu(h, samples):
    """Publish the samples one by one, each once the previous one arrived (the node's IMU
    subscription keeps the last 5, best effort: a burst could lose some)."""
    for sample in samples:
        before = h.node.gravity.samples_added
        h.imu_pub.publish(sample)
        if not wait_for(lambda: h.node.gravity.samples_added > before, 5.0):
            h.imu_pub.publish(sample)  # best effort: once more
            assert wait_for(lambda: h.node.gravity.samples_added > before, 5.0), \
                'the node did not receive an IMU sample'


def _labels(h, msg):
    """The node's ground flags of ``msg``'s valid points, from its labeled topic."""
    h.publish_and_wait(msg)
    labeled = wait_for(lambda: h.labeled_for(msg.header.stamp), 10.0)
    assert labeled is not None, 'no labeled cloud for the frame'
    return read_cloud(labeled)[GROUND_FIELD] == 1


def _level_labels(points, sec, params=SegmenterParams()):
    result = process_cloud(_cloud(points, sec), GroundSegmenter(params)).result
    return result.ground_mask[result.valid_mask]


@pytest.mark.parametrize('how', ['orientation', 'acceleration'])
def test_tilted_cloud_with_its_imu_gets_the_level_labels(scan, ros_harness, how):
    tilt = (10 * DEG, 0.0) if how == 'orientation' else (4 * DEG, -9.17 * DEG)  # both ~10 deg
    level = SensorPose(roll=tilt[0], pitch=tilt[1]).rotation()
    if how == 'orientation':  # an IMU aligned with the LiDAR, any heading
        extra = {}
        samples = [_imu(100.0 + 0.01 * k,
                        quaternion_of(rotation_from_rpy(0.0, 0.0, 0.7) @ level)) for k in range(8)]
    else:  # no orientation; the IMU mounted at 90 degrees of yaw to the LiDAR
        extra = {'imu_lidar_yaw_rad': math.pi / 2}
        lidar_in_imu = rotation_from_rpy(0.0, 0.0, math.pi / 2)
        force = lidar_in_imu @ level.T @ np.array([0.0, 0.0, G])  # at rest, in the IMU frame
        samples = [_imu(100.0 + 0.01 * k, None, force) for k in range(8)]
    h = ros_harness(node_kwargs=_overrides(imu_topic=TOPIC, **extra), labeled=True,
                    imu_topic=TOPIC)
    _publish_imu(h, samples)
    tilted = _cloud(scan, 100.033, tilt)
    labels = _labels(h, tilted)
    pose = h.node.last_imu_pose
    assert pose.from_imu and pose.source == how and pose.age_s == pytest.approx(0.003, abs=1e-6)
    np.testing.assert_allclose([pose.roll, pose.pitch], tilt, atol=1e-9)
    level_labels = _level_labels(scan, 100.033)
    agreement = float(np.mean(labels == level_labels))
    assert agreement >= 0.995, agreement
    # the test can fail: the same tilted cloud segmented without the IMU's pose
    unlevelled = process_cloud(tilted, GroundSegmenter()).result
    without = float(np.mean(unlevelled.ground_mask[unlevelled.valid_mask] == level_labels))
    print(f'{how}: labels equal to the level scan\'s {agreement:.4f} with the IMU, '
          f'{without:.4f} without')
    assert without < 0.98
    status = h.wait_status(lambda s: status_values(s).get('imu_pose_source') == how)
    assert status is not None, 'no diagnostics naming the IMU pose'
    values = status_values(status)
    assert float(values['sensor_roll_rad_used']) == pytest.approx(tilt[0], abs=1e-3)
    assert float(values['imu_age_s']) == pytest.approx(0.003, abs=1e-3)
    assert 'IMU' not in status.message


def test_stale_or_missing_imu_falls_back_to_the_static_pose_losing_no_frame(
        scan, ros_harness):
    from diagnostic_msgs.msg import DiagnosticStatus
    tilt = (0.0, 10 * DEG)
    # the static pose is the tilt: the fallback must give the level labels too
    h = ros_harness(node_kwargs=_overrides(imu_topic=TOPIC, imu_max_age_s=0.05,
                                           sensor_pitch_rad=tilt[1]),
                    labeled=True, imu_topic=TOPIC)
    level_labels = _level_labels(scan, 200.0)
    # 1. no IMU sample at all
    labels = _labels(h, _cloud(scan, 200.0, tilt))
    assert float(np.mean(labels == level_labels)) >= 0.995
    pose = h.node.last_imu_pose
    assert not pose.from_imu and pose.age_s is None and pose.pitch == tilt[1]
    status = h.wait_status(lambda s: 'no IMU sample received yet' in s.message)
    assert status is not None and status.level == DiagnosticStatus.WARN
    # 2. samples, but 5 s from the cloud's stamp (and saying: level): not used
    _publish_imu(h, [_imu(195.0 + 0.01 * k, (0.0, 0.0, 0.0, 1.0)) for k in range(3)])
    labels = _labels(h, _cloud(scan, 200.1, tilt))
    assert float(np.mean(labels == level_labels)) >= 0.995
    pose = h.node.last_imu_pose
    assert not pose.from_imu and pose.age_s == pytest.approx(5.08, abs=1e-6)
    status = h.wait_status(lambda s: 'nearest IMU sample is 5.080 s from the cloud stamp'
                           in s.message)
    assert status is not None and status.level == DiagnosticStatus.WARN
    assert status_values(status)['imu_age_s'] == '5.080'
    assert status_values(status)['imu_pose_source'] == 'static'
    # 3. a fresh sample: used again (it says level, so the tilted cloud is now NOT levelled)
    _publish_imu(h, [_imu(200.19, (0.0, 0.0, 0.0, 1.0))])
    h.publish_and_wait(_cloud(scan, 200.2, tilt))
    pose = h.node.last_imu_pose
    assert pose.from_imu and (pose.roll, pose.pitch) == (0.0, 0.0)
    assert h.node.segmenter_params.sensor_pitch_rad == 0.0
    assert h.node.declared_params.sensor_pitch_rad == tilt[1]  # the static one, kept
    counts = h.steady_counts()
    assert counts is not None and counts['frames_processed'] == 3
    assert counts['frames_failed'] == counts['frames_dropped'] == 0


def test_without_imu_topic_there_is_no_imu_subscription(ros_harness):
    h = ros_harness()
    assert h.node.gravity is None and h.node.last_imu_pose is None
    assert not [s for s in h.node.subscriptions if 'Imu' in str(s.msg_type)]


def test_an_invalid_imu_topic_stops_the_node_with_one_line():
    from conftest import NODE_MODULE, start_module
    proc = start_module(NODE_MODULE, '--ros-args', '-p', 'imu_topic:=bad topic!')
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and 'FATAL' in lines[0] and "parameter 'imu_topic'" in lines[0], out
    assert 'Invalid topic name' in lines[0] and 'Traceback' not in out
