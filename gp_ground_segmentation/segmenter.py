"""GroundSegmenter: radial grid -> line-segments -> whole-frame GP -> per-point labels.

TEMPORARY STUB: the API below is final; the body is being written (issue 3).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np

from .params import SegmenterParams


class Hyperparameters(NamedTuple):
    """GP hyperparameters theta shared by all segments of a frame."""

    sigma_f: float  # signal std (m)
    gain: float  # a in L_i = a * d_i
    sigma_n: float  # noise std (m)


@dataclass
class SegmentationResult:
    """Output of ``GroundSegmenter.segment`` for one frame of N points."""

    ground_mask: np.ndarray  # bool (N,): valid and ground
    valid_mask: np.ndarray  # bool (N,): finite and not exactly (0, 0, 0)
    ground_height: np.ndarray  # float64 (N,): predicted ground z at the point's (segment, r); NaN if undefined
    hyperparameters: Hyperparameters
    timings_ms: dict = field(default_factory=dict)  # stage -> milliseconds, plus 'total'
    stats: dict = field(default_factory=dict)  # counters: candidates, cholesky fallbacks, ...
    details: Optional[object] = None  # intermediate arrays when segment(..., details=True)

    @property
    def obstacle_mask(self) -> np.ndarray:
        """Valid points that are not ground."""
        return self.valid_mask & ~self.ground_mask

    @property
    def num_invalid(self) -> int:
        """Points that are NaN/Inf or the (0, 0, 0) no-return value: neither ground nor obstacle."""
        return int(self.valid_mask.size - np.count_nonzero(self.valid_mask))


def valid_points_mask(xyz: np.ndarray) -> np.ndarray:
    """Finite and not exactly (0, 0, 0), the no-return value of organized drivers (Ouster)."""
    finite = np.isfinite(xyz).all(axis=1)
    origin = (xyz == 0).all(axis=1)
    return finite & ~origin


class GroundSegmenter:
    """Stateful segmenter: theta is warm-started from one frame to the next."""

    def __init__(self, params: SegmenterParams | None = None):
        self._params = (params or SegmenterParams()).validate()
        self._theta = Hyperparameters(self._params.sigma_f_init_m,
                                      self._params.length_scale_gain_init,
                                      self._params.sigma_n_init_m)

    @property
    def params(self) -> SegmenterParams:
        return self._params

    @property
    def hyperparameters(self) -> Hyperparameters:
        return self._theta

    def segment(self, points: np.ndarray, details: bool = False) -> SegmentationResult:
        t0 = time.perf_counter()
        xyz = np.asarray(points)[:, :3].astype(np.float64)
        valid = valid_points_mask(xyz)
        height = np.full(len(xyz), np.nan)
        if valid.any():
            height[valid] = np.median(xyz[valid, 2])
        ground = valid & (xyz[:, 2] - np.nan_to_num(height) <= 0.2)
        return SegmentationResult(ground, valid, height, self._theta,
                                  {'total': (time.perf_counter() - t0) * 1e3})
