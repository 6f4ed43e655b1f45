# SPDX-License-Identifier: Apache-2.0
"""Unit tests of the radial grid (grid.py) against brute-force Python loops over points.

Every reference here is computed point by point with ``math`` and plain dicts, independently of
the vectorised code under test, on small random clouds that include the awkward cases: points
exactly at a segment's r_max, azimuths of exactly +pi and -pi, a segment holding a single point,
empty segments and tied lowest points.
"""

import math

import numpy as np
import pytest

from gp_ground_segmentation.core.grid import build_grid, segment_of
from gp_ground_segmentation.core.length_factors import relative_density
from conftest import compiled_ready


# --------------------------------------------------------------------------------------------
# Brute-force reference
# --------------------------------------------------------------------------------------------
def brute_segment(x, y, num_segments):
    """Segment m covers azimuth [-pi + m w, -pi + (m + 1) w), w = 2 pi / M; +pi joins M - 1."""
    theta = math.atan2(y, x)
    m = math.floor((theta + math.pi) / (2.0 * math.pi / num_segments))
    return min(max(m, 0), num_segments - 1)


def brute_grid(xyz, num_segments, num_bins, slices):
    """Per-point loop: segment, r range per segment, bins, lowest point, z max, rho~ by slices."""
    segs, radii = [], []
    for x, y, _ in xyz:
        segs.append(brute_segment(float(x), float(y), num_segments))
        radii.append(math.sqrt(float(x) ** 2 + float(y) ** 2))
    r_lo, r_hi = {}, {}
    for m, r in zip(segs, radii):
        r_lo[m] = min(r_lo.get(m, math.inf), r)
        r_hi[m] = max(r_hi.get(m, -math.inf), r)
    r_min = [r_lo.get(m, 0.0) for m in range(num_segments)]
    width = [max((r_hi[m] - r_lo[m]) / num_bins, 1e-3) if m in r_lo else 1e-3
             for m in range(num_segments)]
    members = {}  # (m, k) -> list of point indices
    for i, (m, r) in enumerate(zip(segs, radii)):
        k = min(int((r - r_min[m]) / width[m]), num_bins - 1)
        members.setdefault((m, k), []).append(i)

    shape = (num_segments, num_bins)
    out = {'count': np.zeros(shape, dtype=int), 'z_min': np.full(shape, np.nan),
           'z_max': np.full(shape, np.nan), 'lowest': {}, 'density': np.zeros(shape),
           'r_min': np.array(r_min), 'width': np.array(width), 'segment': segs}
    dtheta = 2.0 * math.pi / num_segments
    for (m, k), idx in members.items():
        zs = [float(xyz[i, 2]) for i in idx]
        z_lo, z_hi = min(zs), max(zs)
        out['count'][m, k] = len(idx)
        out['z_min'][m, k] = z_lo
        out['z_max'][m, k] = z_hi
        out['lowest'][(m, k)] = {i for i in idx if float(xyz[i, 2]) == z_lo}
        # rho~ by its definition: j horizontal layers ("vertical slices") from z_min to z_max,
        # each holding count points over the bin's footprint area; mean of count/area.
        inner = r_min[m] + k * width[m]
        outer = inner + width[m]
        area = 0.5 * dtheta * (outer ** 2 - inner ** 2)  # integral of r dr dtheta
        per_slice = [0] * slices
        for z in zs:
            if z_hi == z_lo:
                s = 0
            else:
                s = min(int((z - z_lo) / (z_hi - z_lo) * slices), slices - 1)
            per_slice[s] += 1
        out['density'][m, k] = sum(c / area for c in per_slice) / slices
    return out


