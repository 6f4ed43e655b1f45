# SPDX-License-Identifier: Apache-2.0
"""Gravity from an IMU (ros/imu.py) against hand-computed values, without ROS.

Quaternions and accelerations of known tilts give the roll and pitch that level the cloud
(SensorPose's convention); the LiDAR-to-IMU rotation is applied; the nearest sample by stamp
is taken, with its age, and an old or missing one gives the static pose and a note; the
low-pass of the acceleration follows its first-order formula; the buffer is trimmed by stamp
and starts anew when stamps go back.
"""

import math
import types

import numpy as np
import pytest
from conftest import quaternion_of

from gp_ground_segmentation.core.sensor_frame import SensorPose
from gp_ground_segmentation import SegmenterParams
from gp_ground_segmentation.ros.imu import (GravityTracker, frame_params, roll_pitch_from_up,
                                            rotation_from_rpy, up_from_acceleration,
                                            up_from_orientation)

DEG = math.pi / 180.0


def test_hand_computed_quaternions():
    # 10 deg about x: up seen from the IMU is (0, sin 10, cos 10) -> roll 10, pitch 0
    s, c = math.sin(5 * DEG), math.cos(5 * DEG)
    up = up_from_orientation(s, 0.0, 0.0, c)
    np.testing.assert_allclose(up, [0.0, math.sin(10 * DEG), math.cos(10 * DEG)], atol=1e-12)
    np.testing.assert_allclose(roll_pitch_from_up(up), [10 * DEG, 0.0], atol=1e-12)
    # 10 deg about y (x axis pointing down): up is (-sin 10, 0, cos 10) -> pitch +10
    up = up_from_orientation(0.0, s, 0.0, c)
    np.testing.assert_allclose(roll_pitch_from_up(up), [0.0, 10 * DEG], atol=1e-12)
    # a yaw alone changes nothing; a quaternion need not be normalised
    up = up_from_orientation(0.0, 0.0, 2 * math.sin(0.6), 2 * math.cos(0.6))
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0], atol=1e-12)
    assert up_from_orientation(0.0, 0.0, 0.0, 0.0) is None
    assert up_from_orientation(math.nan, 0.0, 0.0, 1.0) is None


@pytest.mark.parametrize('roll, pitch, yaw', [(10 * DEG, 0.0, 0.0), (4 * DEG, -9.2 * DEG, 0.7),
                                              (-30 * DEG, 20 * DEG, -2.5)])
def test_orientation_and_acceleration_give_the_levelling_pose(roll, pitch, yaw):
    level = SensorPose(roll=roll, pitch=pitch).rotation()  # R_y(pitch) R_x(roll)
    orientation = rotation_from_rpy(0.0, 0.0, yaw) @ level  # any heading
    np.testing.assert_allclose(roll_pitch_from_up(up_from_orientation(*quaternion_of(
        orientation))), [roll, pitch], atol=1e-9)
    specific_force = level.T @ np.array([0.0, 0.0, 9.81])  # at rest, in the tilted frame
    np.testing.assert_allclose(roll_pitch_from_up(up_from_acceleration(*specific_force)),
                               [roll, pitch], atol=1e-9)
    assert up_from_acceleration(0.0, 0.0, 0.0) is None


def test_rotation_from_rpy_is_fixed_axis_zyx():
    np.testing.assert_allclose(rotation_from_rpy(0.0, 0.0, math.pi / 2) @ [1.0, 0.0, 0.0],
                               [0.0, 1.0, 0.0], atol=1e-12)
    r, p, y = 0.3, -0.2, 1.1
    rx = rotation_from_rpy(r, 0, 0)
    ry = rotation_from_rpy(0, p, 0)
    rz = rotation_from_rpy(0, 0, y)
    np.testing.assert_allclose(rotation_from_rpy(r, p, y), rz @ ry @ rx, atol=1e-12)
    np.testing.assert_allclose(SensorPose(roll=r, pitch=p).rotation(), ry @ rx, atol=1e-12)


def test_lidar_to_imu_rotation_is_applied():
    # the LiDAR is yawed 90 deg in the IMU frame: LiDAR x = IMU y. The IMU's pitch (its x
    # axis down) is the LiDAR's roll about its -y... worked by hand: IMU pitched by +8 deg has
    # up_imu = (-sin 8, 0, cos 8); up_lidar = R_z(90)^T up_imu = (0, sin 8, cos 8): roll +8
    tracker = GravityTracker(lidar_in_imu=(0.0, 0.0, math.pi / 2))
    s, c = math.sin(4 * DEG), math.cos(4 * DEG)
    tracker.add(10.0, (0.0, s, 0.0, c))
    pose = tracker.pose_at(10.0)
    assert pose.from_imu and pose.source == 'orientation' and pose.age_s == 0.0
    np.testing.assert_allclose([pose.roll, pose.pitch], [8 * DEG, 0.0], atol=1e-12)
    tracker.configure(lidar_in_imu=(0.0, 0.0, 0.0))  # kept samples, new rotation
    np.testing.assert_allclose([tracker.pose_at(10.0).roll, tracker.pose_at(10.0).pitch],
                               [0.0, 8 * DEG], atol=1e-12)


