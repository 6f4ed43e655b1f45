# SPDX-License-Identifier: Apache-2.0
"""Stage ``coupled_surface`` [ours, ``use_coupled_surface``]: the ground followed across
segments, not only along them.

The paper's model is z(r) per segment: one curve along r, the same over the segment's whole
width, changing in a step at the border to the next segment. A bin's candidate is its lowest
point, which lies wherever in the bin the ground is lowest: where the ground rises *across* the
beams (an embankment beside the road, a cross slope, the flank of a valley) the candidates of
neighbouring segments sit at different azimuths and heights, and a curve per segment cannot
follow that.

This stage predicts the ground on every border between two segments with a GP over the
training candidates of *both* segments at their (x, y) positions: the paper's kernel in two
dimensions (``paciorek.paciorek_2d``, each candidate's L_i = a d_i), with the frame's theta
(learned by the paper's per-segment model, gp.py), its noise, prior mean and anchor at the
sensor. A point's ground height is linear along r between the bin edges of its segment, as in
the paper, on both borders of its segment, then linear in azimuth between the two borders: the
surface is continuous across segments.

Border b lies between segments b and b + 1 (they wrap around), at azimuth -pi + (b + 1) 2 pi / M.
Its knots are segment b's bin edges; segment b + 1 reads it there too, linear between the knots
(:func:`segment_borders`). A border whose two segments have no training candidate has no model:
it takes the frame's default height, as the per-segment model's segments without one do. The
length scale at a knot is a d of segment b's nearest training candidate (as the per-segment
prediction takes it), else of segment b + 1's, else of the flat clip ``max_length_factor``.

Cost: one Cholesky of n <= 2 N + 1 points per border and (N + 1) n kernel values (with one
length scale for every point, the stationary kernel, three exps a training point: the knots are
equally spaced); the posterior std stays the per-segment model's (the threshold's
``use_std_threshold`` and the surface's z_std read it).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import Stage, Twin, kernel
from .length_factors import factors_at_edges
from .paciorek import paciorek_2d, paciorek_2d_compiled

__all__ = ['border_azimuths', 'coupled_ground', 'segment_borders']


def border_azimuths(num_segments: int) -> np.ndarray:
    """(M,) azimuth of border b, between segments b and b + 1 (rad)."""
    return -np.pi + (np.arange(num_segments) + 1.0) * (2.0 * np.pi / num_segments)


def coupled_ground(model, grid, x, y, edges, max_length_factor: float, compiled: bool = True):
    """(lattice (M, 2, N + 1), centre mean (M, N + 1)) of a frame: the ground on each
    segment's left and right border at its bin edges, and halfway between them (the ground
    surface's rows). ``model``: the frame's ``predict.GroundModel``; ``grid``: its RadialGrid;
    x, y: the valid points' coordinates; ``edges``: (M, N + 1) bin edges (m)."""
    args = _border_arguments(model, grid, x, y, edges, max_length_factor, compiled)
    border = BORDERS.run(compiled, *args)
    border = np.where(np.isnan(border), model.default_height, border)
    lattice = segment_borders(border, edges)
    return lattice, 0.5 * (lattice[:, 0] + lattice[:, 1])


def _border_arguments(model, grid, x, y, edges, max_length_factor, compiled):
    """The arguments of :data:`BORDERS` from a frame's model and grid (float64, contiguous)."""
    sigma_f, gain, sigma_n = (float(t) for t in model.theta)
    index = grid.candidate_index
    has = index >= 0
    pick = np.where(has, index, 0)
    cand_x = np.where(has, x[pick], 0.0).astype(np.float64)
    cand_y = np.where(has, y[pick], 0.0).astype(np.float64)
    cand_z = np.where(has, grid.candidate_z, 0.0).astype(np.float64)
    d = model.length_factor
    cand_l = gain * np.where(np.isfinite(d), d, max_length_factor)
    training = np.ascontiguousarray(model.training)
    rows = np.arange(training.shape[0])
    knot_d = factors_at_edges(np.where(np.isfinite(d), d, max_length_factor), training, rows,
                              compiled)
    # a segment without a training candidate: its neighbour's d, else the flat clip
    empty = ~training.any(axis=1)
    knot_d[empty] = knot_d[(rows[empty] + 1) % rows.size]
    knot_d[empty & empty[(rows + 1) % rows.size]] = max_length_factor
    anchor = model.gp.anchor
    anchor_on = (np.zeros(rows.size, dtype=bool) if anchor is None
                 else np.ascontiguousarray(anchor.segments, dtype=bool))
    anchor_l = (np.ones(rows.size) if anchor is None
                else gain * np.asarray(anchor.length_factor, dtype=np.float64))
    return (cand_x, cand_y, cand_z, np.ascontiguousarray(cand_l), training,
            np.ascontiguousarray(edges, dtype=np.float64), gain * knot_d, sigma_f, sigma_n,
            float(model.gp.mean), float(anchor.height_m) if anchor is not None else 0.0,
            float(anchor.noise_var) if anchor is not None else 0.0, anchor_l, anchor_on)


