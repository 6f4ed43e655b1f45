# SPDX-License-Identifier: Apache-2.0
"""GroundSurface (core/surface.py): the GP ground surface, height_at, height_above_ground."""

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core.surface import GroundSurface
from conftest import compiled_and_reference
from scenes import synthetic


@pytest.fixture(scope='module')
def ramp():
    """A sloped synthetic scan (exact terrain) and its result on the second (warm) frame."""
    scan = synthetic.scan_scene('ramp15')
    points = np.ascontiguousarray(scan.points)
    seg = GroundSegmenter(SegmenterParams())
    seg.segment(points)
    return scan, points, seg.segment(points)


def test_height_at_points_is_the_labels_ground_height(ramp):
    _, points, result = ramp
    z_hat, z_std = result.ground_surface.height_at(points[:, 0], points[:, 1])
    assert np.isfinite(z_hat).all() and np.isfinite(z_std).all()
    surface = result.ground_surface
    offset, _ = _interpolated(surface, surface.ground_offset, points)
    # ramp15: the lowest points lie ~1.5 cm under the exact terrain, more on the ramp
    low, median, high = np.percentile(offset, [5, 50, 95])
    assert 0.005 < median < 0.05 and -0.05 < low and high < 0.1
    np.testing.assert_allclose(z_hat, result.ground_height + offset, atol=1e-4)


def _interpolated(surface, values, points):
    """``values`` (M, N + 1) at the points with height_at's interpolation (z_std unused)."""
    from gp_ground_segmentation.core.surface import GroundSurface
    other = GroundSurface(surface.r[:, 0], surface.r[:, 1] - surface.r[:, 0],
                          np.ones(surface.num_segments, bool), values, surface.supported[:, 0],
                          np.zeros(values.shape))
    return other.height_at(points[:, 0], points[:, 1])


def test_ground_offsets_bins_to_edges_clipped_and_filled():
    from gp_ground_segmentation.core.surface import ground_offsets
    # segment 0: bin 0 holds 0.01, 0.03 and an obstacle point at 5 m (clipped to 0.02 + 0.3);
    # bin 1 is empty; segment 1 has no ground point at all; the last point is not ground
    z_hat = np.array([1.0, 1.0, 1.0, -1.0, -1.0, 0.0])
    z = z_hat + np.array([0.01, 0.03, 5.0, 0.02, 0.02, 7.0])
    ground = np.array([True, True, True, True, True, False])
    segment = np.array([0, 0, 0, 0, 0, 1])
    bins = np.array([0, 0, 0, 2, 2, 1])
    for compiled in (True, False):
        out = ground_offsets(z, z_hat, ground, segment, bins, 2, 3, noise_std=0.1,
                             compiled=compiled)
        median = 0.02
        bin0 = (0.01 + 0.03 + median + 0.3) / 3
        np.testing.assert_allclose(out[0], [bin0, bin0, 0.02, 0.02])
        np.testing.assert_allclose(out[1], median)
    assert np.array_equal(ground_offsets(z, z_hat, ground & False, segment, bins, 2, 3, 0.1),
                          np.zeros((2, 4)))  # no ground point: no offset


def _offset_inputs(rng, size, m, n, z_dtype=np.float64):
    """Heights scattered about z_hat with outliers on both sides (clipped), many ties (z on a
    1 cm lattice), empty bins and segments, and a third of the points not ground."""
    z_hat = rng.normal(0.0, 0.5, size)
    z = (z_hat + rng.normal(0.0, 0.05, size)
         + rng.choice([0.0, 3.0, -2.0], size, p=[.8, .1, .1])).round(2).astype(z_dtype)
    ground = rng.random(size) < 0.67
    segment = rng.integers(0, max(1, m - 2), size).astype(np.int32)
    bins = rng.integers(0, max(1, n - 1), size).astype(np.int32)
    return z, z_hat, ground, segment, bins


@pytest.mark.parametrize('seed', range(6))
def test_ground_offsets_compiled_equals_the_numpy_reference(seed):
    from gp_ground_segmentation.core import surface
    rng = np.random.default_rng(seed)
    # odd and even numbers of ground points (the median's two cases), float32 and float64 z
    size = (1, 2, 3, 400, 401, 5000)[seed]
    args = _offset_inputs(rng, size, 7, 5, (np.float32, np.float64)[seed % 2]) + (7, 5, 0.05)
    compiled, reference = compiled_and_reference(surface.ground_offsets, *args)
    assert np.array_equal(compiled, reference)  # same sums in the same order: bit-identical


