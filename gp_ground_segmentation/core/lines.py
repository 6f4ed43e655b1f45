# SPDX-License-Identifier: Apache-2.0
"""Stage ``lines``: the paper's Algorithm 1 over each segment's candidates, the steep-line
filter, and our chord slopes of one-point lines.

Fit [paper]: an errors-in-variables (Deming) maximum-likelihood line with variance ratio
lambda = var(z error) / var(r error), closed form from the second moments:

    beta = (s_zz - lambda s_rr + sqrt((s_zz - lambda s_rr)^2 + 4 lambda s_rz^2)) / (2 s_rz)
    alpha = mean_z - beta * mean_r

lambda -> infinity tends to OLS of z on r. lambda = 1, the default, is orthogonal regression:
exactly the method the paper rejects ("the method assumes that both parameters have the same
error while this assumption is not valid"), which asks for unequal errors without giving a
ratio. The default stays 1 until a measured choice replaces it.

Growing (how Algorithm 1 is read here): candidates are visited in order of r. The current line
of a segment accumulates its candidates' moments; the next candidate is a *critical point* -- it
ends the current line and starts a new one -- when any of these holds:

* radial gap to the previous candidate > zeta_m (``max_gap_m``): a break in the data;
* rho~ changes by more than a factor ``max_density_jump`` (the paper's "smoothness of rho~");
* its perpendicular distance to the current line (>= 2 points) > delta (``max_distance_m``);
* the line with it added would be steeper than zeta_b (``max_slope``); for a one-point line
  this is the slope of the two-point chord.

All segments advance in lock-step, bin index by bin index, in both implementations (the numba
loop and the numpy reference, one vectorised step over the M segments per bin index); they
evaluate the same scalar formulas in the same order and number the lines alike.

Output per candidate: its line id, whether it starts a line after a critical point, the slope
g = |beta| of its final line (NaN for one-point lines), and the signed slope of its line just
before it joined (what the ``plateau`` stage extrapolates).

Steep lines [paper]: candidates on a line steeper than zeta_b do not train the GP ("large sloped
line-segments relate to non-ground structures"). Chord slopes [ours,
``use_chord_slope_for_single_points``]: Algorithm 1 ends a line *before* it gets steeper than
zeta_b, so a wall is a string of one-point lines whose NaN slope would read as flat ground; each
gets the slope of the chord from the previous candidate of its segment (the chord to the *next*
candidate would mark the last ground candidate before a crest as steep).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, kernel


@dataclass
class LineSegments:
    """Line-segments of a frame, arrays (M, N) aligned with the grid's candidates."""

    line_id: np.ndarray  # (M, N) int id of the candidate's line, -1 where no candidate
    is_critical: np.ndarray  # (M, N) bool: candidate starts a new line after a critical point
    slope: np.ndarray  # (M, N) |dz/dr| of the candidate's line; NaN for one-point lines / empty
    intercept: np.ndarray  # (L,) alpha of every line
    line_slope: np.ndarray  # (L,) signed beta of every line (NaN for one-point lines)
    line_count: np.ndarray  # (L,) candidates per line
    line_r_range: np.ndarray  # (L, 2) first and last candidate r of every line (m)
    slope_before: np.ndarray  # (M, N) signed beta of the current line (>= 2 points) just
    #                           before the candidate was visited; NaN otherwise


def deming_fit(n, s_r, s_z, s_rr, s_zz, s_rz, variance_ratio):
    """Deming (errors-in-variables ML) line from raw sums, vectorised over lines.

    ``n, s_r, s_z, s_rr, s_zz, s_rz`` are the count and the sums of r, z, r^2, z^2 and r*z
    (take them about a nearby origin: the central moments are differences of these sums).
    Returns ``(alpha, beta)``. Where the covariance of r and z is 0 the line is horizontal if
    the spread is mostly along r, else vertical (beta = +-inf); lines with n = 0 give NaN.
    """
    with np.errstate(divide='ignore', invalid='ignore'):
        mean_r = s_r / n
        mean_z = s_z / n
        cov_rr = np.maximum(s_rr / n - mean_r * mean_r, 0.0)
        cov_zz = np.maximum(s_zz / n - mean_z * mean_z, 0.0)
        cov_rz = s_rz / n - mean_r * mean_z
        diff = cov_zz - variance_ratio * cov_rr
        beta = (diff + np.sqrt(diff * diff + 4.0 * variance_ratio * cov_rz * cov_rz)) / (
            2.0 * cov_rz)
        beta = np.where(cov_rz == 0, np.where(diff > 0, np.inf, 0.0), beta)
        alpha = mean_z - beta * mean_r
    return alpha, beta