def segment_borders(border: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(M, 2, N + 1): each segment's left border (border s - 1, linear between its knots,
    segment s - 1's edges, and held beyond them) and right border (border s) at the segment's
    own bin edges."""
    m_count = border.shape[0]
    left_row = (np.arange(m_count) - 1) % m_count
    # one sorted table of all borders, row b offset by a span larger than any r: np.interp
    # then reads every segment's edges on its left border at once
    span = float(np.max(edges)) + 1.0
    offset = np.arange(m_count)[:, None] * span
    knots = (edges + offset).ravel()
    query = np.clip(edges, edges[left_row, :1], edges[left_row, -1:]) + offset[left_row]
    left = np.interp(query, knots, border.ravel())
    return np.stack([left, border], axis=1)


# ------------------------------------------------------------------ the borders' ground

def _borders_numpy(cand_x, cand_y, cand_z, cand_l, training, knot_r, knot_l, sigma_f, sigma_n,
                   mean, anchor_z, anchor_var, anchor_l, anchor_on):
    """(M, N + 1) posterior mean of the ground at every border's knots (NaN: no training
    point): the numpy reference of :func:`_borders_loop`, equal to round-off. (M, N) candidate
    position, height, length scale (m) and training mask; (M, N + 1) knot r and length scale;
    theta's sigma_f and sigma_n (m); the prior mean (m); the anchor's height (m), extra noise
    variance (m^2), (M,) length scale in each segment and the segments that have it."""
    m_count = training.shape[0]
    nxt = (np.arange(m_count) + 1) % m_count
    anchor_in = anchor_on | anchor_on[nxt]
    a_l = np.where(anchor_on & anchor_on[nxt], 0.5 * (anchor_l + anchor_l[nxt]),
                   np.where(anchor_on, anchor_l, anchor_l[nxt]))
    # border b's points: the anchor (slot 0), segment b's candidates, segment b + 1's
    valid = np.concatenate([anchor_in[:, None], training, training[nxt]], axis=1)
    px, py, pz, pl = (np.where(valid, np.concatenate(parts, axis=1), fill) for parts, fill in (
        ((np.zeros((m_count, 1)), cand_x, cand_x[nxt]), 0.0),
        ((np.zeros((m_count, 1)), cand_y, cand_y[nxt]), 0.0),
        ((np.full((m_count, 1), anchor_z), cand_z, cand_z[nxt]), mean),
        ((a_l[:, None], cand_l, cand_l[nxt]), 1.0)))
    noise = np.where(valid, sigma_n * sigma_n, 1.0)
    noise[:, 0] += np.where(anchor_in, anchor_var, 0.0)
    sf2 = sigma_f * sigma_f
    k = paciorek_2d(px[:, :, None] - px[:, None, :], py[:, :, None] - py[:, None, :],
                    pl[:, :, None], pl[:, None, :], sf2)
    a = np.where(valid[:, :, None] & valid[:, None, :], k, 0.0)
    a[:, np.arange(a.shape[1]), np.arange(a.shape[1])] += noise  # padding: identity rows
    out = np.full(knot_r.shape, np.nan)
    has = valid.any(axis=1)
    if has.any():
        alpha = np.linalg.solve(a[has], (pz - mean)[has][:, :, None])[:, :, 0]
        phi = border_azimuths(m_count)[has][:, None]
        kx, ky = knot_r[has] * np.cos(phi), knot_r[has] * np.sin(phi)
        k_star = paciorek_2d(kx[:, :, None] - px[has][:, None, :],
                             ky[:, :, None] - py[has][:, None, :], knot_l[has][:, :, None],
                             pl[has][:, None, :], sf2)
        k_star = np.where(valid[has][:, None, :], k_star, 0.0)
        out[has] = mean + np.einsum('bkn,bn->bk', k_star, alpha)
    return out


def _borders_loop(cand_x, cand_y, cand_z, cand_l, training, knot_r, knot_l, sigma_f, sigma_n,
                  mean, anchor_z, anchor_var, anchor_l, anchor_on):
    """:func:`_borders_numpy` per border at its own size (compiled with numba): the kernel, an
    in-place Cholesky, two triangular solves and the prediction; a border whose matrix is not
    positive definite keeps NaN (the caller's default height)."""
    m_count, n_count = training.shape
    n_max = 2 * n_count + 1
    a = np.empty((n_max, n_max))
    alpha, px, py, pl = np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max)
    out = np.full(knot_r.shape, np.nan)
    sf2 = sigma_f * sigma_f
    width = 2.0 * math.pi / m_count
    for b in range(m_count):
        nb = b + 1 if b + 1 < m_count else 0
        n = 0
        if anchor_on[b] or anchor_on[nb]:
            both = anchor_on[b] and anchor_on[nb]
            pl[0] = (0.5 * (anchor_l[b] + anchor_l[nb]) if both
                     else (anchor_l[b] if anchor_on[b] else anchor_l[nb]))
            px[0], py[0], alpha[0] = 0.0, 0.0, anchor_z - mean
            n = 1
        for m in (b, nb):
            for j in range(n_count):
                if training[m, j]:
                    px[n], py[n], pl[n] = cand_x[m, j], cand_y[m, j], cand_l[m, j]
                    alpha[n] = cand_z[m, j] - mean
                    n += 1
        if n == 0:
            continue
        for i in range(n):
            for j in range(i + 1):
                a[i, j] = paciorek_2d_compiled(px[i] - px[j], py[i] - py[j], pl[i], pl[j], sf2)
            a[i, i] += sigma_n * sigma_n
        if anchor_on[b] or anchor_on[nb]:
            a[0, 0] += anchor_var
        if not _cholesky_solve(a, alpha, n):
            continue
        phi = -math.pi + (b + 1.0) * width
        if _one_length_scale(pl, n, knot_l, b):
            _predict_stationary(out, b, knot_r, px, py, alpha, n, math.cos(phi), math.sin(phi),
                                2.0 * pl[0] * pl[0], sf2, mean)
            continue
        c, s = math.cos(phi), math.sin(phi)
        for k in range(knot_r.shape[1]):
            kx, ky = knot_r[b, k] * c, knot_r[b, k] * s
            acc = 0.0
            for i in range(n):
                acc += paciorek_2d_compiled(kx - px[i], ky - py[i], knot_l[b, k], pl[i],
                                            sf2) * alpha[i]
            out[b, k] = mean + acc
    return out


