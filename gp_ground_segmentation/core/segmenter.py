# SPDX-License-Identifier: Apache-2.0
"""GroundSegmenter: one frame through the stage table (core/stages.py) in one readable sequence.

The stages of :meth:`GroundSegmenter._segment` (the keys of ``SegmentationResult.timings_ms``),
[paper] marking the paper's steps and [ours] our additions, each with its ``use_*`` switch:

``grid``      [paper] valid points binned into M x N, the lowest point of a bin its ground
              candidate, rho~ (grid.py).
``lines``     [paper] Algorithm 1 per segment; candidates on steep lines do not train (lines.py).
              [ours] chord slopes of one-point lines (lines.py), elevated plateaus (plateau.py).
``gp_fit``    [paper] length factors by eq. 12 (length_factors.py; off by default, one length
              factor for every candidate: ``use_nonstationary_length_scale``), the whole-frame
              GP and theta learned on its marginal likelihood (gp.py). [ours] rho~ normalised
              per range ring and d smoothed along the segment (length_factors.py), the ground
              under the vehicle as a shared training point and prior mean (anchor.py),
              leave-one-out outlier rejection before and after learning (outliers.py), learning
              only on every ``optimizer_interval_frames``-th frame of a stream.
``predict``   [paper] the posterior ground height at every bin edge (predict.py). [ours] the
              coupled surface: the ground on every border between two segments from a GP over
              both segments' candidates at their (x, y) (coupled_surface.py).
``label``     [paper] the label rule on the ground height interpolated to each point (with the
              coupled surface: between its segment's borders). [ours] the threshold widened by
              the GP std and the cross-slope rise (labels.py).
``structure`` [ours] the feet of vertical structures become obstacles (structure.py), but for
              those under which the sensor saw free space (free_space.py).

The ground surface output (surface.py) is built from the same arrays, its extras when read. A
cloud not in the sensor's own frame is first moved into the levelled sensor frame with the
``sensor_*`` pose parameters (sensor_frame.py; no copy when they are all 0). Labels and validity
are per input point; ``ground_height``, ``height_above_ground`` and ``ground_surface`` are in
the input's frame; ``details`` (grid, lines, GP) are in the levelled frame.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

from . import anchor, compiled, coupled_surface, labels, outliers, plateau, stages
from . import structure
from .gp import FrameGP, GPSolution, numpy_blas_limit, resolve_backend
from .grid import RadialGrid, build_grid, valid_columns, valid_points_mask
from .length_factors import frame_length_factors
from .lines import (CHORD_SLOPES, LineSegments, extract_lines, one_point_line_slopes,
                    training_candidates, with_slope)
from .params import SegmenterParams
from .predict import GroundModel, ground_at_bin_edges
from .result import Hyperparameters, SegmentationDetails, SegmentationResult
from .sensor_frame import ground_height_in_cloud_frame, to_levelled_frame
from .surface import GroundSurface, frame_surface

__all__ = ['GroundSegmenter', 'Hyperparameters', 'SegmentationDetails', 'SegmentationResult',
           'valid_points_mask']

# warm_up() waits this long (s) for the background compilations: loading them from numba's
# cache takes ~0.1 s; a first compilation (~16-20 s on 2 cores) goes on while frames use numpy
_BACKGROUND_WAIT_S = 0.5
# The GP step loads from numba's cache in ~0.2-0.4 s and compiles in 1.5-3 s: when it took
# longer than this (s), the cache was empty, the background stages are compiling too, and
# waiting _BACKGROUND_WAIT_S for them would only delay the first frame
_GP_CACHE_LOAD_MAX_S = 1.0


class _Clock:
    """``with clock('grid'): ...`` puts the block's milliseconds into ``timings['grid']``."""

    __slots__ = ('timings', '_name', '_start')

    def __init__(self, timings: dict):
        self.timings = timings

    def __call__(self, name: str) -> '_Clock':
        self._name = name
        return self

    def __enter__(self):
        self._start = time.perf_counter()

    def __exit__(self, *_):
        self.timings[self._name] = (time.perf_counter() - self._start) * 1e3