def test_ground_offsets_compiled_equals_the_numpy_reference_on_a_scan(ramp):
    from gp_ground_segmentation.core import surface
    _, points, result = ramp
    grid_args = result.ground_surface.num_segments, result.ground_surface.num_bins
    # the labels the surface uses, in made-up grid cells
    seg = surface.segment_of(points[:, 0], points[:, 1], grid_args[0])
    bins = np.arange(points.shape[0], dtype=np.int32) % grid_args[1]
    args = (points[:, 2].copy(), result.ground_height, result.ground_mask, seg, bins,
            *grid_args, 0.03)
    compiled, reference = compiled_and_reference(surface.ground_offsets, *args)
    assert result.ground_mask.sum() > 10000 and np.array_equal(compiled, reference)


def test_ground_offsets_leave_non_finite_residuals_to_the_reference():
    from gp_ground_segmentation.core import surface
    args = list(_offset_inputs(np.random.default_rng(7), 300, 4, 4))
    args[0][np.flatnonzero(args[2])[:3]] = np.nan  # three ground points without a height
    compiled, reference = compiled_and_reference(surface.ground_offsets, *args, 4, 4, 0.05)
    assert np.array_equal(compiled, reference, equal_nan=True)


@pytest.mark.parametrize('seed', range(4))
def test_ground_offsets_compiled_equals_the_reference_with_cells_in_runs(seed):
    """Points grouped by cell, as a scan's come ring by ring (the kernel adds a run of one cell
    in a register): still the reference's sums, bit for bit; runs of one cell that come back
    later, single points between runs, a first run at cell 0 and one at the last cell."""
    from gp_ground_segmentation.core import surface
    rng = np.random.default_rng(seed)
    m, n = 6, 5
    runs = rng.integers(0, m * n, 300)
    runs[0], runs[-1] = 0, m * n - 1
    cells = np.repeat(runs, rng.integers(1, 30, runs.size))
    z, z_hat, ground, _, _ = _offset_inputs(rng, cells.size, m, n,
                                            (np.float32, np.float64)[seed % 2])
    args = (z, z_hat, ground, (cells // n).astype(np.int32), (cells % n).astype(np.int32), m, n,
            0.05)
    compiled, reference = compiled_and_reference(surface.ground_offsets, *args)
    assert np.array_equal(compiled, reference)


def _surface_points(surface, supported_only, compiled):
    return surface.points(supported_only, compiled=compiled)


def _points_compiled_and_reference(surface, supported_only):
    """(compiled, reference) points of ``surface``, checking that the kernel ran and that the
    reference's rows are the surface's x, y, z, z_std."""
    from gp_ground_segmentation.core import surface as module
    out = compiled_and_reference(_surface_points, surface, supported_only)
    assert module.POINTS.kernel.signatures, 'the points kernel never compiled'
    rows = np.flatnonzero(surface.supported[:, 0]) if supported_only else slice(None)
    with np.errstate(over='ignore', invalid='ignore'):
        columns = [np.asarray(c, np.float32)[rows] for c in (surface.x, surface.y, surface.z,
                                                             surface.z_std)]
    properties = np.stack(columns, axis=-1).reshape(-1, 4)
    _assert_same_rows(out[1], properties[np.isfinite(properties).all(axis=1)])
    return out


def _assert_same_rows(compiled, reference):
    assert compiled.dtype == reference.dtype == np.float32
    assert compiled.shape == reference.shape and compiled.tobytes() == reference.tobytes()


_POSES = [(0.0, 0.0, 0.0, 0.0, 0.0), (0.4, -0.3, 1.8, 0.0, 0.0), (0.4, -0.3, 1.8, 0.07, -0.12),
          (0.0, 0.0, 0.0, -0.2, 0.0)]


@pytest.mark.parametrize('pose', _POSES)
@pytest.mark.parametrize('supported_only', [True, False])
def test_surface_points_compiled_equal_the_numpy_reference_on_a_scan(ramp, pose, supported_only):
    """The node's surface rows from the one-pass kernel are the reference's, byte for byte:
    a real frame's surface (offsets, GP std, unsupported segments) under every kind of pose."""
    from gp_ground_segmentation.core.sensor_frame import SensorPose
    _, points, result = ramp
    s = result.ground_surface
    surface = GroundSurface(s._r_min, s._width, s._has_points, s._mean, s._segment_supported,
                            s.gp_std, compute_offset=lambda: s.ground_offset,
                            pose=SensorPose(*pose))
    compiled, reference = _points_compiled_and_reference(surface, supported_only)
    assert len(reference) > 1000
    _assert_same_rows(compiled, reference)


@pytest.mark.parametrize('seed', range(12))
def test_surface_points_compiled_equal_the_numpy_reference_on_random_surfaces(seed):
    """Random grids: NaN and absurd heights (rows not finite in float32 are left out), NaN and
    infinite offsets (read as 0), unsupported and empty segments, NaN r_min, a single segment,
    translated and tilted poses."""
    from gp_ground_segmentation.core.sensor_frame import SensorPose
    rng = np.random.default_rng(seed)
    m, n = (1 if seed == 0 else int(rng.integers(2, 40))), int(rng.integers(1, 30))
    r_min = rng.uniform(0.0, 20.0, m)
    width = rng.uniform(0.01, 3.0, m)
    mean = rng.normal(0.0, 1.0, (m, n + 1)) * rng.uniform(0.0, 3.0)
    std = np.abs(rng.normal(0.0, 0.2, (m, n + 1)))
    offset = rng.normal(0.0, 0.02, (m, n + 1))
    if seed % 2:
        mean[rng.random(mean.shape) < 0.05] = np.nan
        mean[rng.random(mean.shape) < 0.03] = 1e39 * rng.choice([-1.0, 1.0])
        offset[rng.random(offset.shape) < 0.05] = rng.choice([np.nan, np.inf])
        std[rng.random(std.shape) < 0.03] = 1e40
    if seed % 4 == 3:
        r_min[rng.integers(0, m)] = np.nan
    supported = rng.random(m) < 0.7
    has_points = supported | (rng.random(m) < 0.5)
    pose = SensorPose(*_POSES[seed % len(_POSES)])
    surface = GroundSurface(r_min, width, has_points, mean, supported, std,
                            compute_offset=lambda: offset, pose=pose)
    for supported_only in (True, False):
        _assert_same_rows(*_points_compiled_and_reference(surface, supported_only))


def test_surface_points_of_an_empty_surface_are_the_reference():
    surface = GroundSurface.empty(8, 4)
    for supported_only in (True, False):
        compiled, reference = _points_compiled_and_reference(surface, supported_only)
        _assert_same_rows(compiled, reference)
    assert compiled.shape == (0, 4)  # all NaN: nothing published


@pytest.mark.parametrize('seed', range(3))
def test_median_by_bucketing_is_numpys_median(seed):
    from gp_ground_segmentation.core import surface
    rng = np.random.default_rng(seed)
    for size in list(range(1, 150)) + [1000, 1001, 70000]:
        # ties (a coarse lattice), far outliers (a first round that keeps almost everything),
        # sorted, reversed and constant inputs
        values = rng.integers(-5, 6, size) * 0.1 if seed == 0 else rng.normal(0, 0.05, size)
        if seed == 2:
            values[rng.integers(0, size, max(1, size // 100))] = 1e6 * rng.normal(size=1)
        for case in (values, np.sort(values), np.sort(values)[::-1].copy(), values * 0):
            assert surface._median_of(case) == np.median(case), (size, case)
    assert surface._median_of(np.array([-1e308, 1e308, 0.0])) == 0.0  # max - min overflows


def test_height_at_is_vectorised_and_nan_outside_the_grid(ramp):
    _, _, result = ramp
    surface = result.ground_surface
    x = np.array([[5.0, 1e4], [np.nan, -7.0]])
    y = np.array([[1.0, 0.0], [0.0, 2.0]])
    z, std = surface.height_at(x, y)
    assert z.shape == std.shape == (2, 2)
    assert np.isnan(z[0, 1]) and np.isnan(z[1, 0]) and np.isnan(std[0, 1])
    assert np.isfinite(z[0, 0]) and np.isfinite(z[1, 1])
    # at the prediction points themselves height_at returns the surface
    z_at, std_at = surface.height_at(surface.x, surface.y)
    ok = np.isfinite(z_at)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(z_at[ok], surface.z[ok], atol=1e-6)
    np.testing.assert_allclose(std_at[ok], surface.z_std[ok], atol=1e-6)


def test_surface_points_follow_the_exact_terrain(ramp):
    scan, _, result = ramp
    s = result.ground_surface
    assert s.x.shape == s.y.shape == s.z.shape == s.z_std.shape == s.supported.shape
    assert s.supported.all()  # a full sweep over open terrain: every segment has candidates
    truth = scan.terrain_z(s.x, s.y)
    assert np.median(np.abs(s.z - truth)) < 0.05  # ramp15, measured 0.017 m at the points
    np.testing.assert_allclose(np.hypot(s.x, s.y), s.r, atol=1e-9)
    points = s.points()
    assert points.dtype == np.float32 and points.shape == (s.z.size, 4)


def test_z_std_is_lazy_and_equals_the_details_std(ramp):
    _, points, _ = ramp
    params = SegmenterParams()
    assert not params.use_std_threshold  # the default does not need the std
    plain = GroundSegmenter(params).segment(points)
    detailed = GroundSegmenter(params).segment(points, details=True)
    assert plain.ground_surface._std is None  # not computed by segment()
    surface = plain.ground_surface
    np.testing.assert_allclose(surface.gp_std, detailed.details.ground_std, rtol=1e-9,
                               atol=1e-12)
    theta = plain.hyperparameters
    assert (surface.gp_std <= theta.sigma_f + 1e-12).all()
    assert surface._std is not None
    # the coupled surface follows the ground across the segment: z_std is the GP's
    assert (surface.across_segment_std == 0).all()
    np.testing.assert_allclose(surface.z_std, surface.gp_std)
    # with the paper's per-segment height, z_std adds the spread across the segment
    per_segment = GroundSegmenter(params.replace(use_coupled_surface=False)).segment(points)
    surface = per_segment.ground_surface
    np.testing.assert_allclose(surface.z_std, np.hypot(surface.gp_std,
                                                       surface.across_segment_std))
    assert (surface.across_segment_std >= 0).all() and surface.across_segment_std.max() > 0


def test_z_std_falls_back_to_numpy_when_the_std_kernel_fails(ramp, monkeypatch):
    """The std's kernel may first be compiled at the first z_std read (warm_up leaves it to the
    background): should that fail, the surface still gets its std, from numpy."""
    import dataclasses
    from gp_ground_segmentation.core import predict
    _, points, _ = ramp
    compiled_std = GroundSegmenter().segment(points).ground_surface.gp_std

    def broken(*args):
        raise RuntimeError('no LLVM here')
    monkeypatch.setattr(predict, 'STD', dataclasses.replace(predict.STD, kernel=broken))
    surface = GroundSegmenter().segment(points).ground_surface
    # sqrt(sigma_f^2 - k*^T A^-1 k*) cancels where the std is small: another summation order
    # moves it by ~1e-8 m there
    np.testing.assert_allclose(surface.gp_std, compiled_std, rtol=1e-5, atol=1e-8)
    assert np.isfinite(surface.z_std).all()


def test_across_segment_std_of_a_plane_sloping_across_the_beams():
    """Hand-computed: on the plane z = a y, segment m (centre azimuth c, width w = 2 pi / M)
    has its neighbours at the same r at a r sin(c +- w): where one is above and the other below,
    the ground spans s = a r min(|sin(c + w) - sin c|, |sin c - sin(c - w)|) across it, and a
    point uniformly across its width is off its centre line by a std of s / (2 sqrt 3)."""
    m_count, n_bins, slope = 36, 5, 0.2
    r_min, width = np.full(m_count, 2.0), np.full(m_count, 3.0)
    centre = -np.pi + (np.arange(m_count) + 0.5) * (2 * np.pi / m_count)
    r = 2.0 + 3.0 * np.arange(n_bins + 1)
    mean = slope * r[None, :] * np.sin(centre)[:, None]
    supported = np.ones(m_count, bool)
    surface = GroundSurface(r_min, width, supported, mean, supported,
                            std=np.zeros_like(mean))
    w = 2 * np.pi / m_count
    up = (np.sin(centre + w) - np.sin(centre))[:, None] * slope * r[None, :]
    down = (np.sin(centre) - np.sin(centre - w))[:, None] * slope * r[None, :]
    s = np.where(up * down > 0, np.minimum(np.abs(up), np.abs(down)), 0.0)
    expected = s / (2 * np.sqrt(3))
    assert (expected[:, 1:] > 0).sum() > 0.8 * m_count * n_bins  # a slope almost everywhere
    np.testing.assert_allclose(surface.across_segment_std, expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(surface.z_std, expected, rtol=1e-9, atol=1e-12)
    # no neighbour's support, no support of its own, flat ground: nothing
    supported[5] = False
    holes = GroundSurface(r_min, width, supported, mean, supported, std=np.zeros_like(mean))
    assert (holes.across_segment_std[4:7] == 0).all()
    flat = GroundSurface(r_min, width, np.ones(m_count, bool), np.zeros_like(mean),
                         np.ones(m_count, bool), std=np.zeros_like(mean))
    assert (flat.across_segment_std == 0).all()


def test_surface_is_calibrated_on_ground_sloping_across_the_beams():
    """Issue 11's calibration, where the GP part alone fell short: the whole scene on a 15 deg
    plane (a cross slope in most segments). The coupled surface follows the plane between the
    borders: median error 0.0007 m, 0.993 of the true ground within +-2 z_std (z_std is the
    per-segment GP's, which knows the ground less well than the coupled surface does). With the
    paper's per-segment height: median error 0.010 m, 0.987 covered with the across-segment
    spread in z_std (0.812 with the GP's std alone)."""
    scan = synthetic.scan_scene('onslope15')
    terrain = np.asarray(scan.kind) == synthetic.KIND_TERRAIN
    xy = scan.points[terrain, :2].astype(np.float64)
    for coupled, max_error, max_covered in ((True, 0.002, 0.996), (False, 0.015, 0.99)):
        seg = GroundSegmenter(SegmenterParams(use_coupled_surface=coupled))
        seg.segment(scan.points[:, :3])
        surface = seg.segment(scan.points[:, :3]).ground_surface
        z, z_std = surface.height_at(xy[:, 0], xy[:, 1])
        err = z - scan.terrain_z(xy[:, 0], xy[:, 1])
        ok = np.isfinite(err)
        assert ok.mean() > 0.99
        covered = np.mean(np.abs(err[ok]) <= 2 * z_std[ok])
        assert 0.95 <= covered <= max_covered, (coupled, covered)
        assert np.median(np.abs(err[ok])) < max_error
    assert np.median(np.abs(err[ok])) <= 0.015


def test_unsupported_segments_and_half_plane_cloud(ramp):
    _, points, _ = ramp
    front = points[points[:, 0] > 2.0]
    result = GroundSegmenter(SegmenterParams()).segment(front)
    s = result.ground_surface
    azimuth_deg = np.degrees(s.azimuth[:, 0])
    assert not s.supported[np.abs(azimuth_deg) > 120].any()
    assert s.supported[np.abs(azimuth_deg) < 30].all()
    z, std = s.height_at(np.array([-10.0, 10.0]), np.array([0.5, 0.5]))
    assert np.isnan(z[0]) and np.isfinite(z[1])
    # segments without points sit at the prior: std sigma_f
    empty = ~s.supported[:, 0]
    np.testing.assert_allclose(s.z_std[empty], result.hyperparameters.sigma_f)
    assert len(s.points()) == int(s.supported.sum())


def test_height_above_ground_with_invalid_points(ramp):
    _, points, _ = ramp
    pts = points.copy()
    pts[::50, 2] = np.nan
    pts[1::50, :3] = 0.0
    result = GroundSegmenter(SegmenterParams()).segment(pts)
    hag = result.height_above_ground
    assert hag.dtype == np.float64 and hag.shape == (len(pts),)
    assert np.isnan(hag[~result.valid_mask]).all()
    valid = result.valid_mask
    np.testing.assert_allclose(hag[valid], pts[valid, 2] - result.ground_height[valid], atol=1e-6)
    assert np.median(hag[result.ground_mask]) < 0.1 < np.median(hag[result.obstacle_mask])


def test_empty_frame_has_an_empty_surface():
    result = GroundSegmenter(SegmenterParams()).segment(np.full((4, 3), np.nan))
    s = result.ground_surface
    assert not s.supported.any() and s.points().shape == (0, 4)
    assert np.isnan(s.height_at(1.0, 1.0)[0])
    assert np.isnan(result.height_above_ground).all()


def test_absurdly_far_points_leave_the_published_points_finite(ramp):
    _, points, _ = ramp
    far = np.r_[points[:, :3].astype(np.float64), np.full((20, 3), 1e30),
                np.full((20, 3), -1e30)]
    result = GroundSegmenter(SegmenterParams()).segment(far)
    out = result.ground_surface.points()
    assert len(out) > 1000 and np.isfinite(out).all()


def test_plot_side_view_draws_the_surface(ramp):
    from gp_ground_segmentation.tools.plot import segment_view
    _, points, result = ramp
    view = segment_view(points[:, :3], result, 60, result.ground_surface.num_segments)
    s = result.ground_surface
    np.testing.assert_array_equal(view['gp_mean'], s.z[60])
    np.testing.assert_array_equal(view['gp_std'], s.z_std[60])