def _one_length_scale(pl, n, knot_l, b):
    """Whether the border's n training points and its knots share one length scale (the
    stationary kernel, ``use_nonstationary_length_scale`` off)."""
    for i in range(n):
        if pl[i] != pl[0]:
            return False
    for k in range(knot_l.shape[1]):
        if knot_l[b, k] != pl[0]:
            return False
    return True


def _predict_stationary(out, b, knot_r, px, py, alpha, n, c, s, s2, sf2, mean):
    """The posterior mean at border b's knots for one length scale (prefactor 1, s2 = 2 L^2):
    the knots are equally spaced along the border (r_k = r_0 + k w), so each training point's
    exp(-|p_k - x_i|^2 / s2) follows from its value at the nearest knot by two ratios, one
    constant (exp(-2 w^2 / s2)): three exps a training point instead of one a knot."""
    n_knots = knot_r.shape[1]
    r0 = knot_r[b, 0]
    w = (knot_r[b, n_knots - 1] - r0) / (n_knots - 1)
    ratio = math.exp(-2.0 * w * w / s2)
    for k in range(n_knots):
        out[b, k] = 0.0
    for i in range(n):
        t = px[i] * c + py[i] * s  # along the border
        h2 = px[i] * px[i] + py[i] * py[i] - t * t  # across it, squared
        peak = int(min(max(round((t - r0) / w) if w > 0.0 else 0.0, 0.0), n_knots - 1.0))
        u = r0 + peak * w - t
        value = math.exp(-(u * u + max(h2, 0.0)) / s2) * alpha[i]
        out[b, peak] += value
        up, step = value, math.exp(-(2.0 * w * u + w * w) / s2)
        for k in range(peak + 1, n_knots):  # farther out: the exponent falls by step / ratio
            up *= step
            out[b, k] += up
            step *= ratio
        down, step = value, math.exp((2.0 * w * u - w * w) / s2)
        for k in range(peak - 1, -1, -1):
            down *= step
            out[b, k] += down
            step *= ratio
    for k in range(n_knots):
        out[b, k] = mean + sf2 * out[b, k]