def relative_to_first(cand_r: np.ndarray, cand_z: np.ndarray):
    """Candidates (M, N) relative to each segment's first one: (present, r - r0, z - z0, r0, z0).

    Moments taken about a nearby origin keep the line arithmetic well conditioned far from the
    sensor; segments without a candidate get the origin (0, 0).
    """
    present = np.isfinite(cand_r) & np.isfinite(cand_z)
    rows = np.arange(cand_r.shape[0])
    first = np.argmax(present, axis=1)
    r0 = np.where(present.any(axis=1), cand_r[rows, first], 0.0)
    z0 = np.where(present.any(axis=1), cand_z[rows, first], 0.0)
    return present, cand_r - r0[:, None], cand_z - z0[:, None], r0, z0


def extract_lines(cand_r: np.ndarray, cand_z: np.ndarray, density: np.ndarray, *,
                  variance_ratio: float, max_slope: float, max_distance_m: float,
                  max_gap_m: float, max_density_jump: float,
                  compiled: bool = True) -> LineSegments:
    """Grow line-segments over the candidates (M, N) of every segment; see module docstring.

    ``compiled``: the numba loop when numba imports (the numpy reference otherwise, or if the
    compiled loop fails).
    """
    args = (cand_r, cand_z, np.asarray(density, dtype=np.float64), float(variance_ratio),
            float(max_slope), float(max_distance_m), float(max_gap_m), 1.0 / max_density_jump,
            float(max_density_jump))
    return LineSegments(*LINES.run(compiled, *args))


def _lines_numpy(cand_r, cand_z, density, variance_ratio, max_slope, max_distance_m,
                 max_gap_m, low_density, high_density):
    """The numpy reference of :func:`_lines_loop`: the fields of :class:`LineSegments`."""
    m_count, n_count = cand_r.shape
    rows = np.arange(m_count)
    present, rr, zz, r0, z0 = relative_to_first(cand_r, cand_z)

    # moments (1, r, z, r^2, z^2, r z) of every candidate, 0 where there is none
    rr0, zz0 = np.where(present, rr, 0.0), np.where(present, zz, 0.0)
    moments = np.stack([present.astype(np.float64), rr0, zz0, rr0 * rr0, zz0 * zz0, rr0 * zz0])
    line_id, is_critical, slope_before, next_line = _grow_lines_numpy(
        present, rr, zz, density, moments, variance_ratio, max_slope, max_distance_m,
        max_gap_m, low_density, high_density)

    # Final fit of every line from its members (bincount over line ids).
    ids = line_id[present]
    r_abs, z_abs = cand_r[present], cand_z[present]
    seg_of = np.broadcast_to(rows[:, None], (m_count, n_count))[present]
    r_rel, z_rel = r_abs - r0[seg_of], z_abs - z0[seg_of]
    num_lines = next_line
    count = np.bincount(ids, minlength=num_lines).astype(np.float64)
    line_sums = [count] + [np.bincount(ids, weights=w, minlength=num_lines)
                           for w in (r_rel, z_rel, r_rel * r_rel, z_rel * z_rel, r_rel * z_rel)]
    alpha_rel, beta = deming_fit(*line_sums, variance_ratio)
    beta = np.where(count >= 2, beta, np.nan)
    line_seg = np.zeros(num_lines, dtype=np.intp)
    line_seg[ids] = seg_of
    intercept = alpha_rel + z0[line_seg] - beta * r0[line_seg]
    r_lo = np.full(num_lines, np.inf)
    r_hi = np.full(num_lines, -np.inf)
    np.minimum.at(r_lo, ids, r_abs)
    np.maximum.at(r_hi, ids, r_abs)

    slope = np.full((m_count, n_count), np.nan)
    slope[present] = np.abs(beta[ids])
    return (line_id, is_critical, slope, intercept, beta, count.astype(np.intp),
            np.stack([r_lo, r_hi], axis=1), slope_before)


