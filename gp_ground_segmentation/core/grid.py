# SPDX-License-Identifier: Apache-2.0
"""Stage ``grid`` [paper, section II]: valid points, the radial grid, ground candidates, rho~.

Valid points are finite and not exactly (0, 0, 0), the no-return value of organised drivers.
Every segment m of the M angular segments is cut into N bins spread evenly between *that
segment's own* minimum and maximum range (the paper's "divided unevenly" across segments). The
ground candidate of a bin is its lowest point (r, z); among equal z the first in input order.
Binning (segment, bin, lowest point) is decided in float64 whatever the input precision, so a
float32 cloud and its float64 copy give the same grid (points within round-off of a segment
border would otherwise change segment, and with it that segment's bins); per-point outputs
stay in the input's precision.

rho~ as computed is a 2-D point density: the bin's point count over its horizontal sector area
A (points per m^2 of ground). The paper (eqs. 3-4) cuts each bin into j vertical slices from
its z_min to z_max and averages rho_i = (points in slice i) / (slice area); with the bin's
sector as every slice's area that mean is n / (j A), i.e. ours up to the constant 1/j, which
changes no result (rho~ is used only through ratios: Algorithm 1's density jump and eq. 12 after
the ring normalisation of ``length_factors``), so there is no j parameter. If the paper's slice
area is the slice's vertical cross-section instead, its rho~ would differ from ours by the
bin's height spread: that reading is not implemented.

Below-ground reflection noise (points metres under the road) becomes the lowest point of its
bin here, as in the paper; the ``outliers`` stage rejects those candidates afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, kernel


@dataclass
class RadialGrid:
    """Binning of the valid points of one frame and the per-bin ground candidates.

    Arrays of shape (M, N) are indexed [segment, bin]; per-point arrays follow the order of the
    points given to :func:`build_grid`.
    """

    num_segments: int
    num_bins: int
    point_r: np.ndarray  # (P,) radial range sqrt(x^2 + y^2) (m)
    point_angle: np.ndarray  # (P,) azimuth arctan2(y, x) (rad, float64; see _angle)
    point_segment: np.ndarray  # (P,) int segment index
    point_bin: np.ndarray  # (P,) int bin index
    point_bin_fraction: np.ndarray  # (P,) position inside the bin, 0 at its inner edge, 1 outer
    segment_r_min: np.ndarray  # (M,) r of the first bin's inner edge (m)
    bin_width: np.ndarray  # (M,) radial width of this segment's bins (m), > 0
    count: np.ndarray  # (M, N) points per bin
    candidate_index: np.ndarray  # (M, N) index of the bin's lowest point, -1 if empty
    candidate_r: np.ndarray  # (M, N) r of the lowest point (m), NaN if empty
    candidate_z: np.ndarray  # (M, N) z of the lowest point (m), NaN if empty
    density: np.ndarray  # (M, N) rho~ (points / m^2), 0 if empty

    @property
    def has_candidate(self) -> np.ndarray:
        """(M, N) bool: the bin holds at least one point."""
        return self.candidate_index >= 0

    def bin_edges(self) -> np.ndarray:
        """(M, N + 1) radial position of each bin's edges (m), from r_min to r_max."""
        return bin_edges(self.segment_r_min, self.bin_width, self.num_bins)


