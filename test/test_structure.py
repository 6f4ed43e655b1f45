# SPDX-License-Identifier: Apache-2.0
"""The structure stage: wall feet become obstacle; curbs, ramps, far ground, overhangs stay ground.

Hand-built point sets in the geometry of a spinning LiDAR at the origin: ground rings a few
decimetres to metres apart radially, points every 0.1-0.2 degrees along a ring, a wall face
hit by one beam above the other at the same xy.
"""

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core.structure import vertical_structure_mask
from gp_ground_segmentation.core.compiled import AVAILABLE as COMPILED
from conftest import compiled_ready

P = SegmenterParams()
KW = dict(cell_m=P.structure_cell_m, cell_deg=P.structure_cell_deg, rise_m=P.structure_rise_m,
          max_height_m=P.structure_max_height_m, step_m=P.structure_step_m)
RNG = np.random.default_rng(0)


def ground_rings(ranges, az_deg=np.arange(-30.0, 30.0, 0.17), z=0.0, slope=0.0, noise=0.02):
    """Points on rings at ``ranges`` (m) over ``az_deg``; z = z + slope * x (+ range noise)."""
    r, a = np.meshgrid(np.asarray(ranges, float), np.radians(az_deg))
    r = r.ravel() + RNG.normal(0.0, noise, r.size)
    x, y = r * np.cos(a.ravel()), r * np.sin(a.ravel())
    return np.c_[x, y, z + slope * x]


def wall(x_face, y_span, heights, noise=0.02):
    """A wall face at x = x_face, one row of points per beam height, every 3 cm along y."""
    y, z = np.meshgrid(np.arange(*y_span, 0.03), np.asarray(heights, float))
    return np.c_[x_face + RNG.normal(0.0, noise, y.size), y.ravel(), z.ravel()]


def run(points, ground_z=None, candidate=None):
    x, y, z = (np.ascontiguousarray(points[:, i]) for i in range(3))
    gz = np.zeros_like(z) if ground_z is None else ground_z
    cand = (z - gz <= P.ground_threshold_m) if candidate is None else candidate
    return vertical_structure_mask(x, y, z, gz, cand, **KW), cand


def test_wall_foot_is_rejected_ground_in_front_is_kept():
    ground = ground_rings(np.arange(3.0, 9.6, 0.3))
    foot = wall(10.0, (-3.0, 3.0), [0.0, 0.05, 0.1])  # lowest returns, within the threshold
    face = wall(10.0, (-3.0, 3.0), np.arange(0.3, 2.5, 0.15))  # above the threshold
    pts = np.r_[ground, foot, face]
    feet, cand = run(pts)
    n_g, n_f = len(ground), len(foot)
    assert feet[n_g:n_g + n_f].mean() > 0.98  # the wall's foot
    assert not feet[:n_g].any()  # ground 0.3 m and more in front of the wall
    assert not feet[n_g + n_f:].any() and (feet <= cand).all()  # only ground candidates


def test_curb_stays_ground():
    # road up to 8 m, a 0.15 m curb face, sidewalk beyond: nothing rises 0.2 m above ground
    road = ground_rings(np.arange(3.0, 8.0, 0.25))
    face = wall(8.0, (-2.0, 2.0), [0.05, 0.1, 0.15])
    sidewalk = ground_rings(np.arange(8.1, 12.0, 0.3), z=0.15)
    feet, cand = run(np.r_[road, face, sidewalk])
    assert cand.all() and not feet.any()


@pytest.mark.parametrize('slope_deg', [10.0, 20.0, 30.0])
def test_ramp_stays_ground(slope_deg):
    # the ground is z = tan(slope) x; the predicted ground follows it with a 5 cm error
    pts = ground_rings(np.arange(3.0, 30.0, 0.2), slope=np.tan(np.radians(slope_deg)))
    gz = pts[:, 2] - RNG.normal(0.0, 0.05, len(pts))
    feet, cand = run(pts, ground_z=gz)
    assert cand.mean() > 0.99 and not feet.any()


def test_sparse_far_ground_stays_ground():
    # rings 7-11 m apart, several points per (wide) far cell, 2 cm height noise, and a
    # predicted ground 0.1 m too low there (the GP is less sure far away). (A noise spike
    # more than structure_rise_m above the predicted ground would condemn its neighbours.)
    pts = ground_rings(np.r_[40.0, 47.0, 55.0, 64.0, 75.0], az_deg=np.arange(0, 360, 0.08))
    pts[:, 2] += RNG.normal(0.0, 0.02, len(pts))
    feet, cand = run(pts, ground_z=np.full(len(pts), -0.1))
    assert cand.mean() > 0.99 and not feet.any()


