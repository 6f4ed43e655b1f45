# SPDX-License-Identifier: Apache-2.0
"""Stage ``plateau`` [ours, ``use_elevated_plateaus``]: candidates on an elevated plateau do not
train the GP.

A bin whose ground is occluded by an obstacle has the obstacle's top as its lowest point (a car
roof seen over its bonnet, a wall's top): a steep step up from the ground before it. A state
machine per segment follows the candidates in order of r and flags those from such a step up
until the candidates come back down to the ground level (or, ``plateau_ends_on_drop``, drop by
the step) or a gap ends it. ``plateau_from_sensor_ground`` starts every segment from the ground
under the sensor (the anchor height), so a person or car filling a segment next to the sensor
is a step up although no ground candidate precedes it.
"""

from __future__ import annotations

import numpy as np

from .compiled import Stage, Twin, kernel
from .lines import relative_to_first


def elevated_plateaus(cand_r: np.ndarray, cand_z: np.ndarray, slope_before: np.ndarray, *,
                      step_up_m: float, max_slope: float, max_gap_m: float,
                      start_height_m: float | None = None,
                      end_on_drop: bool = True, compiled: bool = True) -> np.ndarray:
    """(M, N) bool: candidates on a plateau entered by a steep step up (an obstacle's top).

    A state machine per segment over its candidates in order of r (all segments in lock-step):

    * enter on a step up from the previous candidate that rises more than ``step_up_m`` with a
      chord slope above ``max_slope`` (a curb is lower than the step, a ramp flatter);
    * stay while elevated: the entering candidate and those after it are flagged;
    * leave (that candidate is not flagged) when the candidate comes back down to within
      ``step_up_m`` of the ground before the step, extrapolated from the last candidate before
      the step along ``slope_before`` there (the slope of the line that ended at the step; 0
      when that line had fewer than two points), or (``end_on_drop``) drops more than
      ``step_up_m`` from the previous candidate, or lies more than ``max_gap_m`` beyond it
      (the far edge of the obstacle or its shadow: whatever is seen beyond is ground again).
      The next candidate may enter again. Without ``end_on_drop`` a drop that stays above the
      ground (a roof down to a bonnet, a wall's top down to a lower wall) keeps the plateau.

    ``start_height_m``: when given, every segment starts from the ground under the sensor,
    a virtual previous candidate at (r = 0, this height) -- so a person or a car filling a
    segment next to the sensor is a step up from the vehicle's own ground even though no
    ground candidate precedes it. None starts at each segment's first candidate.

    ``slope_before`` is ``LineSegments.slope_before``. Heights are taken relative to each
    segment's first candidate, as in ``lines.extract_lines``.

    ``compiled``: a numba loop over bins and segments when numba imports (else, or if it
    fails, the numpy reference, vectorised over the segments); both give the same mask.
    """
    from_sensor = start_height_m is not None
    args = (cand_r, cand_z, np.asarray(slope_before, dtype=np.float64), from_sensor,
            float(start_height_m) if from_sensor else 0.0, float(step_up_m), float(max_slope),
            float(max_gap_m), bool(end_on_drop))
    return PLATEAUS.run(compiled, *args)


def _plateaus_numpy(cand_r, cand_z, slope_before, from_sensor, start_height_m, step_up_m,
                    max_slope, max_gap_m, end_on_drop):
    """The numpy reference of :func:`elevated_plateaus`' state machine (all segments at once).
    """
    present, rr, zz, r0, z0 = relative_to_first(cand_r, cand_z)
    m_count, n_count = present.shape
    last_r = np.full(m_count, np.nan)
    last_z = np.full(m_count, np.nan)
    if from_sensor:
        last_r = -r0
        last_z = start_height_m - z0
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
                drop = (rise < -step_up_m) if end_on_drop else np.zeros_like(has)
                leave = has & elevated_now & (drop | back_down | (dr > max_gap_m))
                elevated_now = (elevated_now | enter) & ~leave
            else:
                elevated_now = enter
            elevated[:, k] = has & elevated_now
            last_r = np.where(has, r, last_r)
            last_z = np.where(has, z, last_z)
    return elevated


def _plateaus_loop(cand_r, cand_z, slope_before, from_sensor, start_height_m, step_up_m,
                   max_slope, max_gap_m, end_on_drop):
    """:func:`_plateaus_numpy` one segment and bin at a time (compiled with numba): the same
    comparisons of the same values, so the same mask. Heights relative to each segment's first
    candidate are taken here, as ``relative_to_first`` does (one numpy pass less)."""
    m_count, n_count = cand_r.shape
    elevated = np.zeros((m_count, n_count), dtype=np.bool_)
    for m in range(m_count):
        r0 = 0.0
        z0 = 0.0
        for k in range(n_count):
            if np.isfinite(cand_r[m, k]) and np.isfinite(cand_z[m, k]):
                r0, z0 = cand_r[m, k], cand_z[m, k]
                break
        prev_r, prev_z = np.nan, np.nan
        if from_sensor:
            prev_r, prev_z = -r0, start_height_m - z0
        elevated_now = False
        base_r = 0.0
        base_z = 0.0
        base_slope = 0.0
        for k in range(n_count):
            if not (np.isfinite(cand_r[m, k]) and np.isfinite(cand_z[m, k])):
                continue
            r, z = cand_r[m, k] - r0, cand_z[m, k] - z0
            dr, rise = r - prev_r, z - prev_z
            # np.maximum(dr, 1e-6): NaN stays NaN
            chord = rise / (dr if (dr >= 1e-6 or np.isnan(dr)) else 1e-6)
            if elevated_now:
                back_down = z <= base_z + base_slope * (r - base_r) + step_up_m
                drop = end_on_drop and rise < -step_up_m
                elevated_now = not (drop or back_down or dr > max_gap_m)
            elif np.isfinite(prev_r) and rise > step_up_m and chord > max_slope:
                elevated_now = True  # enter: the ground before the step is the base
                before = slope_before[m, k]
                base_r, base_z = prev_r, prev_z
                base_slope = before if np.isfinite(before) else 0.0
            elevated[m, k] = elevated_now
            prev_r, prev_z = r, z
    return elevated


def _plateaus_examples(_dtype):
    grid = np.ones((2, 2))
    return [(grid, grid, grid, False, 0.0, 0.3, 1.0, 1.0, False)]


PLATEAUS = Twin('plateau state machine', _plateaus_numpy,
                kernel(_plateaus_loop, error_model='numpy'), _plateaus_examples)
STAGE = Stage('plateaus', 'ours', 'use_elevated_plateaus', (PLATEAUS,))
STAGES = (STAGE,)