def make_cloud(seed, num_segments, used_fraction=0.6, points=60):
    """Random cloud over a subset of segments (others empty), plus the special cases."""
    rng = np.random.default_rng(seed)
    w = 2.0 * np.pi / num_segments
    # segments 0 and M-1 hold only the +-pi points added below
    inner = np.arange(1, num_segments - 1)
    used = rng.choice(inner, size=min(inner.size - 1, max(2, int(used_fraction * num_segments))),
                      replace=False)
    single = used[0]  # this segment gets exactly one point
    multi = used[1:]
    m = rng.choice(multi, size=points)
    theta = -np.pi + (m + rng.uniform(0.02, 0.98, points)) * w
    r = rng.uniform(0.5, 25.0, points)
    z = rng.normal(-1.5, 0.8, points)
    pts = [np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)]
    t1 = -np.pi + (single + 0.5) * w
    pts.append([[7.0 * np.cos(t1), 7.0 * np.sin(t1), 0.3]])
    # azimuth exactly +pi (y = +0.0) and exactly -pi (y = -0.0): arctan2 returns +-pi
    pts.append([[-9.0, 0.0, -1.0], [-4.0, -0.0, -2.0], [-30.0, 0.0, 0.5]])
    # a tie: a second point with the same z as an existing one, almost on top of it
    pts.append([[pts[0][0, 0] * 1.0000001, pts[0][0, 1], pts[0][0, 2]]])
    return np.concatenate([np.asarray(p, dtype=np.float64) for p in pts])


CASES = [(0, 6, 3), (1, 7, 5), (2, 12, 8), (3, 5, 1), (4, 9, 4), (5, 16, 6)]  # seed, M, N


# --------------------------------------------------------------------------------------------
# segment_of
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('num_segments', [4, 8, 12, 360])
def test_segment_of_centres_and_boundaries(num_segments):
    w = 2.0 * np.pi / num_segments
    m = np.arange(num_segments)
    centre = -np.pi + (m + 0.5) * w
    np.testing.assert_array_equal(segment_of(np.cos(centre), np.sin(centre), num_segments), m)
    # just after each boundary -> that segment; just before -> the previous one
    after = -np.pi + m * w + 1e-9
    np.testing.assert_array_equal(segment_of(np.cos(after), np.sin(after), num_segments), m)
    before = -np.pi + m[1:] * w - 1e-9
    np.testing.assert_array_equal(segment_of(np.cos(before), np.sin(before), num_segments),
                                  m[1:] - 1)