def _lines_loop(cand_r, cand_z, density, variance_ratio, max_slope, max_distance_m,
                max_gap_m, low_density, high_density):
    """:func:`_lines_numpy` as scalar loops (compiled with numba): the same values in the same
    order (the line sums accumulate in ``np.bincount``'s order, row by row), so the same
    outputs. It replaces the numpy set-up (``relative_to_first``, the moments array) and the
    final fit (bincounts, ``minimum.at``, gathers): ~30 small numpy calls."""
    m_count, n_count = cand_r.shape
    present = np.empty((m_count, n_count), dtype=np.bool_)
    rr = np.empty((m_count, n_count))
    zz = np.empty((m_count, n_count))
    r0 = np.zeros(m_count)
    z0 = np.zeros(m_count)
    for m in range(m_count):
        for k in range(n_count):
            present[m, k] = np.isfinite(cand_r[m, k]) and np.isfinite(cand_z[m, k])
        for k in range(n_count):
            if present[m, k]:  # relative_to_first: the origin is the first candidate
                r0[m] = cand_r[m, k]
                z0[m] = cand_z[m, k]
                break
        for k in range(n_count):
            rr[m, k] = cand_r[m, k] - r0[m]
            zz[m, k] = cand_z[m, k] - z0[m]
    line_id, is_critical, slope_before, num_lines = _grow_lines_compiled(
        present, rr, zz, density, variance_ratio, max_slope, max_distance_m, max_gap_m,
        low_density, high_density)

    sums = np.zeros((6, num_lines))
    line_seg = np.zeros(num_lines, dtype=np.intp)
    r_lo = np.full(num_lines, np.inf)
    r_hi = np.full(num_lines, -np.inf)
    for m in range(m_count):
        for k in range(n_count):
            if present[m, k]:  # the moments, summed as np.bincount sums them
                i = line_id[m, k]
                r, z = rr[m, k], zz[m, k]
                sums[0, i] += 1.0
                sums[1, i] += r
                sums[2, i] += z
                sums[3, i] += r * r
                sums[4, i] += z * z
                sums[5, i] += r * z
                line_seg[i] = m
                r_lo[i] = min(r_lo[i], cand_r[m, k])
                r_hi[i] = max(r_hi[i], cand_r[m, k])
    intercept = np.empty(num_lines)
    beta = np.empty(num_lines)
    count = np.empty(num_lines, dtype=np.intp)
    r_range = np.empty((num_lines, 2))
    for i in range(num_lines):
        alpha_rel, b = _deming_scalar(sums[0, i], sums[1, i], sums[2, i], sums[3, i],
                                      sums[4, i], sums[5, i], variance_ratio)
        if not sums[0, i] >= 2:
            b = np.nan
        beta[i] = b
        intercept[i] = alpha_rel + z0[line_seg[i]] - b * r0[line_seg[i]]
        count[i] = int(sums[0, i])
        r_range[i, 0] = r_lo[i]
        r_range[i, 1] = r_hi[i]
    slope = np.empty((m_count, n_count))
    for m in range(m_count):
        for k in range(n_count):
            slope[m, k] = np.abs(beta[line_id[m, k]]) if present[m, k] else np.nan
    return (line_id, is_critical, slope, intercept, beta, count, r_range, slope_before)


def _grow_lines_numpy(present, rr, zz, density, moments, variance_ratio, max_slope,
                      max_distance_m, max_gap_m, low_density, high_density):
    """The numpy reference of the growing loop: (line_id, is_critical, slope_before, lines)."""
    m_count, n_count = present.shape
    sums = np.zeros((6, m_count))  # n, Sr, Sz, Srr, Szz, Srz of each segment's current line
    last_r = np.full(m_count, np.nan)
    last_rho = np.full(m_count, np.nan)
    current_line = np.full(m_count, -1, dtype=np.intp)
    slope_before = np.full((m_count, n_count), np.nan)
    next_line = 0
    line_id = np.full((m_count, n_count), -1, dtype=np.intp)
    is_critical = np.zeros((m_count, n_count), dtype=bool)

    with np.errstate(divide='ignore', invalid='ignore'):  # empty lines give NaN: never true
        for k in range(n_count):
            has = present[:, k]
            if not has.any():
                continue
            r, z, rho = rr[:, k], zz[:, k], density[:, k]
            n = sums[0]
            started = has & (n > 0)
            gap = r - last_r > max_gap_m
            ratio = rho / last_rho
            jump = (ratio > high_density) | (ratio < low_density)
            alpha, beta = deming_fit(*sums, variance_ratio)
            slope_before[:, k] = np.where(has & (n >= 2), beta, np.nan)
            far = (n >= 2) & (np.abs(z - alpha - beta * r) / np.sqrt(1.0 + beta * beta)
                              > max_distance_m)
            # slope of the line if this candidate joins it (two-point chord for one-point lines)
            _, beta_new = deming_fit(*(sums + moments[:, :, k]), variance_ratio)
            steep = np.abs(beta_new) > max_slope
            critical = started & (gap | jump | far | steep)

            new_line = has & ~(n > 0) | critical
            n_new = int(np.count_nonzero(new_line))
            current_line[new_line] = np.arange(next_line, next_line + n_new)
            next_line += n_new
            sums = np.where(new_line, 0.0, sums) + moments[:, :, k]
            line_id[has, k] = current_line[has]
            is_critical[:, k] = critical
            last_r = np.where(has, r, last_r)
            last_rho = np.where(has, rho, last_rho)
    return line_id, is_critical, slope_before, next_line


