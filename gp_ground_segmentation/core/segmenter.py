# SPDX-License-Identifier: Apache-2.0
"""GroundSegmenter: radial grid -> line-segments -> whole-frame GP -> per-point labels.

Pipeline of one frame (stage names are the keys of ``SegmentationResult.timings_ms``); [paper]
marks the paper's steps, [ours] our additions (``additions.py``, each with a ``use_*`` switch):

``grid``     [paper] valid points binned into M x N, lowest point per bin = ground candidate,
             rho~ (grid.py).
``lines``    [paper] Algorithm 1 over each segment's candidates: line-segments, critical
             points, slopes (lines.py). Candidates on lines steeper than zeta_b do not train
             the GP ("large sloped line-segments relate to non-ground structures").
             [ours] nor do candidates on elevated plateaus (``use_elevated_plateaus``; the
             test starts from the ground under the sensor, ``plateau_from_sensor_ground``);
             one-point lines take the slope of the chord from the previous candidate
             (``use_chord_slope_for_single_points``), so walls are steep, not flat.
``gp_fit``   [paper] length scales from slope and rho~, theta learned on the whole-frame
             marginal likelihood (eq. 14; warm-started, capped, and after the first frame
             only on every ``optimizer_interval_frames``-th frame: ours).
             [ours] the ground under the vehicle as a shared training point at r = 0
             (``use_anchor``), also the GP prior mean (``prior_mean_at_anchor``);
             leave-one-out rejection of outlier candidates before and after learning
             (``use_outlier_rejection``).
``predict``  [paper] GP posterior mean (and std) of the ground height, here at every bin edge
             (N + 1 per segment: a dense N x n kernel against every raw point would cost 100x
             more).
``label``    ground height of each point by linear interpolation along r between the bin
             edges of its segment; ground when z - z_hat <= threshold ([ours] widened by
             the ground's rise across the segment where it slopes across the beams,
             ``use_cross_slope_threshold``).
``structure`` (``use_vertical_structure_test``) ground points with a column of returns right
             above them are the feet of walls, fences, cars, trunks and bushes: obstacle
             (``structure.vertical_structure_mask``).

The grid is centred at the origin and z is taken as up: a cloud not in the sensor's own frame
is first moved into the levelled sensor frame with the ``sensor_*`` pose parameters
(sensor_frame.py; no copy when they are all 0). Labels and validity are per input point;
``ground_height``, ``height_above_ground`` and ``ground_surface`` are in the input's frame;
``details`` (grid, lines, GP) are in the levelled frame.

Choices where the paper is vague, each a parameter (see params.py):

* Outlier candidates. The lowest point of a bin is not always ground: below-ground reflection
  noise (points metres under the road) and the tops of obstacles whose ground is occluded
  (a car roof seen over its bonnet) both become candidates. A candidate whose leave-one-out
  GP residual is above ``outlier_residual_m`` (and above ``outlier_std_factor`` leave-one-out
  predictive stds, so that sparse candidates, which the GP predicts loosely, are not rejected
  for that alone) or below ``-noise_spike_m`` is given a large noise variance (it stops pulling
  the fit) and the GP is solved again. There are two passes,
  one before and one after theta is learned, so that an outlier pair masking each other in the
  first pass is caught in the second.
* "Close to the ground". A point is ground when z - z_hat(r) <= ground_threshold_m +
  ground_threshold_std_factor * std(r), capped at max_threshold_m: the threshold widens where
  the GP is unsure (far, sparse, between lines) but never becomes a height cut-off. The test is
  one-sided, as in the paper: anything below the predicted ground is ground (below-ground noise
  included -- it is not an obstacle). There is no height or range truncation anywhere.
* The ground under the vehicle. All segments meet at r = 0, where the ground is the one the
  vehicle stands on (also on a slope). Every segment with a candidate gets one shared
  pseudo-candidate at r = 0 with the frame's estimate of that height
  (``additions.ground_under_sensor``) and noise std ``anchor_std_m``. It ties the segments
  together, so that a car parked right beside the sensor -- whose roof is the first and only
  nearby candidate of its segments -- shows up as a step up from the vehicle's own ground and
  is rejected, instead of becoming the ground. Segments without a training point predict that
  height (the GP's prior mean without the anchor) with the prior std sigma_f.
"""

from __future__ import annotations

import contextlib
import copy
import time
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np
from threadpoolctl import ThreadpoolController

from . import additions
from . import compiled, gp_compiled
from .gp import (FrameGP, GPSolution, GroundAnchor, factors_from_logs, length_scale_factors,
                 resolve_backend, slope_terms)
from .grid import (RING_RATIO, RadialGrid, build_grid, relative_density, ring_log_deviation,
                   usable_bins)
from .lines import LineSegments, extract_lines
from .params import SegmenterParams
from .sensor_frame import ground_height_in_cloud_frame, to_levelled_frame
from .structure import structure_feet, vertical_structure_mask
from .surface import GroundSurface, ground_offsets

_OUTLIER_NOISE_VAR = 1e4  # m^2: a rejected candidate's noise variance (std 100 m)
_blas = None  # threadpoolctl controller, made on first use (after scipy has loaded its BLAS)
# warm_up() waits this long (s) for the background compilations: loading them from numba's
# cache takes ~0.1 s; a first compilation (~16-20 s on 2 cores) goes on while frames use numpy
_BACKGROUND_WAIT_S = 0.5
# The GP step loads from numba's cache in ~0.2 s (0.4 s on a loaded machine) and compiles in
# 1.5-3 s: when it took longer than this (s), the cache was empty, the background stages are
# compiling too, and waiting _BACKGROUND_WAIT_S for them would only delay the first frame
_GP_CACHE_LOAD_MAX_S = 1.0


def _single_threaded_blas():
    """Limit BLAS to one thread for one frame.

    The GP factorises many tiny (n <= N + 1) matrices; OpenBLAS threads only spin on them.
    Measured on the 124k-point KITTI frame: the same wall time, half the CPU time (31 vs 62 ms
    per frame), which leaves the other core to the ROS executor (benchmarks/RESULTS.md).
    Only the numpy GP needs it: the compiled one calls no BLAS (``segment`` skips the ~10 us
    of setting and restoring the limit then). A compiled frame can still run numpy's GP
    without the limit, with the same numbers: when its kernel fails half-way, and when the
    compiled Cholesky finds a matrix not positive definite and that solve falls back to numpy
    (``FrameGP._solve_compiled`` returns None; not seen on the shared scans). That costs CPU
    time on the other core for that frame only.
    """
    global _blas
    if _blas is None:
        _blas = ThreadpoolController()
    return _blas.limit(limits=1, user_api='blas')


class Hyperparameters(NamedTuple):
    """GP hyperparameters theta shared by all segments of a frame."""

    sigma_f: float  # signal std (m)
    gain: float  # a in L_i = a * d_i (m per unit d)
    sigma_n: float  # noise std (m)


