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

z_std is the posterior standard deviation of the *latent* ground height, sqrt(k** - k*^T A^-1 k*),
without the sensor noise sigma_n: it says how well the ground height is known, not how far a
single measured ground point may scatter around it (add sigma_n^2 to the variance for that).

Calibration choice, the lowest-point offset: the GP is trained on the *lowest* point of every
bin, which lies below the ground by the lower tail of the points' noise (about 1.5 cm on the
synthetic scans, 2-3 cm on KITTI; see benchmarks/RESULTS.md, "Ground surface"). The labels keep
that height (``SegmentationResult.ground_height``; their threshold was chosen with it), but the
surface is meant to be *the* ground, so its z is the GP mean plus ``lowest_point_offset``: the
median height above the labels' z_hat of the points labelled ground in the same frame (points
on the ground scatter symmetrically about it; no truth or constant is involved).

Everything the labels do not need is computed on first access only: x, y, azimuth, and z_std when
the threshold did not use the std (``ground_threshold_std_factor`` = 0, the default), and the
lowest-point offset.
"""

from __future__ import annotations

from functools import cached_property
from typing import Callable, Optional

import numpy as np

from .grid import segment_of

# Tolerance (in bins) of height_at's range test: r recomputed in float64 from float32 x, y can
# land a hair outside the [r_min, r_max] the grid computed in float32 for the same point.
_RANGE_TOLERANCE_BINS = 1e-4


class GroundSurface:
    """GP ground surface at the bin edges of one frame's radial grid (module docstring).

    Read-only: arrays are (M, N + 1) [segment, bin edge] unless said otherwise.
    """

    def __init__(self, segment_r_min: np.ndarray, bin_width: np.ndarray,
                 segment_has_points: np.ndarray, mean: np.ndarray,
                 segment_supported: np.ndarray, std: Optional[np.ndarray] = None,
                 compute_std: Optional[Callable[[], np.ndarray]] = None,
                 compute_offset: Optional[Callable[[], float]] = None):
        """``segment_r_min``, ``bin_width``, ``segment_has_points``, ``segment_supported``:
        (M,) grid geometry and flags; ``mean`` (M, N + 1) posterior mean at the bin edges.
        ``std`` is the posterior std there, or None and ``compute_std()`` returns it when first
        read (it costs a GP variance evaluation). ``compute_offset()`` returns the lowest-point
        offset (m) when first needed; None: no offset."""
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
        k = np.arange(self.num_bins + 1)
        return self._r_min[:, None] + k[None, :] * self._width[:, None]

    @cached_property
    def azimuth(self) -> np.ndarray:
        """Azimuth of each prediction point: its segment's centre (rad, in (-pi, pi))."""
        m = self.num_segments
        centre = -np.pi + (np.arange(m) + 0.5) * (2.0 * np.pi / m)
        return np.broadcast_to(centre[:, None], self._mean.shape)

    @cached_property
    def x(self) -> np.ndarray:
        """x of each prediction point in the input frame (m)."""
        return self.r * np.cos(self.azimuth)

    @cached_property
    def y(self) -> np.ndarray:
        """y of each prediction point in the input frame (m)."""
        return self.r * np.sin(self.azimuth)

    @cached_property
    def lowest_point_offset(self) -> float:
        """Height (m) of the ground above the GP mean trained on the lowest points (module
        docstring): the median z - z_hat of the frame's ground points; 0 without them."""
        if self._compute_offset is None:
            return 0.0
        offset = float(self._compute_offset())
        self._compute_offset = None
        return offset if np.isfinite(offset) else 0.0

    @cached_property
    def z(self) -> np.ndarray:
        """Ground height at each prediction point (m, input frame): the GP posterior mean plus
        the lowest-point offset."""
        return self._mean + self.lowest_point_offset

    @property
    def z_std(self) -> np.ndarray:
        """Posterior std of the latent ground height (m; without sensor noise sigma_n)."""
        if self._std is None:
            self._std = np.asarray(self._compute_std(), dtype=np.float64)
            self._compute_std = None
        return self._std

    @cached_property
    def supported(self) -> np.ndarray:
        """True where ground candidates back the estimate (their segment trained the GP)."""
        return np.broadcast_to(self._segment_supported[:, None], self._mean.shape)

    def points(self, supported_only: bool = True) -> np.ndarray:
        """(K, 4) float32 x, y, z, z_std of the prediction points (the supported ones)."""
        keep = self.supported if supported_only else np.ones(self._mean.shape, bool)
        columns = (self.x, self.y, self.z, self.z_std)
        return np.stack([c[keep] for c in columns], axis=1).astype(np.float32)

    # --- anywhere ----------------------------------------------------------------------------
    def height_at(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(z, z_std) of the ground at points (x, y) of the input frame (m), same shape as x.

        Linear interpolation along r between the bin edges of the point's segment, exactly as
        the labels' ground height; NaN outside the grid's range (see the module docstring).
        """
        x, y = np.asarray(x), np.asarray(y)
        # the segment in the points' own precision, as the grid found it (float32 and float64
        # arctan2 disagree for points on a segment border)
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
        inside = (finite & self._has_points[seg] & (position >= -_RANGE_TOLERANCE_BINS)
                  & (position <= n + _RANGE_TOLERANCE_BINS))
        seg, position = seg[inside], np.clip(position[inside], 0.0, n)
        bins = np.minimum(position.astype(np.intp), n - 1)
        frac = position - bins
        for values, out in ((self.z, z_out), (self.z_std, std_out)):
            low = values[seg, bins]
            out[inside] = low + frac * (values[seg, bins + 1] - low)
        return z_out.reshape(shape), std_out.reshape(shape)
