# SPDX-License-Identifier: Apache-2.0
"""Line extraction over the ground candidates of every segment (paper Algorithm 1).

Fit: errors-in-variables (Deming) maximum-likelihood line with variance ratio
lambda = var(z error) / var(r error), closed form from the second moments:

    beta = (s_zz - lambda s_rr + sqrt((s_zz - lambda s_rr)^2 + 4 lambda s_rz^2)) / (2 s_rz)
    alpha = mean_z - beta * mean_r

(lambda = 1 is orthogonal regression; lambda -> infinity tends to OLS of z on r.) Unlike OLS it
does not flatten steep noisy lines, which matters on ramps where both r and z of a candidate
carry error.

Growing (how Algorithm 1 is read here): candidates are visited in order of r. The current
line of a segment accumulates its candidates' moments; the next candidate is a *critical point*
-- it ends the current line and starts a new one -- when any of these holds:

* radial gap to the previous candidate > zeta_m (``max_gap_m``): a break in the data;
* rho~ changes by more than a factor ``max_density_jump`` (the paper's "smoothness of rho~");
* its perpendicular distance to the current line (>= 2 points) > delta (``max_distance_m``);
* the line with it added would be steeper than zeta_b (``max_slope``); for a one-point line
  this is the slope of the two-point chord.

All segments advance in lock-step (one numpy step per bin index, vectorised over the M
segments), so the cost is N small vector operations, not M*N Python iterations.

Elevated plateaus. A critical point reached by a steep step *up* (chord slope > zeta_b and rise
> ``step_up_m``, higher than any curb) from the previous candidate is where the ground meets an
obstacle; the candidates that follow are the obstacle's lowest points (a car roof whose ground
is occluded) until the sequence comes back down to within ``step_up_m`` of the ground level
before the step (extrapolated along the slope of the line that ended there), or drops by more
than ``step_up_m`` from one candidate to the next, or jumps a radial gap > zeta_m (the far edge
of the obstacle or its occlusion shadow: whatever is seen beyond it, a rising ramp included, is
taken as ground again). Such candidates are flagged
``elevated`` and do not train the GP.

Output per candidate: its line id (unique in the frame), whether it starts a line after a
critical point, and the slope g = |beta| of its final line. One-point lines have no slope: they
get NaN, which the GP treats as flat (g_d); a line steeper than zeta_b is flagged non-ground.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    elevated: np.ndarray  # (M, N) bool: candidate lies on a plateau entered by a steep step up


def deming_fit(s_rr, s_zz, s_rz, mean_r, mean_z, variance_ratio):
    """Deming (errors-in-variables ML) line from central second moments; vectorised.

    ``s_rr, s_zz, s_rz`` are the (co)variances of r and z (any normalisation, the same for all
    three). Returns ``(alpha, beta)``. Where s_rz == 0 the line is horizontal if the spread is
    mostly along r, else vertical (beta = +-inf).
    """
    s_rr, s_zz, s_rz = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (s_rr, s_zz, s_rz)))
    lam = float(variance_ratio)
    diff = s_zz - lam * s_rr
    with np.errstate(divide='ignore', invalid='ignore'):
        beta = (diff + np.sqrt(diff * diff + 4.0 * lam * s_rz * s_rz)) / (2.0 * s_rz)
    degenerate = s_rz == 0
    beta = np.where(degenerate, np.where(diff > 0, np.inf, 0.0), beta)
    with np.errstate(invalid='ignore'):
        alpha = mean_z - beta * mean_r
    return alpha, beta


def _fit_from_sums(n, sr, sz, srr, szz, srz, variance_ratio):
    """Deming fit from raw sums (n, Sr, Sz, Srr, Szz, Srz), vectorised over lines.

    The same closed form as :func:`deming_fit`, inlined without its argument checks because
    it runs twice per bin inside the line-growing loop.
    """
    with np.errstate(divide='ignore', invalid='ignore'):
        mean_r = sr / n
        mean_z = sz / n
        cov_rr = np.maximum(srr / n - mean_r * mean_r, 0.0)
        cov_zz = np.maximum(szz / n - mean_z * mean_z, 0.0)
        cov_rz = srz / n - mean_r * mean_z
        diff = cov_zz - variance_ratio * cov_rr
        beta = (diff + np.sqrt(diff * diff + 4.0 * variance_ratio * cov_rz * cov_rz)) / (
            2.0 * cov_rz)
        beta = np.where(cov_rz == 0, np.where(diff > 0, np.inf, 0.0), beta)
        alpha = mean_z - beta * mean_r
    return alpha, beta


def extract_lines(cand_r: np.ndarray, cand_z: np.ndarray, density: np.ndarray, *,
                  variance_ratio: float, max_slope: float, max_distance_m: float,
                  max_gap_m: float, max_density_jump: float,
                  step_up_m: float = 0.3) -> LineSegments:
    """Grow line-segments over the candidates (M, N) of every segment; see module docstring.

    Sums are taken about each segment's first candidate r/z to keep the moment arithmetic
    well conditioned far from the sensor.
    """
    m_count, n_count = cand_r.shape
    present = np.isfinite(cand_r) & np.isfinite(cand_z)
    rows = np.arange(m_count)
    first = np.argmax(present, axis=1)
    r0 = np.where(present.any(axis=1), cand_r[rows, first], 0.0)
    z0 = np.where(present.any(axis=1), cand_z[rows, first], 0.0)
    rr = cand_r - r0[:, None]
    zz = cand_z - z0[:, None]

    # moments (1, r, z, r^2, z^2, r z) of every candidate, 0 where there is none
    rr0, zz0 = np.where(present, rr, 0.0), np.where(present, zz, 0.0)
    moments = np.stack([present.astype(np.float64), rr0, zz0, rr0 * rr0, zz0 * zz0, rr0 * zz0])
    sums = np.zeros((6, m_count))  # n, Sr, Sz, Srr, Szz, Srz of each segment's current line
    last_r = np.full(m_count, np.nan)
    last_z = np.full(m_count, np.nan)
    last_rho = np.full(m_count, np.nan)
    current_line = np.full(m_count, -1, dtype=np.intp)
    elevated_now = np.zeros(m_count, dtype=bool)
    base_r = np.zeros(m_count)  # ground r, z and slope just before the step up
    base_z = np.zeros(m_count)
    base_slope = np.zeros(m_count)
    elevated = np.zeros((m_count, n_count), dtype=bool)
    next_line = 0
    line_id = np.full((m_count, n_count), -1, dtype=np.intp)
    is_critical = np.zeros((m_count, n_count), dtype=bool)
    low_density, high_density = 1.0 / max_density_jump, max_density_jump

    with np.errstate(divide='ignore', invalid='ignore'):  # empty lines give NaN: never true
        for k in range(n_count):
            has = present[:, k]
            if not has.any():
                continue
            r, z, rho = rr[:, k], zz[:, k], density[:, k]
            n = sums[0]
            started = has & (n > 0)
            dr, rise = r - last_r, z - last_z
            gap = dr > max_gap_m
            ratio = rho / last_rho
            jump = (ratio > high_density) | (ratio < low_density)
            alpha, beta = _fit_from_sums(*sums, variance_ratio)
            far = (n >= 2) & (np.abs(z - alpha - beta * r) / np.sqrt(1.0 + beta * beta)
                              > max_distance_m)
            # slope of the line if this candidate joins it (two-point chord for one-point lines)
            _, beta_new = _fit_from_sums(*(sums + moments[:, :, k]), variance_ratio)
            steep = np.abs(beta_new) > max_slope
            critical = started & (gap | jump | far | steep)

            chord = rise / np.maximum(dr, 1e-6)
            step_up = started & (rise > step_up_m) & (chord > max_slope)
            enter = step_up & ~elevated_now
            if enter.any():
                line_slope = np.where((n >= 2) & np.isfinite(beta), beta, 0.0)
                base_r = np.where(enter, last_r, base_r)
                base_z = np.where(enter, last_z, base_z)
                base_slope = np.where(enter, line_slope, base_slope)
            if elevated_now.any():
                back_down = z <= base_z + base_slope * (r - base_r) + step_up_m
                leave = has & elevated_now & ((rise < -step_up_m) | back_down | gap)
                elevated_now = (elevated_now | enter) & ~leave
            else:
                elevated_now = enter
            elevated[:, k] = has & elevated_now

            new_line = has & ~(n > 0) | critical
            n_new = int(np.count_nonzero(new_line))
            current_line[new_line] = np.arange(next_line, next_line + n_new)
            next_line += n_new
            sums = np.where(new_line, 0.0, sums) + moments[:, :, k]
            line_id[has, k] = current_line[has]
            is_critical[:, k] = critical
            last_r = np.where(has, r, last_r)
            last_z = np.where(has, z, last_z)
            last_rho = np.where(has, rho, last_rho)

    # Final fit of every line from its members (bincount over line ids).
    ids = line_id[present]
    r_abs, z_abs = cand_r[present], cand_z[present]
    seg_of = np.broadcast_to(rows[:, None], (m_count, n_count))[present]
    r_rel, z_rel = r_abs - r0[seg_of], z_abs - z0[seg_of]
    num_lines = next_line
    count = np.bincount(ids, minlength=num_lines).astype(np.float64)
    line_sums = [count] + [np.bincount(ids, weights=w, minlength=num_lines)
                           for w in (r_rel, z_rel, r_rel * r_rel, z_rel * z_rel, r_rel * z_rel)]
    alpha_rel, beta = _fit_from_sums(*line_sums, variance_ratio)
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
    return LineSegments(line_id, is_critical, slope, intercept, beta, count.astype(np.intp),
                        np.stack([r_lo, r_hi], axis=1), elevated)
