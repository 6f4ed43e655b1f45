# SPDX-License-Identifier: Apache-2.0
"""GroundSegmenter: radial grid -> line-segments -> whole-frame GP -> per-point labels.

Pipeline of one frame (stage names are the keys of ``SegmentationResult.timings_ms``):

``grid``     valid points binned into M x N, lowest point per bin = ground candidate, rho~.
``lines``    Algorithm 1 over each segment's candidates: line-segments, critical points, slopes.
             Candidates on lines steeper than zeta_b are structure (walls, car fronts), not
             ground: they do not train the GP (the paper: "large sloped line-segments relate to
             non-ground structures").
``gp_fit``   length scales from slope and rho~, robust rejection of outlier candidates, then
             theta learned on the whole-frame marginal likelihood (warm-started, capped).
``predict``  GP posterior mean and std of the ground height at every bin edge (N + 1 per
             segment: a dense N x n kernel against every raw point would cost 100x more).
``label``    ground height of each point by linear interpolation along r between the bin
             edges of its segment; ground when z - z_hat <= threshold.

The grid is centred at the origin and z is taken as up: a cloud not in the sensor's own frame
is first moved into the levelled sensor frame with the ``sensor_*`` pose parameters
(sensor_frame.py; no copy when they are all 0). Labels are per input point; ``ground_height``
is in the input's frame; ``details`` (grid, lines, GP) are in the levelled frame.

Choices where the paper is vague, each a parameter (see params.py):

* Outlier candidates. The lowest point of a bin is not always ground: below-ground reflection
  noise (points metres under the road) and the tops of obstacles whose ground is occluded
  (a car roof seen over its bonnet) both become candidates. A candidate whose leave-one-out
  GP residual is above ``outlier_residual_m`` or below ``-noise_spike_m`` is given a large
  noise variance (it stops pulling the fit) and the GP is solved again. There are two passes,
  one before and one after theta is learned, so that an outlier pair masking each other in the
  first pass is caught in the second.
* "Close to the ground". A point is ground when z - z_hat(r) <= ground_threshold_m +
  ground_threshold_std_factor * std(r), capped at max_threshold_m: the threshold widens where
  the GP is unsure (far, sparse, between lines) but never becomes a height cut-off. The test is
  one-sided, as in the paper: anything below the predicted ground is ground (below-ground noise
  included -- it is not an obstacle). There is no height or range truncation anywhere.
* The ground under the vehicle. All segments meet at r = 0, where the ground is the one the
  vehicle stands on (also on a slope). Every segment's GP gets one shared pseudo-candidate at
  r = 0 with the frame's estimate of that height (the median over segments of their first
  line extrapolated to r = 0) and noise std ``anchor_std_m``. It ties the segments together,
  so that a car parked right beside the sensor -- whose roof is the first and only nearby
  candidate of its segments -- shows up as a step up from the vehicle's own ground and is
  rejected, instead of becoming the ground. Segments without a single candidate predict that
  height with the prior std sigma_f.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np
from threadpoolctl import ThreadpoolController

from .gp import FrameGP, length_scale_factors
from .grid import RadialGrid, build_grid, relative_density
from .lines import LineSegments, extract_lines
from .params import SegmenterParams
from .sensor_frame import ground_height_in_cloud_frame, to_levelled_frame

_OUTLIER_NOISE_VAR = 1e4  # m^2: a rejected candidate's noise variance (std 100 m)
_blas = None  # threadpoolctl controller, made on first use (after scipy has loaded its BLAS)


def _single_threaded_blas():
    """Limit BLAS to one thread for one frame.

    The GP factorises many tiny (n <= N + 1) matrices; OpenBLAS threads only spin on them.
    Measured on the 124k-point KITTI frame: the same wall time, half the CPU time (31 vs 62 ms
    per frame), which leaves the other core to the ROS executor (benchmarks/RESULTS.md).
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
    gp_solution: Optional[object] = None  # its final factorisation (gp.GPSolution)
    length_factor_at_edges: Optional[np.ndarray] = None  # (S, N + 1) d used at the bin edges


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