def _cholesky_solve(a, b, n):
    """Solve a[:n, :n] x = b[:n] in place (x into b) with the Cholesky factor of the lower
    triangle, written over it; False at a pivot that is not positive."""
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            v = a[i, j]
            for k in range(j):
                v -= a[i, k] * a[j, k]
            a[i, j] = v / d
    for i in range(n):
        v = b[i]
        for k in range(i):
            v -= a[i, k] * b[k]
        b[i] = v / a[i, i]
    for i in range(n - 1, -1, -1):
        v = b[i]
        for k in range(i + 1, n):
            v -= a[k, i] * b[k]
        b[i] = v / a[i, i]
    return True


_cholesky_solve = kernel(_cholesky_solve, inline='always') or _cholesky_solve
_one_length_scale = kernel(_one_length_scale, inline='always') or _one_length_scale
_predict_stationary = kernel(_predict_stationary) or _predict_stationary


# ----------------------------------------------------------------------- the points' height

def between_borders(lattice, grid, compiled: bool = True) -> np.ndarray:
    """z_hat of every point of ``grid`` (in its points' precision) from the (M, 2, N + 1)
    ``lattice`` of :func:`coupled_ground` (module docstring)."""
    return BETWEEN.run(compiled, np.ascontiguousarray(lattice), grid.point_segment,
                       grid.point_bin, grid.point_bin_fraction, grid.point_angle)


def _between_numpy(lattice, point_segment, point_bin, point_frac, point_angle):
    """The numpy reference of :func:`_between_loop` (the same values bit for bit)."""
    m_count, _, n_knots = lattice.shape
    flat = lattice.ravel().astype(point_frac.dtype)
    inner = point_segment.astype(np.intp) * (2 * n_knots) + point_bin
    left = _lerp(flat[inner], flat[inner + 1], point_frac)
    inner += n_knots
    right = _lerp(flat[inner], flat[inner + 1], point_frac)
    w = (point_angle + np.pi) * (m_count / (2.0 * np.pi)) - point_segment
    return _lerp(left, right, np.minimum(np.maximum(w, 0.0), 1.0).astype(point_frac.dtype))


def _lerp(low, high, frac):
    """low + (high - low) frac in the arrays' precision (a new array)."""
    step = high - low
    step *= frac
    step += low
    return step


def _between_loop(lattice, point_segment, point_bin, point_frac, point_angle):
    """Each point's ground on the two borders of its segment at its r (linear between the bin
    edges), then linear in azimuth between them, in one pass (compiled with numba)."""
    m_count, _, n_knots = lattice.shape
    flat = lattice.ravel().astype(point_frac.dtype)
    out = np.empty(point_frac.size, dtype=point_frac.dtype)
    scale = m_count / (2.0 * math.pi)
    for i in range(point_frac.size):
        s = point_segment[i]
        f = point_frac[i]
        inner = s * (2 * n_knots) + point_bin[i]
        low = flat[inner]
        left = (flat[inner + 1] - low) * f + low
        inner += n_knots
        low = flat[inner]
        right = (flat[inner + 1] - low) * f + low
        w = point_frac.dtype.type(min(max((point_angle[i] + math.pi) * scale - s, 0.0), 1.0))
        out[i] = (right - left) * w + left
    return out


def _borders_examples(_dtype):
    """Two segments of two bins, a training candidate each, the anchor in one."""
    training = np.array([[True, False], [False, True]])
    ones = np.ones((2, 2))
    return [(ones, -ones, -ones, 2.0 * ones, training, np.ones((2, 3)), 2.0 * np.ones((2, 3)),
             0.5, 0.05, -1.0, -1.7, 0.09, np.ones(2), np.array([True, False]))]


def _between_examples(dtype):
    return [(np.zeros((2, 2, 3)), np.array([0, 1], dtype=np.int32),
             np.array([0, 1], dtype=np.int32), np.array([0.5, 0.25], dtype=dtype),
             np.array([-1.0, 1.0]))]


# the borders' solve equals its reference to round-off (loops against LAPACK): compiled
# before use, like the GP step
BORDERS = Twin('coupled surface borders', _borders_numpy, kernel(_borders_loop),
               _borders_examples, exact=False)
BETWEEN = Twin('coupled surface points', _between_numpy, kernel(_between_loop),
               _between_examples)
STAGE = Stage('coupled_surface', 'ours', 'use_coupled_surface', (BORDERS, BETWEEN))
STAGES = (STAGE,)