def _input_xyz(points) -> np.ndarray:
    """x, y, z (N, 3) of ``points`` in the working precision: float32 input (every LiDAR
    driver's) stays float32 up to the candidates (the per-point arithmetic is memory-bound and
    mm precision is plenty), anything else becomes float64. One-line errors for what is not an
    (N, >= 3) array of real numbers."""
    pts = np.asarray(points)
    if pts.dtype.names is not None:
        raise ValueError(f'points must be an (N, >=3) numeric array, got a structured array '
                         f'with fields {pts.dtype.names}; pass np.column_stack((points["x"], '
                         'points["y"], points["z"]))')
    if pts.dtype.kind not in 'fiu':
        raise ValueError(f'points must be real numbers (float, int), got dtype {pts.dtype}')
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f'points must be an (N, >=3) array, got shape {pts.shape}')
    work_dtype = pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64
    return pts[:, :3].astype(work_dtype, copy=False)


def _per_input_point(valid: np.ndarray, ground_v: np.ndarray, z_hat: np.ndarray):
    """(ground mask, float64 ground height) of every input point from the valid points'
    (NaN height and not ground where invalid)."""
    if ground_v.size == valid.size:  # copies (ground_v stays the surface's), without a fill
        return ground_v.copy(), z_hat.astype(np.float64)
    index = np.flatnonzero(valid)
    ground = np.zeros(valid.size, dtype=bool)
    height = np.full(valid.size, np.nan)
    ground[index] = ground_v
    height[index] = z_hat
    return ground, height


def _new_stats() -> dict:
    return {'points': 0, 'valid_points': 0, 'candidates': 0, 'training_candidates': 0,
            'outlier_candidates': 0, 'steep_line_candidates': 0, 'lines': 0,
            'elevated_candidates': 0, 'cholesky_fallbacks': 0, 'optimizer_evaluations': 0,
            'optimizer_iterations': 0, 'optimizer_failures': 0,
            'log_marginal_likelihood': float('nan'), 'structure_feet': 0}


