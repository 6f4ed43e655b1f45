# SPDX-License-Identifier: Apache-2.0
"""The sensor's pose in the cloud's frame: levelling and centring a cloud for the radial grid.

The radial grid (grid.py) is centred at the origin of the points it gets, and the ground model
assumes z is up. A spinning LiDAR's own frame satisfies both. A cloud published in another frame
does not: in ``base_link`` the sensor sits 1-2 m above and ahead of the origin, in ``odom`` or
``map`` it can be anywhere, and a sensor mounted with a tilt has its z axis off the vertical.

``SensorPose`` says where the sensor is in the cloud's frame (``x, y, z``, m) and how the
cloud's frame is tilted against level ground (``roll, pitch``, rad; REP 103: roll about x, then
pitch about y, positive pitch = x axis pointing down, as an IMU on that frame reports it). The
segmenter works in the *levelled sensor frame* L, origin at the sensor, z up:

    p_L = R (p_C - t),   R = R_y(pitch) R_x(roll),   t = (x, y, z)

Labels are per input point, so they need no transform back. ``ground_height`` is returned in the
cloud's frame: the z, in the cloud's frame, of the ground point vertically below (along L's z)
each point, ``(R^T (x_L, y_L, z_hat_L) + t).z``. With roll = pitch = 0 that is simply
``z_hat_L + t_z`` and ``point.z - ground_height`` is the height above ground; with a tilt the
height above ground along the vertical is ``(point.z - ground_height) / (cos(roll) cos(pitch))``.

The pose is a static offset: for a cloud in a moving frame (odom, map), transform the clouds
into the sensor frame upstream (TF) instead. ``centring_note`` spots a cloud that does not
look sensor-centred so that the node can say so.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

__all__ = ['SensorPose', 'to_levelled_frame', 'ground_height_in_cloud_frame', 'centring_note',
           'units_note', 'cloud_notes', 'MAX_PLAUSIBLE_MEDIAN_RANGE_M',
           'NEAR_RADIUS_M', 'MIN_NEAR_SHARE', 'MAX_ONE_SIDEDNESS', 'NOT_CENTRED']

# A spinning LiDAR in its own frame has a large share of its returns close by (point density
# falls with range squared) and sees all around it: on the shared real scans (KITTI HDL-64,
# VLP-16/32, XT32, RELLIS Ouster) 45-100 % of the returns lie within 10 m and the mean unit
# vector towards the returns is 0.02-0.64 long (0.64: a VLP-32 in a one-sided room); the same
# scans moved 20 m away keep 0-6 % within 10 m and a mean unit vector of 0.77-1.0. Both must
# fail, so that a synthetic cloud spread evenly to 80 m (10 % within 10 m, balanced) or a
# forward-looking sensor (one-sided, most returns near) is not flagged.
NEAR_RADIUS_M = 10.0
MIN_NEAR_SHARE = 0.15
MAX_ONE_SIDEDNESS = 0.5
NOT_CENTRED = 'cloud does not look sensor-centred'  # how centring_note's text starts
_MIN_POINTS_TO_JUDGE = 1000
_SAMPLE_POINTS = 1024  # the share is estimated on an evenly strided sample (+- 0.02)


# No LiDAR measures beyond ~500 m: a cloud whose median horizontal range is above this is not in
# metres (millimetres, as some drivers and exporters write, put a 10 m street at 10,000)
MAX_PLAUSIBLE_MEDIAN_RANGE_M = 1000.0


class SensorPose(NamedTuple):
    """Sensor position (m) in the cloud's frame and the cloud frame's roll/pitch (rad)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0

    @property
    def is_identity(self) -> bool:
        return not any(self)

    @property
    def has_rotation(self) -> bool:
        return self.roll != 0.0 or self.pitch != 0.0

    def rotation(self) -> np.ndarray:
        """R = R_y(pitch) R_x(roll): cloud-frame directions -> levelled frame directions."""
        cr, sr = math.cos(self.roll), math.sin(self.roll)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        rot_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        return rot_y @ rot_x