def valid_points_mask(xyz: np.ndarray) -> np.ndarray:
    """Finite and not exactly (0, 0, 0), the no-return value of organized drivers (Ouster)."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]  # per column: reductions over axis 1 are slow
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    return finite & ~((x == 0) & (y == 0) & (z == 0))


def _valid_columns(xyz: np.ndarray):
    """(valid mask (N,), x, y, z of the valid points as contiguous arrays) of (N, 3) ``xyz``:
    the numpy reference of :func:`_valid_columns_loop`."""
    valid = valid_points_mask(xyz)
    valid_xyz = xyz if valid.all() else xyz[valid]
    return (valid,) + tuple(np.ascontiguousarray(valid_xyz[:, i]) for i in range(3))


def _valid_columns_loop(xyz):
    """:func:`_valid_columns` in one pass over the points (compiled with numba): the same
    tests and values. Every point is copied to the next free slot, which advances only past a
    valid one (no branch: faster than a counting and a copying pass)."""
    n_points = xyz.shape[0]
    valid = np.empty(n_points, dtype=np.bool_)
    x = np.empty(n_points, dtype=xyz.dtype)
    y = np.empty(n_points, dtype=xyz.dtype)
    z = np.empty(n_points, dtype=xyz.dtype)
    k = 0
    for i in range(n_points):
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        ok = (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)
              and not (px == 0 and py == 0 and pz == 0))
        valid[i] = ok
        x[k], y[k], z[k] = px, py, pz
        k += ok
    return valid, x[:k], y[:k], z[:k]


def _cloud_layouts(dtype):
    """The (N, 3) layouts of a frame's points: C and F order (the node's copy when x, y, z are
    not side by side), the x, y, z columns of (N, 4) rows, read-only (the node's decode: views
    on msg.data) with and without intensity."""
    rows, xyz_rows = np.ones((2, 4), dtype), np.ones((2, 3), dtype)
    for view in (rows, xyz_rows):
        view.flags.writeable = False
    xyz = np.ones((3, 2), dtype)
    return [(cloud,) for cloud in (xyz.T.copy(), xyz.T, np.ones((2, 4), dtype)[:, :3],
                                   rows[:, :3], xyz_rows)]


VALID_COLUMNS = Twin('valid points', _valid_columns, kernel(_valid_columns_loop),
                     _cloud_layouts)


def valid_columns(xyz: np.ndarray, compiled: bool = True):
    """(valid mask (N,), x, y, z (P,) of the valid points, contiguous, in ``xyz``'s dtype)."""
    return VALID_COLUMNS.run(compiled, xyz)


def bin_edges(segment_r_min: np.ndarray, bin_width: np.ndarray, num_bins: int) -> np.ndarray:
    """(M, N + 1) radial position of the bin edges of segments starting at ``segment_r_min``
    with bins ``bin_width`` wide (m)."""
    k = np.arange(num_bins + 1)
    return segment_r_min[:, None] + k[None, :] * bin_width[:, None]


def segment_of(x: np.ndarray, y: np.ndarray, num_segments: int) -> np.ndarray:
    """Angular segment index in [0, M) of each point (float64 maths); segment 0 starts at -pi."""
    return _segment_of_angle(_angle(x, y), num_segments)


def _angle(x, y):
    """float64 arctan2(y, x): numpy's (SIMD) arctan2 on every path, compiled or not -- the C
    library's atan2 that numba calls differs from it in the last bit for ~7 % of angles, which
    would move points lying on a segment border."""
    return np.arctan2(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64))


def _segment_of_angle(theta, num_segments):
    """int32 segment index of float64 azimuths ``theta`` in [-pi, pi] (numpy; the compiled grid
    pass does the same per point)."""
    seg = ((theta + np.pi) * (num_segments / (2.0 * np.pi))).astype(np.int32)
    # arctan2 can return exactly +pi, which would land in segment M: clip, never wrap silently.
    return np.minimum(seg, num_segments - 1, out=seg)


def _segment_widths(r_min, r_max, n_count):
    """(r_min, bin width, 1 / width) per segment; empty segments (r_min = inf) get r_min 0."""
    empty_segment = ~np.isfinite(r_min)
    r_min[empty_segment] = 0.0
    r_max[empty_segment] = 0.0
    width = np.maximum((r_max - r_min) / n_count, 1e-3)
    return r_min, width, 1.0 / width


