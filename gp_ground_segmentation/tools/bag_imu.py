# SPDX-License-Identifier: Apache-2.0
"""``replay --imu-topic``: the sensor_msgs/Imu samples of a bag level its clouds, as the node's
``imu_topic`` does.

The samples of the topic are read once with rosbags (ROS 2 or ROS 1 bags; only their stamps,
orientations and accelerations are kept: 64 bytes a sample), sorted by header stamp, and given to
a ``ros.imu.GravityTracker`` in that order as the clouds need them: every sample stamped up to
``imu_max_age_s`` after a cloud's stamp before that cloud is levelled, so the nearest sample on
either side is there, as in the node once the IMU has caught up. Each frame then gets
``ros.imu.frame_pose`` (the node's code: the pose of the sample nearest the cloud's stamp, or the
static ``sensor_roll_rad``/``sensor_pitch_rad`` when none lies within ``imu_max_age_s``). The
tracker's settings are the node's ``imu_*`` parameters of the replay's parameter file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from ..core.params import SegmenterParams
from ..ros.imu import GravityTracker, frame_pose, imu_sample, stamp_seconds, tracker_settings
from .errors import BagError, one_line

IMU = 'sensor_msgs/msg/Imu'
NOTES_KEPT = 5  # notes of frames levelled with the static pose kept for the summary


def read_imu_samples(paths: Sequence[Path], topic: str) -> tuple:
    """(stamps s (K,), orientations (K, 4) x, y, z, w with NaN rows where the driver gives
    none, accelerations (K, 3) m/s^2) of the Imu messages on ``topic``, in stamp order."""
    name = ', '.join(str(p) for p in paths)
    try:
        reader = AnyReader(list(paths), default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except Exception as err:  # noqa: BLE001 - any reader failure is a bad bag
        raise BagError(f'cannot read bag {name} for its IMU: {one_line(err, 300)}') from None
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            imus = sorted({c.topic for c in reader.connections if c.msgtype == IMU})
            raise BagError(f'--imu-topic {topic} not in bag {name}; its {IMU} topics: '
                           f'{", ".join(imus) or "none"}')
        types = sorted({c.msgtype for c in conns})
        if types != [IMU]:
            raise BagError(f'--imu-topic {topic} carries {"|".join(types)}, not {IMU}')
        samples = [_sample(reader, c, raw, name, topic) for c, _, raw in
                   reader.messages(connections=conns)]
    finally:
        reader.close()
    if not samples:
        raise BagError(f'--imu-topic {topic} in bag {name} has no messages')
    stamps = np.array([s[0] for s in samples], dtype=np.float64)
    orientations = np.array([s[1] if s[1] is not None else (np.nan,) * 4 for s in samples],
                            dtype=np.float64)
    accelerations = np.array([s[2] for s in samples], dtype=np.float64)
    order = np.argsort(stamps, kind='stable')  # bag order is arrival order, not stamp order
    return stamps[order], orientations[order], accelerations[order]


def _sample(reader, connection, raw, name, topic) -> tuple:
    try:
        return imu_sample(reader.deserialize(raw, connection.msgtype))
    except Exception as err:  # noqa: BLE001 - a message rosbags cannot decode
        raise BagError(f'bag {name} is corrupt or truncated (an IMU message on {topic}): '
                       f'{one_line(err, 300)}') from None


class BagGravity:
    """The IMU samples of a bag topic and the tracker they feed; what it did per frame.

    ``node_values``: the node parameter values (``imu_max_age_s``, ``imu_lidar_*_rad``,
    ``imu_accel_time_constant_s``).
    """

    def __init__(self, paths: Sequence[Path], topic: str, node_values: dict):
        self.topic = topic
        self.tracker = GravityTracker(**tracker_settings(node_values))
        self._stamps, self._orientations, self._accelerations = read_imu_samples(paths, topic)
        self._fed = 0  # samples given to the tracker so far
        self.levelled = 0  # frames levelled with an IMU sample
        self.static = 0  # frames with the static pose: no sample within imu_max_age_s
        self.notes = []  # (frame index, note) of the first NOTES_KEPT static frames

    @property
    def samples(self) -> int:
        return int(self._stamps.size)

    def frame_pose(self, static: SegmenterParams, stamp, index: int) -> tuple:
        """(ImuPose, SegmenterParams) of frame ``index`` stamped ``stamp``
        (``ros.imu.frame_pose`` once the samples up to imu_max_age_s after it are in)."""
        limit = stamp_seconds(stamp) + self.tracker.max_age_s
        while self._fed < self._stamps.size and self._stamps[self._fed] <= limit:
            k = self._fed
            orientation = self._orientations[k]
            self.tracker.add(float(self._stamps[k]),
                             None if np.isnan(orientation[0]) else tuple(orientation),
                             tuple(self._accelerations[k]))
            self._fed += 1
        pose, params = frame_pose(self.tracker, static, stamp)
        if pose.from_imu:
            self.levelled += 1
        else:
            self.static += 1
            if len(self.notes) < NOTES_KEPT:
                self.notes.append((index, pose.note))
        return pose, params

    def summary(self) -> dict:
        return {'topic': self.topic, 'samples': self.samples, 'levelled': self.levelled,
                'static': self.static, 'max_age_s': self.tracker.max_age_s,
                'notes': list(self.notes)}