def test_ground_under_an_overhang_stays_ground():
    # a tree crown or car body 1.0-2.5 m above visible ground is not a column
    ground = ground_rings(np.arange(3.0, 12.0, 0.3))
    crown = ground_rings(np.arange(6.0, 9.0, 0.1), z=1.0)
    crown[:, 2] += RNG.uniform(0.0, 1.5, len(crown))
    feet, _ = run(np.r_[ground, crown])
    assert not feet.any()


def test_azimuth_wraps_around_behind_the_sensor():
    # a wall across the -x axis (azimuth +-180 degrees): its foot on both sides of the seam
    foot = wall(-10.0, (-1.0, 1.0), [0.0, 0.05])
    face = wall(-10.0, (-1.0, 1.0), np.arange(0.25, 1.5, 0.15))
    feet, _ = run(np.r_[foot, face])
    assert feet[:len(foot)].all()
    # and a foot point exactly on the seam sees the column on the other side of it
    seam = np.array([[-10.0, 0.0, 0.0], [-10.0, 0.004, 0.4], [-10.0, -0.004, 0.4]])
    for column in (seam[[0, 1]], seam[[0, 2]]):
        assert run(column)[0][0]


def test_points_beyond_the_largest_cell_keep_their_label():
    # cells grow with range up to 0.5 m (115 m at 0.25 degrees); a scene 1e6 m away would
    # otherwise share kilometre-wide cells with every obstacle
    ground = ground_rings(np.arange(3.0, 9.6, 0.3)) + [1e6, 0.0, 0.0]
    face = wall(1e6 + 10.0, (-3.0, 3.0), np.arange(0.25, 2.5, 0.15))
    feet, cand = run(np.r_[ground, face])
    assert cand[:len(ground)].all() and not feet.any()


def test_nothing_to_do():
    pts = ground_rings([5.0])
    feet, _ = run(pts, candidate=np.zeros(len(pts), bool))
    assert not feet.any()
    feet, cand = run(pts)  # no column anywhere
    assert cand.all() and not feet.any()


def test_switch_and_stage_timing_in_the_segmenter():
    pts = np.r_[ground_rings(np.arange(3.0, 9.6, 0.3), az_deg=np.arange(0, 360, 0.5), z=-1.7),
                wall(10.0, (-3.0, 3.0), np.arange(-1.7, 1.0, 0.1))]
    on = GroundSegmenter().segment(pts)
    off = GroundSegmenter(P.replace(use_vertical_structure_test=False)).segment(pts)
    assert 'structure' in on.timings_ms and 'structure' not in off.timings_ms
    assert on.stats['structure_feet'] > 0 and off.stats['structure_feet'] == 0
    assert (on.ground_mask <= off.ground_mask).all()
    assert np.count_nonzero(off.ground_mask & ~on.ground_mask) == on.stats['structure_feet']


# --- compiled table and look-ups == numpy reference (same mask) ------------------------------