def _grid_numpy(x, y, z, angle, m_count, n_count):
    """The numpy reference of :func:`_grid_pass`: (ok, point r, segment, bin, fraction, r_min,
    width, count, candidate index, r and z, density), the last five flat (M * N).

    Binning in float64 (module docstring); the per-point r and fraction in the input's dtype.
    ``ok`` is always True (the compiled pass gives up on r overflow).
    """
    x64, y64 = x.astype(np.float64, copy=False), y.astype(np.float64, copy=False)
    r64 = np.sqrt(x64 * x64 + y64 * y64)
    if not np.isfinite(r64).all():
        # x*x overflows for finite coordinates beyond ~1.3e154 m: hypot does not square
        r64 = np.hypot(x64, y64)
    seg = _segment_of_angle(angle, m_count)
    r_min = np.full(m_count, np.inf)
    r_max = np.full(m_count, -np.inf)
    np.minimum.at(r_min, seg, r64)
    np.maximum.at(r_max, seg, r64)
    r_min, width, inv_width = _segment_widths(r_min, r_max, n_count)
    position = (r64 - r_min[seg]) * inv_width[seg]
    bins = position.astype(np.int32)  # position >= 0: truncation is floor
    fraction = position  # in place from here: one array less at millions of points
    fraction -= bins
    np.minimum(fraction, 1.0, out=fraction)
    last = bins >= n_count  # only r == r_max (or round-off just below it) lands here
    bins[last] = n_count - 1
    fraction[last] = 1.0
    key = seg * np.int32(n_count) + bins
    size = m_count * n_count
    count = np.bincount(key, minlength=size)
    z_min = np.full(size, np.inf, dtype=z.dtype)
    np.minimum.at(z_min, key, z)
    lowest = np.flatnonzero(z == z_min[key])
    candidate_index = np.full(size, z.size, dtype=np.intp)
    np.minimum.at(candidate_index, key[lowest], lowest)  # ties: the first in input order
    candidate_index[candidate_index == z.size] = -1

    occupied = candidate_index >= 0
    cand_r = np.full(size, np.nan)
    cand_z = np.full(size, np.nan)
    cand_r[occupied] = r64[candidate_index[occupied]]
    cand_z[occupied] = z[candidate_index[occupied]]
    # rho~ = n / A: see the module docstring for the dropped 1/j.
    k = np.arange(n_count)
    inner = r_min[:, None] + k[None, :] * width[:, None]
    outer = inner + width[:, None]
    # (dtheta / 2)(ro^2 - ri^2), factored so absurdly far bins give inf, not inf - inf
    sector_area = (np.pi / m_count) * width[:, None] * (outer + inner)
    density = count / sector_area.ravel()
    # per-point outputs in the input's precision (float32 from drivers: half the traffic later)
    return (True, r64.astype(x.dtype, copy=False), seg, bins,
            fraction.astype(x.dtype, copy=False), r_min, width, count, candidate_index,
            cand_r, cand_z, density)