def test_segment_of_exact_pi_and_range():
    m_count = 8
    x = np.array([-1.0, -1.0, 1.0, 0.0, 0.0])
    y = np.array([0.0, -0.0, 0.0, 1.0, -1.0])
    assert math.atan2(0.0, -1.0) == math.pi and math.atan2(-0.0, -1.0) == -math.pi
    got = segment_of(x, y, m_count)
    # +pi clipped into the last segment (not wrapped to M), -pi is the start of segment 0,
    # azimuth 0 starts segment M/2, +-pi/2 start segments 3M/4 and M/4.
    np.testing.assert_array_equal(got, [m_count - 1, 0, m_count // 2, 3 * m_count // 4,
                                        m_count // 4])
    rng = np.random.default_rng(7)
    xy = rng.normal(size=(20000, 2)) * rng.choice([1e-6, 1.0, 1e3], size=(20000, 1))
    for m_count in (1, 3, 8, 120):
        s = segment_of(xy[:, 0], xy[:, 1], m_count)
        assert s.min() >= 0 and s.max() <= m_count - 1
        ref = [brute_segment(a, b, m_count) for a, b in xy[:500]]
        np.testing.assert_array_equal(s[:500], ref)


# --------------------------------------------------------------------------------------------
# build_grid against the brute force
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('compiled', [True, False])
@pytest.mark.parametrize('seed,num_segments,num_bins', CASES)
def test_build_grid_matches_brute_force(seed, num_segments, num_bins, compiled):
    xyz = make_cloud(seed, num_segments)
    slices = 1 + seed % 4
    if compiled:  # the compiled pass, not the reference it runs while compiling
        compiled_ready(build_grid, *xyz.T, num_segments, num_bins)
    g = build_grid(*xyz.T, num_segments, num_bins, compiled=compiled)
    ref = brute_grid(xyz, num_segments, num_bins, slices)

    np.testing.assert_array_equal(g.point_segment, ref['segment'])
    np.testing.assert_allclose(g.point_r, np.hypot(xyz[:, 0], xyz[:, 1]), rtol=1e-15)
    np.testing.assert_array_equal(g.count, ref['count'])
    assert g.count.sum() == len(xyz)
    occupied = ref['count'] > 0
    np.testing.assert_array_equal(g.has_candidate, occupied)
    # the special cases really are in the cloud
    segs_used = np.flatnonzero(np.bincount(ref['segment'], minlength=num_segments))
    assert len(segs_used) < num_segments, 'test cloud should leave some segments empty'
    assert (np.bincount(ref['segment'], minlength=num_segments) == 1).any()

    for m in range(num_segments):
        for k in range(num_bins):
            if not occupied[m, k]:
                assert g.candidate_index[m, k] == -1
                assert np.isnan(g.candidate_r[m, k]) and np.isnan(g.candidate_z[m, k])
                assert g.density[m, k] == 0.0
                continue
            idx = int(g.candidate_index[m, k])
            assert idx in ref['lowest'][(m, k)], (m, k)
            assert g.candidate_z[m, k] == ref['z_min'][m, k]
            assert g.candidate_r[m, k] == pytest.approx(math.hypot(*xyz[idx, :2]), rel=1e-15)
            assert g.point_segment[idx] == m and g.point_bin[idx] == k
    # the paper's rho~ over j slices is ours / j: a constant factor (see grid.py)
    np.testing.assert_allclose(g.density / slices, ref['density'], rtol=1e-12)
    np.testing.assert_allclose(g.segment_r_min, ref['r_min'], rtol=1e-15)
    np.testing.assert_allclose(g.bin_width, ref['width'], rtol=1e-12)


def test_points_at_r_max_and_pi_fall_in_valid_bins():
    xyz = make_cloud(11, 6)
    g = build_grid(*xyz.T, 6, 5)
    assert g.point_bin.min() >= 0 and g.point_bin.max() <= 4
    # the farthest point of every non-empty segment (r == r_max) is in the outer bin
    for m in np.unique(g.point_segment):
        members = np.flatnonzero(g.point_segment == m)
        if np.ptp(g.point_r[members]) == 0:
            continue  # single-r segment: 1 mm bins, the point is in bin 0
        far = members[np.argmax(g.point_r[members])]
        assert g.point_bin[far] == 4
    # the three points on the negative x axis: y = +0.0 -> last segment, y = -0.0 -> segment 0
    np.testing.assert_array_equal(g.point_segment[-4:-1], [5, 0, 5])


@pytest.mark.parametrize('compiled', [True, False])
def test_tied_lowest_points_pick_the_first(compiled):
    xyz = np.array([[5.1, 0.1, 0.5], [5.1, 0.1, -1.0], [5.0, 0.1, -1.0], [9.0, 0.1, 0.0]])
    if compiled:
        compiled_ready(build_grid, *xyz.T, 4, 2)
    g = build_grid(*xyz.T, 4, 2, compiled=compiled)
    m = segment_of(np.array([5.0]), np.array([0.1]), 4)[0]
    assert g.candidate_index[m, 0] == 1  # the first in input order: no dependence on layout
    assert g.candidate_z[m, 0] == -1.0
    assert g.count[m, 0] == 3 and g.count[m, 1] == 1


def test_single_point_and_empty_segments():
    xyz = np.array([[3.0, 0.5, -1.7]])
    g = build_grid(*xyz.T, 8, 4)
    m = segment_of(xyz[:, 0], xyz[:, 1], 8)[0]
    assert g.count.sum() == 1 and g.count[m, 0] == 1
    assert g.candidate_index[m, 0] == 0
    assert g.candidate_z[m, 0] == -1.7
    assert g.segment_r_min[m] == pytest.approx(math.hypot(3.0, 0.5))
    assert g.bin_width[m] == pytest.approx(1e-3)  # documented: a single-r segment gets 1 mm bins
    others = np.ones(8, dtype=bool)
    others[m] = False
    assert not g.has_candidate[others].any()
    assert np.all(g.density[others] == 0) and np.all(g.bin_width[others] > 0)
    assert np.isfinite(g.density).all()


# --------------------------------------------------------------------------------------------
# bin widths and rho~
# --------------------------------------------------------------------------------------------
def test_bin_width_is_segment_span_over_n():
    m_count, n_count = 6, 7
    xyz = make_cloud(3, m_count, used_fraction=1.0, points=400)
    g = build_grid(*xyz.T, m_count, n_count)
    for m in range(m_count):
        r = g.point_r[g.point_segment == m]
        if r.size < 2:
            continue
        assert g.segment_r_min[m] == r.min()
        assert g.bin_width[m] == pytest.approx((r.max() - r.min()) / n_count, rel=1e-12)
        edges = g.bin_edges()[m]
        assert edges.shape == (n_count + 1,)
        np.testing.assert_allclose(np.diff(edges), g.bin_width[m], rtol=1e-9)
        assert edges[0] == r.min()
        assert edges[-1] == pytest.approx(r.max(), rel=1e-12)
        # every point of the segment lies inside its own bin's edges
        members = np.flatnonzero(g.point_segment == m)
        k = g.point_bin[members]
        assert np.all(edges[k] <= g.point_r[members] * (1 + 1e-12))
        assert np.all(g.point_r[members] <= edges[k + 1] * (1 + 1e-12))
    # segments differ ("divided unevenly"): widths are not all equal
    assert np.ptp(g.bin_width) > 0


@pytest.mark.parametrize('slices', [1, 2, 4, 7])
def test_density_closed_form_equals_mean_over_slices(slices):
    m_count, n_count = 5, 4
    xyz = make_cloud(20 + slices, m_count, used_fraction=1.0, points=300)
    g = build_grid(*xyz.T, m_count, n_count)
    ref = brute_grid(xyz, m_count, n_count, slices)
    inner = g.segment_r_min[:, None] + np.arange(n_count)[None, :] * g.bin_width[:, None]
    outer = inner + g.bin_width[:, None]
    area = (2.0 * np.pi / m_count) / 2.0 * (outer ** 2 - inner ** 2)
    np.testing.assert_allclose(g.density, g.count / area, rtol=1e-12)
    # the paper's mean over j slices is the closed form n / (j A) for every j
    np.testing.assert_allclose(ref['density'], g.count / (slices * area), rtol=1e-12)
    # the slices really split the points (the closed form is not trivially the same loop)
    assert (g.count > 2).any()


def test_density_sector_area_by_numerical_integration():
    """The sector area used by rho~ equals a Monte-Carlo-free numerical integral of the bin."""
    m_count, n_count = 3, 2
    xyz = np.array([[2.0, 0.1, 0.0], [6.0, 0.2, 0.0], [5.5, 0.15, 1.0]])
    g = build_grid(*xyz.T, m_count, n_count)
    m = g.point_segment[0]
    # midpoint rule over a fine polar grid of the outer bin of segment m
    ri = g.segment_r_min[m] + g.bin_width[m]
    ro = ri + g.bin_width[m]
    rr = np.linspace(ri, ro, 20001)
    rmid = 0.5 * (rr[1:] + rr[:-1])
    area = np.sum(rmid * np.diff(rr)) * (2.0 * np.pi / m_count)
    assert g.count[m, 1] == 2
    assert g.density[m, 1] == pytest.approx(2.0 / area, rel=1e-9)


# --------------------------------------------------------------------------------------------
# relative_density
# --------------------------------------------------------------------------------------------
def brute_relative(density, cand_r, mask, ratio):
    out = np.ones_like(density)
    rings = {}
    for idx in np.ndindex(density.shape):
        if mask[idx] and density[idx] > 0 and np.isfinite(cand_r[idx]) and cand_r[idx] > 0:
            ring = math.floor(math.log(cand_r[idx]) / math.log(ratio))
            rings.setdefault(ring, []).append(idx)
    for members in rings.values():
        geo = math.exp(sum(math.log(density[i]) for i in members) / len(members))
        for i in members:
            out[i] = density[i] / geo
    return out


def test_relative_density_ordinary_ring_is_one_and_spike_is_ten():
    m_count, n_count, ratio = 40, 12, 1.15
    r_col = 1.15 ** (np.arange(n_count) + 6.5)  # one column per log ring, centred in it
    cand_r = np.broadcast_to(r_col, (m_count, n_count)).copy()
    density = 800.0 / cand_r ** 2  # falls with range like a spinning LiDAR's
    density[7, 5] *= 10.0  # ten times the points: an obstacle stacked on the candidate
    mask = np.ones((m_count, n_count), dtype=bool)
    rel = relative_density(density, cand_r, mask, ratio)
    ordinary = np.ones_like(mask)
    ordinary[:, 5] = False
    np.testing.assert_allclose(rel[ordinary], 1.0, rtol=1e-12)
    # the geometric mean of column 5 includes the spike once: 10^(1/M)
    np.testing.assert_allclose(rel[np.arange(m_count) != 7, 5], 10.0 ** (-1.0 / m_count),
                               rtol=1e-12)
    assert rel[7, 5] == pytest.approx(10.0 ** (1.0 - 1.0 / m_count), rel=1e-12)
    assert rel[7, 5] / rel[8, 5] == pytest.approx(10.0, rel=1e-12)


def test_relative_density_removes_range_dependence():
    rng = np.random.default_rng(5)
    cand_r = rng.uniform(0.5, 80.0, (60, 20))
    density = 3000.0 / cand_r ** 2
    mask = rng.random(cand_r.shape) < 0.9
    rel = relative_density(density, cand_r, mask, 1.15)
    # within one log ring r varies by < 1.15, so 1/r^2 by < 1.15^2 about the ring's mean
    assert np.all(rel[mask] < 1.15 ** 2) and np.all(rel[mask] > 1.15 ** -2)
    np.testing.assert_allclose(rel, brute_relative(density, cand_r, mask, 1.15), rtol=1e-12)
    assert np.ptp(density[mask]) > 1000  # raw rho~ spans orders of magnitude


def test_relative_density_masked_out_and_unusable_entries_get_one():
    rng = np.random.default_rng(6)
    cand_r = rng.uniform(1.0, 50.0, (10, 8))
    density = rng.lognormal(2.0, 1.0, (10, 8))
    mask = rng.random((10, 8)) < 0.7
    density[0, 0] = 0.0  # empty bin
    mask[0, 0] = True
    cand_r[1, 1] = np.nan  # no candidate
    mask[1, 1] = True
    rel = relative_density(density, cand_r, mask, 1.3)
    assert np.all(rel[~mask] == 1.0)
    assert rel[0, 0] == 1.0 and rel[1, 1] == 1.0
    np.testing.assert_allclose(rel, brute_relative(density, cand_r, mask, 1.3), rtol=1e-12)
    # masked-out densities do not influence the others
    density2 = density.copy()
    density2[~mask] *= 1000.0
    np.testing.assert_array_equal(relative_density(density2, cand_r, mask, 1.3), rel)
    # nothing usable -> all ones
    assert np.all(relative_density(density, cand_r, np.zeros_like(mask), 1.3) == 1.0)


@pytest.mark.parametrize('compiled', [True, False])
def test_float32_and_float64_input_give_the_same_grid(compiled):
    """Binning is decided in float64: float32 input and its float64 copy bin alike.

    The cloud puts points within float32 round-off of segment borders (where float32 arctan2
    would move them to the neighbour segment and shift its r_min) and ties in z.
    """
    rng = np.random.default_rng(4)
    m_count = 120
    border = -np.pi + 2 * np.pi * rng.integers(0, m_count, 4000) / m_count
    azimuth = np.concatenate([border + rng.normal(0, 3e-7, border.size),
                              rng.uniform(-np.pi, np.pi, 4000)])
    r = np.concatenate([rng.uniform(0.3, 3.0, border.size), rng.uniform(2, 60, 4000)])
    z = np.round(rng.normal(-1.0, 0.3, r.size), 2)  # 1 cm steps: many tied lowest points
    p32 = np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1).astype(np.float32)
    p64 = p32.astype(np.float64)
    if compiled:
        compiled_ready(build_grid, *p32.T.copy(), m_count, 24)
        compiled_ready(build_grid, *p64.T.copy(), m_count, 24)
    g32 = build_grid(*p32.T.copy(), m_count, 24, compiled=compiled)
    g64 = build_grid(*p64.T.copy(), m_count, 24, compiled=compiled)
    for name in ('point_segment', 'point_bin', 'count', 'candidate_index', 'candidate_r',
                 'candidate_z', 'segment_r_min', 'bin_width', 'density'):
        np.testing.assert_array_equal(getattr(g32, name), getattr(g64, name), err_msg=name)
    assert g32.point_r.dtype == np.float32 and g64.point_r.dtype == np.float64
    np.testing.assert_allclose(g32.point_bin_fraction, g64.point_bin_fraction, atol=1e-6)
    # the cloud does exercise the border: float32 arctan2 puts points in other segments
    theta32 = np.arctan2(p32[:, 1], p32[:, 0])
    seg32 = np.minimum(((theta32 + np.float32(np.pi)) * np.float32(m_count / (2 * np.pi)))
                       .astype(np.int32), m_count - 1)
    assert (seg32 != g64.point_segment).sum() > 0


# --------------------------------------------------------------------------------------------
# the compiled pass == the numpy reference, bit for bit
# --------------------------------------------------------------------------------------------
def _assert_same_grid(a, b):
    for name in a.__dataclass_fields__:
        u, v = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert u.dtype == v.dtype, name
        assert np.array_equal(u, v, equal_nan=True), name


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize('seed,num_segments,num_bins', CASES)
def test_compiled_grid_equals_the_numpy_reference_on_random_clouds(seed, num_segments,
                                                                   num_bins, dtype):
    from conftest import compiled_and_reference
    xyz = make_cloud(seed, num_segments).astype(dtype)
    _assert_same_grid(*compiled_and_reference(build_grid, *xyz.T.copy(), num_segments,
                                              num_bins))


@pytest.mark.parametrize('source', ['sensors/velodyne_vlp16.pcd', 'sensors/hesai_xt32.pcd',
                                    'kitti_sequnknown_spvnas_000000.bin', 'mixed'])
def test_compiled_grid_equals_the_numpy_reference_on_real_scans(source):
    from conftest import DATA, compiled_and_reference
    from scenes import synthetic
    from gp_ground_segmentation.tools.io import read_points_file
    if '.' in source:
        if not (DATA / source).exists():
            pytest.skip(f'{DATA / source} not found')
        arr = read_points_file(DATA / source)
        xyz = np.stack([arr[c] for c in 'xyz'], axis=1).astype(np.float32)  # as drivers give
    else:
        xyz = synthetic.scan_scene(source).points[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1) & (np.abs(xyz).sum(axis=1) > 0)]
    _assert_same_grid(*compiled_and_reference(build_grid, *xyz.T.copy(), 120, 24))


def test_compiled_grid_hands_overflowing_ranges_to_the_reference():
    """x^2 overflows beyond ~1.3e154 m: the compiled pass gives up, the reference uses hypot."""
    from conftest import compiled_and_reference
    xyz = make_cloud(3, 8)
    xyz[5, :2] = [3e200, 4e200]
    with np.errstate(over='ignore'):  # the far bins' areas are inf (as in the segmenter)
        compiled, reference = compiled_and_reference(build_grid, *xyz.T.copy(), 8, 4)
    _assert_same_grid(compiled, reference)
    assert compiled.point_r[5] == pytest.approx(5e200)