class GroundSegmenter:
    """Stateful segmenter: theta is warm-started from one frame to the next.

    >>> seg = GroundSegmenter(SegmenterParams())
    >>> result = seg.segment(points)          # (N, >=3) float array
    >>> points[result.ground_mask]            # ground; result.obstacle_mask for the rest
    """

    def __init__(self, params: SegmenterParams | None = None,
                 hyperparameters: Hyperparameters | None = None, backend: str = 'auto'):
        """``backend`` of the compiled stages: 'numba', 'numpy' or 'auto' (numba if it
        imports). If the compiled GP fails at run time this segmenter uses numpy from then on
        (``backend`` tells which one is in use)."""
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
        """Compiled stages in use: 'numba' or 'numpy'."""
        return self._backend

    @property
    def hyperparameters(self) -> Hyperparameters:
        """Current theta (the one the next frame starts from)."""
        return self._theta

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the GP step now, not inside the first frame,
        and queue every other compiled stage of the table for the background compiler
        (core/stages.py), float32 frames' signatures first. Up to _BACKGROUND_WAIT_S is waited
        for those, enough to load them from the cache, unless the GP step took longer than
        _GP_CACHE_LOAD_MAX_S (the cache was empty: they are compiling, and frames take their
        numpy twins meanwhile). The GP's posterior std is compiled now only when the labels use
        it (``use_std_threshold``); otherwise it is the background compiler's first job.

        On failure this segmenter switches to numpy and the error is raised for the caller to
        report; segmenting still works.
        """
        if self._backend != 'numba':
            return
        start = time.perf_counter()
        try:
            stages.compile_round_off(background_too=labels.STD_THRESHOLD.on(self._params))
        except Exception:
            self._backend = 'numpy'
            raise
        cache_was_filled = time.perf_counter() - start < _GP_CACHE_LOAD_MAX_S
        stages.queue_exact()
        if cache_was_filled:
            compiled.wait(_BACKGROUND_WAIT_S)

    def set_params(self, params: SegmenterParams) -> None:
        """Use new parameters from the next frame on; theta is kept (clipped to new bounds)."""
        self._params = params.validate()
        self._theta = self._clip_theta(self._theta)

    def reset(self) -> None:
        """Forget the learned theta: the next frame is a cold start."""
        p = self._params
        self._theta = Hyperparameters(p.sigma_f_init_m, p.length_scale_gain_init, p.sigma_n_init_m)
        self._frames_since_learning = None

    # ------------------------------------------------------------------------------------
    def segment(self, points: np.ndarray, details: bool = False) -> SegmentationResult:
        """Label every point of one frame as ground or not; see the module docstring."""
        # overflow to inf is handled where it can happen (absurdly far points: the kernel between
        # them becomes 0); do not spray RuntimeWarnings into a node's log for it
        blas = numpy_blas_limit() if self._backend != 'numba' else contextlib.nullcontext()
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
        """The frame's stages in order (module docstring)."""
        p = self._params
        t_start = time.perf_counter()
        timings, stats = {}, _new_stats()
        xyz = _input_xyz(points)
        valid, x, y, z = valid_columns(xyz, self._backend == 'numba')
        stats.update(points=xyz.shape[0], valid_points=z.size)
        if z.size == 0:
            timings['total'] = (time.perf_counter() - t_start) * 1e3
            return SegmentationResult(
                np.zeros(valid.size, dtype=bool), valid, np.full(valid.size, np.nan),
                self._theta, timings, stats, point_z=xyz[:, 2],
                ground_surface=GroundSurface.empty(p.num_segments, p.num_bins))
        clock = _Clock(timings)
        with clock('grid'):
            grid = build_grid(x, y, z, p.num_segments, p.num_bins,
                              compiled=self._backend == 'numba')
        with clock('lines'):
            lines = self._lines(grid)
            training = self._training_candidates(grid, lines, stats)
        with clock('gp_fit'):
            model = self._fit_ground_model(grid, lines, training, stats)
        use_compiled = self._backend == 'numba'  # numpy for good once the compiled GP failed
        need_std = details or labels.STD_THRESHOLD.on(p)
        with clock('predict'):
            edges = grid.bin_edges()
            mean, std, d_star, k_star, lattice = self._ground_at_edges(model, grid, x, y, edges,
                                                                       need_std)
        with clock('label'):
            threshold = labels.edge_thresholds(edges, mean, std, p, use_compiled)
            if lattice is None:
                z_hat, ground_v = labels.label_points(mean, threshold, grid, z, use_compiled)
            else:
                z_hat, ground_v = coupled_surface.coupled_labels(lattice, grid, z, threshold,
                                                                 use_compiled)
        feet = None
        if structure.STAGE.on(p):
            with clock('structure'):
                feet = structure.structure_feet(p, x, y, z, z_hat, ground_v, r=grid.point_r,
                                                angle=grid.point_angle, compiled=use_compiled)
                ground_v &= ~feet
                stats['structure_feet'] = int(np.count_nonzero(feet))
        ground, height = _per_input_point(valid, ground_v, z_hat)
        timings['total'] = (time.perf_counter() - t_start) * 1e3
        extra = None
        if details:
            if np.ndim(threshold):
                threshold = labels.interpolate_at_points(threshold, grid)
            extra = SegmentationDetails(
                np.flatnonzero(valid), grid, lines, model.training, model.outliers,
                np.where(grid.has_candidate, model.theta[1] * model.length_factor, np.nan),
                edges, mean, std, np.broadcast_to(np.asarray(threshold, np.float64), z.shape),
                model.gp, model.solution, d_star, feet, lattice)
        surface = frame_surface(model, grid, edges, mean, std if need_std else None, z,
                                ground_v, z_hat, k_star, p.sensor_pose, use_compiled, lattice)
        return SegmentationResult(ground, valid, height, self._theta, timings, stats, extra,
                                  surface, xyz[:, 2])

    # --- the stages -----------------------------------------------------------------------
    def _ground_at_edges(self, model: GroundModel, grid: RadialGrid, x, y, edges, need_std):
        """Stage ``predict``: (mean, std, d*, k* at the bin edges, coupled lattice or None).
        The paper's per-segment posterior, or the coupled surface's borders and their centre
        (coupled_surface.py) with the per-segment std when the labels or details need it."""
        p, use_compiled = self._params, self._backend == 'numba'
        if not coupled_surface.STAGE.on(p):
            return (*ground_at_bin_edges(model, edges, need_std, use_compiled), None)
        lattice, mean = coupled_surface.coupled_ground(model, grid, x, y, edges,
                                                       p.max_length_factor, use_compiled)
        std = d_star = k_star = None
        if need_std:
            _, std, d_star, k_star = ground_at_bin_edges(model, edges, True, use_compiled)
        return mean, std, d_star, k_star, lattice

    def _lines(self, grid: RadialGrid) -> LineSegments:
        """Algorithm 1 over the candidates, with the chord slopes of one-point lines."""
        p, use_compiled = self._params, self._backend == 'numba'
        lines = extract_lines(grid.candidate_r, grid.candidate_z, grid.density,
                              variance_ratio=p.deming_variance_ratio, max_slope=p.line_max_slope,
                              max_distance_m=p.line_max_distance_m, max_gap_m=p.line_max_gap_m,
                              max_density_jump=p.line_max_density_jump, compiled=use_compiled)
        if CHORD_SLOPES.on(p):
            lines = with_slope(lines, one_point_line_slopes(
                lines.slope, grid.candidate_r, grid.candidate_z, compiled=use_compiled))
        return lines

    def _training_candidates(self, grid: RadialGrid, lines: LineSegments, stats: dict):
        """Candidates that may train the GP: not on a steep line, not on an elevated plateau."""
        p, use_compiled = self._params, self._backend == 'numba'
        training, candidates, steep_count = training_candidates(
            grid.candidate_index, lines.slope, p.line_max_slope, use_compiled)
        elevated_count = 0
        if plateau.STAGE.on(p):
            start = None
            if p.plateau_from_sensor_ground:
                start = anchor.ground_under_sensor(grid.candidate_z, training, lines.line_id,
                                                   lines.line_count, lines.intercept,
                                                   compiled=use_compiled)
            elevated = plateau.elevated_plateaus(
                grid.candidate_r, grid.candidate_z, lines.slope_before, step_up_m=p.plateau_step_m,
                max_slope=p.line_max_slope, max_gap_m=p.line_max_gap_m, start_height_m=start,
                end_on_drop=p.plateau_ends_on_drop, compiled=use_compiled)
            elevated_count = int(np.count_nonzero(elevated))
            training &= ~elevated
        stats.update(candidates=int(candidates), steep_line_candidates=int(steep_count),
                     elevated_candidates=elevated_count, lines=int(lines.line_count.size))
        return training

    def _fit_ground_model(self, grid: RadialGrid, lines: LineSegments, training,
                          stats: dict) -> GroundModel:
        """Stage ``gp_fit``: length factors, the anchor, the GP, robust learning of theta."""
        p, use_compiled = self._params, self._backend == 'numba'
        d = frame_length_factors(lines.slope, grid.density, grid.candidate_r, training, p,
                                 use_compiled)
        ground_anchor = mean = None
        if anchor.STAGE.on(p):
            ground_anchor = anchor.make_anchor(grid.candidate_index, grid.candidate_z, training,
                                               lines, d, p.anchor_std_m, use_compiled)
            stats['anchor_height_m'] = ground_anchor.height_m
            if p.prior_mean_at_anchor:
                mean = anchor.prior_mean(ground_anchor, grid.candidate_z[training])
        gp = FrameGP(grid.candidate_r, grid.candidate_z, d, training, anchor=ground_anchor,
                     backend=self._backend, mean=mean)
        gp, sol, theta, rejected = self._fit_robustly(gp, stats)
        self._theta = Hyperparameters(*(float(v) for v in theta))
        # the GP's grid slots are the training candidates, less the rejected ones
        trained = training & ~rejected
        stats['outlier_candidates'] = int(np.count_nonzero(rejected))
        stats['training_candidates'] = int(np.count_nonzero(trained))
        default_height = ground_anchor.height_m if ground_anchor is not None else gp.mean
        return GroundModel(gp, sol, theta, trained, rejected, d, default_height)

    def _fit_robustly(self, gp: FrameGP, stats: dict):
        """Outlier pass at the warm-started theta, theta learning, outlier pass at the new
        theta: two passes, so that an outlier pair masking each other in the first is caught in
        the second. Returns (final GP, its solution, theta, outliers (M, N))."""
        theta = np.asarray(self._theta, dtype=np.float64)
        rejected = np.zeros(gp.shape, dtype=bool)
        if not gp.num_points:
            return gp, None, theta, rejected
        gp, sol, rejected = self._reject_outliers(gp, gp.solve(theta), rejected)
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
        if not all(a == b or abs(a - b) <= 1e-8 + 1e-5 * abs(b)
                   for a, b in zip(new_theta.tolist(), theta.tolist())):
            theta = new_theta
            sol = gp.solve(theta)
        gp, sol, rejected = self._reject_outliers(gp, sol, rejected)
        stats['log_marginal_likelihood'] = float(sol.lml)
        stats['cholesky_fallbacks'] = gp.cholesky_fallbacks
        self._backend = gp.backend  # 'numpy' for good once the compiled kernel failed
        return gp, sol, theta, rejected

    def _reject_outliers(self, gp: FrameGP, sol: GPSolution, rejected):
        if not outliers.STAGE.on(self._params):
            return gp, sol, rejected
        return outliers.reject_outliers(gp, sol, rejected, self._params)

    # --- theta's bounds and the learning budget ------------------------------------------------
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