def test_nearest_sample_by_stamp_and_the_static_fallback():
    tracker = GravityTracker(max_age_s=0.05)
    for k, stamp in enumerate((1.00, 1.01, 1.02, 1.03)):
        s, c = math.sin(k * DEG / 2), math.cos(k * DEG / 2)  # roll k degrees
        tracker.add(stamp, (s, 0.0, 0.0, c))
    pose = tracker.pose_at(1.012)  # nearest: 1.01, roll 1 deg, 2 ms away
    assert pose.from_imu and pose.note is None
    assert pose.age_s == pytest.approx(0.002) and pose.roll == pytest.approx(1 * DEG)
    pose = tracker.pose_at(1.0251)  # nearest: 1.03 (4.9 ms) rather than 1.02 (5.1 ms)
    assert pose.roll == pytest.approx(3 * DEG)
    pose = tracker.pose_at(0.9)  # before the buffer: 0.1 s from its oldest sample
    assert not pose.from_imu and (pose.roll, pose.pitch) == (0.0, 0.0)
    assert pose.age_s == pytest.approx(0.1) and 'is 0.100 s from the cloud stamp' in pose.note
    pose = tracker.pose_at(2.0, static_roll=0.25, static_pitch=-0.5)  # stale: the static pose
    assert (pose.roll, pose.pitch, pose.source) == (0.25, -0.5, 'static')
    empty = GravityTracker().pose_at(1.0, 0.1, 0.2)
    assert (empty.roll, empty.pitch, empty.age_s) == (0.1, 0.2, None)
    assert empty.note.startswith('no IMU sample received yet')


def test_acceleration_low_pass_and_orientation_precedence():
    tracker = GravityTracker(accel_time_constant_s=0.5, max_age_s=1.0)
    tracker.add(0.0, None, (0.0, 0.0, 9.81))  # the first sample starts the filter
    tracker.add(0.5, None, (0.0, 9.81, 0.0))  # one time constant later
    gain = 1.0 - math.exp(-1.0)
    expected = np.array([0.0, gain * 9.81, (1 - gain) * 9.81])
    pose = tracker.pose_at(0.5)
    assert pose.source == 'acceleration'
    np.testing.assert_allclose(pose.roll, math.atan2(expected[1], expected[2]), atol=1e-12)
    # an orientation wins over the acceleration when both are given
    tracker.add(0.6, (0.0, 0.0, 0.0, 1.0), (0.0, 9.81, 0.0))
    assert tracker.pose_at(0.6).source == 'orientation' and tracker.pose_at(0.6).roll == 0.0
    raw = GravityTracker(accel_time_constant_s=0.0)
    raw.add(0.0, None, (0.0, 0.0, 9.81))
    raw.add(0.01, None, (0.0, 9.81, 0.0))  # no filtering: the sample itself
    assert raw.pose_at(0.01).roll == pytest.approx(math.pi / 2)


def test_buffer_trimmed_by_stamp_and_restarted_when_stamps_go_back():
    tracker = GravityTracker(buffer_s=1.0, max_age_s=10.0)
    for k in range(30):  # stamps 0 .. 3.625 s, 8 a second (exact in binary)
        tracker.add(0.125 * k, (0.0, 0.0, 0.0, 1.0))
    # only the last second is kept: its oldest sample is 2.625 s
    assert tracker.pose_at(0.0).age_s == 2.625
    tracker.add(0.5, (math.sin(5 * DEG), 0.0, 0.0, math.cos(5 * DEG)))  # a bag played again
    pose = tracker.pose_at(3.625)
    assert pose.age_s == 3.125 and pose.roll == pytest.approx(10 * DEG)


def test_messages_of_any_imu_type_and_unusable_samples():
    def imu(sec, nanosec, q, covariance0, a):
        return types.SimpleNamespace(
            header=types.SimpleNamespace(stamp=types.SimpleNamespace(sec=sec, nanosec=nanosec)),
            orientation=types.SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3]),
            orientation_covariance=[covariance0] + [0.0] * 8,
            linear_acceleration=types.SimpleNamespace(x=a[0], y=a[1], z=a[2]))
    tracker = GravityTracker()
    s, c = math.sin(5 * DEG), math.cos(5 * DEG)
    assert tracker.add_message(imu(3, 500_000_000, (s, 0, 0, c), 0.01, (0, 0, 0)))
    assert tracker.pose_at(3.5).roll == pytest.approx(10 * DEG)
    # no orientation (covariance[0] == -1): the zero quaternion is not read, the accel is
    assert tracker.add_message(imu(3, 600_000_000, (0, 0, 0, 0), -1.0, (0, 0, 9.81)))
    assert tracker.pose_at(3.6).source == 'acceleration'
    # neither (an all-zero acceleration and no orientation): counted, not kept
    unusable = GravityTracker()
    assert not unusable.add_message(imu(4, 0, (0, 0, 0, 0), -1.0, (0.0, 0.0, 0.0)))
    assert unusable.samples_unusable == 1 and unusable.pose_at(4.0).age_s is None


def test_frame_params_take_the_imu_roll_and_pitch_only_from_the_imu():
    static = SegmenterParams(sensor_z_m=1.8, sensor_pitch_rad=0.1, ground_threshold_m=0.25)
    tracker = GravityTracker()
    assert frame_params(static, tracker.pose_at(1.0, 0.0, 0.1)) is static  # no sample: static
    tracker.add(1.0, (math.sin(5 * DEG), 0.0, 0.0, math.cos(5 * DEG)))
    params = frame_params(static, tracker.pose_at(1.0, 0.0, 0.1))
    assert params.sensor_roll_rad == pytest.approx(10 * DEG) and params.sensor_pitch_rad == 0.0
    assert params.sensor_z_m == 1.8 and params.ground_threshold_m == 0.25  # the rest kept
