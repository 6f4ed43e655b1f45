# SPDX-License-Identifier: Apache-2.0
"""Gravity from an IMU: the roll and pitch of the cloud's frame at a cloud's stamp.

Nothing here imports rclpy or a message package (as cloud.py): an IMU sample is anything with
the ``sensor_msgs/Imu`` attributes (``header.stamp.sec/nanosec``, ``orientation.x/y/z/w``,
``orientation_covariance``, ``linear_acceleration.x/y/z``), so the node's rclpy messages and
the ``rosbags`` messages of a bag both work (``GravityTracker.add_message``), and the numbers
can be given directly (``GravityTracker.add``).

Conventions (sensor_msgs/Imu, REP 103, REP 145):

* ``orientation`` is the IMU frame's orientation in a gravity-aligned frame (z up): it maps
  IMU-frame vectors to that frame, so "up" seen from the IMU is the third row of its rotation
  matrix. Its yaw does not matter here.
* ``orientation_covariance[0] == -1`` says the driver gives no orientation; then "up" is the
  direction of the low-passed ``linear_acceleration`` (at rest an accelerometer measures
  +9.81 m/s^2 along the up axis; the low-pass, a first-order filter with time constant
  ``accel_time_constant_s`` over the sample stamps, keeps most of the motion out of it).
* ``lidar_in_imu``: the rotation of the LiDAR (cloud) frame in the IMU frame, as roll, pitch,
  yaw (rad; fixed axes x, y, z, R = R_z(yaw) R_y(pitch) R_x(roll), REP 103), i.e. the rotation
  of a TF from the IMU frame to the LiDAR frame: LiDAR-frame vectors v map to R v in the IMU
  frame. (0, 0, 0) when the IMU's axes are the LiDAR's.

The result is the pose ``core.sensor_frame.SensorPose`` takes: the cloud frame's roll (about
x) and pitch (about y after roll; positive = x axis pointing down), from the up vector u in
the cloud's frame: roll = atan2(u_y, u_z), pitch = atan2(-u_x, hypot(u_y, u_z)), the roll and
pitch of R_y(pitch) R_x(roll), which levels the cloud.

``GravityTracker`` keeps a short buffer (``buffer_s`` of sample stamps) and gives the sample
nearest a cloud's header stamp, with its age |cloud stamp - IMU stamp| (stamps only, never the
wall clock), or the static pose with a one-line note when no sample lies within
``max_age_s``. It is thread-safe: the node adds samples from its executor and reads from its
worker thread. ``frame_params`` turns the pose into the frame's SegmenterParams, and
``frame_pose`` does both for a cloud stamp: the node and ``replay --imu-topic`` level each
frame with it.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import deque
from typing import NamedTuple, Optional

import numpy as np

from ..core.params import SegmenterParams

__all__ = ['GravityTracker', 'ImuPose', 'frame_params', 'frame_pose', 'imu_sample',
           'rotation_from_rpy', 'roll_pitch_from_up', 'stamp_seconds', 'tracker_settings',
           'up_from_orientation', 'up_from_acceleration']

_MIN_ACCEL = 1e-6  # m/s^2: below this an acceleration has no direction (free fall, zeros)


def stamp_seconds(stamp) -> float:
    """A builtin_interfaces/Time (``sec``, ``nanosec``) in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = R_z(yaw) R_y(pitch) R_x(roll) (rad, fixed axes, REP 103)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def up_from_orientation(x: float, y: float, z: float, w: float) -> Optional[np.ndarray]:
    """The up direction (unit vector) in the IMU frame of the orientation quaternion (x, y,
    z, w) of the IMU frame in a gravity-aligned frame: the third row of its rotation matrix.
    None for a quaternion that is not finite or is (close to) zero."""
    q = np.array([x, y, z, w], dtype=float)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9:
        return None
    x, y, z, w = q / norm
    return np.array([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)])


def up_from_acceleration(ax: float, ay: float, az: float) -> Optional[np.ndarray]:
    """The up direction (unit vector) of a measured specific force (m/s^2; +g up at rest);
    None when it is not finite or has no length."""
    a = np.array([ax, ay, az], dtype=float)
    norm = float(np.linalg.norm(a))
    if not np.isfinite(norm) or norm < _MIN_ACCEL:
        return None
    return a / norm


