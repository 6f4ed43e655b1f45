# SPDX-License-Identifier: Apache-2.0
"""Rules that are ours, not the paper's, kept apart so each can be read, tested and switched off.

Each is a function from arrays to a mask or a height and has a ``use_*`` switch in
``SegmenterParams``; ``segmenter.GroundSegmenter`` composes them with the paper's stages.

* :func:`elevated_plateaus` (``use_elevated_plateaus``): candidates on an obstacle top whose
  ground is occluded do not train the GP. README "How it works" gives its measured effect.
* :func:`ground_under_sensor` (``use_anchor``): height of the ground under the vehicle, given
  to the GP as one shared extra training point at r = 0 in every segment.
* :func:`outlier_candidates` (``use_outlier_rejection``): leave-one-out residual tests that
  drop below-ground reflection noise and obstacle tops from the training set.

:func:`steep_line_candidates` is the paper's reading ("large sloped line-segments relate to
non-ground structures"), not an addition; it lives here because it is a mask over the
candidates like the others, applied by the segmenter after Algorithm 1.
"""

from __future__ import annotations

import numpy as np

from .lines import relative_to_first


def steep_line_candidates(slope: np.ndarray, max_slope: float) -> np.ndarray:
    """(M, N) bool: candidates whose line is steeper than zeta_b (NaN slopes are not)."""
    with np.errstate(invalid='ignore'):
        return slope > max_slope


def elevated_plateaus(cand_r: np.ndarray, cand_z: np.ndarray, slope_before: np.ndarray, *,
                      step_up_m: float, max_slope: float, max_gap_m: float) -> np.ndarray:
    """(M, N) bool: candidates on a plateau entered by a steep step up (an obstacle's top).

    A state machine per segment over its candidates in order of r (all segments in lock-step):

    * enter on a step up from the previous candidate that rises more than ``step_up_m`` with a
      chord slope above ``max_slope`` (a curb is lower than the step, a ramp flatter);
    * stay while elevated: the entering candidate and those after it are flagged;
    * leave (that candidate is not flagged) when the candidate comes back down to within
      ``step_up_m`` of the ground before the step, extrapolated from the last candidate before
      the step along ``slope_before`` there (the slope of the line that ended at the step; 0
      when that line had fewer than two points), or drops more than ``step_up_m`` from the
      previous candidate, or lies more than ``max_gap_m`` beyond it (the far edge of the
      obstacle or its shadow: whatever is seen beyond is ground again). The next candidate
      may enter again.

    ``slope_before`` is ``LineSegments.slope_before``. Heights are taken relative to each
    segment's first candidate, as in ``lines.extract_lines``.
    """
    present, rr, zz, _, _ = relative_to_first(cand_r, cand_z)
    m_count, n_count = cand_r.shape
    last_r = np.full(m_count, np.nan)
    last_z = np.full(m_count, np.nan)
    elevated_now = np.zeros(m_count, dtype=bool)
    base_r = np.zeros(m_count)  # ground r, z and slope just before the step up
    base_z = np.zeros(m_count)
    base_slope = np.zeros(m_count)
    elevated = np.zeros((m_count, n_count), dtype=bool)
    with np.errstate(invalid='ignore'):  # NaN (no previous candidate) compares False
        for k in range(n_count):
            has = present[:, k]
            if not has.any():
                continue
            r, z = rr[:, k], zz[:, k]
            dr, rise = r - last_r, z - last_z
            started = has & np.isfinite(last_r)
            chord = rise / np.maximum(dr, 1e-6)
            enter = started & (rise > step_up_m) & (chord > max_slope) & ~elevated_now
            if enter.any():
                line_slope = np.where(np.isfinite(slope_before[:, k]), slope_before[:, k], 0.0)
                base_r = np.where(enter, last_r, base_r)
                base_z = np.where(enter, last_z, base_z)
                base_slope = np.where(enter, line_slope, base_slope)
            if elevated_now.any():
                back_down = z <= base_z + base_slope * (r - base_r) + step_up_m
                leave = has & elevated_now & ((rise < -step_up_m) | back_down | (dr > max_gap_m))
                elevated_now = (elevated_now | enter) & ~leave
            else:
                elevated_now = enter
            elevated[:, k] = has & elevated_now
            last_r = np.where(has, r, last_r)
            last_z = np.where(has, z, last_z)
    return elevated


def ground_under_sensor(cand_z: np.ndarray, training: np.ndarray, line_id: np.ndarray,
                        line_count: np.ndarray, intercept: np.ndarray) -> float:
    """Height of the ground under the vehicle (r = 0), shared by all segments (m).

    Every segment starts at the sensor, so all segment GPs meet at r = 0 where the ground is
    the one the vehicle stands on, on a slope too. The first training candidate of each
    segment belongs to a line; where that line has two or more candidates its intercept (the
    line extrapolated to r = 0) is one estimate, and the median over segments is robust to the
    few whose first line is a car or a wall. Fallbacks: without such a line, the median of the
    training candidates' heights; without training candidates, the median of all candidates;
    without candidates, 0.
    """
    rows = np.flatnonzero(training.any(axis=1))
    if rows.size == 0:
        z = cand_z[np.isfinite(cand_z)]
        return float(np.median(z)) if z.size else 0.0
    first = np.argmax(training[rows], axis=1)
    ids = line_id[rows, first]
    usable = (line_count[ids] >= 2) & np.isfinite(intercept[ids])
    if usable.any():
        return float(np.median(intercept[ids[usable]]))
    return float(np.median(cand_z[training]))


def outlier_candidates(loo_residual: np.ndarray, *, above_m: float,
                       below_m: float) -> np.ndarray:
    """Mask of candidates whose leave-one-out residual z_i - mean_{-i} is an outlier.

    Above ``above_m``: an obstacle top, not ground. Below ``-below_m``: below-ground reflection
    noise. NaN residuals (no training candidate there) are not outliers.
    """
    with np.errstate(invalid='ignore'):
        return (loo_residual > above_m) | (loo_residual < -below_m)
