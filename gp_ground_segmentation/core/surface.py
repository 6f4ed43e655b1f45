# SPDX-License-Identifier: Apache-2.0
"""The ground itself as an output: the GP's elevation surface of one frame, with uncertainty.

The segmenter evaluates the GP posterior at the bin edges of every segment (``predict`` stage);
:class:`GroundSurface` hands that surface out (``SegmentationResult.ground_surface``):

* the prediction points: segment centre azimuth, range r, and x, y, z (posterior mean), z_std in
  the input frame, as (M, N + 1) arrays [segment, bin edge];
* ``supported``: False where no ground candidate backs the estimate (the segment has no
  candidate that trained the GP), so that z there is the prior (the ground under the vehicle,
  or the median training height) and z_std grows towards the prior std sigma_f;
* ``height_at(x, y)``: (z, z_std) at arbitrary points, with the interpolation the labels use
  (segment of the point's azimuth, linear along r between the two bin edges around it); NaN
  outside the grid (beyond that segment's [r_min, r_max], or in a segment with no point).

z_std is the standard deviation of the *latent* ground height at a point, without the sensor noise
sigma_n: it says how well the ground height is known there, not how far a single measured ground
point may scatter around it (add sigma_n^2 to the variance for that). Two parts, combined in
quadrature: the GP's posterior std of the segment's ground, sqrt(k** - k*^T A^-1 k*)
(``gp_std``), and the spread of the ground across the segment (``across_segment_std``): the
surface is one z(r) per segment, so where the ground slopes across the beams a point off the
segment's centre line lies above or below it, by an amount read from the neighbouring segments.
The GP part alone covers too little of the true ground within +-2 z_std on inclines and in
valleys; with both parts the coverage is as asked (benchmarks/RESULTS.md, "Ground surface").

Calibration choice, the ground offset: the GP is trained on the *lowest* point of every bin,
which lies below the ground by the lower tail of the points' scatter. That offset is not one
number: it grows where rays hit the terrain steeply (ramps facing the sensor, hills) and where a
segment spans a cross slope (its lowest points sit on the downhill side): a few cm
(benchmarks/RESULTS.md, "Ground surface"). The labels keep
the GP mean (``SegmentationResult.ground_height``; their threshold was chosen with it), but the
surface is meant to be *the* ground, so its z is the GP mean plus ``ground_offset``: at every bin
edge, the mean height above the labels' z_hat of the points labelled ground in the two bins
beside it (points on the ground scatter symmetrically about it), each height clipped to the
frame's median +- 3 sigma_n so that a few obstacle points called ground cannot drag it; edges
with no such point get the frame's median. That median is taken over an evenly strided sample of
at most 8192 of the residuals (all of them in a smaller frame): it only centres a band 6 sigma_n
wide, and the sample's median is within a few millimetres of the full one at a fraction of the
cost. No truth and no tuned constant is involved (3 sigma is the usual Gaussian outlier bound).

Everything the labels do not need is computed on first access only: x, y, azimuth, and z_std when
the threshold did not use the std (``use_std_threshold`` false, the default), and the
ground offset.
"""

from __future__ import annotations

import contextlib
from functools import cached_property, lru_cache
from typing import Callable, Optional

import numpy as np

from .compiled import Stage, Twin, kernel, sort_in_place
from .gp import numpy_blas_limit
from .grid import bin_edges, segment_of
from .labels import _rise_compiled, cross_segment_rise
from .predict import ground_at_bin_edges
from .sensor_frame import SensorPose

# Tolerance (in bins) of height_at's range test: round-off between the grid's r and the one
# recomputed here must not drop a point at r_min or r_max.
_RANGE_TOLERANCE_BINS = 1e-4
# height_at with a tilted sensor pose: fixed-point steps finding where the input frame's
# vertical through (x, y) meets the ground; each step shrinks the error by about
# tan(tilt) * ground slope (< 0.05 for 10 degrees on a 15 % slope)
_TILT_ITERATIONS = 6
# across_segment_std: labels.cross_segment_rise caps the step at this slope times the
# segment's width; the spread of the ground is not capped
_UNCAPPED_SLOPE = 1e6


