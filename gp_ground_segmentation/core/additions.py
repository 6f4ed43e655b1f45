# SPDX-License-Identifier: Apache-2.0
"""Rules that are ours, not the paper's, kept apart so each can be read, tested and switched off.

Each is a function from arrays to a mask or a height and has a ``use_*`` switch in
``SegmenterParams``; ``segmenter.GroundSegmenter`` composes them with the paper's stages.

* :func:`elevated_plateaus` (``use_elevated_plateaus``): candidates on an obstacle top whose
  ground is occluded do not train the GP. README "How it works" gives its measured effect.
* :func:`ground_under_sensor` (``use_anchor``): height of the ground under the vehicle, given
  to the GP as one shared extra training point at r = 0 in every segment.
* :func:`outlier_candidates` (``use_outlier_rejection``): leave-one-out residual tests that
  drop below-ground reflection noise and obstacle tops from the training set
  (``outlier_worst_per_segment``: at most the worst obstacle top per segment and pass; off).
* :func:`wide_terrain_candidates` (``outlier_wide_terrain_m``): an obstacle top that both
  neighbouring segments continue at its height, with no ground right beside it below, is
  terrain, and keeps training the GP.
* ``start_height_m`` of :func:`elevated_plateaus` (``plateau_from_sensor_ground``): the plateau
  test of every segment starts from the ground under the sensor.
* :func:`one_point_line_slopes` (``use_chord_slope_for_single_points``): one-point lines get
  the slope of the chord from the previous candidate, so walls meet the steep-line filter.
* :func:`cross_segment_rise` (``use_cross_slope_threshold``): widen the ground threshold
  by the rise of the ground across the segment.
* :func:`smooth_length_factors` (``length_factor_smoothing_passes``): a running mean of log d_i
  along each segment, so that the non-stationary kernel's prefactor does not pull the ground
  towards the prior mean where neighbouring length scales differ.

The GP prior mean at the anchor height (``prior_mean_at_anchor``) is set in the segmenter.

:func:`steep_line_candidates` is the paper's reading ("large sloped line-segments relate to
non-ground structures"), not an addition; it lives here because it is a mask over the
candidates like the others, applied by the segmenter after Algorithm 1.
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import kernel, run, sort_in_place
from .lines import relative_to_first


def steep_line_candidates(slope: np.ndarray, max_slope: float) -> np.ndarray:
    """(M, N) bool: candidates whose line is steeper than zeta_b (NaN slopes are not)."""
    with np.errstate(invalid='ignore'):
        return slope > max_slope


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
    return run(compiled, _plateaus_compiled, _plateaus_numpy, *args)


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


_plateaus_compiled = kernel(_plateaus_loop, error_model='numpy')


def ground_under_sensor(cand_z: np.ndarray, training: np.ndarray, line_id: np.ndarray,
                        line_count: np.ndarray, intercept: np.ndarray,
                        compiled: bool = True) -> float:
    """Height of the ground under the vehicle (r = 0), shared by all segments (m).

    Every segment starts at the sensor, so all segment GPs meet at r = 0 where the ground is
    the one the vehicle stands on, on a slope too. The first training candidate of each
    segment belongs to a line; where that line has two or more candidates its intercept (the
    line extrapolated to r = 0) is one estimate, and the median over segments is robust to the
    few whose first line is a car or a wall. Fallbacks: without such a line, the median of the
    training candidates' heights; without training candidates, the median of all candidates;
    without candidates, 0. ``compiled``: the per-segment look-up in numba (as
    :func:`elevated_plateaus`).
    """
    any_training, estimates = run(compiled, _first_line_intercepts_compiled,
                                  _first_line_intercepts_numpy, training, line_id, line_count,
                                  intercept)
    if not any_training:
        z = cand_z[np.isfinite(cand_z)]
        return _median(z, compiled) if z.size else 0.0
    if estimates.size:
        return _median(estimates, compiled)
    return _median(cand_z[training], compiled)


def _median(values: np.ndarray, compiled: bool) -> float:
    """``float(np.median(values))`` of finite values (one or more); ``compiled``: sorted in
    numba (np.median's Python costs ~10 us, ~10x the sort of a hundred values)."""
    median = run(compiled, _median_compiled, _median_numpy, values)
    return float(np.median(values)) if math.isnan(median) else median


def _median_numpy(values):
    return float(np.median(values))


def _median_loop(values):
    """np.median's value of finite ``values`` (compiled with numba): the middle one of the sorted
    values, or the two middle ones' (a + b) / 2, as np.median's mean of them. NaN, for np.median
    itself to decide, when a middle value is zero: np.median's partition may order -0.0 and
    +0.0 otherwise than a sort, and its mean turns -0.0 into +0.0."""
    ordered = values.copy()
    sort_in_place(ordered)
    half = ordered.size // 2
    upper = ordered[half]
    lower = ordered[half - 1] if ordered.size % 2 == 0 else upper
    if lower == 0.0 or upper == 0.0:
        return np.nan
    if ordered.size % 2 == 1:
        return upper
    return (lower + upper) / 2.0


_median_compiled = kernel(_median_loop)


def _first_line_intercepts_numpy(training, line_id, line_count, intercept):
    """(any training candidate, intercepts of the segments' first training lines that have
    two or more candidates and a finite intercept, in segment order)."""
    rows = np.flatnonzero(training.any(axis=1))
    first = np.argmax(training[rows], axis=1)
    ids = line_id[rows, first]
    usable = (line_count[ids] >= 2) & np.isfinite(intercept[ids])
    return rows.size > 0, intercept[ids[usable]]


def _first_line_intercepts_loop(training, line_id, line_count, intercept):
    """:func:`_first_line_intercepts_numpy` as one loop (compiled with numba), the same values
    in the same order; it replaces ~8 numpy calls of 1-4 us each."""
    m_count, n_count = training.shape
    estimates = np.empty(m_count)
    found = 0
    any_training = False
    for m in range(m_count):
        for k in range(n_count):
            if training[m, k]:
                any_training = True
                i = line_id[m, k]
                if line_count[i] >= 2 and np.isfinite(intercept[i]):
                    estimates[found] = intercept[i]
                    found += 1
                break
    return any_training, estimates[:found]


_first_line_intercepts_compiled = kernel(_first_line_intercepts_loop)


def outlier_candidates(loo_residual: np.ndarray, *, above_m: float, below_m: float,
                       worst_above_only: bool = False, loo_std: np.ndarray | None = None,
                       std_factor: float = 0.0) -> np.ndarray:
    """Mask of candidates whose leave-one-out residual z_i - mean_{-i} is an outlier.

    Above ``above_m`` (and above ``std_factor`` times ``loo_std``, the leave-one-out predictive
    std, when given): an obstacle top, not ground. Below ``-below_m``: below-ground reflection
    noise. NaN residuals (no training candidate there) are not outliers.

    ``worst_above_only``: of the candidates above ``above_m`` keep only the highest residual
    of each segment (row). One obstacle top pulls its neighbours' leave-one-out means up or
    down too; dropping every candidate over the limit at once also drops good ground next to
    it (the near slope before a crest, seen between the anchor and a low far flat). Removing
    the worst per pass is the usual iterative way.
    """
    with np.errstate(invalid='ignore'):
        limit = above_m if loo_std is None else np.maximum(above_m, std_factor * loo_std)
        above = loo_residual > limit
        if worst_above_only and above.any():
            top = np.max(np.where(np.isnan(loo_residual), -np.inf, loo_residual), axis=1)
            above &= loo_residual >= top[:, None]
        return above | (loo_residual < -below_m)


def wide_terrain_candidates(mask: np.ndarray, z: np.ndarray, tolerance_m: float,
                            r: np.ndarray | None = None, max_slope: float = np.inf,
                            compiled: bool = True) -> np.ndarray:
    """The ``mask`` (M, N) candidates that both neighbouring segments continue: segment m - 1
    and segment m + 1 (segments wrap around) each have a candidate in bin n - 1, n or n + 1
    whose height ``z`` (M, N; NaN where none) is within ``tolerance_m`` of the candidate's, and
    no candidate in bins n - 1 .. n + 1 of those three segments (its own segment: n - 1 and
    n + 1) lies more than ``tolerance_m`` below it (a step up from the ground next to it is an
    object), and, given the candidates' ranges ``r`` (M, N), it rises above the previous
    candidate of its own segment (the nearest at a smaller bin, however far) no steeper than
    ``max_slope`` (dz / dr).

    Why: the leave-one-out test calls a candidate an obstacle top when it stands far above
    what its segment's other candidates predict. That is a bin filled by one object (its
    lowest point on the object), a few segments wide at most; but it is also sparse far
    ground on rising terrain, one candidate after a long gap (16-beam rings, high mounts),
    where the segment's near candidates predict the flat. Terrain is wider than a 3 degree
    segment: its neighbours' candidates at that range lie at its height. Both sides are
    required, so that an object two segments wide, or one beside a raised neighbour, is not
    called terrain. The step test looks into the neighbouring segments too: points above the
    ground in rings all around the sensor (test_malformed's every-5th-point denormal z, 1.73 m
    up) are continued by every segment and often have no candidate of their own segment in the
    bins beside them, but the segments beside them do, on the ground (12 of 780 such points
    became ground when only the own segment's bins were looked at). The slope test keeps a wall
    seen over an occlusion shadow from being terrain: in a room seen from 0.3 m, the lowest
    visible part of the far wall (0.9 m up, the floor before it hidden behind furniture) is
    continued by the neighbouring segments like terrain, but it rises 0.65 m per metre from the
    floor before the shadow, where far ground on a hill seen by a 16-beam sensor rises gently
    over the gap (benchmarks/RESULTS.md, "The wide-terrain rule on by default").

    ``compiled``: one numba pass over the asked-for candidates when numba imports (else the
    numpy reference, whole-grid shifts); both give the same mask.
    """
    mask = np.ascontiguousarray(mask, dtype=bool)
    z = np.ascontiguousarray(z, dtype=np.float64)
    r = np.full(z.shape, np.nan) if r is None else np.ascontiguousarray(r, dtype=np.float64)
    return run(compiled, _wide_terrain_compiled, _wide_terrain_numpy, mask, z, r,
               float(tolerance_m), float(max_slope))


def _wide_terrain_numpy(mask, z, r, tolerance_m, max_slope):
    """The numpy reference of :func:`wide_terrain_candidates` (r NaN: no slope test)."""
    m, n = z.shape
    padded = np.full((m, n + 2), np.nan)
    padded[:, 1:-1] = z
    out = mask.copy()
    with np.errstate(invalid='ignore'):
        for side in (1, -1):
            neighbour = np.roll(padded, side, axis=0)
            close = np.zeros((m, n), dtype=bool)
            for k in range(3):  # bins n - 1, n, n + 1 of the neighbouring segment
                close |= np.abs(neighbour[:, k:k + n] - z) <= tolerance_m
                # ... and none of them lower by more than that: a step up from the ground
                out &= ~(neighbour[:, k:k + n] < z - tolerance_m)
            out &= close
        for k in (0, 2):  # a step up from its own segment's next candidates: an object
            out &= ~(padded[:, k:k + n] < z - tolerance_m)
        out &= ~(_slope_from_previous_candidate(z, r) > max_slope)
    return out


def _wide_terrain_loop(mask, z, r, tolerance_m, max_slope):
    """:func:`_wide_terrain_numpy` for the asked-for candidates only (compiled with numba;
    the outlier pass asks for a handful): the same comparisons in the same float64
    arithmetic, so the same mask."""
    m_count, n_bins = z.shape
    out = np.zeros((m_count, n_bins), dtype=np.bool_)
    for m in range(m_count):
        for b in range(n_bins):
            if not mask[m, b]:
                continue
            height = z[m, b]
            low = height - tolerance_m
            keep = True
            for side in (-1, 1):
                row = (m + side) % m_count
                close = False
                for k in range(max(b - 1, 0), min(b + 2, n_bins)):
                    other = z[row, k]
                    if abs(other - height) <= tolerance_m:
                        close = True
                    if other < low:
                        keep = False
                if not close:
                    keep = False
            for k in (b - 1, b + 1):
                if 0 <= k < n_bins and z[m, k] < low:
                    keep = False
            if keep and np.isfinite(height):
                for k in range(b - 1, -1, -1):  # the previous candidate of the segment
                    if np.isfinite(z[m, k]):
                        rise = height - z[m, k]
                        run_m = r[m, b] - r[m, k]
                        if run_m != 0.0:
                            slope = rise / run_m
                        elif rise != 0.0:
                            slope = math.copysign(math.inf, rise)
                        else:
                            slope = math.nan
                        if slope > max_slope:
                            keep = False
                        break
            out[m, b] = keep and np.isfinite(height)
    return out


_wide_terrain_compiled = kernel(_wide_terrain_loop)


def _slope_from_previous_candidate(z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(M, N) dz / dr from each candidate's previous candidate in its segment (the nearest known
    one at a smaller bin) to it; NaN where either is missing."""
    m, n = z.shape
    known = np.isfinite(z)
    # the last known bin up to each bin, shifted by one: the previous known bin (-1: none)
    last = np.maximum.accumulate(np.where(known, np.arange(n), -1), axis=1)
    previous = np.full((m, n), -1)
    previous[:, 1:] = last[:, :-1]
    rows = np.arange(m)[:, None]
    at = np.maximum(previous, 0)
    with np.errstate(invalid='ignore', divide='ignore'):
        slope = (z - z[rows, at]) / (r - r[rows, at])
    return np.where(known & (previous >= 0), slope, np.nan)


def cross_segment_rise(edges: np.ndarray, mean: np.ndarray, max_slope: float,
                       compiled: bool = True) -> np.ndarray:
    """(M, N + 1) how much the predicted ground rises across one segment at each bin edge (m).

    The GP models z(r) per segment, and a bin's candidate is its lowest point: where the ground
    rises *across* the beams (an embankment beside the road), the candidate follows the
    segment's low side and the high side sits above z_hat by up to the rise across the
    segment. The rise is estimated from the neighbouring segments' ground at the same r
    (segments wrap around): only where the ground rises on one side of the segment and falls on
    the other (a slope across it), by the smaller of the two steps, |z_hat[m + 1] - z_hat[m]|
    and |z_hat[m] - z_hat[m - 1]|. A single raised neighbour (a fit bent up by an obstacle, a
    car beside the road) is no slope; half the neighbours' difference, measured first, widened
    the threshold there and cost RELLIS-3D 0.002 F1 (benchmarks/RESULTS.md). The rise is
    capped at what a slope of ``max_slope`` gives over the segment's width 2 pi r / M there: a
    steeper rise is structure (or a poor fit next to it), not ground, and must not widen the
    threshold more.

    ``edges``: (M, N + 1) r of every segment's bin edges (increasing along each row);
    ``mean``: z_hat there. ``compiled``: one numba pass when numba imports (else the numpy
    reference); both give the same values.
    """
    return run(compiled, _rise_compiled, _rise_numpy, edges, mean, float(max_slope))


def _rise_numpy(edges, mean, max_slope):
    """The numpy reference of :func:`cross_segment_rise`."""
    span = float(np.nanmax(edges)) + 1.0  # more than any r
    m_count = edges.shape[0]
    # one sorted 1-D table of all rows (row offset by a span larger than any r): np.interp
    # then looks up every segment's edges in its neighbour's row at once
    offset = np.arange(m_count)[:, None] * span
    flat_r = (edges + offset).ravel()
    flat_z = mean.ravel()

    def neighbour(shift):
        rows = (np.arange(m_count) + shift) % m_count
        query = np.clip(edges, edges[rows, :1], edges[rows, -1:]) + offset[rows]
        return np.interp(query, flat_r, flat_z)

    ahead = neighbour(1) - mean
    behind = mean - neighbour(-1)
    rise = np.where(ahead * behind > 0, np.minimum(np.abs(ahead), np.abs(behind)), 0.0)
    cap = max_slope * (2.0 * np.pi / m_count) * edges
    return np.minimum(rise, cap)


def _rise_loop(edges, mean, max_slope):
    """:func:`_rise_numpy` in one pass (compiled with numba): each edge looked up in its
    neighbours' rows with np.interp's own arithmetic (the slope of the interval, then
    slope * (x - x_j) + z_j, the other end if that is NaN, z_j where x = x_j), the same
    query and table values, so the same numbers without the reference's (M, N + 1)
    temporaries. A row's edges increase, so the interval of the next edge is found by
    walking on from the last one. The span is the reference's np.nanmax + 1 (a max is
    exact), without its ~5 us of Python."""
    m_count, n_edges = edges.shape
    span = np.nan  # np.nanmax: NaN when every edge is NaN
    for m in range(m_count):
        for k in range(n_edges):
            x = edges[m, k]
            if not np.isnan(x) and (np.isnan(span) or x > span):
                span = x
    span = span + 1.0
    rise = np.empty((m_count, n_edges))
    neighbour = np.empty((2, n_edges))  # ground of the segment ahead and behind at each edge
    factor = max_slope * (2.0 * np.pi / m_count)
    for m in range(m_count):
        for side in range(2):
            n = m + 1 if side == 0 else m - 1
            if n == m_count:
                n = 0
            elif n < 0:
                n = m_count - 1
            offset = n * span
            j = 0  # the last table entry of row n at or before x
            for k in range(n_edges):
                x = edges[m, k]  # np.clip(edges, first, last) + offset, then np.interp
                if x < edges[n, 0]:
                    x = edges[n, 0]
                if x > edges[n, n_edges - 1]:
                    x = edges[n, n_edges - 1]
                x = x + offset
                if np.isnan(x):
                    neighbour[side, k] = x
                    continue
                if edges[n, j] + offset > x:
                    j = 0  # edges not increasing after all: search the row from its start
                while j + 1 < n_edges and edges[n, j + 1] + offset <= x:
                    j += 1
                x_j = edges[n, j] + offset
                if j == n_edges - 1 or x_j == x:
                    value = mean[n, j]
                else:
                    x_next = edges[n, j + 1] + offset
                    slope = (mean[n, j + 1] - mean[n, j]) / (x_next - x_j)
                    value = slope * (x - x_j) + mean[n, j]
                    if np.isnan(value):
                        value = slope * (x - x_next) + mean[n, j + 1]
                        if np.isnan(value) and mean[n, j] == mean[n, j + 1]:
                            value = mean[n, j]
                neighbour[side, k] = value
        for k in range(n_edges):
            step_ahead = neighbour[0, k] - mean[m, k]
            step_behind = mean[m, k] - neighbour[1, k]
            value = 0.0
            if step_ahead * step_behind > 0:
                value = abs(step_ahead)  # np.minimum: NaN if either is NaN
                if not (np.isnan(value) or value <= abs(step_behind)):
                    value = abs(step_behind)
            cap = factor * edges[m, k]
            rise[m, k] = value if np.isnan(value) or value <= cap else cap
    return rise


_rise_compiled = kernel(_rise_loop)


def one_point_line_slopes(slope: np.ndarray, cand_r: np.ndarray, cand_z: np.ndarray,
                          compiled: bool = True) -> np.ndarray:
    """``slope`` (M, N) with every one-point line (NaN slope) given |dz/dr| of the chord from
    the previous candidate of its segment.

    Algorithm 1 ends a line *before* it gets steeper than zeta_b, so a wall or a car front is
    not a steep line but a string of one-point lines, and a NaN slope would read as flat
    ground (the longest length scale, and no steep-line filter). The chord that ended the
    previous line is the slope the data show there. (The chord to the *next* candidate was
    measured too: it marks the last ground candidate before a crest as steep and cost the
    crest family 0.009 F1.) A segment's first candidate keeps NaN. ``compiled``: one numba
    loop (as :func:`elevated_plateaus`).
    """
    return run(compiled, _chord_slopes_compiled, _chord_slopes_numpy,
               np.asarray(slope, dtype=np.float64), cand_r, cand_z)


def _chord_slopes_numpy(slope, cand_r, cand_z):
    """The numpy reference of :func:`one_point_line_slopes`."""
    present = np.isfinite(cand_r) & np.isfinite(cand_z)
    col = np.where(present, np.arange(cand_r.shape[1]), -1)
    prev = np.maximum.accumulate(col, axis=1)  # last candidate at or before each bin
    prev = np.concatenate([np.full((prev.shape[0], 1), -1), prev[:, :-1]], axis=1)
    safe = np.maximum(prev, 0)
    with np.errstate(divide='ignore', invalid='ignore'):
        chord = np.abs((cand_z - np.take_along_axis(cand_z, safe, axis=1))
                       / (cand_r - np.take_along_axis(cand_r, safe, axis=1)))
    chord = np.where((prev >= 0) & present & np.isfinite(chord), chord, np.nan)
    return np.where(np.isnan(slope), chord, slope)


def _chord_slopes_loop(slope, cand_r, cand_z):
    """:func:`_chord_slopes_numpy` one segment at a time (compiled with numba): the same chord
    of the same values; it replaces ~15 numpy calls (accumulate, take_along_axis, where)."""
    m_count, n_count = slope.shape
    out = np.empty((m_count, n_count))
    for m in range(m_count):
        prev = -1
        for k in range(n_count):
            present = np.isfinite(cand_r[m, k]) and np.isfinite(cand_z[m, k])
            value = slope[m, k]
            if np.isnan(value):
                value = np.nan
                if present and prev >= 0:
                    chord = np.abs((cand_z[m, k] - cand_z[m, prev])
                                   / (cand_r[m, k] - cand_r[m, prev]))
                    if np.isfinite(chord):
                        value = chord
            out[m, k] = value
            if present:
                prev = k
    return out


_chord_slopes_compiled = kernel(_chord_slopes_loop, error_model='numpy')


def smooth_length_factors(d: np.ndarray, training: np.ndarray, passes: int,
                          compiled: bool = True) -> np.ndarray:
    """(M, N) length factors d_i with ``passes`` rounds of a (1, 2, 1) / 4 running mean of
    log d over each segment's ``training`` candidates (neighbours in bin order, gaps skipped;
    the first and last of a row average (2, 1) / 3 with their one neighbour, a lone candidate
    keeps its d). Other entries are returned unchanged.

    Why: Paciorek's kernel between two points carries the prefactor
    sqrt(2 L_i L_j / (L_i^2 + L_j^2)), below 1 whenever their length scales differ, so the
    posterior at a point is pulled towards the prior mean by a fraction of its distance from
    it. The relative density rho~ of a bin jumps with how many rings happen to fall in it, and
    with it d_i: on a constant 15 deg ramp seen from 4.5 m, L alternates between 3 and 7 m from
    one bin to the next, and where the ground is metres above the prior mean (high mounts, long
    ramps, hills) that pull reaches decimetres; the leave-one-out test then rejects clean ramp
    candidates as obstacle tops (495 of 2,544 on that scan) and the ramp becomes obstacle
    (benchmarks/RESULTS.md, "Length factors smoothed along the segment"). Averaging in log
    space keeps d where it is constant and the paper's slow variation of L with slope and
    density (5 passes: a spread of ~1.6 bins). 0 passes: the paper's d_i.

    ``compiled``: the passes as one numba loop per row (when numba imports) instead of the
    numpy reference's neighbour gathers; log and exp are numpy's in both, so the outputs are
    equal bit for bit.
    """
    if passes <= 0:
        return d
    log_d = np.log(np.where(training, d, 1.0))
    log_d = run(compiled, _smooth_compiled, _smooth_numpy, log_d,
                np.ascontiguousarray(training, dtype=bool), int(passes))
    return np.where(training, np.exp(log_d), d)


def _smooth_numpy(log_d, training, passes):
    """The numpy reference of :func:`smooth_length_factors`' passes over log d."""
    m_count, n_count = log_d.shape
    columns = np.arange(n_count)
    # the previous and the next training candidate of every bin in its row (-1 / N: none)
    before = np.maximum.accumulate(np.where(training, columns, -1), axis=1)
    before = np.concatenate([np.full((m_count, 1), -1), before[:, :-1]], axis=1)
    after = np.minimum.accumulate(np.where(training, columns, n_count)[:, ::-1], axis=1)[:, ::-1]
    after = np.concatenate([after[:, 1:], np.full((m_count, 1), n_count)], axis=1)
    has_before, has_after = before >= 0, after < n_count
    rows = np.arange(m_count)[:, None]
    before, after = np.maximum(before, 0), np.minimum(after, n_count - 1)
    for _ in range(passes):
        prev, nxt = log_d[rows, before], log_d[rows, after]
        smoothed = np.where(has_before & has_after, 0.25 * prev + 0.5 * log_d + 0.25 * nxt,
                            np.where(has_before, (2.0 * log_d + prev) / 3.0,
                                     np.where(has_after, (2.0 * log_d + nxt) / 3.0, log_d)))
        log_d = np.where(training, smoothed, log_d)
    return log_d


def _smooth_loop(log_d, training, passes):
    """:func:`_smooth_numpy` row by row (compiled with numba): the same arithmetic in the same
    order on each row's training candidates, gathered into a short buffer."""
    m_count, n_count = log_d.shape
    out = log_d.copy()
    index = np.empty(n_count, dtype=np.int64)
    values = np.empty(n_count)
    smoothed = np.empty(n_count)
    for m in range(m_count):
        k = 0
        for j in range(n_count):
            if training[m, j]:
                index[k] = j
                values[k] = log_d[m, j]
                k += 1
        if k < 2:  # a lone candidate keeps its d
            continue
        for _ in range(passes):
            smoothed[0] = (2.0 * values[0] + values[1]) / 3.0
            for i in range(1, k - 1):
                smoothed[i] = 0.25 * values[i - 1] + 0.5 * values[i] + 0.25 * values[i + 1]
            smoothed[k - 1] = (2.0 * values[k - 1] + values[k - 2]) / 3.0
            for i in range(k):
                values[i] = smoothed[i]
        for i in range(k):
            out[m, index[i]] = values[i]
    return out


_smooth_compiled = kernel(_smooth_loop)
