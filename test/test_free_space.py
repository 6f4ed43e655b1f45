# SPDX-License-Identifier: Apache-2.0
"""The free-space stage (core/free_space.py): hand-placed feet, columns and rays, both twins, and
a ray-cast scene with an overhang beside a wall."""

import math

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core import compiled
from gp_ground_segmentation.core.free_space import FREE_SPACE, spared_numpy

N_AZ = 1440


def _one_foot(other_r, other_z, foot_z=-1.7, foot_r=8.0, same_cell=True):
    """A foot at (foot_r, foot_z) over predicted ground at -1.7 m, the structure test's column
    height 0.2 m, and one other ground candidate at (other_r, other_z): the stage's arguments."""
    feet = np.array([True, False])
    cand = np.array([0, 1], dtype=np.intp)
    az = np.array([7, 7 if same_cell else 8], dtype=np.int32)
    return (feet, cand, az, np.array([foot_r, other_r]), np.array([foot_z, other_z]),
            np.array([-1.7, -1.7]), 0.2, N_AZ, 0.03, 0.1)


def _spared(args, use_compiled=False):
    return not FREE_SPACE.run(use_compiled, *args)[0]


def test_a_ray_under_the_column_height_spares_the_foot():
    # the ray to (8.4, -1.7) passes r = 8 at -1.7 * 8 / 8.4 = -1.619 m: 0.081 m above the foot,
    # 0.119 m below the column height (-1.7 + 0.2): more than the 0.03 m clearance both ways
    assert _spared(_one_foot(8.4, -1.7))
    assert _spared(_one_foot(8.4, -1.7), use_compiled=compiled.AVAILABLE)


@pytest.mark.parametrize('case, args', [
    # a wall: nothing is seen beyond the foot
    ('no return beyond', _one_foot(7.5, -1.7)),
    # the return is not farther out than beyond_m (0.1 m)
    ('too close', _one_foot(8.09, -1.69)),
    # its ray passes r = 8 at -1.7 * 8 / 8.12 = -1.675: 0.025 m above the foot, within 0.03
    ('too low over the foot', _one_foot(8.12, -1.7)),
    # a return far out whose ray passes r = 8 at -1.2 * 8 / 12 = -0.8: above the column height
    ('above the column height', _one_foot(12.0, -1.2)),
    # a foot 0.19 m above the ground: no room below the column height for a ray
    ('no room below the column height', _one_foot(8.4, -1.65, foot_z=-1.51)),
    # the return is in another azimuth cell
    ('other azimuth', _one_foot(8.4, -1.7, same_cell=False)),
])
def test_no_free_space_keeps_the_foot(case, args):
    assert not _spared(args), case


def test_not_a_foot_is_untouched():
    feet = np.array([False, False, True])  # point 2 is no candidate of the stage's
    out = spared_numpy(feet, np.array([0, 1], dtype=np.intp), np.array([3, 3], dtype=np.int32),
                       np.array([8.0, 8.4]), np.array([-1.7, -1.7]), np.full(3, -1.7), 0.2,
                       N_AZ, 0.03, 0.1)
    assert out.tolist() == [False, False, True]


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_twins_agree_on_random_feet(dtype):
    rng = np.random.default_rng(3)
    n_points, n_cand, n_az = 4000, 3000, 90
    cand = np.sort(rng.choice(n_points, n_cand, replace=False)).astype(np.intp)
    feet = np.zeros(n_points, dtype=bool)
    feet[cand[rng.random(n_cand) < 0.3]] = True
    r = rng.uniform(2.0, 30.0, n_cand)
    z = (-1.7 + rng.normal(0.0, 0.05, n_cand)).astype(dtype)
    ground = (-1.7 + rng.normal(0.0, 0.05, n_points)).astype(dtype)
    args = (feet, cand, rng.integers(0, n_az, n_cand).astype(np.int32), r, z, ground, 0.2,
            n_az, 0.03, 0.1)
    reference = FREE_SPACE.reference(*args)
    assert 0 < np.count_nonzero(feet & ~reference) < np.count_nonzero(feet)  # some spared
    assert np.array_equal(FREE_SPACE.kernel(*args), reference)


# --- a ray-cast scene: flat ground, a slab held 0.35 m above it, a wall standing on it ---------