def _grid_pass(x, y, z, angle, m_count, n_count):
    """:func:`_grid_numpy` in two passes over the points (compiled with numba): the same
    float64 operations in the same order, so the same outputs. It replaces the numpy
    r, segment, ``minimum.at`` / ``bincount`` / ``flatnonzero`` binning, candidate gathers,
    casts and the rho~ arithmetic (~15 numpy calls).
    Returns ``ok`` False (outputs unfinished) when some r = sqrt(x^2 + y^2) overflows: the
    caller then runs the reference, which switches to hypot."""
    p_count = x.size
    r64 = np.empty(p_count)
    seg = np.empty(p_count, dtype=np.int32)
    bins = np.empty(p_count, dtype=np.int32)
    point_r = np.empty_like(x)
    fraction = np.empty_like(x)
    size = m_count * n_count
    count = np.zeros(size, dtype=np.intp)
    candidate_index = np.full(size, -1, dtype=np.intp)
    cand_r = np.full(size, np.nan)
    cand_z = np.full(size, np.nan)
    density = np.empty(size)
    r_min = np.full(m_count, np.inf)
    r_max = np.full(m_count, -np.inf)
    to_segment = m_count / (2.0 * np.pi)
    for i in range(p_count):  # no branch in this loop: it vectorises
        xi, yi = np.float64(x[i]), np.float64(y[i])
        r64[i] = np.sqrt(xi * xi + yi * yi)
        seg[i] = min(int((angle[i] + np.pi) * to_segment), m_count - 1)
    # a scan comes in azimuth order: the range of the current segment is kept in registers and
    # stored when the segment changes (exact: min and max do not round)
    run_s, run_min, run_max = 0, np.inf, -np.inf
    for i in range(p_count):
        s, r = seg[i], r64[i]
        if s != run_s:
            r_min[run_s] = min(r_min[run_s], run_min)
            r_max[run_s] = max(r_max[run_s], run_max)
            run_s, run_min, run_max = s, r_min[s], r_max[s]
        run_min = min(run_min, r)
        run_max = max(run_max, r)
    r_min[run_s] = min(r_min[run_s], run_min)
    r_max[run_s] = max(r_max[run_s], run_max)
    for s in range(m_count):
        if r_max[s] == np.inf:  # x, y are finite: only an overflowing r is not
            return (False, point_r, seg, bins, fraction, r_min, r_max, count,
                    candidate_index, cand_r, cand_z, density)
    r_min, width, inv_width = _segment_widths_compiled(r_min, r_max, n_count)
    for i in range(p_count):
        s = seg[i]
        r = r64[i]
        position = (r - r_min[s]) * inv_width[s]
        # the reference's "last bin, fraction 1" for position >= N without a branch: there
        # position - (N - 1) >= 1 is clipped to 1 like every fraction
        b = min(int(position), n_count - 1)
        f = min(position - b, 1.0)
        bins[i] = b
        fraction[i] = f  # rounded to the input's dtype, as astype does
        point_r[i] = r
        key = s * n_count + b
        count[key] += 1
        c = candidate_index[key]
        if c < 0 or z[i] < z[c]:  # strict: among equal z the first point stays
            candidate_index[key] = i
    sector = np.pi / m_count
    for s in range(m_count):
        for k in range(n_count):
            key = s * n_count + k
            c = candidate_index[key]
            if c >= 0:
                cand_r[key] = r64[c]
                cand_z[key] = z[c]
            inner = r_min[s] + k * width[s]
            outer = inner + width[s]
            density[key] = count[key] / (sector * width[s] * (outer + inner))
    return (True, point_r, seg, bins, fraction, r_min, width, count, candidate_index, cand_r,
            cand_z, density)


_grid_compiled = None
if AVAILABLE:  # the pass calls the compiled _segment_widths
    _segment_widths_compiled = kernel(_segment_widths)
    _grid_compiled = kernel(_grid_pass, error_model='numpy')
GRID_PASS = Twin('grid pass', _grid_numpy, _grid_compiled,
                 lambda dtype: [(*np.ones((3, 2), dtype), np.ones(2), 2, 2)])
STAGES = (Stage('grid', 'paper', None, (VALID_COLUMNS, GRID_PASS)),)


def build_grid(x: np.ndarray, y: np.ndarray, z: np.ndarray, num_segments: int,
               num_bins: int, compiled: bool = True) -> RadialGrid:
    """Bin valid points (P,) x, y, z into the radial grid and pick the lowest point of every bin.

    The coordinates must be finite (only valid points), float32 or float64 arrays of one dtype.
    Per segment the bins span [r_min, r_max] of that segment's points; a segment whose points
    all share one r gets bins 1 mm wide. ``compiled``: the numba pass when numba imports (the
    numpy reference otherwise, or if the compiled pass fails).
    """
    m_count, n_count = int(num_segments), int(num_bins)
    angle = _angle(x, y)
    args = (x, y, z, angle, m_count, n_count)
    out = GRID_PASS.run(compiled, *args)
    if not out[0]:  # r overflowed in the compiled pass
        out = _grid_numpy(*args)
    (_, r, seg, bins, fraction, r_min, width, count, candidate_index, cand_r, cand_z,
     density) = out
    shape = (m_count, n_count)
    return RadialGrid(m_count, n_count, r, angle, seg, bins, fraction, r_min, width,
                      count.reshape(shape), candidate_index.reshape(shape),
                      cand_r.reshape(shape), cand_z.reshape(shape), density.reshape(shape))