def _deming_scalar(n, s_r, s_z, s_rr, s_zz, s_rz, variance_ratio):
    """:func:`deming_fit` for one line, the same operations in the same order."""
    mean_r = s_r / n
    mean_z = s_z / n
    cov_rr = s_rr / n - mean_r * mean_r
    if cov_rr < 0.0:  # np.maximum(x, 0): NaN stays NaN
        cov_rr = 0.0
    cov_zz = s_zz / n - mean_z * mean_z
    if cov_zz < 0.0:
        cov_zz = 0.0
    cov_rz = s_rz / n - mean_r * mean_z
    diff = cov_zz - variance_ratio * cov_rr
    if cov_rz == 0:
        beta = np.inf if diff > 0 else 0.0
    else:
        beta = (diff + np.sqrt(diff * diff + 4.0 * variance_ratio * cov_rz * cov_rz)) / (
            2.0 * cov_rz)
    return mean_z - beta * mean_r, beta


def _grow_lines_loop(present, rr, zz, density, variance_ratio, max_slope, max_distance_m,
                     max_gap_m, low_density, high_density):
    """:func:`_grow_lines_numpy` as scalar loops (compiled with numba): same outputs. The
    moments of a candidate, (1, r, z, r^2, z^2, r z) or 0 where there is none, are made here
    as the reference's ``moments`` array holds them."""
    # np.empty and fill loops rather than np.full: they compile faster
    m_count, n_count = present.shape
    sums = np.zeros((6, m_count))
    last_r = np.empty(m_count)
    last_rho = np.empty(m_count)
    current_line = np.empty(m_count, dtype=np.intp)
    slope_before = np.empty((m_count, n_count))
    line_id = np.empty((m_count, n_count), dtype=np.intp)
    is_critical = np.zeros((m_count, n_count), dtype=np.bool_)
    for m in range(m_count):
        last_r[m] = np.nan
        last_rho[m] = np.nan
        current_line[m] = -1
        for k in range(n_count):
            slope_before[m, k] = np.nan
            line_id[m, k] = -1
    joined = np.zeros(6)
    moment = np.zeros(6)
    line_alpha = np.full(m_count, np.nan)
    line_beta = np.full(m_count, np.nan)
    next_line = 0
    for k in range(n_count):
        column_has = False
        for m in range(m_count):
            column_has = column_has or present[m, k]
        if not column_has:
            continue  # no segment has a candidate at this bin index
        for m in range(m_count):
            has = present[m, k]
            n = sums[0, m]
            r, z = rr[m, k], zz[m, k]
            if has:
                moment[0], moment[1], moment[2] = 1.0, r, z
                moment[3], moment[4], moment[5] = r * r, z * z, r * z
            else:
                for j in range(6):
                    moment[j] = 0.0
            critical = False
            if has and n > 0:
                # the current line's fit (used from 2 points on) is the joined fit made when
                # its last candidate joined: the same sums, so no second Deming fit
                alpha, beta = line_alpha[m], line_beta[m]
                if n >= 2:
                    slope_before[m, k] = beta
                rho = density[m, k]
                gap = r - last_r[m] > max_gap_m
                ratio = rho / last_rho[m]
                jump = ratio > high_density or ratio < low_density
                far = n >= 2 and (np.abs(z - alpha - beta * r) / np.sqrt(1.0 + beta * beta)
                                  > max_distance_m)
                for j in range(6):
                    joined[j] = sums[j, m] + moment[j]
                alpha_new, beta_new = _deming_scalar(joined[0], joined[1], joined[2],
                                                     joined[3], joined[4], joined[5],
                                                     variance_ratio)
                steep = np.abs(beta_new) > max_slope
                critical = gap or jump or far or steep
                # read as the current fit only once it joined (n >= 2)
                line_alpha[m], line_beta[m] = alpha_new, beta_new
            if (has and not n > 0) or critical:
                current_line[m] = next_line
                next_line += 1
                for j in range(6):
                    sums[j, m] = 0.0 + moment[j]
            else:
                for j in range(6):
                    sums[j, m] = sums[j, m] + moment[j]
            if has:
                line_id[m, k] = current_line[m]
                last_r[m] = rr[m, k]
                last_rho[m] = density[m, k]
            is_critical[m, k] = critical
    return line_id, is_critical, slope_before, next_line


