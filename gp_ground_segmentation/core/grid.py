# SPDX-License-Identifier: Apache-2.0
"""Radial grid: M angular segments x N radial bins, ground candidates and the density-like rho~.

Paper section II. Every segment m is cut into N bins spread evenly between *that segment's own*
minimum and maximum radial range ("divided unevenly" across segments: a segment facing a wall
at 6 m gets fine bins, one facing an open road gets coarse ones). The ground candidate of a bin
is its lowest point, kept as (r, z); among points of equal z the first in input order.

Binning decisions (segment, bin, lowest point) are made in float64 whatever the input precision,
so a float32 cloud and the same values as float64 give the same grid, candidates and GP: with
float32 arithmetic, points within round-off of a segment's border change segment, which moves
that segment's r_min and every bin edge of it, and the cold-start theta follows (measured on
the VLP-16 scan: 19 points, 14 candidates). Per-point outputs (r, position in the bin) are kept
in the input's precision. Two implementations give the same grid: a compiled (numba) pass over
the points, and the numpy reference (``np.minimum.at`` / ``np.bincount`` over integer bin
keys), used without numba.

Density-like value rho~ (paper eq. 3): each bin is cut into j vertical slices from its z_min to
its z_max, rho_i = (points in slice i) / (slice area) and rho~ = mean_i rho_i. All slices of a
bin share the bin's horizontal (sector) area A, so the mean has the closed form
rho~ = n_bin / (j * A): a bin with many points stacked above its lowest point (an obstacle on
or beside the ground) gets a high rho~, which is what the paper asks of it ("a higher
density-like value to the points ... with an obstacle in their proximity"). We compute
rho~ = n_bin / A [points per m^2]: the constant 1/j changes no result -- the segmenter uses
rho~ only through ratios (the density-jump test of Algorithm 1, ``relative_density``) -- so
there is no j parameter.

Below-ground reflection noise (the shared SemanticKITTI frame has points down to z = -27 m)
would make such a point the "lowest point" of its bin. The grid keeps the plain lowest point, as
in the paper; the segmenter rejects these candidates afterwards with the GP's leave-one-out
residual (a candidate far *below* the ground predicted from its neighbours is noise), see
``gp.loo_residuals`` and ``SegmenterParams.noise_spike_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .compiled import AVAILABLE, kernel, run


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
    casts and the rho~ arithmetic (~15 numpy calls of 2-30 us each on a 15k-point scan).
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
    out = run(compiled, _grid_compiled, _grid_numpy, *args)
    if not out[0]:  # r overflowed in the compiled pass
        out = _grid_numpy(*args)
    (_, r, seg, bins, fraction, r_min, width, count, candidate_index, cand_r, cand_z,
     density) = out
    shape = (m_count, n_count)
    return RadialGrid(m_count, n_count, r, angle, seg, bins, fraction, r_min, width,
                      count.reshape(shape), candidate_index.reshape(shape),
                      cand_r.reshape(shape), cand_z.reshape(shape), density.reshape(shape))


RING_RATIO = 1.15  # relative_density's range rings: r within this factor


def relative_density(density: np.ndarray, candidate_r: np.ndarray, mask: np.ndarray,
                     ring_ratio: float = RING_RATIO) -> np.ndarray:
    """rho~ divided by its typical value at the same range; 1 = an ordinary bin at that range.

    A spinning LiDAR's point density falls roughly as 1/r^2 to 1/r^3, so raw rho~ mostly encodes
    range: used as is in L = a log(1/g) / rho~, it would give 0.3 m length scales next to the
    sensor and 100 m ones far away. Dividing by the geometric mean of rho~ over the candidates
    (``mask``) in the same logarithmic range ring (r within a factor ``ring_ratio``) keeps what
    the paper wants from rho~ -- bins with points stacked above the candidate (obstacles) stand
    out with rho~ > 1 -- and makes it independent of range and of the sensor's beam count.
    Entries outside ``mask`` or in a ring with no masked candidate get 1.
    """
    out = np.ones_like(density, dtype=np.float64)
    usable = usable_bins(density, candidate_r, mask)
    if not usable.any():
        return out
    out[usable] = np.exp(ring_log_deviation(np.log(candidate_r[usable]),
                                            np.log(density[usable]), np.log(ring_ratio)))
    return out


def usable_bins(density, candidate_r, mask) -> np.ndarray:
    """The bins :func:`relative_density` compares: in ``mask``, with rho~ > 0 and a finite
    range > 0."""
    return mask & (density > 0) & np.isfinite(candidate_r) & (candidate_r > 0)


def ring_log_deviation(log_r: np.ndarray, log_rho: np.ndarray, log_ratio: float) -> np.ndarray:
    """log rho~ minus its mean over the log-range ring of width ``log_ratio`` it falls in
    (:func:`relative_density`'s arithmetic on its usable bins; the segmenter's compiled
    length-factor pass uses it as its numpy twin)."""
    if log_r.size == 0:
        return np.empty(0)
    ring = np.floor(log_r / log_ratio).astype(np.intp)
    ring -= ring.min()
    sums = np.bincount(ring, weights=log_rho)
    counts = np.bincount(ring)
    return log_rho - sums[ring] / counts[ring]