def _ground_under_sensor(grid: RadialGrid, lines: LineSegments, training: np.ndarray) -> float:
    """Height of the ground under the vehicle (r = 0), shared by all segments (m).

    Every segment starts at the sensor, so all segment GPs meet at r = 0 where the ground is
    the one the vehicle stands on, on a slope too. Each segment's first line-segment (two or
    more candidates, not steep) extrapolated to r = 0 gives one estimate; the median over
    segments is robust to the few whose first line is a car or a wall. Without such lines,
    the median of the training candidates.
    """
    rows = np.flatnonzero(training.any(axis=1))
    if rows.size == 0:
        z = grid.candidate_z[np.isfinite(grid.candidate_z)]
        return float(np.median(z)) if z.size else 0.0
    first = np.argmax(training[rows], axis=1)
    ids = lines.line_id[rows, first]
    usable = (lines.line_count[ids] >= 2) & np.isfinite(lines.intercept[ids])
    if usable.any():
        return float(np.median(lines.intercept[ids[usable]]))
    return float(np.median(grid.candidate_z[training]))


class _GroundModel(NamedTuple):
    """What the ``gp_fit`` stage hands to ``predict``."""

    gp: FrameGP
    solution: Optional[object]  # gp.GPSolution, None when no segment has a candidate
    theta: np.ndarray  # (3,) sigma_f, a, sigma_n used for the frame
    training: np.ndarray  # (M, N) candidates that trained the GP
    outliers: np.ndarray  # (M, N) candidates rejected by the robust passes
    length_factor: np.ndarray  # (M, N) d_i
    anchor_z: float  # ground height under the vehicle (m)


def _ground_at_bin_edges(model: _GroundModel, grid: RadialGrid, need_std: bool):
    """GP posterior mean (and std) at the N + 1 bin edges of every segment (stage ``predict``).

    Segments without any candidate keep the anchor height and the prior std sigma_f.
    Returns (edges, mean, std, d at the edges of the GP's segments) with (M, N + 1) arrays.
    """
    m_count, n_bins = grid.num_segments, grid.num_bins
    edges = grid.bin_edges()
    mean = np.full((m_count, n_bins + 1), model.anchor_z)
    std = np.full((m_count, n_bins + 1), model.theta[0])
    d_star = None
    if model.solution is not None:
        rows = model.gp.segments
        d_fill = _fill_along_rows(model.length_factor, model.training)
        d_star = np.concatenate([d_fill, d_fill[:, -1:]], axis=1)[rows]
        mean_b, std_b = model.gp.predict(model.solution, edges[rows], d_star, with_std=need_std)
        mean[rows] = mean_b
        if need_std:
            std[rows] = std_b
    return edges, mean, std, d_star


def _interpolate_at_points(values: np.ndarray, grid: RadialGrid) -> np.ndarray:
    """(M, N + 1) values at bin edges -> every point, linearly along r within its bin.

    Flat gathers in the points' precision: at 2 M points every float64 temporary is 16 MB.
    """
    frac = grid.point_bin_fraction
    flat = values.ravel().astype(frac.dtype)
    edge = grid.point_segment * np.int32(grid.num_bins + 1) + grid.point_bin
    out = flat[edge]
    edge += 1
    step = flat[edge]
    step -= out
    step *= frac
    out += step
    return out


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