@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize('seed', range(3))
def test_compiled_pass_equals_the_numpy_reference(seed, dtype):
    if not COMPILED:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(seed)
    # a full turn (azimuth wrap), near and far rings, walls, boxes and posts of every height,
    # and column points exactly step_m above a candidate (the comparison's edge)
    parts = [ground_rings(np.arange(2.0, 60.0, 0.7), np.arange(-180.0, 180.0, 0.2),
                          noise=0.01)]
    for _ in range(12):
        az = rng.uniform(-np.pi, np.pi)
        r = rng.uniform(3.0, 120.0)
        heights = rng.uniform(0.0, 1.2, 6)
        face = wall(r, (-1.0, 1.0), heights)
        c, s = np.cos(az), np.sin(az)
        parts.append(np.c_[c * face[:, 0] - s * face[:, 1], s * face[:, 0] + c * face[:, 1],
                           face[:, 2]])
    points = np.concatenate(parts).astype(dtype)
    edge = points[:50].copy()
    edge[:, 2] = points[:50, 2] + dtype(P.structure_step_m) + dtype(P.structure_rise_m)
    points = np.concatenate([points, edge])
    x, y, z = (np.ascontiguousarray(points[:, i]) for i in range(3))
    gz = np.zeros_like(z)
    cand = z - gz <= P.ground_threshold_m
    compiled_ready(vertical_structure_mask, x, y, z, gz, cand, **KW)
    compiled = vertical_structure_mask(x, y, z, gz, cand, **KW)
    reference = vertical_structure_mask(x, y, z, gz, cand, **KW, compiled=False)
    assert 100 < np.count_nonzero(reference) < np.count_nonzero(cand)
    assert np.array_equal(compiled, reference)


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_compiled_pass_equals_the_numpy_reference_on_a_real_scan(dtype):
    from conftest import DATA
    from gp_ground_segmentation.tools.io import read_points_file
    path = DATA / 'kitti_sequnknown_spvnas_000000.bin'
    if not COMPILED or not path.exists():
        pytest.skip('numba or the scan is missing')
    arr = read_points_file(path)
    x, y, z = (np.ascontiguousarray(arr[c], dtype=dtype) for c in 'xyz')
    result = GroundSegmenter(SegmenterParams(use_vertical_structure_test=False)).segment(
        np.c_[x, y, z])
    gz = result.ground_height.astype(dtype)
    cand = result.ground_mask
    compiled_ready(vertical_structure_mask, x, y, z, gz, cand, **KW)
    compiled = vertical_structure_mask(x, y, z, gz, cand, **KW)
    reference = vertical_structure_mask(x, y, z, gz, cand, **KW, compiled=False)
    assert np.count_nonzero(reference) > 1000
    assert np.array_equal(compiled, reference)


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_compiled_selection_equals_the_numpy_reference(dtype):
    """Column points and candidates within the range limit: the compiled pass returns the
    reference's points (indices, azimuths, heights, ranges), with heights and ranges exactly at the
    limits."""
    from gp_ground_segmentation.core import structure
    if not COMPILED:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(11)
    n_points = 5000
    limit, rise, top = dtype(115.0), dtype(0.2), dtype(0.7)
    r = rng.uniform(0.0, 130.0, n_points).astype(dtype)
    r[:20] = limit
    ground_z = rng.normal(0.0, 0.3, n_points).astype(dtype)
    z = ground_z + rng.uniform(-0.2, 1.0, n_points).astype(dtype)
    z[20:40] = ground_z[20:40] + rise
    z[40:60] = ground_z[40:60] + top
    candidate = rng.random(n_points) < 0.5
    x, y = (rng.normal(0.0, 30.0, n_points).astype(dtype) for _ in range(2))
    angle = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    args = (angle, z, ground_z, candidate, r, rise, top, limit)
    ours = structure._select_compiled(*args)
    reference = structure._select_numpy(*args)
    for a, b in zip(ours, reference):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert 0 < reference[0].size < reference[3].size < n_points


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_compiled_cells_equal_their_numpy_twins(dtype):
    """The compiled path's two passes (selection with the cells, then far rings, table and
    look-ups) give their numpy twins' outputs, near and far points, and the same mask as the
    numpy path of vertical_structure_mask."""
    from gp_ground_segmentation.core import structure
    if structure._cells_hits_compiled is None:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(5)
    n_points = 6000
    r = rng.uniform(0.5, 130.0, n_points).astype(dtype)
    angle = rng.uniform(-np.pi, np.pi, n_points)
    angle[:5] = np.pi  # the last azimuth cell's edge
    ground_z = np.zeros(n_points, dtype)
    z = rng.choice(np.array([0.0, 0.05, 0.3, 0.6], dtype), n_points)
    candidate = z < 0.1
    cell_rad = np.radians(KW['cell_deg'])
    n_az = int(np.ceil(2.0 * np.pi / cell_rad))
    r_square = KW['cell_m'] / cell_rad
    select = (angle, z, ground_z, candidate, r, dtype(0.2), dtype(0.7), dtype(115.0), n_az,
              n_az / (2.0 * np.pi), 1.0 / KW['cell_m'], r_square, 1.0 / r_square)
    ours = structure._select_cells_compiled(*select)
    twin = structure._select_cells_numpy(*select)
    for a, b in zip(ours, twin):
        np.testing.assert_array_equal(a, b)
    far_index, n_far_col, far_ratio, r_cand = twin[7:]
    assert 0 < n_far_col < far_index.size < n_points
    assert r_cand.dtype == np.float64 and r_cand.size == np.count_nonzero(candidate & (r <= 115))
    hits = (n_points, *twin[:7], far_index, n_far_col, np.log(far_ratio), r_square / KW['cell_m'],
            1.0 / cell_rad, n_az, dtype(KW['step_m']))
    reference = structure._cells_hits_numpy(*hits)
    np.testing.assert_array_equal(structure._cells_hits_compiled(*hits), reference)
    assert 0 < np.count_nonzero(reference) < np.count_nonzero(candidate)
    x, y = (r * np.cos(angle)).astype(dtype), (r * np.sin(angle)).astype(dtype)
    kw = dict(KW, r=r, angle=angle)
    np.testing.assert_array_equal(
        vertical_structure_mask(x, y, z, ground_z, candidate, **kw),
        vertical_structure_mask(x, y, z, ground_z, candidate, **kw, compiled=False))