@dataclass
class SegmentationDetails:
    """Intermediate arrays of one frame, for plots and debugging (``segment(details=True)``).

    Per-point arrays are over the *valid* points, in input order; ``valid_index`` maps them
    back to input rows. (M, N) arrays are indexed [segment, bin].
    """

    valid_index: np.ndarray  # (P,) input row of each valid point
    grid: RadialGrid
    lines: LineSegments
    training: np.ndarray  # (M, N) bool: candidate trained the GP
    outliers: np.ndarray  # (M, N) bool: candidate rejected as outlier by the robust pass
    length_scale: np.ndarray  # (M, N) L_i = a d_i of every candidate (m), NaN if none
    prediction_r: np.ndarray  # (M, N + 1) r where the GP was evaluated: the bin edges (m)
    ground_mean: np.ndarray  # (M, N + 1) posterior mean ground height there (m)
    ground_std: np.ndarray  # (M, N + 1) posterior std there (m)
    threshold: np.ndarray  # (P,) ground threshold applied to each valid point (m)
    gp: Optional[FrameGP] = None  # the frame's GP batch (rows = gp.segments), for analysis
    gp_solution: Optional[GPSolution] = None  # its final factorisation
    length_factor_at_edges: Optional[np.ndarray] = None  # (S, N + 1) d used at the bin edges
    structure_feet: Optional[np.ndarray] = None  # (P,) bool: passed the height test, obstacle
    # as the foot of a vertical structure (None when use_vertical_structure_test is off)


@dataclass
class SegmentationResult:
    """Output of ``GroundSegmenter.segment`` for one frame of N points."""

    ground_mask: np.ndarray  # bool (N,): valid and ground
    valid_mask: np.ndarray  # bool (N,): finite and not exactly (0, 0, 0)
    ground_height: np.ndarray  # float64 (N,): predicted ground z below the point; NaN if invalid
    hyperparameters: Hyperparameters
    timings_ms: dict = field(default_factory=dict)  # stage -> milliseconds, plus 'total'
    stats: dict = field(default_factory=dict)  # counters: candidates, cholesky fallbacks, ...
    details: Optional[SegmentationDetails] = None
    # The GP ground surface of the frame (surface.py); its extras are computed on first read.
    ground_surface: Optional[GroundSurface] = None
    # z of the points as given to segment() (a view, not a copy), for height_above_ground
    point_z: Optional[np.ndarray] = field(default=None, repr=False)

    @property
    def height_above_ground(self) -> np.ndarray:
        """float64 (N,): z - ground_height of every point (m); NaN for invalid points."""
        if self.point_z is None:
            raise ValueError('height_above_ground: the result carries no point z')
        return self.point_z.astype(np.float64) - self.ground_height

    @property
    def obstacle_mask(self) -> np.ndarray:
        """Valid points that are not ground."""
        return self.valid_mask & ~self.ground_mask

    @property
    def num_invalid(self) -> int:
        """NaN/Inf points and the (0, 0, 0) no-return value: neither ground nor obstacle."""
        return int(self.valid_mask.size - np.count_nonzero(self.valid_mask))


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
    tests (finite, not (0, 0, 0)) and the same values, without the reference's six masks.
    Every point is copied to the next free slot, which advances only past a valid one (no
    branch; ~25 % less time than a counting pass and a copying pass); the columns are the
    first slots of arrays of all the points' length."""
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


_valid_columns_compiled = compiled.kernel(_valid_columns_loop)


class _GroundModel(NamedTuple):
    """What the ``gp_fit`` stage hands to ``predict``."""

    gp: FrameGP
    solution: Optional[GPSolution]  # None when no segment has a training point
    theta: np.ndarray  # (3,) sigma_f, a, sigma_n used for the frame
    training: np.ndarray  # (M, N) candidates that trained the GP
    outliers: np.ndarray  # (M, N) candidates rejected by the robust passes
    length_factor: np.ndarray  # (M, N) d_i
    default_height: float  # ground height of segments without a training point (m)


def _ground_at_bin_edges(model: _GroundModel, edges: np.ndarray, need_std: bool):
    """GP posterior mean (and std) at the (M, N + 1) bin ``edges`` (stage ``predict``).

    Segments outside the GP batch keep ``model.default_height`` and the prior std sigma_f.
    Returns (mean, std, d at the edges of the GP's segments, k* there) with (M, N + 1) mean
    and std (None unless ``need_std``); k* (``FrameGP.predict``'s kernel) is None unless the
    compiled backend ran.
    """
    mean = np.full(edges.shape, model.default_height)
    std = np.full(edges.shape, model.theta[0]) if need_std else None  # None: not asked for
    d_star = k_star = None
    if model.solution is not None:
        rows = model.gp.segments
        d_star = compiled.run(model.gp.backend == 'numba', _fill_rows_to_edges_compiled,
                              _fill_rows_to_edges, model.length_factor, model.training, rows)
        mean_b, std_b, k_star = model.gp.predict(model.solution, edges[rows], d_star,
                                                 with_std=need_std, return_kernel=True)
        mean[rows] = mean_b
        if need_std:
            std[rows] = std_b
    return mean, std, d_star, k_star


def _ground_surface(model: _GroundModel, grid: RadialGrid, edges, mean, std, z, ground, z_hat,
                    k_star, pose, compiled_surface: bool) -> GroundSurface:
    """The frame's GroundSurface; ``std`` None: its z_std is computed when first read.
    ``z``, ``ground`` and ``z_hat`` are the valid points' heights, labels and ground heights.

    The deferred computations keep the model, the edges, those arrays and the points' grid
    cells alive, not the rest of the per-point grid.
    """
    point_segment, point_bin = grid.point_segment, grid.point_bin  # over the valid points
    m_count, n_bins = grid.num_segments, grid.num_bins

    def compute_std():
        if k_star is None:  # numpy backend: the prediction again, with the std
            with _single_threaded_blas(), np.errstate(over='ignore'):
                return _ground_at_bin_edges(model, edges, need_std=True)[1]
        std = np.full(edges.shape, model.theta[0])  # from the predict stage's k*: cheaper
        std[model.gp.segments] = model.gp.std_from_kernel(model.solution, k_star)
        return std

    def compute_offset():
        return ground_offsets(z, z_hat, ground, point_segment, point_bin, m_count, n_bins,
                              model.theta[2], compiled=compiled_surface)

    return GroundSurface(grid.segment_r_min, grid.bin_width, grid.count.sum(axis=1) > 0, mean,
                         model.training.any(axis=1), std,
                         compute_std if std is None else None, compute_offset, pose,
                         compiled=compiled_surface)


def _inner_edge_index(point_segment, point_bin, row_length) -> np.ndarray:
    """Flat (M, N + 1) index of every point's inner bin edge (the outer one is the next)."""
    return point_segment * np.int32(row_length) + point_bin


def _interpolate_at_points(values: np.ndarray, grid: RadialGrid) -> np.ndarray:
    """(M, N + 1) values at bin edges -> every point, linearly along r within its bin.

    Flat gathers in the points' precision: at 2 M points every float64 temporary is 16 MB.
    """
    frac = grid.point_bin_fraction
    inner = _inner_edge_index(grid.point_segment, grid.point_bin, grid.num_bins + 1)
    return _interpolate_flat(values.ravel().astype(frac.dtype), inner, frac)