def roll_pitch_from_up(up) -> tuple[float, float]:
    """(roll, pitch) in rad of the frame in which ``up`` (3 numbers) is the up direction: the
    SensorPose convention (module docstring); roll in [-pi, pi], pitch in [-pi/2, pi/2]."""
    ux, uy, uz = (float(v) for v in up)
    return math.atan2(uy, uz), math.atan2(-ux, math.hypot(uy, uz))


class ImuPose(NamedTuple):
    """What :meth:`GravityTracker.pose_at` found for one cloud stamp."""

    roll: float  # rad: the cloud frame's roll used for the frame
    pitch: float  # rad: its pitch
    from_imu: bool  # True: from the IMU sample nearest the stamp; False: the static pose
    age_s: Optional[float]  # |cloud stamp - stamp of the nearest IMU sample| (s); None: none
    source: str  # 'orientation', 'acceleration' or 'static'
    note: Optional[str]  # one line when the static pose was used, else None


def frame_params(static: SegmenterParams, pose: ImuPose) -> SegmenterParams:
    """The segmenter parameters of one frame: ``static`` (the configured ones) with the roll and
    pitch of ``pose`` when it comes from the IMU, else ``static`` itself (what the node gives
    its segmenter per frame; a bag replay taking an IMU topic does the same)."""
    if not pose.from_imu:
        return static
    return static.replace(sensor_roll_rad=pose.roll, sensor_pitch_rad=pose.pitch)


def frame_pose(tracker: 'GravityTracker', static: SegmenterParams, stamp) -> tuple:
    """(ImuPose, SegmenterParams) of the cloud stamped ``stamp`` (builtin_interfaces/Time):
    ``tracker``'s pose at the stamp, the static roll and pitch of ``static`` when no IMU sample
    is near, and :func:`frame_params` of it. The node levels each frame with it, and so does
    ``gp-ground-seg replay --imu-topic``."""
    pose = tracker.pose_at(stamp_seconds(stamp), static.sensor_roll_rad, static.sensor_pitch_rad)
    return pose, frame_params(static, pose)


def tracker_settings(node_values: dict) -> dict:
    """The :meth:`GravityTracker.configure` keywords of the node's ``imu_*`` parameter values
    (``config.NODE_PARAMS``: imu_lidar_roll/pitch/yaw_rad, imu_max_age_s,
    imu_accel_time_constant_s)."""
    return {'lidar_in_imu': tuple(float(node_values[f'imu_lidar_{a}_rad'])
                                  for a in ('roll', 'pitch', 'yaw')),
            'max_age_s': float(node_values['imu_max_age_s']),
            'accel_time_constant_s': float(node_values['imu_accel_time_constant_s'])}


def imu_sample(msg) -> tuple:
    """(stamp s, orientation (x, y, z, w) or None, linear acceleration (x, y, z) m/s^2) of a
    sensor_msgs/Imu-like message: no orientation when ``orientation_covariance[0] == -1``."""
    q, a = msg.orientation, msg.linear_acceleration
    has_orientation = float(msg.orientation_covariance[0]) != -1.0
    return (stamp_seconds(msg.header.stamp), (q.x, q.y, q.z, q.w) if has_orientation else None,
            (a.x, a.y, a.z))