class GroundSurface:
    """GP ground surface at the bin edges of one frame's radial grid (module docstring).

    Read-only: arrays are (M, N + 1) [segment, bin edge] unless said otherwise.
    """

    def __init__(self, segment_r_min: np.ndarray, bin_width: np.ndarray,
                 segment_has_points: np.ndarray, mean: np.ndarray,
                 segment_supported: np.ndarray, std: Optional[np.ndarray] = None,
                 compute_std: Optional[Callable[[], np.ndarray]] = None,
                 compute_offset: Optional[Callable[[], np.ndarray]] = None,
                 pose: SensorPose = SensorPose(), compiled: bool = True,
                 borders: Optional[np.ndarray] = None):
        """``segment_r_min``, ``bin_width``, ``segment_has_points``, ``segment_supported``:
        (M,) grid geometry and flags; ``mean`` (M, N + 1) posterior mean at the bin edges.
        ``std`` is the posterior std there, or None and ``compute_std()`` returns it when first
        read (it costs a GP variance evaluation). ``compute_offset()`` returns the ground offset
        (m, scalar or (M, N + 1)) when first needed; None: no offset. The grid and ``mean``
        are in the levelled sensor frame of ``pose`` (sensor_frame.py); x, y, z and height_at
        are in the input's frame. ``compiled``: :meth:`points` in one numba pass (the same
        values as its numpy reference) unless told otherwise. ``borders``: (M, 2, N + 1) the
        ground on each segment's left and right border (the coupled surface,
        coupled_surface.py; ``mean`` is then halfway between them): height_at then
        interpolates in azimuth between them, as the labels do."""
        if std is None and compute_std is None:
            raise ValueError('GroundSurface needs std or compute_std')
        self._r_min = np.asarray(segment_r_min, dtype=np.float64)
        self._width = np.asarray(bin_width, dtype=np.float64)
        self._has_points = np.asarray(segment_has_points, dtype=bool)
        self._mean = np.asarray(mean, dtype=np.float64)
        self._segment_supported = np.asarray(segment_supported, dtype=bool)
        self._std = std
        self._compute_std = compute_std
        self._compute_offset = compute_offset
        self._pose = pose
        self._compiled = bool(compiled)
        self._borders = None if borders is None else np.asarray(borders, dtype=np.float64)

    @classmethod
    def empty(cls, num_segments: int, num_bins: int) -> 'GroundSurface':
        """The surface of a frame without valid points: nothing supported, height_at all NaN."""
        m, n = int(num_segments), int(num_bins)
        nan = np.full((m, n + 1), np.nan)
        return cls(np.zeros(m), np.ones(m), np.zeros(m, bool), nan, np.zeros(m, bool), nan)

    # --- shape -------------------------------------------------------------------------------
    @property
    def num_segments(self) -> int:
        return int(self._mean.shape[0])

    @property
    def num_bins(self) -> int:
        return int(self._mean.shape[1] - 1)

    # --- the prediction points ---------------------------------------------------------------
    @cached_property
    def r(self) -> np.ndarray:
        """Range of each prediction point: the bin edges of its segment (m)."""
        return bin_edges(self._r_min, self._width, self.num_bins)

    @property
    def _segment_centre(self) -> np.ndarray:
        """(M, 1) azimuth of each segment's centre (rad, in (-pi, pi)); read-only."""
        return _segment_centres(self.num_segments)[0]

    @cached_property
    def azimuth(self) -> np.ndarray:
        """Azimuth of each prediction point: its segment's centre (rad, in (-pi, pi))."""
        return np.broadcast_to(self._segment_centre, self._mean.shape)

    @cached_property
    def x(self) -> np.ndarray:
        """x of each prediction point in the input frame (m)."""
        if self._pose.has_rotation:
            return self._tilted_xyz[0]
        return self._level_x + self._pose.x

    @cached_property
    def y(self) -> np.ndarray:
        """y of each prediction point in the input frame (m)."""
        if self._pose.has_rotation:
            return self._tilted_xyz[1]
        return self._level_y + self._pose.y

    @property
    def _centre_cos_sin(self):
        """(M, 1) cosine and sine of the segment centres (numpy's, for every path)."""
        return _segment_centres(self.num_segments)[1:]

    @cached_property
    def _level_x(self) -> np.ndarray:
        # the cosine of the M centres, not of all M x (N + 1) points: the same numbers
        return self.r * self._centre_cos_sin[0]

    @cached_property
    def _level_y(self) -> np.ndarray:
        return self.r * self._centre_cos_sin[1]

    @cached_property
    def _tilted_xyz(self):
        """x, y, z of the prediction points in a tilted input frame: p_C = R^T p_L + t."""
        return _tilted(self._level_x, self._level_y, self._level_z, self._pose.rotation(),
                       (self._pose.x, self._pose.y, self._pose.z))

    @cached_property
    def ground_offset(self) -> np.ndarray:
        """Height (m) of the ground above the GP mean at each prediction point (module
        docstring); 0 when no point was labelled ground."""
        if self._compute_offset is None:
            return np.zeros(self._mean.shape)
        offset = np.broadcast_to(np.asarray(self._compute_offset(), dtype=np.float64),
                                 self._mean.shape)
        self._compute_offset = None
        return np.where(np.isfinite(offset), offset, 0.0)

    @cached_property
    def z(self) -> np.ndarray:
        """Ground height at each prediction point (m, input frame): the GP posterior mean plus
        the ground offset."""
        if self._pose.has_rotation:
            return self._tilted_xyz[2]
        return self._level_z + self._pose.z

    @cached_property
    def _level_z(self) -> np.ndarray:
        """The ground height in the levelled sensor frame: the GP mean plus the ground offset."""
        return self._mean + self.ground_offset

    @cached_property
    def z_std(self) -> np.ndarray:
        """Std of the ground height at each prediction point (m; without sensor noise sigma_n):
        the GP's posterior std of its segment's ground, combined with the spread of the ground
        across the segment (module docstring)."""
        return np.hypot(self.gp_std, self.across_segment_std)

    @property
    def gp_std(self) -> np.ndarray:
        """The GP's posterior std of the latent ground height of each segment at its bin edges
        (m): how well the segment's z(r) is known."""
        if self._std is None:
            self._std = np.asarray(self._compute_std(), dtype=np.float64)
            self._compute_std = None
        return self._std

    @cached_property
    def across_segment_std(self) -> np.ndarray:
        """(M, N + 1) std (m) of the true ground around the surface across each segment.

        The surface is one z(r) per segment: a point off the segment's centre line lies on
        ground that differs by the slope across the segment times its offset. That slope is
        read from the neighbouring segments' surface at the same r, as the cross-slope
        threshold reads it (labels.cross_segment_rise): only where the ground rises on one
        side of the segment and falls on the other, by the smaller of the two steps s; the
        ground then spans about s across the segment's width, and a point anywhere across it
        (uniformly) is off the centre by a std of s / (2 sqrt 3). A single raised or lowered
        neighbour (a fit bent by an obstacle, the noise of two independent fits on flat ground),
        a missing neighbour and a segment without support (at the prior, whose std sigma_f
        says it) add nothing. The coupled surface (``borders``) follows the ground across the
        segment itself: nothing either.
        """
        if self._borders is not None:
            return np.zeros(self._mean.shape)
        return _across_segment_std(self.r, self._level_z, self._segment_supported)

    @cached_property
    def supported(self) -> np.ndarray:
        """True where ground candidates back the estimate (their segment trained the GP)."""
        return np.broadcast_to(self._segment_supported[:, None], self._mean.shape)

    def points(self, supported_only: bool = True,
               compiled: Optional[bool] = None) -> np.ndarray:
        """(K, 4) float32 x, y, z, z_std of the prediction points (the supported ones); points
        whose values are not finite in float32 (absurdly far returns) are left out.

        ``compiled`` (default: the constructor's): one numba pass from the grid, the GP mean,
        the ground offset and the GP std straight to the float32 rows (the node's surface
        cloud), without the x, y, z, z_std arrays and their temporaries; the same
        operations in the same order as the numpy reference, so the same values, bit for
        bit."""
        use_compiled = self._compiled if compiled is None else bool(compiled)
        pose = self._pose
        rotated = bool(pose.has_rotation)
        cos_c, sin_c = self._centre_cos_sin
        return POINTS.run(use_compiled, self._r_min, self._width, self._mean,
                          self.ground_offset, self.gp_std, self._segment_supported,
                          cos_c.reshape(-1), sin_c.reshape(-1),
                          pose.rotation() if rotated else np.eye(3),
                          np.array([pose.x, pose.y, pose.z], dtype=np.float64), rotated,
                          bool(supported_only))

    # --- anywhere ----------------------------------------------------------------------------
    def height_at(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(z, z_std) of the ground at points (x, y) of the input frame (m), same shape as x.

        Linear interpolation along r between the bin edges of the point's segment, exactly as
        the labels' ground height; NaN outside the grid's range (see the module docstring).
        With a tilted sensor pose, z is where the input frame's vertical through (x, y) meets
        that ground (z_std is the levelled frame's).
        """
        pose = self._pose
        if pose.is_identity:
            return self._level_height_at(x, y)
        x, y = (np.asarray(v, dtype=np.float64) - t for v, t in ((x, pose.x), (y, pose.y)))
        if not pose.has_rotation:
            z, z_std = self._level_height_at(x, y)
            return np.asarray(z + pose.z), z_std
        rot = pose.rotation()
        x, y = np.broadcast_arrays(x, y)
        z = np.zeros(x.shape)  # first guess: the sensor's height (relative to t)
        for step in range(_TILT_ITERATIONS):
            level = [rot[i, 0] * x + rot[i, 1] * y + rot[i, 2] * z for i in range(2)]
            # a guess beyond the grid's range takes its end's height; the last step decides
            ground, z_std = self._level_height_at(*level,
                                                  beyond_range=step < _TILT_ITERATIONS - 1)
            # (x, y, z) - t lies on the ground where its levelled z equals the ground there
            z = (ground - rot[2, 0] * x - rot[2, 1] * y) / rot[2, 2]
            z = np.where(np.isnan(z), 0.0, z) if step < _TILT_ITERATIONS - 1 else z
        return np.asarray(z + pose.z), z_std

    def _level_height_at(self, x, y, beyond_range: bool = False):
        """height_at in the levelled sensor frame; ``beyond_range``: the height at the nearest
        end of the grid's range instead of NaN beyond it."""
        x, y = np.asarray(x), np.asarray(y)
        # the segment as the grid found it: from the points' own values (float32 input stays
        # float32 values), decided in float64 by segment_of
        angle_dtype = np.result_type(x.dtype, y.dtype, np.float32)
        shape = np.broadcast_shapes(x.shape, y.shape)
        x, y = (np.broadcast_to(v, shape).ravel().astype(angle_dtype) for v in (x, y))
        finite = np.isfinite(x) & np.isfinite(y)
        seg = segment_of(np.where(finite, x, 0), np.where(finite, y, 0), self.num_segments)
        x, y = x.astype(np.float64), y.astype(np.float64)
        z_out = np.full(x.shape, np.nan)
        std_out = np.full(x.shape, np.nan)
        position = (np.hypot(x, y) - self._r_min[seg]) / self._width[seg]
        n = self.num_bins
        inside = finite & self._has_points[seg]
        if not beyond_range:
            inside &= ((position >= -_RANGE_TOLERANCE_BINS)
                       & (position <= n + _RANGE_TOLERANCE_BINS))
        seg, position = seg[inside], np.clip(position[inside], 0.0, n)
        bins = np.minimum(position.astype(np.intp), n - 1)
        frac = position - bins
        for values, out in ((self._level_z, z_out), (self.z_std, std_out)):
            low = values[seg, bins]
            out[inside] = low + frac * (values[seg, bins + 1] - low)
        if self._borders is not None:  # between the segment's two borders, as the labels
            z_out[inside] = self._between_borders(x[inside], y[inside], seg, bins, frac)
        return z_out.reshape(shape), std_out.reshape(shape)

    def _between_borders(self, x, y, seg, bins, frac):
        """The coupled surface's height (plus the ground offset) at points of segments
        ``seg``, bins ``bins`` and positions ``frac`` in them: linear along r on the segment's
        two borders, then in azimuth between them (coupled_surface.py)."""
        offset = self.ground_offset
        offset = (np.broadcast_to(offset, self._mean.shape) if np.ndim(offset) else
                  np.full(self._mean.shape, float(offset)))
        sides = []
        for side in (0, 1):
            values = self._borders[:, side] + offset
            low = values[seg, bins]
            sides.append(low + frac * (values[seg, bins + 1] - low))
        w = (np.arctan2(y, x) + np.pi) * (self.num_segments / (2.0 * np.pi)) - seg
        return sides[0] + np.clip(w, 0.0, 1.0) * (sides[1] - sides[0])


def frame_surface(model, grid, edges, mean, std, z, ground, z_hat, k_star, pose,
                  compiled: bool = True, borders=None) -> GroundSurface:
    """The GroundSurface of one frame from its ``predict.GroundModel``, RadialGrid ``grid``,
    the (M, N + 1) bin ``edges`` and the posterior ``mean`` and ``std`` there (None: computed
    from the prediction's ``k_star`` when first read), and the valid points' heights ``z``,
    labels ``ground`` and ground heights ``z_hat`` (for the offset, when first read). The
    deferred computations keep these alive, not the rest of the per-point grid."""
    point_segment, point_bin = grid.point_segment, grid.point_bin
    m_count, n_bins = grid.num_segments, grid.num_bins

    def compute_std():
        std = np.full(edges.shape, model.theta[0])  # the prior std where no GP segment is
        if model.solution is None:
            return std
        kernel = k_star
        if kernel is None:  # no per-segment prediction ran (the coupled surface): run it now
            kernel = ground_at_bin_edges(model, edges, False, compiled)[3]
        numpy_solution = model.gp.backend != 'numba' or model.solution.gradient is None
        limit = numpy_blas_limit() if numpy_solution else contextlib.nullcontext()
        with limit, np.errstate(over='ignore'):
            std[model.gp.segments] = model.gp.std_from_kernel(model.solution, kernel)
        return std

    def compute_offset():
        return ground_offsets(z, z_hat, ground, point_segment, point_bin, m_count, n_bins,
                              model.theta[2], compiled=compiled)

    return GroundSurface(grid.segment_r_min, grid.bin_width, grid.count.sum(axis=1) > 0, mean,
                         model.training.any(axis=1), std,
                         compute_std if std is None else None, compute_offset, pose,
                         compiled=compiled, borders=borders)


@lru_cache(maxsize=8)
def _segment_centres(num_segments: int):
    """(M, 1) azimuth of the segment centres, their cosine and sine: read-only, made once per
    M (the same numbers every frame)."""
    m = int(num_segments)
    centre = (-np.pi + (np.arange(m) + 0.5) * (2.0 * np.pi / m))[:, None]
    out = (centre, np.cos(centre), np.sin(centre))
    for values in out:
        values.flags.writeable = False
    return out


def _tilted(level_x, level_y, level_z, rotation, translation):
    """x, y, z in a tilted input frame of points (x, y, z) of the levelled sensor frame:
    p_C = R^T p_L + t."""
    p_l = (level_x, level_y, level_z)
    return tuple(sum(rotation[j, i] * p_l[j] for j in range(3)) + translation[i]
                 for i in range(3))


def _across_segment_std(r, level_z, supported, compiled: bool = True):
    """:attr:`GroundSurface.across_segment_std` of the surface ``level_z`` at ranges ``r``
    ((M, N + 1), levelled frame) with the (M,) ``supported`` segments."""
    level = np.where(supported[:, None], level_z, np.nan)
    # the threshold's rule, uncapped (a slope cap of 1e6: finite, so r = 0 stays 0)
    step = cross_segment_rise(r, level, _UNCAPPED_SLOPE, compiled=compiled)
    # a segment without support sits at the prior, whose std (sigma_f) already says it
    step = np.where(supported[:, None], step, 0.0)
    return step / (2.0 * np.sqrt(3.0))


def _points_numpy(r_min, width, mean, offset, gp_std, supported, cos_c, sin_c, rotation,
                  translation, rotated, supported_only):
    """The numpy reference of :func:`_points_loop`: the properties' x, y, z, z_std as float32
    rows of the (supported) segments, the rows that are not finite left out."""
    r = bin_edges(r_min, width, mean.shape[1] - 1)
    level = (r * cos_c[:, None], r * sin_c[:, None], mean + offset)
    if rotated:
        xyz = _tilted(*level, rotation, translation)
    else:
        xyz = tuple(level[i] + translation[i] for i in range(3))
    z_std = np.hypot(gp_std, _across_segment_std(r, level[2], supported))
    rows = np.flatnonzero(supported) if supported_only else slice(None)
    out = np.empty(mean[rows].shape + (4,), dtype=np.float32)
    with np.errstate(over='ignore', invalid='ignore'):
        for i, column in enumerate((*xyz, z_std)):
            out[..., i] = column[rows]
    out = out.reshape(-1, 4)
    return out[np.isfinite(out).all(axis=1)]


def _points_loop(r_min, width, mean, offset, gp_std, supported, cos_c, sin_c, rotation,
                 translation, rotated, supported_only):
    """:meth:`GroundSurface.points` in one pass (compiled with numba): per prediction point the
    reference's x, y, z (r, the GP mean plus the ground offset, the pose), z_std (the GP std and
    the across-segment spread from the uncapped cross-segment rise, labels._rise_loop) in
    float64, the same operations in the same order, then the float32 row, kept
    when finite. ``cos_c``, ``sin_c``: (M,) numpy's cosine and sine of the segment centres;
    ``rotation``, ``translation``: the pose's R and t, R used when ``rotated``."""
    m_count, n_edges = mean.shape
    r = np.empty((m_count, n_edges))
    level = np.empty((m_count, n_edges))  # the supported segments' ground, NaN elsewhere
    for s in range(m_count):
        for k in range(n_edges):
            r[s, k] = r_min[s] + k * width[s]
            level[s, k] = mean[s, k] + offset[s, k] if supported[s] else np.nan
    rise = _rise_compiled(r, level, _UNCAPPED_SLOPE)
    divisor = 2.0 * np.sqrt(3.0)
    rows = 0
    for s in range(m_count):
        if supported[s] or not supported_only:
            rows += 1
    out = np.empty((rows * n_edges, 4), np.float32)
    kept = 0
    for s in range(m_count):
        if supported_only and not supported[s]:
            continue
        for k in range(n_edges):
            level_x = r[s, k] * cos_c[s]
            level_y = r[s, k] * sin_c[s]
            level_z = mean[s, k] + offset[s, k]
            if rotated:  # p_C = R^T p_L + t, summed as the reference's sum() from 0
                x = (0.0 + rotation[0, 0] * level_x + rotation[1, 0] * level_y
                     + rotation[2, 0] * level_z + translation[0])
                y = (0.0 + rotation[0, 1] * level_x + rotation[1, 1] * level_y
                     + rotation[2, 1] * level_z + translation[1])
                z = (0.0 + rotation[0, 2] * level_x + rotation[1, 2] * level_y
                     + rotation[2, 2] * level_z + translation[2])
            else:
                x = level_x + translation[0]
                y = level_y + translation[1]
                z = level_z + translation[2]
            step = rise[s, k] if supported[s] else 0.0
            z_std = np.hypot(gp_std[s, k], step / divisor)
            fx, fy, fz, fs = np.float32(x), np.float32(y), np.float32(z), np.float32(z_std)
            if np.isfinite(fx) and np.isfinite(fy) and np.isfinite(fz) and np.isfinite(fs):
                out[kept, 0] = fx
                out[kept, 1] = fy
                out[kept, 2] = fz
                out[kept, 3] = fs
                kept += 1
    return out[:kept]


def ground_offsets(z, z_hat, ground, segment, bin_index, num_segments: int, num_bins: int,
                   noise_std: float, compiled: bool = True) -> np.ndarray:
    """(M, N + 1) ground offset at the bin edges (module docstring) from the labels: over the
    valid points, ``z`` (m), the labels' ground height ``z_hat`` (m), the ``ground`` mask and
    each point's ``segment`` and ``bin_index`` in the grid; ``noise_std`` sigma_n (m) bounds each
    residual z - z_hat to the frame's median (of a strided sample, module docstring) +- 3
    sigma_n.

    ``compiled``: one numba kernel (when numba imports) gathers the residuals, selects their
    median and sums them per bin, instead of the numpy reference's gathers, ``np.median`` and
    bincounts; both add the same numbers in the same order, so the outputs are equal.
    """
    m, n = int(num_segments), int(num_bins)
    args = (np.asarray(z), np.asarray(z_hat), np.asarray(ground, dtype=bool),
            np.asarray(segment), np.asarray(bin_index), m, n, 3.0 * float(noise_std))
    out = OFFSETS.run(compiled, *args)
    # None: the kernel met a residual that is not finite, which the reference handles
    return _ground_offsets_numpy(*args) if out is None else out


def _ground_offsets_numpy(z, z_hat, ground, segment, bin_index, m, n, band):
    """The numpy reference of :func:`ground_offsets`."""
    residual = z[ground].astype(np.float64) - z_hat[ground]
    if residual.size == 0:
        return np.zeros((m, n + 1))
    stride = max(1, -(-residual.size // _MEDIAN_SAMPLE))  # the sample of the module docstring
    centre = float(np.median(residual[::stride]))
    return _edge_means_numpy(residual, segment[ground], bin_index[ground], m, n, centre,
                             centre - band, centre + band)


def _ground_offsets_kernel(z, z_hat, ground, segment, bin_index, m, n, band):
    """Compiled :func:`ground_offsets`: None when a residual is not finite (np.median and
    np.clip treat NaN differently from this selection; the reference decides then)."""
    residual = np.empty(ground.size)  # the ground points' z - z_hat, compacted
    cell = np.empty(ground.size, np.int64)  # and their flat grid cell
    count = 0
    for i in range(ground.size):
        if ground[i]:
            value = np.float64(z[i]) - z_hat[i]
            if not np.isfinite(value):
                return None
            residual[count] = value
            cell[count] = segment[i] * n + bin_index[i]
            count += 1
    if count == 0:
        return np.zeros((m, n + 1))
    residual = residual[:count]
    stride = max(1, -(-count // _MEDIAN_SAMPLE))  # the reference's sample
    centre = _median_of(residual[::stride].copy())
    sums = np.zeros(m * n)
    counts = np.zeros(m * n)
    low, high = centre - band, centre + band
    # the reference's bincount order, point by point; a run of points in one cell (a scan's
    # points come ring by ring, ~15 in a row per bin) adds up in a register, not through
    # memory: the same additions in the same order
    current = cell[0]
    total = 0.0
    number = 0.0
    for k in range(count):
        if cell[k] != current:
            sums[current] = total
            counts[current] = number
            current = cell[k]
            total = sums[current]
            number = counts[current]
        total += min(max(residual[k], low), high)
        number += 1.0
    sums[current] = total
    counts[current] = number
    sums = sums.reshape(m, n)
    counts = counts.reshape(m, n)
    return _sums_to_edges(sums, counts, m, n, centre)


# ground_offsets: the residuals' median is taken over an evenly strided sample of at most this
# many of them (module docstring)
_MEDIAN_SAMPLE = 8192

# _median_of: buckets a round of bucketing splits the candidates into; at most this many are
# sorted outright
_MEDIAN_BUCKETS = 2048
_MEDIAN_SORT_SIZE = 64


def _median_of(values):
    """np.median of finite ``values``, exactly, in a few O(size) passes (a third of numpy's
    partition-based time here): bucket the candidates by value between their min and max, keep
    only the bucket that holds the middle rank, repeat until few are left, sort those. The
    order statistic below the middle one, for an even size, is the largest value of the lower
    buckets seen on the way, or in the last sort.

    Plain loops for min, max and the last sort (``compiled.sort_in_place``): numba's ``np.sort``,
    ``.min()`` and ``.max()`` cost a new install seconds of compilation.
    """
    size = values.size
    rank = size // 2  # of the upper middle value, within the candidates
    below = -np.inf  # the largest value ranked below every candidate
    candidates = values
    while True:
        low = candidates[0]
        high = candidates[0]
        for v in candidates:
            if v < low:
                low = v
            elif v > high:
                high = v
        if high == low:
            upper = low
            lower = low if rank > 0 else below
            break
        scale = _MEDIAN_BUCKETS / (high - low)
        if candidates.size > _MEDIAN_SORT_SIZE and np.isfinite(scale):
            kept, passed, below = _bucket_of_rank(candidates, low, scale, rank, below)
            # round-off may put everything in one bucket: then sort, as for a few candidates
            if kept.size < candidates.size:
                candidates = kept
                rank -= passed
                continue
        ordered = candidates.copy()
        sort_in_place(ordered)
        upper = ordered[rank]
        lower = ordered[rank - 1] if rank > 0 else below
        break
    if size % 2 == 1:
        return upper
    return (lower + upper) / 2.0  # as np.median: the mean of the two middle values


def _bucket_of_rank(candidates, low, scale, rank, below):
    """One round of :func:`_median_of`: (the candidates of the bucket holding ``rank``, how
    many lie in lower buckets, ``below`` raised to the largest of those)."""
    counts = np.zeros(_MEDIAN_BUCKETS, np.int64)
    for v in candidates:
        counts[min(int((v - low) * scale), _MEDIAN_BUCKETS - 1)] += 1
    passed = 0
    bucket = 0
    while passed + counts[bucket] <= rank:
        passed += counts[bucket]
        bucket += 1
    kept = np.empty(counts[bucket], candidates.dtype)
    j = 0
    for v in candidates:
        b = min(int((v - low) * scale), _MEDIAN_BUCKETS - 1)
        if b == bucket:
            kept[j] = v
            j += 1
        elif b < bucket and v > below:
            below = v
    return kept, passed, below


def _edge_means_numpy(residual, segment, bin_index, m, n, centre, low, high):
    """Per-edge means of the clipped residuals of the two bins beside each edge (numpy)."""
    clipped = np.clip(residual, low, high)
    key = np.asarray(segment, np.intp) * n + np.asarray(bin_index, np.intp)
    sums = np.bincount(key, weights=clipped, minlength=m * n).reshape(m, n)
    counts = np.bincount(key, minlength=m * n).reshape(m, n).astype(np.float64)
    edge_sums, edge_counts = np.zeros((m, n + 1)), np.zeros((m, n + 1))
    for values, edge in ((sums, edge_sums), (counts, edge_counts)):
        edge[:, :-1] += values  # edge k is the inner edge of bin k ...
        edge[:, 1:] += values  # ... and the outer edge of bin k - 1
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where(edge_counts > 0, edge_sums / edge_counts, centre)


def _sums_to_edges(sums, counts, m, n, centre):
    """Per-edge means of the two bins beside each edge (the reference's order of additions:
    0 + bin k's sum + bin k - 1's sum); ``centre`` where neither bin has a point."""
    out = np.empty((m, n + 1))
    for s in range(m):
        for k in range(n + 1):
            total = 0.0
            count = 0.0
            if k < n:
                total += sums[s, k]
                count += counts[s, k]
            if k > 0:
                total += sums[s, k - 1]
                count += counts[s, k - 1]
            out[s, k] = total / count if count > 0 else centre
    return out


_bucket_of_rank = kernel(_bucket_of_rank) or _bucket_of_rank
_median_of = kernel(_median_of) or _median_of
_sums_to_edges = kernel(_sums_to_edges) or _sums_to_edges


def _offsets_examples(dtype):
    z = np.ones(2, dtype)  # z_hat in the points' precision, as the labels
    index = np.zeros(2, np.int32)
    return [(z, z * 0, np.ones(2, bool), index, index, 2, 2, 0.3)]


def _points_examples(_dtype):
    segments, edges = np.ones(2), np.zeros((2, 3))
    centres = np.ones(2)
    centres.flags.writeable = False  # the segment centres' cosines are shared, read-only
    return [(np.zeros(2), segments, edges, edges, edges, np.ones(2, bool), centres, centres,
             np.eye(3), np.zeros(3), False, True)]


OFFSETS = Twin('ground offsets', _ground_offsets_numpy, kernel(_ground_offsets_kernel),
               _offsets_examples)
# the points kernel calls the compiled rise (None without numba)
POINTS = Twin('surface rows', _points_numpy,
              kernel(_points_loop) if _rise_compiled is not None else None, _points_examples)
STAGES = (Stage('surface', 'ours', None, (OFFSETS, POINTS)),)