def _interpolate_flat(flat: np.ndarray, inner: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """``flat[inner]`` moved ``frac`` of the way to ``flat[inner + 1]``, in ``flat``'s dtype."""
    out = flat[inner]
    step = flat[inner + 1]
    step -= out
    step *= frac
    out += step
    return out


def _label_points(mean: np.ndarray, threshold, grid: RadialGrid, z: np.ndarray,
                  use_compiled: bool):
    """(z_hat, ground) of every point: the (M, N + 1) ``mean`` and ``threshold`` (or a scalar
    threshold) at the bin edges interpolated to the points (:func:`_interpolate_at_points`)
    and the height test z - z_hat <= threshold, in the points' precision."""
    if np.ndim(threshold) == 0:
        z_hat = _interpolate_at_points(mean, grid)
        return z_hat, z - z_hat <= threshold
    frac = grid.point_bin_fraction
    args = (mean.ravel().astype(frac.dtype), threshold.ravel().astype(frac.dtype),
            grid.point_segment, grid.point_bin, frac, z, grid.num_bins + 1)
    return compiled.run(use_compiled, _label_compiled, _label_numpy, *args)


def _label_numpy(mean, threshold, point_segment, point_bin, frac, z, row_length):
    """The numpy reference of :func:`_label_loop`: flat (M * (N + 1)) ``mean`` and
    ``threshold`` at the bin edges, each point's segment, bin and position in the bin ->
    (z_hat, ground)."""
    inner = _inner_edge_index(point_segment, point_bin, row_length)
    z_hat = _interpolate_flat(mean, inner, frac)
    return z_hat, z - z_hat <= _interpolate_flat(threshold, inner, frac)


def _label_loop(mean, threshold, point_segment, point_bin, frac, z, row_length):
    """:func:`_label_numpy` in one pass over the points (compiled with numba): the same
    operations in the same precision for each point, without the reference's six gathers and
    per-point temporaries."""
    z_hat = np.empty(z.size, dtype=frac.dtype)
    ground = np.empty(z.size, dtype=np.bool_)
    for i in range(z.size):
        inner = point_segment[i] * row_length + point_bin[i]
        f = frac[i]
        low = mean[inner]
        height = low + (mean[inner + 1] - low) * f
        low = threshold[inner]
        z_hat[i] = height
        ground[i] = z[i] - height <= low + (threshold[inner + 1] - low) * f
    return z_hat, ground


_label_compiled = compiled.kernel(_label_loop)


def _fill_along_rows(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill unknown entries of each row with the nearest known entry to their left (else right)."""
    n = values.shape[1]
    idx = np.where(known, np.arange(n), -1)
    left = np.maximum.accumulate(idx, axis=1)
    idx_r = np.where(known, np.arange(n), n)
    right = np.minimum.accumulate(idx_r[:, ::-1], axis=1)[:, ::-1]
    pick = np.where(left >= 0, left, right)
    pick = np.clip(pick, 0, n - 1)
    return np.take_along_axis(values, pick, axis=1)


def _fill_rows_to_edges(values: np.ndarray, known: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows), N + 1): ``_fill_along_rows(values, known)`` of ``rows``, its last column
    repeated for the outer edge; the numpy reference of :func:`_fill_rows_to_edges_loop`."""
    filled = _fill_along_rows(values, known)
    return np.concatenate([filled, filled[:, -1:]], axis=1)[rows]


def _fill_rows_to_edges_loop(values, known, rows):
    """:func:`_fill_rows_to_edges` in one pass (compiled with numba): only the rows asked for,
    without the reference's two accumulations, three where and the gather (the same values).
    """
    n = values.shape[1]
    out = np.empty((rows.size, n + 1), dtype=values.dtype)
    for s in range(rows.size):
        m = rows[s]
        pick = n - 1  # a row without a known entry takes its last one
        for j in range(n):
            if known[m, j]:
                pick = j  # the first known entry fills the entries before it
                break
        for j in range(n):
            if known[m, j]:
                pick = j
            out[s, j] = values[m, pick]
        out[s, n] = out[s, n - 1]
    return out


_fill_rows_to_edges_compiled = compiled.kernel(_fill_rows_to_edges_loop)


def _new_outliers_loop(alpha, a_inv, valid, is_anchor, segments, bins, outliers, above_m,
                       below_m, worst_above_only, std_factor):
    """(M, N) candidates not yet in ``outliers`` whose leave-one-out residual is an outlier, in
    one pass over the GP's slots (compiled with numba). Replaces, with the same values,
    ``~outliers & additions.outlier_candidates(gp.to_grid(gp.loo_residuals(sol), nan), ...)``
    (the reference in ``_reject_outliers``): residual alpha_i / [A^-1]_ii of each grid
    candidate's slot, the same comparisons (the limit above is also ``std_factor`` times the
    leave-one-out std sqrt(1 / [A^-1]_ii)), and with ``worst_above_only`` the row's highest
    residual."""
    new = np.zeros(outliers.shape, dtype=np.bool_)
    n_slots = valid.shape[1]
    for s in range(segments.size):
        m = segments[s]
        top = -np.inf  # the segment's highest residual (NaN residuals do not count)
        if worst_above_only:
            for i in range(n_slots):
                if valid[s, i] and not is_anchor[s, i]:
                    loo = alpha[s, i] / a_inv[s, i, i]
                    if loo > top:
                        top = loo
        for i in range(n_slots):
            if not valid[s, i] or is_anchor[s, i]:
                continue
            loo = alpha[s, i] / a_inv[s, i, i]
            limit = max(above_m, std_factor * np.sqrt(1.0 / a_inv[s, i, i]))
            above = loo > limit
            if worst_above_only and above:
                above = loo >= top
            b = bins[s, i]
            new[m, b] = (above or loo < -below_m) and not outliers[m, b]
    return new


# numpy's error model: a zero [A^-1]_ii gives an infinite residual as in the reference, not
# a ZeroDivisionError out of segment()
_new_outliers_compiled = compiled.kernel(_new_outliers_loop, error_model='numpy')


def _not_wide_terrain_loop(new, alpha, a_inv, valid, is_anchor, segments, bins, r, z,
                           tolerance_m, max_slope):
    """``new`` (M, N) without the candidates that ``additions.wide_terrain_candidates`` calls
    terrain among those with a leave-one-out residual above 0 (compiled with numba): the
    grids of residual, z and r that the reference (in ``_reject_outliers``) makes with
    ``FrameGP.to_grid`` (NaN where no grid candidate trains), filled from the GP's slots in
    one pass, and the compiled wide-terrain pass on them; the same values, so the same mask.
    """
    m_count, n_bins = new.shape
    above = np.zeros((m_count, n_bins), dtype=np.bool_)
    z_grid = np.full((m_count, n_bins), np.nan)
    r_grid = np.full((m_count, n_bins), np.nan)
    for s in range(segments.size):
        m = segments[s]
        for i in range(valid.shape[1]):
            if valid[s, i] and not is_anchor[s, i]:
                b = bins[s, i]
                z_grid[m, b] = z[s, i]
                r_grid[m, b] = r[s, i]
                above[m, b] = new[m, b] and alpha[s, i] / a_inv[s, i, i] > 0
    wide = additions._wide_terrain_compiled(above, z_grid, r_grid, tolerance_m, max_slope)
    out = np.empty((m_count, n_bins), dtype=np.bool_)
    for m in range(m_count):
        for b in range(n_bins):
            out[m, b] = new[m, b] and not wide[m, b]
    return out


_not_wide_terrain_compiled = None
if compiled.AVAILABLE:  # the pass calls the compiled wide-terrain loop
    _not_wide_terrain_compiled = compiled.kernel(_not_wide_terrain_loop, error_model='numpy')


def _length_factors_numpy(slope, density, candidate_r, training, slope_floor, slope_ceiling,
                          density_in_flat_branch, d_min, d_max, passes):
    """d_i of every candidate (stage ``gp_fit``): ``grid.relative_density``, then
    ``gp.length_scale_factors``, then ``additions.smooth_length_factors`` (the numpy reference
    of :func:`_length_factors_fused`)."""
    d = length_scale_factors(slope, relative_density(density, candidate_r, training),
                             slope_floor=slope_floor, slope_ceiling=slope_ceiling,
                             density_in_flat_branch=density_in_flat_branch, d_min=d_min,
                             d_max=d_max)
    return additions.smooth_length_factors(d, training, passes, compiled=False)


def _length_factors_fused(slope, density, candidate_r, training, slope_floor, slope_ceiling,
                          density_in_flat_branch, d_min, d_max, passes):
    """:func:`_length_factors_numpy` with its arithmetic in compiled passes and only its
    logarithms and exponentials left to numpy, on the arrays the reference takes them of
    (numpy's SIMD log and exp differ from numba's in the last bit; an element's value does not
    depend on the array around it): ~10 numpy calls instead of ~35. While a pass is not
    compiled, its numpy twin runs (the same values)."""
    training = np.ascontiguousarray(training, dtype=bool)
    # as relative_density and length_scale_factors compute these constants
    log_ratio, log_flat = float(np.log(RING_RATIO)), float(np.log(1.0 / slope_floor))
    usable, r_usable, rho_usable, inverse_slope, flat = compiled.run(
        True, _usable_bins_compiled, _usable_bins_reference, density, candidate_r, training,
        slope, float(slope_floor), float(slope_ceiling))
    # rho~ over its ring's geometric mean, of the usable bins (relative_density)
    log_rho = np.log(rho_usable)
    density_rel = np.exp(compiled.run(True, _ring_deviation_compiled, ring_log_deviation,
                                      np.log(r_usable), log_rho, log_ratio))
    d, smoothing_input = compiled.run(
        True, _raw_length_factors_compiled, _raw_length_factors_reference, np.log(inverse_slope),
        density_rel, usable, flat, training, bool(density_in_flat_branch), log_flat,
        float(d_min), float(d_max))
    if passes <= 0:
        return d
    log_d = compiled.run(True, _smooth_compiled, additions._smooth_numpy,
                         np.log(smoothing_input), training, int(passes))
    return np.where(training, np.exp(log_d), d)


def _usable_bins_loop(density, candidate_r, training, slope, slope_floor, slope_ceiling):
    """The bins ``relative_density`` uses and, of every bin, the slope part of
    ``length_scale_factors`` (compiled with numba): (usable (M, N), their r and rho~ in row
    order (as a boolean index gathers them), 1 / g, whether the slope is below the floor)."""
    m_count, n_count = density.shape
    usable = np.empty((m_count, n_count), dtype=np.bool_)
    r_usable = np.empty(m_count * n_count)
    rho_usable = np.empty(m_count * n_count)
    inverse_slope = np.empty((m_count, n_count))
    flat = np.empty((m_count, n_count), dtype=np.bool_)
    count = 0
    for m in range(m_count):
        for k in range(n_count):
            r = candidate_r[m, k]
            ok = training[m, k] and density[m, k] > 0 and np.isfinite(r) and r > 0
            usable[m, k] = ok
            if ok:
                r_usable[count] = r
                rho_usable[count] = density[m, k]
                count += 1
            g = slope[m, k]
            raw = 0.0 if np.isnan(g) else np.abs(g)  # no slope = flat; +inf = steep
            flat[m, k] = raw < slope_floor
            inverse_slope[m, k] = 1.0 / min(max(raw, slope_floor), slope_ceiling)
    return usable, r_usable[:count], rho_usable[:count], inverse_slope, flat


def _usable_bins_reference(density, candidate_r, training, slope, slope_floor, slope_ceiling):
    """numpy twin of :func:`_usable_bins_loop` (run only while the pass compiles)."""
    usable = usable_bins(density, candidate_r, training)
    inverse_slope, flat = slope_terms(slope, slope_floor, slope_ceiling)
    return usable, candidate_r[usable], density[usable], inverse_slope, flat


def _ring_deviation_loop(log_r, log_rho, log_ratio):
    """``grid.ring_log_deviation`` (compiled with numba): log rho~ minus the mean of its range
    ring, the ring sums accumulated in the order np.bincount sums them."""
    count = log_r.size
    deviation = np.empty(count)
    if count == 0:
        return deviation
    ring = np.empty(count, dtype=np.intp)
    ring_min = 0
    for i in range(count):
        ring[i] = np.intp(np.floor(log_r[i] / log_ratio))
        if i == 0 or ring[i] < ring_min:
            ring_min = ring[i]
    ring_max = 0
    for i in range(count):
        ring[i] -= ring_min
        ring_max = max(ring_max, ring[i])
    sums = np.zeros(ring_max + 1)
    counts = np.zeros(ring_max + 1, dtype=np.intp)
    for i in range(count):
        sums[ring[i]] += log_rho[i]
        counts[ring[i]] += 1
    for i in range(count):
        deviation[i] = log_rho[i] - sums[ring[i]] / np.float64(counts[ring[i]])
    return deviation


def _raw_length_factors_loop(log_inverse_slope, density_rel, usable, flat, training,
                             density_in_flat_branch, log_flat, d_min, d_max):
    """The rest of ``length_scale_factors`` (compiled with numba), given log(1 / g) of every
    bin and the relative rho~ of the ``usable`` ones (1 elsewhere): (d, and d where
    ``training`` else 1, whose log the smoothing takes)."""
    m_count, n_count = flat.shape
    d = np.empty((m_count, n_count))
    smoothing_input = np.empty((m_count, n_count))
    i = 0
    for m in range(m_count):
        for k in range(n_count):
            rho = 1.0
            if usable[m, k]:
                rho = density_rel[i]
                i += 1
            value = log_inverse_slope[m, k] / (rho if rho > 0 else 1.0)
            if not density_in_flat_branch and flat[m, k]:
                value = log_flat
            if value < d_min:  # np.maximum / np.minimum: NaN stays NaN
                value = d_min
            if value > d_max:
                value = d_max
            d[m, k] = value
            smoothing_input[m, k] = value if training[m, k] else 1.0
    return d, smoothing_input


def _raw_length_factors_reference(log_inverse_slope, density_rel, usable, flat, training,
                                  density_in_flat_branch, log_flat, d_min, d_max):
    """numpy twin of :func:`_raw_length_factors_loop` (run only while the pass compiles)."""
    rho = np.ones(flat.shape)
    rho[usable] = density_rel
    d = factors_from_logs(log_inverse_slope, rho, flat, flat_value=log_flat,
                          density_in_flat_branch=density_in_flat_branch, d_min=d_min,
                          d_max=d_max)
    return d, np.where(training, d, 1.0)


_usable_bins_compiled = compiled.kernel(_usable_bins_loop)
_ring_deviation_compiled = compiled.kernel(_ring_deviation_loop)
_raw_length_factors_compiled = compiled.kernel(_raw_length_factors_loop)
_smooth_compiled = additions._smooth_compiled


def _replace_slope(lines: LineSegments, slope: np.ndarray) -> LineSegments:
    """``dataclasses.replace(lines, slope=slope)`` (a new object sharing the other fields)
    without its field-by-field ``__init__`` (~4 us)."""
    out = copy.copy(lines)
    out.slope = slope
    return out


def _not_steep(candidate_index, slope, max_slope):
    """(candidates not on a line steeper than ``max_slope`` (M, N), the number of candidates,
    the number on steep lines): ``additions.steep_line_candidates`` over the grid's
    candidates; the numpy reference of :func:`_not_steep_loop`."""
    has = candidate_index >= 0
    steep = additions.steep_line_candidates(slope, max_slope)
    steep &= has
    # count_nonzero: a fifth of bool.sum()'s cost at this size
    return has & ~steep, np.count_nonzero(has), np.count_nonzero(steep)


def _not_steep_loop(candidate_index, slope, max_slope):
    """:func:`_not_steep` in one pass (compiled with numba): the same comparisons (a NaN
    slope is not steep)."""
    m_count, n_count = slope.shape
    training = np.empty((m_count, n_count), dtype=np.bool_)
    candidates = 0
    steep_count = 0
    for m in range(m_count):
        for k in range(n_count):
            has = candidate_index[m, k] >= 0
            steep = has and slope[m, k] > max_slope
            training[m, k] = has and not steep
            candidates += has
            steep_count += steep
    return training, candidates, steep_count


_not_steep_compiled = compiled.kernel(_not_steep_loop)


def _anchor_rows(candidate_index, d, training):
    """(segments with a candidate (M,), each one's first training candidate's d, the last d
    of a row without one): the anchor's rows and length factors; the numpy reference of
    :func:`_anchor_rows_loop`."""
    return (candidate_index >= 0).any(axis=1), _first_known_along_rows(d, training)


def _anchor_rows_loop(candidate_index, d, training):
    """:func:`_anchor_rows` in one pass over the rows (compiled with numba): the same values
    without its ~8 numpy calls."""
    m_count, n_count = d.shape
    segments = np.zeros(m_count, dtype=np.bool_)
    length_factor = np.empty(m_count, dtype=d.dtype)
    for m in range(m_count):
        for k in range(n_count):
            if candidate_index[m, k] >= 0:
                segments[m] = True
                break
        pick = n_count - 1
        for k in range(n_count):
            if training[m, k]:
                pick = k
                break
        length_factor[m] = d[m, pick]
    return segments, length_factor


_anchor_rows_compiled = compiled.kernel(_anchor_rows_loop)


def _first_known_along_rows(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Column 0 of ``_fill_along_rows(values, known)`` without filling the rows: each row's
    first known entry, the last entry in a row without one."""
    first = np.where(known.any(axis=1), known.argmax(axis=1), values.shape[1] - 1)
    return values[np.arange(values.shape[0]), first]


class GroundSegmenter:
    """Stateful segmenter: theta is warm-started from one frame to the next.

    >>> seg = GroundSegmenter(SegmenterParams())
    >>> result = seg.segment(points)          # (N, >=3) float array
    >>> points[result.ground_mask]            # ground; result.obstacle_mask for the rest
    """

    def __init__(self, params: SegmenterParams | None = None,
                 hyperparameters: Hyperparameters | None = None, backend: str = 'auto'):
        """``backend`` of the GP factorisation: 'numba', 'numpy' or 'auto' (numba if it
        imports). If the compiled kernel fails at run time this segmenter uses numpy from then
        on (``backend`` tells which one is in use)."""
        if params is None:
            params = SegmenterParams()
        elif not isinstance(params, SegmenterParams):
            raise TypeError(f'params must be a SegmenterParams, got {type(params).__name__}; '
                            'for a dict of values use SegmenterParams(**values)')
        self._params = params.validate()
        self._backend = resolve_backend(backend)
        if hyperparameters is None:
            p = self._params
            hyperparameters = Hyperparameters(p.sigma_f_init_m, p.length_scale_gain_init,
                                              p.sigma_n_init_m)
        self._theta = self._clip_theta(hyperparameters)
        # frames segmented since theta last learned; None until it has learned once (then the
        # next frame is a cold start with optimizer_first_frame_evaluations)
        self._frames_since_learning: int | None = None

    @property
    def params(self) -> SegmenterParams:
        return self._params

    @property
    def backend(self) -> str:
        """GP factorisation in use: 'numba' or 'numpy'."""
        return self._backend

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the GP step now, not inside the first frame, and
        have the stages with a bit-identical numpy twin (valid points, grid pass, line growing,
        plateau state machine, training mask, length factors, the anchor's rows, GP batch
        padding, outlier pass with its wide-terrain rule, the slots' noise, length factors at
        the bin edges, cross-segment rise, label pass, structure selection with its cells and
        look-ups, surface offsets and rows) compiled in the background (core/compiled.py; up to
        _BACKGROUND_WAIT_S is waited for them, enough to load them from the cache, unless the
        GP step took longer than _GP_CACHE_LOAD_MAX_S: then the cache was empty and they are
        compiling, which frames need not wait for). See gp_compiled.py for where the cache lives.

        The GP's posterior std at the bin edges is compiled now only when the labels use it
        (``ground_threshold_std_factor`` > 0); otherwise only the ground surface's z_std and
        ``segment(details=True)`` read it, and it is the first job of the background compiler
        (0.26-0.46 s less warm_up on a new install, 0.2-0.4 s less to the first labels; a read
        in the ~0.3 s before it is ready waits for it).

        On failure this segmenter switches to numpy and the error is raised for the caller to
        report; segmenting still works.
        """
        if self._backend == 'numba':
            start = time.perf_counter()
            labels_use_std = self._params.ground_threshold_std_factor > 0
            try:
                gp_compiled.warm_up(std_now=labels_use_std)
            except Exception:
                self._backend = 'numpy'
                raise
            cache_was_filled = time.perf_counter() - start < _GP_CACHE_LOAD_MAX_S
            # Queued in the order a frame needs them, for float32 input (what the node decodes
            # from float32 fields) first, so that frames leave the numpy path stage by stage
            # on a new install; then the float64 signatures; the surface's offsets last (only
            # the ground_surface output reads them). The GP's std, when the labels do not use
            # it, went first (gp_compiled.warm_up): it is not bit for bit its numpy twin, so a
            # z_std read before it is compiled waits for it.
            grids = {}
            for dtype in (np.float32, np.float64):  # both input precisions of these passes
                xyz = np.ones((3, 2), dtype=dtype)
                rows, xyz_rows = np.ones((2, 4), dtype), np.ones((2, 3), dtype)
                for view in (rows, xyz_rows):  # the node's decode: read-only views on msg.data
                    view.flags.writeable = False
                # five signatures to numba: (N, 3) C and F (the node's copy when x, y, z are
                # not side by side), the columns of (N, 4) rows, read-only x, y, z, intensity
                # rows and read-only x, y, z-only rows
                for cloud in (xyz.T.copy(), xyz.T, np.ones((2, 4), dtype)[:, :3], rows[:, :3],
                              xyz_rows):
                    compiled.run(True, _valid_columns_compiled, _valid_columns, cloud)
                grid = grids[dtype] = build_grid(*xyz, 2, 2)
                if dtype == np.float32:
                    self._queue_float64_stages(grid)
                _label_points(np.zeros((2, 3)), np.zeros((2, 3)), grid, xyz[2], True)
                # a ground point with a column point right above it reaches the compiled part
                vertical_structure_mask(xyz[0], xyz[1] * 0, np.array([0.0, 0.5], dtype),
                                        np.zeros(2, dtype), np.array([True, False]),
                                        cell_m=0.03, cell_deg=0.25, rise_m=0.2,
                                        max_height_m=0.7, step_m=0.05)
            for dtype, grid in grids.items():
                z = np.ones(2, dtype=dtype)  # z_hat in the points' precision, as the labels
                ground_offsets(z, z * 0, np.ones(2, bool), grid.point_segment, grid.point_bin,
                               2, 2, 0.1)
            # the surface cloud's rows (GroundSurface.points), in float64 whatever the input
            GroundSurface(np.zeros(2), np.ones(2), np.ones(2, bool), np.zeros((2, 3)),
                          np.ones(2, bool), np.zeros((2, 3))).points()
            # These stages compile in the background (core/compiled.py); loading them from
            # numba's cache takes ~0.1 s, so wait that long, not the ~16-20 s of a first compile
            # (and not at all when the GP's compile showed the cache empty).
            if cache_was_filled:
                compiled.wait(_BACKGROUND_WAIT_S)

    def _queue_float64_stages(self, grid: RadialGrid) -> None:
        """warm_up(): run (and so queue for compiling) the stages between the grid and the
        labels on a tiny grid, in a frame's order; they work on float64 candidates whatever the
        input. test_warm_up_queues_every_compiled_stage_a_frame_needs checks none is missed."""
        # the line growing loop and the plateau state machine
        lines = extract_lines(grid.candidate_r, grid.candidate_z, grid.density,
                              variance_ratio=1.0, max_slope=1.0, max_distance_m=1.0,
                              max_gap_m=1.0, max_density_jump=2.0)
        # the training mask (candidates not on steep lines)
        compiled.run(True, _not_steep_compiled, _not_steep, grid.candidate_index, lines.slope,
                     1.0)
        additions.elevated_plateaus(grid.candidate_r, grid.candidate_z, lines.slope_before,
                                    step_up_m=0.3, max_slope=1.0, max_gap_m=1.0)
        # the chord slopes of one-point lines, the anchor (first lines' intercepts, a median)
        additions.one_point_line_slopes(lines.slope, grid.candidate_r, grid.candidate_z)
        additions.ground_under_sensor(grid.candidate_z, grid.has_candidate, lines.line_id,
                                      lines.line_count, lines.intercept)
        # the length factors (relative rho~, slopes, the smoothing along the segments)
        _length_factors_fused(lines.slope, grid.density, grid.candidate_r, grid.has_candidate,
                              0.1, 0.9, False, 0.05, 50.0, 1)
        # the anchor's rows and length factors
        compiled.run(True, _anchor_rows_compiled, _anchor_rows, grid.candidate_index,
                     np.ones((2, 2)), grid.has_candidate)
        # the GP batch's padding, the outlier pass, the length factors at the bin edges, the
        # threshold's rise
        gp = FrameGP(grid.candidate_r, grid.candidate_z, np.ones((2, 2)), grid.has_candidate,
                     backend='numba')
        sol = gp.solve(np.ones(3))
        self._reject_outliers(gp, sol, np.zeros(gp.shape, dtype=bool))
        gp.with_noise(np.zeros(gp.shape))  # the slots' noise (when a pass finds outliers)
        # the wide-terrain rule of the outlier pass (run only when a pass finds outliers)
        compiled.run(True, _not_wide_terrain_compiled, lambda new, *_: new,
                     grid.has_candidate, sol.alpha, sol.a_inv, gp.valid, gp.is_anchor,
                     gp.segments, gp.bins, gp.r, gp.z, 1.0, 1.0)
        additions.wide_terrain_candidates(grid.has_candidate, np.ones((2, 2)), 1.0,
                                          r=np.ones((2, 2)), max_slope=1.0)
        compiled.run(True, _fill_rows_to_edges_compiled, _fill_rows_to_edges,
                     np.ones((2, 2)), grid.has_candidate, gp.segments)
        additions.cross_segment_rise(np.ones((2, 3)), np.ones((2, 3)), 1.0)

    @property
    def hyperparameters(self) -> Hyperparameters:
        """Current theta (the one the next frame starts from)."""
        return self._theta

    def set_params(self, params: SegmenterParams) -> None:
        """Use new parameters from the next frame on; theta is kept (clipped to new bounds)."""
        self._params = params.validate()
        self._theta = self._clip_theta(self._theta)

    def reset(self) -> None:
        """Forget the learned theta: the next frame is a cold start."""
        p = self._params
        self._theta = Hyperparameters(p.sigma_f_init_m, p.length_scale_gain_init, p.sigma_n_init_m)
        self._frames_since_learning = None

    def _bounds(self):
        p = self._params
        return [(p.sigma_f_min_m, p.sigma_f_max_m),
                (p.length_scale_gain_min, p.length_scale_gain_max),
                (p.sigma_n_min_m, p.sigma_n_max_m)]

    def _clip_theta(self, theta) -> Hyperparameters:
        lo, hi = zip(*self._bounds())
        return Hyperparameters(*(float(v) for v in np.clip(np.asarray(theta, float), lo, hi)))

    def _learning_budget_and_bounds(self, theta):
        """Evaluation cap and bounds of this frame's theta search (a trust region once learned;
        no evaluation between the learning frames of ``optimizer_interval_frames``)."""
        p = self._params
        bounds = self._bounds()
        if self._frames_since_learning is None:
            return p.optimizer_first_frame_evaluations, bounds
        if self._frames_since_learning + 1 < p.optimizer_interval_frames:
            return 0, bounds
        ratio = p.optimizer_max_step_ratio  # theta moves at most x/÷ ratio a frame
        return p.optimizer_max_evaluations, [(max(lo, t / ratio), min(hi, t * ratio))
                                             for t, (lo, hi) in zip(theta, bounds)]

    def _training_candidates(self, grid: RadialGrid, lines: LineSegments, stats: dict):
        """Candidates that may train the GP: not on a steep line, not on an elevated plateau."""
        p = self._params
        use_compiled = self._backend == 'numba'
        training, candidates, steep_count = compiled.run(
            use_compiled, _not_steep_compiled, _not_steep, grid.candidate_index, lines.slope,
            float(p.line_max_slope))
        elevated_count = 0
        if p.use_elevated_plateaus:
            start = None
            if p.plateau_from_sensor_ground:
                start = additions.ground_under_sensor(grid.candidate_z, training, lines.line_id,
                                                      lines.line_count, lines.intercept,
                                                      compiled=use_compiled)
            elevated = additions.elevated_plateaus(
                grid.candidate_r, grid.candidate_z, lines.slope_before, step_up_m=p.plateau_step_m,
                max_slope=p.line_max_slope, max_gap_m=p.line_max_gap_m, start_height_m=start,
                end_on_drop=p.plateau_ends_on_drop, compiled=use_compiled)
            elevated_count = int(np.count_nonzero(elevated))
            training &= ~elevated
        stats.update(candidates=int(candidates), steep_line_candidates=int(steep_count),
                     elevated_candidates=elevated_count, lines=int(lines.line_count.size))
        return training

    def _length_factors(self, grid: RadialGrid, lines: LineSegments, training):
        """d_i of every candidate from its line's slope and its relative rho~ (gp.py), smoothed
        along the segment when ``length_factor_smoothing_passes`` asks (ours, additions.py)."""
        p = self._params
        return (_length_factors_fused if self._backend == 'numba' else _length_factors_numpy)(
            lines.slope, grid.density, grid.candidate_r, training, p.slope_floor,
            p.slope_ceiling, p.density_in_flat_branch, p.min_length_factor, p.max_length_factor,
            p.length_factor_smoothing_passes)

    def _anchor(self, grid: RadialGrid, lines: LineSegments, training, d, stats):
        """The ground under the vehicle as a GP point at r = 0 of every segment with candidates."""
        p = self._params
        if not p.use_anchor:
            return None
        height = additions.ground_under_sensor(grid.candidate_z, training, lines.line_id,
                                               lines.line_count, lines.intercept)
        stats['anchor_height_m'] = height
        segments, length_factor = compiled.run(
            self._backend == 'numba', _anchor_rows_compiled, _anchor_rows, grid.candidate_index,
            d, training)
        return GroundAnchor(height, p.anchor_std_m ** 2, segments, length_factor)

    def _reject_outliers(self, gp: FrameGP, sol: GPSolution, outliers):
        """One robust pass: (GP, solution, outliers) with the new outliers' noise made huge."""
        p = self._params
        if not p.use_outlier_rejection:
            return gp, sol, outliers

        def reference(*_):
            loo = gp.to_grid(gp.loo_residuals(sol), np.nan)
            return ~outliers & additions.outlier_candidates(
                loo, above_m=p.outlier_residual_m, below_m=p.noise_spike_m,
                worst_above_only=p.outlier_worst_per_segment,
                loo_std=gp.to_grid(gp.loo_std(sol), np.nan), std_factor=p.outlier_std_factor)

        new = compiled.run(gp.backend == 'numba', _new_outliers_compiled, reference, sol.alpha,
                           sol.a_inv, gp.valid, gp.is_anchor, gp.segments, gp.bins, outliers,
                           float(p.outlier_residual_m), float(p.noise_spike_m),
                           bool(p.outlier_worst_per_segment), float(p.outlier_std_factor))
        if new.any() and p.outlier_wide_terrain_m > 0:
            # obstacle tops (residual above, not the reflection noise below) that the
            # neighbouring segments continue are terrain: they keep training
            def wide_terrain_reference(*_):
                above = new & (gp.to_grid(gp.loo_residuals(sol), np.nan) > 0)
                return new & ~additions.wide_terrain_candidates(
                    above, gp.to_grid(gp.z, np.nan), p.outlier_wide_terrain_m,
                    r=gp.to_grid(gp.r, np.nan), max_slope=p.outlier_wide_terrain_max_slope,
                    compiled=gp.backend == 'numba')

            new = compiled.run(gp.backend == 'numba', _not_wide_terrain_compiled,
                               wide_terrain_reference, new, sol.alpha, sol.a_inv, gp.valid,
                               gp.is_anchor, gp.segments, gp.bins, gp.r, gp.z,
                               float(p.outlier_wide_terrain_m),
                               float(p.outlier_wide_terrain_max_slope))
        if not new.any():
            return gp, sol, outliers
        outliers = outliers | new
        gp = gp.with_noise(np.where(outliers, _OUTLIER_NOISE_VAR, 0.0))
        return gp, gp.solve(sol.theta), outliers

    def _fit_robustly(self, gp: FrameGP, stats: dict):
        """Robust pass at the warm-started theta, theta learning, robust pass at the new theta.

        Two passes, so that an outlier pair masking each other in the first is caught in the
        second. Returns (final GP, its solution, theta, outliers (M, N)).
        """
        theta = np.asarray(self._theta, dtype=np.float64)
        outliers = np.zeros(gp.shape, dtype=bool)
        if not gp.num_points:
            return gp, None, theta, outliers
        gp, sol, outliers = self._reject_outliers(gp, gp.solve(theta), outliers)
        evaluations, bounds = self._learning_budget_and_bounds(theta)
        new_theta, info = gp.fit(theta, bounds, evaluations)
        stats.update(optimizer_evaluations=info['evaluations'],
                     optimizer_iterations=info['iterations'],
                     optimizer_failures=int(info['failed']))
        if evaluations > 0 and not info['failed']:
            self._frames_since_learning = 0
        elif self._frames_since_learning is not None:
            self._frames_since_learning += 1
        # np.allclose's test (rtol 1e-5, atol 1e-8) on the three floats, without its ~20 us
        # of array set-up
        if not all(a == b or abs(a - b) <= 1e-8 + 1e-5 * abs(b)
                   for a, b in zip(new_theta.tolist(), theta.tolist())):
            theta = new_theta
            sol = gp.solve(theta)
        gp, sol, outliers = self._reject_outliers(gp, sol, outliers)
        stats['log_marginal_likelihood'] = float(sol.lml)
        stats['cholesky_fallbacks'] = gp.cholesky_fallbacks
        self._backend = gp.backend  # 'numpy' for good once the compiled kernel failed
        return gp, sol, theta, outliers

    def _fit_ground_model(self, grid: RadialGrid, lines: LineSegments, training,
                          stats: dict) -> _GroundModel:
        """Stage ``gp_fit``: length scales, the anchor, the GP, robust learning of theta."""
        p = self._params
        d = self._length_factors(grid, lines, training)
        anchor = self._anchor(grid, lines, training, d, stats)
        # the prior mean: the level plane through the ground under the vehicle, or the median
        # height of the training points (FrameGP's default). The anchor extrapolates lines to
        # r = 0; kept within the heights of the training candidates, so a scene seen from far
        # away (no ground near the sensor) cannot put the prior kilometres off.
        mean = None
        if anchor is not None and p.prior_mean_at_anchor and training.any():
            seen = grid.candidate_z[training]
            # np.clip of one number, without np.clip's array set-up (same value)
            mean = float(min(max(anchor.height_m, float(seen.min())), float(seen.max())))
        gp = FrameGP(grid.candidate_r, grid.candidate_z, d, training, anchor=anchor,
                     backend=self._backend, mean=mean)
        gp, sol, theta, outliers = self._fit_robustly(gp, stats)
        self._theta = Hyperparameters(*(float(v) for v in theta))
        # the GP's grid slots are the training candidates (gp.to_grid(gp.valid, False) is
        # ``training``), less the rejected ones
        trained = training & ~outliers
        stats['outlier_candidates'] = int(np.count_nonzero(outliers))
        stats['training_candidates'] = int(np.count_nonzero(trained))
        default_height = anchor.height_m if anchor is not None else gp.mean
        return _GroundModel(gp, sol, theta, trained, outliers, d, default_height)

    def _threshold_at_bin_edges(self, edges, mean, std):
        """Ground threshold (m): a scalar, or (M, N + 1) at the bin edges when it varies."""
        p = self._params
        threshold = p.ground_threshold_m
        if p.ground_threshold_std_factor > 0:
            threshold = threshold + p.ground_threshold_std_factor * std
        if p.use_cross_slope_threshold:
            rise = additions.cross_segment_rise(edges, mean, p.cross_slope_max,
                                                compiled=self._backend == 'numba')
            rise += threshold  # a new array: threshold + rise, in place (addition commutes)
            return np.minimum(rise, p.max_threshold_m, out=rise)
        return np.minimum(threshold, p.max_threshold_m)

    # ------------------------------------------------------------------------------------
    def segment(self, points: np.ndarray, details: bool = False) -> SegmentationResult:
        """Label every point of one frame as ground or not; see the module docstring."""
        # overflow to inf is handled where it can happen (absurdly far points: the kernel between
        # them becomes 0); do not spray RuntimeWarnings into a node's log for it
        blas = _single_threaded_blas() if self._backend != 'numba' else contextlib.nullcontext()
        with blas, np.errstate(over='ignore'):
            pose = self._params.sensor_pose
            if pose.is_identity:  # a cloud in the sensor frame: no copy
                return self._segment(points, details)
            # sensor_frame.py: segment in the levelled sensor frame, report heights in ours
            t_start = time.perf_counter()
            levelled = to_levelled_frame(points, pose)
            # validity is the input's: the pose must not move a (0, 0, 0) no-return into view
            levelled[~valid_points_mask(np.asarray(points)[:, :3])] = np.nan
            result = self._segment(levelled, details)
            result.ground_height = ground_height_in_cloud_frame(levelled, result.ground_height,
                                                                pose)
            result.point_z = np.asarray(points)[:, 2]  # the input's z, as ground_height
            result.timings_ms['total'] = (time.perf_counter() - t_start) * 1e3  # with the pose
            return result

    def _segment(self, points: np.ndarray, details: bool) -> SegmentationResult:
        p = self._params
        t_start = time.perf_counter()
        timings = {}
        stats = {'points': 0, 'valid_points': 0, 'candidates': 0, 'training_candidates': 0,
                 'outlier_candidates': 0, 'steep_line_candidates': 0, 'lines': 0,
                 'elevated_candidates': 0, 'cholesky_fallbacks': 0, 'optimizer_evaluations': 0,
                 'optimizer_iterations': 0, 'optimizer_failures': 0,
                 'log_marginal_likelihood': float('nan'), 'structure_feet': 0}
        pts = np.asarray(points)
        if pts.dtype.names is not None:
            raise ValueError(f'points must be an (N, >=3) numeric array, got a structured array '
                             f'with fields {pts.dtype.names}; pass np.column_stack((points["x"], '
                             'points["y"], points["z"]))')
        if pts.dtype.kind not in 'fiu':
            raise ValueError(f'points must be real numbers (float, int), got dtype {pts.dtype}')
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise ValueError(f'points must be an (N, >=3) array, got shape {pts.shape}')
        # float32 input (every LiDAR driver) is processed in float32 up to the candidates: the
        # per-point arithmetic is memory-bound and mm precision is plenty for r and z.
        work_dtype = pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64
        xyz = pts[:, :3].astype(work_dtype, copy=False)
        n_points = xyz.shape[0]
        valid, x, y, z = compiled.run(self._backend == 'numba', _valid_columns_compiled,
                                      _valid_columns, xyz)
        n_valid = z.size
        all_valid = n_valid == n_points
        # index arrays only when some points are invalid (8 bytes a point otherwise wasted)
        valid_index = slice(None) if all_valid else np.flatnonzero(valid)
        stats['points'] = n_points
        stats['valid_points'] = n_valid
        if n_valid == 0:
            ground = np.zeros(n_points, dtype=bool)
            height = np.full(n_points, np.nan)
            timings['total'] = (time.perf_counter() - t_start) * 1e3
            return SegmentationResult(ground, valid, height, self._theta, timings, stats,
                                      ground_surface=GroundSurface.empty(p.num_segments,
                                                                         p.num_bins),
                                      point_z=xyz[:, 2])

        t = time.perf_counter()
        grid = build_grid(x, y, z, p.num_segments, p.num_bins,
                          compiled=self._backend == 'numba')
        timings['grid'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        lines = extract_lines(grid.candidate_r, grid.candidate_z, grid.density,
                              variance_ratio=p.deming_variance_ratio, max_slope=p.line_max_slope,
                              max_distance_m=p.line_max_distance_m, max_gap_m=p.line_max_gap_m,
                              max_density_jump=p.line_max_density_jump,
                              compiled=self._backend == 'numba')
        if p.use_chord_slope_for_single_points:
            lines = _replace_slope(lines, additions.one_point_line_slopes(
                lines.slope, grid.candidate_r, grid.candidate_z,
                compiled=self._backend == 'numba'))
        training = self._training_candidates(grid, lines, stats)
        timings['lines'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        model = self._fit_ground_model(grid, lines, training, stats)
        theta = model.theta
        timings['gp_fit'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        need_std = details or p.ground_threshold_std_factor > 0
        edges = grid.bin_edges()
        mean_full, std_full, d_star, k_star = _ground_at_bin_edges(model, edges, need_std)
        timings['predict'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        edge_threshold = self._threshold_at_bin_edges(edges, mean_full, std_full)
        z_hat, ground_v = _label_points(mean_full, edge_threshold, grid, z,
                                        self._backend == 'numba')
        timings['label'] = (time.perf_counter() - t) * 1e3

        feet = None
        if p.use_vertical_structure_test:
            t = time.perf_counter()
            feet = structure_feet(p, x, y, z, z_hat, ground_v, r=grid.point_r,
                                  angle=grid.point_angle)
            ground_v &= ~feet
            stats['structure_feet'] = int(np.count_nonzero(feet))
            timings['structure'] = (time.perf_counter() - t) * 1e3
        if all_valid:  # copies (ground_v stays the surface's), without the fill first
            ground, height = ground_v.copy(), z_hat.astype(np.float64)
        else:
            ground = np.zeros(n_points, dtype=bool)
            height = np.full(n_points, np.nan)
            ground[valid_index] = ground_v
            height[valid_index] = z_hat
        timings['total'] = (time.perf_counter() - t_start) * 1e3

        extra = None
        if details:
            threshold = edge_threshold
            if np.ndim(threshold):
                threshold = _interpolate_at_points(threshold, grid)
            threshold = np.broadcast_to(np.asarray(threshold, dtype=np.float64), z.shape)
            extra = SegmentationDetails(
                np.flatnonzero(valid), grid, lines, model.training, model.outliers,
                np.where(grid.has_candidate, theta[1] * model.length_factor, np.nan), edges,
                mean_full, std_full, threshold, model.gp, model.solution, d_star, feet)
        surface = _ground_surface(model, grid, edges, mean_full, std_full if need_std else None,
                                  z, ground_v, z_hat, k_star, p.sensor_pose,
                                  self._backend == 'numba')
        return SegmentationResult(ground, valid, height, self._theta, timings, stats, extra,
                                  surface, xyz[:, 2])