class GravityTracker:
    """Buffer of IMU "up" vectors by stamp; the cloud frame's roll and pitch at a stamp.

    ``lidar_in_imu``: (roll, pitch, yaw) rad of the LiDAR frame in the IMU frame;
    ``max_age_s``: the largest |cloud stamp - IMU stamp| (s) at which a sample is used;
    ``accel_time_constant_s``: time constant (s) of the low-pass on linear_acceleration (0: the
    raw sample); ``buffer_s``: how much IMU time (s, by stamp) is kept.
    """

    def __init__(self, lidar_in_imu=(0.0, 0.0, 0.0), max_age_s: float = 0.1,
                 accel_time_constant_s: float = 0.5, buffer_s: float = 2.0):
        self._lock = threading.Lock()
        self._stamps = deque()  # s, ascending
        self._ups = deque()  # (up vector in the IMU frame, source), one per stamp
        self._filtered = None  # low-passed acceleration (m/s^2)
        self._filtered_stamp = None
        self.samples_added = 0
        self.samples_unusable = 0
        self.configure(lidar_in_imu, max_age_s, accel_time_constant_s, buffer_s)

    def configure(self, lidar_in_imu=None, max_age_s=None, accel_time_constant_s=None,
                  buffer_s=None) -> None:
        """Change any of the constructor's settings; the buffer is kept (its up vectors are
        in the IMU frame, the LiDAR rotation is applied when a pose is read)."""
        with self._lock:
            if lidar_in_imu is not None:
                self._lidar_in_imu = tuple(float(v) for v in lidar_in_imu)
                # up in the LiDAR frame = R^T (up in the IMU frame)
                self._imu_to_lidar = rotation_from_rpy(*self._lidar_in_imu).T
            if max_age_s is not None:
                self.max_age_s = float(max_age_s)
            if accel_time_constant_s is not None:
                self.accel_time_constant_s = float(accel_time_constant_s)
            if buffer_s is not None:
                self.buffer_s = float(buffer_s)

    def add_message(self, msg) -> bool:
        """Add a sensor_msgs/Imu-like message (module docstring); False when it carries no
        usable direction (counted in ``samples_unusable``)."""
        return self.add(*imu_sample(msg))

    def add(self, stamp_s: float, orientation_xyzw=None, acceleration=None) -> bool:
        """Add one sample: its stamp (s), the orientation quaternion (x, y, z, w) or None when
        the driver gives none, and the linear acceleration (m/s^2). The orientation wins when
        given; the acceleration is low-passed in stamp order either way. A stamp before the
        newest one (a bag played again, a clock jump) starts the buffer and filter anew."""
        with self._lock:
            if self._stamps and stamp_s < self._stamps[-1]:
                self._stamps.clear()
                self._ups.clear()
                self._filtered = self._filtered_stamp = None
            accel_up = None if acceleration is None else self._low_pass(stamp_s, acceleration)
            up, source = None, None
            if orientation_xyzw is not None:
                up, source = up_from_orientation(*orientation_xyzw), 'orientation'
            elif accel_up is not None:
                up, source = accel_up, 'acceleration'
            self.samples_added += 1
            if up is None:
                self.samples_unusable += 1
                return False
            self._stamps.append(float(stamp_s))
            self._ups.append((up, source))
            while self._stamps and self._stamps[0] < stamp_s - self.buffer_s:
                self._stamps.popleft()
                self._ups.popleft()
            return True

    def _low_pass(self, stamp_s: float, acceleration) -> Optional[np.ndarray]:
        """The up direction of the low-passed acceleration after this sample (lock held)."""
        a = np.asarray(acceleration, dtype=float)
        if not np.isfinite(a).all():
            return None if self._filtered is None else up_from_acceleration(*self._filtered)
        if self._filtered is None or self.accel_time_constant_s <= 0.0:
            self._filtered = a
        else:
            dt = max(stamp_s - self._filtered_stamp, 0.0)
            gain = 1.0 - math.exp(-dt / self.accel_time_constant_s)
            self._filtered = self._filtered + gain * (a - self._filtered)
        self._filtered_stamp = stamp_s
        return up_from_acceleration(*self._filtered)

    def nearest(self, stamp_s: float):
        """(age s, up vector in the IMU frame, source, IMU-to-LiDAR rotation) of the sample
        nearest ``stamp_s``, or None when the buffer is empty."""
        with self._lock:
            if not self._stamps:
                return None
            i = bisect.bisect_left(self._stamps, stamp_s)
            candidates = [j for j in (i - 1, i) if 0 <= j < len(self._stamps)]
            j = min(candidates, key=lambda k: abs(self._stamps[k] - stamp_s))
            up, source = self._ups[j]
            return abs(self._stamps[j] - stamp_s), up, source, self._imu_to_lidar

    def pose_at(self, stamp_s: float, static_roll: float = 0.0,
                static_pitch: float = 0.0) -> ImuPose:
        """The cloud frame's roll and pitch for a cloud stamped ``stamp_s`` (s): from the IMU
        sample nearest it when that lies within ``max_age_s``, else the static ones with a
        one-line note giving the age."""
        found = self.nearest(stamp_s)
        if found is None:
            return ImuPose(static_roll, static_pitch, False, None, 'static',
                           'no IMU sample received yet: the static sensor_roll_rad/'
                           'sensor_pitch_rad are used')
        age, up, source, imu_to_lidar = found
        if age > self.max_age_s:
            return ImuPose(static_roll, static_pitch, False, age, 'static',
                           f'nearest IMU sample is {age:.3f} s from the cloud stamp '
                           f'(imu_max_age_s {self.max_age_s:g}): the static sensor_roll_rad/'
                           'sensor_pitch_rad are used')
        roll, pitch = roll_pitch_from_up(imu_to_lidar @ up)
        return ImuPose(roll, pitch, True, age, source, None)
