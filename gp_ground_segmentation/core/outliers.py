# SPDX-License-Identifier: Apache-2.0
"""Stage ``outliers`` [ours, ``use_outlier_rejection``]: candidates that are not ground stop
training the GP.

The lowest point of a bin is not always ground: below-ground reflection noise (points metres
under the road) and the tops of obstacles whose ground is occluded both become candidates. A
candidate whose leave-one-out GP residual z_i - mean_{-i} = alpha_i / [A^-1]_ii (R&W eq. 5.12)
is above ``outlier_residual_m`` (an obstacle top) or below ``-noise_spike_m`` (reflection noise)
gets a huge noise variance (it stops pulling the fit) and the GP is solved again. The segmenter
runs a pass before and one after learning theta, so that an outlier pair masking each other in
the first is caught in the second.

Two rules refine "above" (ours):

* ``use_outlier_std_limit``: the limit above is also ``outlier_std_factor`` leave-one-out
  predictive stds sqrt(1 / [A^-1]_ii): where candidates are sparse (16-beam rings, far ground,
  high mounts) the GP predicts a left-out candidate loosely, and the fixed limit alone rejected
  true ground. Off: ``outlier_residual_m`` alone.
* ``use_wide_terrain_rule``: an obstacle top that both neighbouring segments continue at its
  height (``outlier_wide_terrain_m``), with no ground right beside it below and rising from its
  segment's previous candidate no steeper than ``outlier_wide_terrain_max_slope``, is terrain
  and keeps training (:func:`wide_terrain_candidates`).

``outlier_worst_per_segment`` (off) drops at most the worst obstacle top per segment and pass.
The compiled passes read the GP's (S, n) slots directly; their numpy references map the slots
to the (M, N) grid first (``FrameGP.to_grid``'s arithmetic).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, kernel
from .gp import leave_one_out, slots_to_grid

OUTLIER_NOISE_VAR = 1e4  # m^2: a rejected candidate's noise variance (std 100 m)


def reject_outliers(gp, sol, outliers: np.ndarray, params):
    """One robust pass over a FrameGP ``gp`` and its solution ``sol``: (GP, solution, outliers)
    with the new outliers' noise made huge; ``outliers`` (M, N) are the ones known already."""
    p = params
    use_compiled = gp.backend == 'numba'
    std_factor = float(p.outlier_std_factor) if STD_LIMIT.on(p) else 0.0  # 0: the limit alone
    new = NEW_OUTLIERS.run(use_compiled, sol.alpha, sol.a_inv, gp.valid, gp.is_anchor,
                           gp.segments, gp.bins, outliers, float(p.outlier_residual_m),
                           float(p.noise_spike_m), bool(p.outlier_worst_per_segment),
                           std_factor)
    if new.any() and WIDE_TERRAIN.on(p):
        # obstacle tops (residual above, not the reflection noise below) that the
        # neighbouring segments continue are terrain: they keep training
        new = NOT_WIDE.run(use_compiled, new, sol.alpha, sol.a_inv, gp.valid, gp.is_anchor,
                           gp.segments, gp.bins, gp.r, gp.z, float(p.outlier_wide_terrain_m),
                           float(p.outlier_wide_terrain_max_slope))
    if not new.any():
        return gp, sol, outliers
    outliers = outliers | new
    gp = gp.with_noise(np.where(outliers, OUTLIER_NOISE_VAR, 0.0))
    return gp, gp.solve(sol.theta), outliers


def _new_outliers_numpy(alpha, a_inv, valid, is_anchor, segments, bins, outliers, above_m,
                        below_m, worst_above_only, std_factor):
    """The numpy reference of :func:`_new_outliers_loop`."""
    residual, std = leave_one_out(alpha, a_inv, valid)
    slots = (valid, is_anchor, segments, bins, outliers.shape)
    return ~outliers & outlier_candidates(
        slots_to_grid(residual, *slots), above_m=above_m, below_m=below_m,
        worst_above_only=worst_above_only, loo_std=slots_to_grid(std, *slots),
        std_factor=std_factor)


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


def _new_outliers_loop(alpha, a_inv, valid, is_anchor, segments, bins, outliers, above_m,
                       below_m, worst_above_only, std_factor):
    """(M, N) candidates not yet in ``outliers`` whose leave-one-out residual is an outlier, in
    one pass over the GP's slots (compiled with numba): :func:`_new_outliers_numpy` (the
    slots mapped to the grid, then :func:`outlier_candidates`) with the same values: residual
    alpha_i / [A^-1]_ii of each grid candidate's slot, the same comparisons (the limit above
    is also ``std_factor`` times the leave-one-out std sqrt(1 / [A^-1]_ii)), and with
    ``worst_above_only`` the row's highest residual."""
    new = np.zeros(outliers.shape, dtype=np.bool_)
    n_slots = valid.shape[1]
    for s in range(segments.size):
        m = segments[s]
        top = -np.inf  # the segment's highest residual (NaN residuals do not count)
        if worst_above_only:
            for i in range(n_slots):
                if valid[s, i] and not is_anchor[s, i]:
                    loo = alpha[s, i] / a_inv[s, i, i]
                    if loo > top:
                        top = loo
        for i in range(n_slots):
            if not valid[s, i] or is_anchor[s, i]:
                continue
            loo = alpha[s, i] / a_inv[s, i, i]
            limit = max(above_m, std_factor * np.sqrt(1.0 / a_inv[s, i, i]))
            above = loo > limit
            if worst_above_only and above:
                above = loo >= top
            b = bins[s, i]
            new[m, b] = (above or loo < -below_m) and not outliers[m, b]
    return new