def to_levelled_frame(points: np.ndarray, pose: SensorPose) -> np.ndarray:
    """(N, 3) points in the levelled sensor frame, a new array (the input is not touched).

    Computed in float64 (a large offset keeps its millimetres) and returned in the input's
    float32 when it is float32, the segmenter's working precision for such clouds.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f'points must be an (N, >=3) array, got shape {pts.shape}')
    xyz = pts[:, :3].astype(np.float64)
    xyz -= np.array([pose.x, pose.y, pose.z])
    if pose.has_rotation:
        xyz = xyz @ pose.rotation().T
    return xyz.astype(np.float32) if pts.dtype == np.float32 else xyz


def ground_height_in_cloud_frame(levelled: np.ndarray, ground_z: np.ndarray,
                                 pose: SensorPose) -> np.ndarray:
    """z in the cloud's frame of the ground point (x_L, y_L, ground_z) below each point."""
    if not pose.has_rotation:
        return ground_z + pose.z
    # z component of R^T q: the third column of R dotted with q
    col = pose.rotation()[:, 2]
    return levelled[:, 0] * col[0] + levelled[:, 1] * col[1] + ground_z * col[2] + pose.z


def cloud_notes(points: np.ndarray, pose: Optional[SensorPose] = None) -> list:
    """The one-line notes of :func:`units_note` and :func:`centring_note` that apply, from one
    evenly strided sample of ``points`` (what the node's input checks call per frame)."""
    sample = _sample_offsets(points, pose)
    if sample is None:
        return []
    return [note for note in (_units_problem(*sample), _centring_problem(*sample, pose))
            if note]


def units_note(points: np.ndarray, pose: Optional[SensorPose] = None) -> Optional[str]:
    """A one-line note when the cloud's ranges from the sensor position of ``pose`` (default
    the origin) cannot be metres, else None. Cheap: an evenly strided sample."""
    sample = _sample_offsets(points, pose)
    return None if sample is None else _units_problem(*sample)


def centring_note(points: np.ndarray, pose: Optional[SensorPose] = None) -> Optional[str]:
    """A one-line note when the cloud does not look centred on the sensor, else None.

    ``points``: (N, >=3) in the cloud's frame; ``pose``: the configured sensor pose (the
    check is made around the sensor position it gives). Cheap: an evenly strided sample.
    """
    sample = _sample_offsets(points, pose)
    return None if sample is None else _centring_problem(*sample, pose)


def _sample_offsets(points, pose):
    """(dx, dy, r) from the sensor position of ``pose`` of an evenly strided sample of the
    finite points that are not the (0, 0, 0) no-return value; None when too few to judge."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[0] < _MIN_POINTS_TO_JUDGE:
        return None
    pts = pts[::max(1, pts.shape[0] // _SAMPLE_POINTS), :3]
    pose = pose or SensorPose()
    # signalling-NaN bit patterns (driver garbage) raise FE_INVALID when widened; they become
    # NaN all the same and are left out below
    with np.errstate(invalid='ignore'):
        dx = pts[:, 0].astype(np.float64) - pose.x
        dy = pts[:, 1].astype(np.float64) - pose.y
    r = np.hypot(dx, dy)
    ok = np.isfinite(r) & ((pts[:, 0] != 0) | (pts[:, 1] != 0) | (pts[:, 2] != 0))
    if np.count_nonzero(ok) < _MIN_POINTS_TO_JUDGE // 20:
        return None
    return dx[ok], dy[ok], r[ok]


def _units_problem(dx, dy, r) -> Optional[str]:
    """units_note of a sample (_sample_offsets)."""
    r = r[r > 0]
    if r.size < _MIN_POINTS_TO_JUDGE // 20:
        return None
    median = float(np.median(r))
    if median <= MAX_PLAUSIBLE_MEDIAN_RANGE_M:
        return None
    return (f'the median horizontal range of the points is {median:,.0f} m: are x, y, z in '
            'millimetres? PointCloud2 coordinates are metres (REP 103); the segmenter assumes '
            'them')


def _centring_problem(dx, dy, r, pose) -> Optional[str]:
    """centring_note of a sample (_sample_offsets)."""
    pose = pose or SensorPose()
    share = float(np.mean(r < NEAR_RADIUS_M))
    if share >= MIN_NEAR_SHARE:
        return None
    inv_r = 1.0 / np.maximum(r, 1e-9)
    one_sided = float(np.hypot(np.mean(dx * inv_r), np.mean(dy * inv_r)))
    if one_sided <= MAX_ONE_SIDEDNESS:
        return None
    centre = 'the origin' if pose.is_identity else f'the sensor position ({pose.x:g}, ' \
        f'{pose.y:g}) m'
    return (f'{NOT_CENTRED}: only {100 * share:.0f} % of the returns lie within '
            f'{NEAR_RADIUS_M:g} m of {centre} and they lie to one side of it (mean direction '
            f'{one_sided:.2f}); publish the cloud in the sensor frame or set the sensor_* pose '
            f'parameters')