_lines_compiled = None
if AVAILABLE:  # the loops call the compiled scalar fit and growing loop
    _deming_scalar = kernel(_deming_scalar, error_model='numpy')
    _grow_lines_compiled = kernel(_grow_lines_loop, error_model='numpy')
    _lines_compiled = kernel(_lines_loop, error_model='numpy')


def _lines_examples(_dtype):
    grid = np.ones((2, 2))
    return [(grid, grid, grid, 1.0, 1.0, 1.0, 1.0, 0.5, 2.0)]


LINES = Twin('line growing', _lines_numpy, _lines_compiled, _lines_examples)


def with_slope(lines: LineSegments, slope: np.ndarray) -> LineSegments:
    """``dataclasses.replace(lines, slope=slope)`` (a new object sharing the other fields)
    without its field-by-field ``__init__``."""
    out = copy.copy(lines)
    out.slope = slope
    return out


# --- the steep-line filter [paper] ------------------------------------------------------------

def training_candidates(candidate_index: np.ndarray, slope: np.ndarray, max_slope: float,
                        compiled: bool = True):
    """(candidates not on a line steeper than ``max_slope`` (M, N) bool, the number of
    candidates, the number on steep lines); a NaN slope is not steep."""
    return NOT_STEEP.run(compiled, candidate_index, slope, float(max_slope))


def _not_steep_numpy(candidate_index, slope, max_slope):
    """The numpy reference of :func:`_not_steep_loop`."""
    has = candidate_index >= 0
    with np.errstate(invalid='ignore'):
        steep = slope > max_slope
    steep &= has
    # count_nonzero: a fifth of bool.sum()'s cost at this size
    return has & ~steep, np.count_nonzero(has), np.count_nonzero(steep)


def _not_steep_loop(candidate_index, slope, max_slope):
    """:func:`_not_steep_numpy` in one pass (compiled with numba): the same comparisons."""
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


NOT_STEEP = Twin('steep-line filter', _not_steep_numpy, kernel(_not_steep_loop),
                 lambda _dtype: [(np.ones((2, 2), dtype=np.intp), np.ones((2, 2)), 1.0)])


# --- chord slopes of one-point lines [ours] ---------------------------------------------------

def one_point_line_slopes(slope: np.ndarray, cand_r: np.ndarray, cand_z: np.ndarray,
                          compiled: bool = True) -> np.ndarray:
    """``slope`` (M, N) with every one-point line (NaN slope) given |dz/dr| of the chord from
    the previous candidate of its segment (module docstring); a segment's first candidate
    keeps NaN."""
    return CHORDS.run(compiled, np.asarray(slope, dtype=np.float64), cand_r, cand_z)


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
    of the same values."""
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


CHORDS = Twin('chord slopes', _chord_slopes_numpy, kernel(_chord_slopes_loop, error_model='numpy'),
              lambda _dtype: [(np.ones((2, 2)),) * 3])

CHORD_SLOPES = Stage('chord slopes', 'ours', 'use_chord_slope_for_single_points', (CHORDS,))
STAGES = (Stage('lines', 'paper', None, (LINES,)), CHORD_SLOPES,
          Stage('steep lines', 'paper', None, (NOT_STEEP,)))