def _not_wide_terrain_numpy(new, alpha, a_inv, valid, is_anchor, segments, bins, r, z,
                            tolerance_m, max_slope):
    """The numpy reference of :func:`_not_wide_terrain_loop`."""
    slots = (valid, is_anchor, segments, bins, new.shape)
    residual = leave_one_out(alpha, a_inv, valid)[0]
    above = new & (slots_to_grid(residual, *slots) > 0)
    return new & ~wide_terrain_candidates(
        above, slots_to_grid(z, *slots), tolerance_m, r=slots_to_grid(r, *slots),
        max_slope=max_slope, compiled=False)


def _not_wide_terrain_loop(new, alpha, a_inv, valid, is_anchor, segments, bins, r, z,
                           tolerance_m, max_slope):
    """``new`` (M, N) without the candidates that :func:`wide_terrain_candidates` calls
    terrain among those with a leave-one-out residual above 0 (compiled with numba): the
    grids of residual, z and r that the reference (:func:`_not_wide_terrain_numpy`) makes
    with :func:`slots_to_grid` (NaN where no grid candidate trains), filled from the GP's slots
    in one pass, and the compiled wide-terrain pass on them; the same values, so the mask.
    """
    m_count, n_bins = new.shape
    above = np.zeros((m_count, n_bins), dtype=np.bool_)
    z_grid = np.full((m_count, n_bins), np.nan)
    r_grid = np.full((m_count, n_bins), np.nan)
    for s in range(segments.size):
        m = segments[s]
        for i in range(valid.shape[1]):
            if valid[s, i] and not is_anchor[s, i]:
                b = bins[s, i]
                z_grid[m, b] = z[s, i]
                r_grid[m, b] = r[s, i]
                above[m, b] = new[m, b] and alpha[s, i] / a_inv[s, i, i] > 0
    wide = _wide_terrain_compiled(above, z_grid, r_grid, tolerance_m, max_slope)
    out = np.empty((m_count, n_bins), dtype=np.bool_)
    for m in range(m_count):
        for b in range(n_bins):
            out[m, b] = new[m, b] and not wide[m, b]
    return out


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
    ground in rings all around the sensor are continued by every segment and often have no
    candidate of their own segment in the bins beside them, but the segments beside them do,
    on the ground. The slope test keeps a wall seen over an occlusion shadow from being
    terrain: the lowest visible part of a far wall whose floor is hidden behind furniture is
    continued by the neighbouring segments like terrain, but it rises steeply from the floor
    before the shadow, where far ground on a hill seen by a 16-beam sensor rises gently over
    the gap.

    ``compiled``: one numba pass over the asked-for candidates when numba imports (else the
    numpy reference, whole-grid shifts); both give the same mask.
    """
    mask = np.ascontiguousarray(mask, dtype=bool)
    z = np.ascontiguousarray(z, dtype=np.float64)
    r = np.full(z.shape, np.nan) if r is None else np.ascontiguousarray(r, dtype=np.float64)
    return WIDE.run(compiled, mask, z, r, float(tolerance_m), float(max_slope))


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


def _gp_slot_examples(_dtype):
    slots, flags = np.ones((2, 2)), np.ones((2, 2), bool)
    return slots, np.ones((2, 2, 2)), flags, flags, np.zeros(2, np.intp), np.zeros((2, 2), np.intp)


# numpy's error model: a zero [A^-1]_ii gives an infinite residual as in the reference, not a
# ZeroDivisionError out of segment()
NEW_OUTLIERS = Twin('outlier pass', _new_outliers_numpy,
                    kernel(_new_outliers_loop, error_model='numpy'),
                    lambda dtype: [(*_gp_slot_examples(dtype), np.ones((2, 2), bool), 1.0, 1.0,
                                    False, 3.0)])
_not_wide_compiled = None
if AVAILABLE:  # the pass calls the compiled wide-terrain loop
    _not_wide_compiled = kernel(_not_wide_terrain_loop, error_model='numpy')
NOT_WIDE = Twin('wide-terrain rule of the outlier pass', _not_wide_terrain_numpy,
                _not_wide_compiled,
                lambda dtype: [(np.ones((2, 2), bool), *_gp_slot_examples(dtype),
                                np.ones((2, 2)), np.ones((2, 2)), 1.0, 1.0)])
WIDE = Twin('wide terrain', _wide_terrain_numpy, _wide_terrain_compiled,
            lambda _dtype: [(np.ones((2, 2), bool), np.ones((2, 2)), np.ones((2, 2)), 1.0,
                             1.0)])

STD_LIMIT = Stage('outlier std limit', 'ours', 'use_outlier_std_limit')
WIDE_TERRAIN = Stage('wide-terrain rule', 'ours', 'use_wide_terrain_rule', (NOT_WIDE, WIDE))
STAGE = Stage('outliers', 'ours', 'use_outlier_rejection', (NEW_OUTLIERS,))
STAGES = (STAGE, STD_LIMIT, WIDE_TERRAIN)