_GROUND_Z = -1.73  # the sensor's height above flat ground (m), KITTI's
_ELEVATIONS = np.radians(np.linspace(-24.8, 2.0, 64))  # an HDL-64E-like fan
# the ring that lands nearest 8 m: the slab's and the wall's near faces stand 2 cm behind it,
# so that its ground returns are structure feet (a column point 2 cm away)
_RING_R = min((_GROUND_Z / math.tan(e) for e in _ELEVATIONS if e < 0), key=lambda r: abs(r - 8))
_SLAB = dict(r=(_RING_R + 0.02, _RING_R + 2.0), az=(-10.0, 10.0),
             z=(_GROUND_Z + 0.35, _GROUND_Z + 1.2))
_WALL = dict(r=(_RING_R + 0.02, _RING_R + 0.3), az=(160.0, 200.0),
             z=(_GROUND_Z - 0.5, _GROUND_Z + 2.5))


def _sector_hit(elev, az_deg, sector):
    """Horizontal distance at which a ray meets a sector-shaped box (near face or top), or
    inf. The sensor is above every box."""
    if not sector['az'][0] <= az_deg % 360.0 <= sector['az'][1] and not (
            sector['az'][0] <= az_deg <= sector['az'][1]):
        return np.inf
    (r0, r1), (z0, z1) = sector['r'], sector['z']
    if z0 <= r0 * math.tan(elev) <= z1:
        return r0
    if elev < 0 and r0 <= z1 / math.tan(elev) <= r1:
        return z1 / math.tan(elev)
    return np.inf


def _scan(sectors):
    """64 beams, 0.1 degree azimuth steps: every ray's first hit of the sectors or the ground
    (within 80 m), as (x, y, z) points."""
    points = []
    for elev in _ELEVATIONS:
        for az in np.arange(-180.0, 180.0, 0.1):
            r = min(_sector_hit(elev, az, sector) for sector in sectors)
            if elev < 0:
                r = min(r, _GROUND_Z / math.tan(elev))
            if r < 80.0:
                a = math.radians(az)
                points.append((r * math.cos(a), r * math.sin(a), r * math.tan(elev)))
    return np.asarray(points, dtype=np.float32)


@pytest.fixture(scope='module')
def overhang_scene():
    points = _scan([_SLAB, _WALL])
    ground = np.abs(points[:, 2] - _GROUND_Z) < 1e-3
    return points, ground


def _near_face(points, sector):
    """Points within 0.1 m in front of the sector's near face, or under it, in its azimuths."""
    r = np.hypot(points[:, 0], points[:, 1])
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    low, high = sector['az'][0] % 360.0, sector['az'][1] % 360.0
    inside = (az >= low) & (az <= high) if low <= high else (az >= low) | (az <= high)
    return inside & (r > sector['r'][0] - 0.1) & (r < sector['r'][1])


def test_ground_under_an_overhang_stays_ground_the_wall_foot_does_not(overhang_scene):
    points, truth = overhang_scene
    slab_ground = truth & _near_face(points, _SLAB)
    wall_feet = truth & _near_face(points, _WALL)  # the ground 2 cm in front of the wall
    wall_bottom = ~truth & _near_face(points, _WALL) & (points[:, 2] < _GROUND_Z + 0.15)
    labels = {}
    for on in (False, True):
        params = SegmenterParams(use_free_space_feet=on)
        labels[on] = GroundSegmenter(params).segment(points).ground_mask
    # without free space the structure test condemns the ground in front of both faces
    condemned = slab_ground & ~labels[False]
    assert condemned.sum() > 100 and np.count_nonzero(wall_feet & ~labels[False]) > 100
    # with it, the ground before and under the slab is found again (rays passed under it),
    # while the ground at the wall's foot and the wall's lowest returns stay obstacles, but
    # for a few at the wall's two ends, where rays of the foot's azimuth cell pass beside it
    assert np.count_nonzero(condemned & labels[True]) >= 0.99 * condemned.sum()
    assert np.count_nonzero(wall_feet & labels[True]) <= 0.01 * wall_feet.sum()
    assert wall_bottom.sum() > 100
    assert np.count_nonzero(wall_bottom & labels[True]) <= 0.01 * wall_bottom.sum()
