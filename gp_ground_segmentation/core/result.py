# SPDX-License-Identifier: Apache-2.0
"""What ``GroundSegmenter.segment`` returns: labels, heights, theta, timings, the details and the
ground surface of one frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np

from .gp import FrameGP, GPSolution
from .grid import RadialGrid
from .lines import LineSegments
from .surface import GroundSurface

__all__ = ['Hyperparameters', 'SegmentationDetails', 'SegmentationResult']


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
    coupled_lattice: Optional[np.ndarray] = None  # (M, 2, N + 1) ground on each segment's
    # left and right border at its bin edges (use_coupled_surface; ground_mean is halfway)


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