class GroundSegmenter:
    """Stateful segmenter: theta is warm-started from one frame to the next.

    >>> seg = GroundSegmenter(SegmenterParams())
    >>> result = seg.segment(points)          # (N, >=3) float array
    >>> points[result.ground_mask]            # ground; result.obstacle_mask for the rest
    """

    def __init__(self, params: SegmenterParams | None = None,
                 hyperparameters: Hyperparameters | None = None):
        self._params = (params or SegmenterParams()).validate()
        if hyperparameters is None:
            p = self._params
            hyperparameters = Hyperparameters(p.sigma_f_init_m, p.length_scale_gain_init,
                                              p.sigma_n_init_m)
        self._theta = self._clip_theta(hyperparameters)
        self._has_learned = False

    @property
    def params(self) -> SegmenterParams:
        return self._params

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
        self._has_learned = False

    def _bounds(self):
        p = self._params
        return [(p.sigma_f_min_m, p.sigma_f_max_m),
                (p.length_scale_gain_min, p.length_scale_gain_max),
                (p.sigma_n_min_m, p.sigma_n_max_m)]

    def _clip_theta(self, theta) -> Hyperparameters:
        lo, hi = zip(*self._bounds())
        return Hyperparameters(*(float(v) for v in np.clip(np.asarray(theta, float), lo, hi)))

    def _fit_ground_model(self, grid: RadialGrid, lines: LineSegments,
                          stats: dict) -> _GroundModel:
        """Length scales, anchor, robust rejection and theta learning (stage ``gp_fit``)."""
        p = self._params
        has = grid.has_candidate
        steep = has & (lines.slope > p.line_max_slope)
        training = has & ~steep & ~lines.elevated
        stats['elevated_candidates'] = int(lines.elevated.sum())
        stats['candidates'] = int(has.sum())
        stats['steep_line_candidates'] = int(steep.sum())
        stats['lines'] = int(lines.line_count.size)
        density_rel = relative_density(grid.density, grid.candidate_r, training)
        d = length_scale_factors(lines.slope, density_rel,
                                 slope_floor=p.slope_floor, slope_ceiling=p.slope_ceiling,
                                 density_in_flat_branch=p.density_in_flat_branch,
                                 d_min=p.min_length_factor, d_max=p.max_length_factor)
        m_count, n_bins = grid.num_segments, grid.num_bins
        anchor_z = _ground_under_sensor(grid, lines, training)
        stats['anchor_height_m'] = anchor_z
        # column 0 of every segment is the shared anchor: the ground under the vehicle (r = 0)
        anchored = has.any(axis=1, keepdims=True)
        gp = FrameGP(np.concatenate([np.zeros((m_count, 1)), grid.candidate_r], axis=1),
                     np.concatenate([np.full((m_count, 1), anchor_z), grid.candidate_z], axis=1),
                     np.concatenate([_fill_along_rows(d, training)[:, :1], d], axis=1),
                     np.concatenate([anchored, training], axis=1))
        is_anchor = (gp.columns == 0) & gp.valid
        gp.extra_noise[is_anchor] = p.anchor_std_m ** 2
        outliers = np.zeros_like(gp.valid)
        theta = np.asarray(self._theta, dtype=np.float64)

        def reject_outliers(sol):
            loo = gp.loo_residuals(sol)
            new = (gp.valid & ~is_anchor & ~outliers
                   & ((loo > p.outlier_residual_m) | (loo < -p.noise_spike_m)))
            outliers[new] = True
            gp.extra_noise[new] = _OUTLIER_NOISE_VAR
            return bool(new.any())

        sol = None
        if gp.num_points:
            # robust pass 1 at the warm-started theta, learning, robust pass 2 at the new theta
            sol = gp.solve(theta)
            if reject_outliers(sol):
                sol = gp.solve(theta)
            iterations = (p.optimizer_max_evaluations if self._has_learned
                          else p.optimizer_first_frame_evaluations)
            bounds = self._bounds()
            if self._has_learned:  # trust region: theta moves at most x/÷ step ratio a frame
                ratio = p.optimizer_max_step_ratio
                bounds = [(max(lo, t / ratio), min(hi, t * ratio))
                          for t, (lo, hi) in zip(theta, bounds)]
            new_theta, info = gp.fit(theta, bounds, iterations)
            stats['optimizer_iterations'] = info['iterations']
            stats['optimizer_failures'] = int(info['failed'])
            if iterations > 0 and not info['failed']:
                self._has_learned = True
            if not np.allclose(new_theta, theta):
                theta = new_theta
                sol = gp.solve(theta)
            if reject_outliers(sol):
                sol = gp.solve(theta)
            stats['log_marginal_likelihood'] = float(sol.lml)
        self._theta = Hyperparameters(*(float(v) for v in theta))
        # back from the GP's padded (S, n) slots to the grid's (M, N) bins
        train_full = np.zeros((m_count, n_bins + 1), dtype=bool)
        out_full = np.zeros((m_count, n_bins + 1), dtype=bool)
        train_full[gp.segments[:, None], gp.columns] = gp.valid & ~outliers
        out_full[gp.segments[:, None], gp.columns] = outliers
        train_full, out_full = train_full[:, 1:], out_full[:, 1:]
        stats['outlier_candidates'] = int(out_full.sum())
        stats['training_candidates'] = int(train_full.sum())
        stats['cholesky_fallbacks'] = gp.cholesky_fallbacks
        return _GroundModel(gp, sol, theta, train_full, out_full, d, anchor_z)

    # ------------------------------------------------------------------------------------
    def segment(self, points: np.ndarray, details: bool = False) -> SegmentationResult:
        """Label every point of one frame as ground or not; see the module docstring."""
        # overflow to inf is handled where it can happen (absurdly far points: the kernel between
        # them becomes 0); do not spray RuntimeWarnings into a node's log for it
        with _single_threaded_blas(), np.errstate(over='ignore'):
            pose = self._params.sensor_pose
            if pose.is_identity:  # a cloud in the sensor frame: no copy
                return self._segment(points, details)
            # sensor_frame.py: segment in the levelled sensor frame, report heights in ours
            levelled = to_levelled_frame(points, pose)
            result = self._segment(levelled, details)
            result.ground_height = ground_height_in_cloud_frame(levelled, result.ground_height,
                                                                pose)
            return result

    def _segment(self, points: np.ndarray, details: bool) -> SegmentationResult:
        p = self._params
        t_start = time.perf_counter()
        timings = {}
        stats = {'points': 0, 'valid_points': 0, 'candidates': 0, 'training_candidates': 0,
                 'outlier_candidates': 0, 'steep_line_candidates': 0, 'lines': 0,
                 'cholesky_fallbacks': 0, 'optimizer_iterations': 0, 'optimizer_failures': 0,
                 'log_marginal_likelihood': float('nan')}
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise ValueError(f'points must be an (N, >=3) array, got shape {pts.shape}')
        # float32 input (every LiDAR driver) is processed in float32 up to the candidates: the
        # per-point arithmetic is memory-bound and mm precision is plenty for r and z.
        work_dtype = pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64
        xyz = pts[:, :3].astype(work_dtype, copy=False)
        n_points = xyz.shape[0]
        valid = valid_points_mask(xyz)
        all_valid = bool(valid.all())
        # index arrays only when some points are invalid (8 bytes a point otherwise wasted)
        valid_index = slice(None) if all_valid else np.flatnonzero(valid)
        n_valid = n_points if all_valid else int(valid_index.size)
        stats['points'] = n_points
        stats['valid_points'] = n_valid
        ground = np.zeros(n_points, dtype=bool)
        height = np.full(n_points, np.nan)
        if n_valid == 0:
            timings['total'] = (time.perf_counter() - t_start) * 1e3
            return SegmentationResult(ground, valid, height, self._theta, timings, stats)
        xyz_v = xyz if all_valid else xyz[valid_index]
        x, y, z = (np.ascontiguousarray(xyz_v[:, i]) for i in range(3))
        del xyz_v

        t = time.perf_counter()
        grid = build_grid(x, y, z, p.num_segments, p.num_bins, p.density_slices)
        timings['grid'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        lines = extract_lines(grid.candidate_r, grid.candidate_z, grid.density,
                              variance_ratio=p.deming_variance_ratio, max_slope=p.line_max_slope,
                              max_distance_m=p.line_max_distance_m, max_gap_m=p.line_max_gap_m,
                              max_density_jump=p.line_max_density_jump,
                              step_up_m=p.plateau_step_m)
        timings['lines'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        model = self._fit_ground_model(grid, lines, stats)
        theta = model.theta
        timings['gp_fit'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        need_std = details or p.ground_threshold_std_factor > 0
        edges, mean_full, std_full, d_star = _ground_at_bin_edges(model, grid, need_std)
        timings['predict'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        z_hat = _interpolate_at_points(mean_full, grid)
        if p.ground_threshold_std_factor > 0:
            std = _interpolate_at_points(std_full, grid)
            threshold = np.minimum(p.ground_threshold_m + p.ground_threshold_std_factor * std,
                                   p.max_threshold_m)
        else:
            threshold = min(p.ground_threshold_m, p.max_threshold_m)
        ground[valid_index] = z - z_hat <= threshold
        height[valid_index] = z_hat
        timings['label'] = (time.perf_counter() - t) * 1e3
        timings['total'] = (time.perf_counter() - t_start) * 1e3

        extra = None
        if details:
            threshold = np.broadcast_to(np.asarray(threshold, dtype=np.float64), z.shape)
            extra = SegmentationDetails(
                np.flatnonzero(valid), grid, lines, model.training, model.outliers,
                np.where(grid.has_candidate, theta[1] * model.length_factor, np.nan), edges,
                mean_full, std_full, threshold, model.gp, model.solution, d_star)
        return SegmentationResult(ground, valid, height, self._theta, timings, stats, extra)
