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

Cost: one Cholesky of n <= 2 N + 1 points per border, its kernel between the two segments (each
segment's own block is computed once: it lies on two borders) and (N + 1) n kernel values (with
one length scale for every point, the stationary kernel, three exps a training point: the knots
are equally spaced); the posterior std stays the per-segment model's (the threshold's
``use_std_threshold`` and the surface's z_std read it).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import Stage, Twin, kernel
from .labels import interpolate_at_points, is_ground, is_ground_compiled
from .length_factors import factors_at_edges
from .paciorek import paciorek_2d, paciorek_2d_compiled, stationary_along_compiled

__all__ = ['border_azimuths', 'coupled_ground', 'coupled_labels']


def border_azimuths(num_segments: int) -> np.ndarray:
    """(M,) azimuth of border b, between segments b and b + 1 (rad)."""
    return -np.pi + (np.arange(num_segments) + 1.0) * (2.0 * np.pi / num_segments)


def coupled_ground(model, grid, x, y, edges, max_length_factor: float, compiled: bool = True):
    """(lattice (M, 2, N + 1), centre mean (M, N + 1)) of a frame: the ground on each
    segment's left and right border at its bin edges, and halfway between them (the ground
    surface's rows). ``model``: the frame's ``predict.GroundModel``; ``grid``: its RadialGrid;
    x, y: the valid points' coordinates; ``edges``: (M, N + 1) bin edges (m)."""
    sigma_f, gain, sigma_n = (float(t) for t in model.theta)
    anchor = model.gp.anchor
    m_count = edges.shape[0]
    anchor_on = (np.zeros(m_count, dtype=bool) if anchor is None
                 else np.ascontiguousarray(anchor.segments, dtype=bool))
    anchor_d = (np.ones(m_count) if anchor is None
                else np.ascontiguousarray(anchor.length_factor, dtype=np.float64))
    lattice = BORDERS.run(
        compiled, x, y, grid.candidate_index, grid.candidate_z,
        np.ascontiguousarray(model.length_factor, dtype=np.float64),
        np.ascontiguousarray(model.training), np.ascontiguousarray(edges, dtype=np.float64),
        gain, float(max_length_factor), sigma_f, sigma_n, float(model.gp.mean),
        float(model.default_height), float(anchor.height_m) if anchor is not None else 0.0,
        float(anchor.noise_var) if anchor is not None else 0.0, anchor_d, anchor_on)
    return lattice, 0.5 * (lattice[:, 0] + lattice[:, 1])


def coupled_labels(lattice, grid, z, threshold, compiled: bool = True):
    """(z_hat, ground) of every point of ``grid``: its ground between its segment's borders
    (``lattice`` of :func:`coupled_ground`) and the label rule with ``threshold``, a scalar or
    (M, N + 1) at the bin edges (linear along r within each point's bin, as labels.py)."""
    scalar = np.ndim(threshold) == 0
    limit = z.dtype.type(threshold if scalar else np.inf)
    z_hat, ground = BETWEEN.run(compiled, np.ascontiguousarray(lattice), grid.point_segment,
                                grid.point_bin, grid.point_bin_fraction, grid.point_angle, z,
                                limit)
    if not scalar:
        ground = is_ground(z, z_hat, interpolate_at_points(threshold, grid))
    return z_hat, ground


# ------------------------------------------------------------------ the borders' ground

def _borders_numpy(x, y, candidate_index, candidate_z, d, training, edges, gain, d_flat,
                   sigma_f, sigma_n, mean, default_height, anchor_z, anchor_var, anchor_d,
                   anchor_on):
    """(M, 2, N + 1) ground on each segment's left and right border at its bin edges: the
    numpy reference of :func:`_borders_loop`, equal to round-off. x, y: the valid points;
    (M, N) candidate index, height, length factor d (NaN: none) and training mask; (M, N + 1)
    bin edges; theta's gain a, sigma_f and sigma_n (m); ``d_flat`` (max_length_factor) where a
    border's segments have no d; the prior mean and default height (m); the anchor's height
    (m), extra noise variance (m^2), (M,) length factor in each segment and where it is."""
    m_count = training.shape[0]
    nxt = (np.arange(m_count) + 1) % m_count
    pick = np.where(candidate_index >= 0, candidate_index, 0)
    cand_x = x[pick].astype(np.float64)
    cand_y = y[pick].astype(np.float64)
    cand_l = gain * np.where(np.isfinite(d), d, d_flat)
    knot_l = gain * _knot_factors(np.where(np.isfinite(d), d, d_flat), training, d_flat)
    anchor_in = anchor_on | anchor_on[nxt]
    a_l = gain * np.where(anchor_on & anchor_on[nxt], 0.5 * (anchor_d + anchor_d[nxt]),
                          np.where(anchor_on, anchor_d, anchor_d[nxt]))
    # border b's points: the anchor (slot 0), segment b's candidates, segment b + 1's
    valid = np.concatenate([anchor_in[:, None], training, training[nxt]], axis=1)
    px, py, pz, pl = (np.where(valid, np.concatenate(parts, axis=1), fill) for parts, fill in (
        ((np.zeros((m_count, 1)), cand_x, cand_x[nxt]), 0.0),
        ((np.zeros((m_count, 1)), cand_y, cand_y[nxt]), 0.0),
        ((np.full((m_count, 1), anchor_z), candidate_z, candidate_z[nxt]), mean),
        ((a_l[:, None], cand_l, cand_l[nxt]), 1.0)))
    noise = np.where(valid, sigma_n * sigma_n, 1.0)
    noise[:, 0] += np.where(anchor_in, anchor_var, 0.0)
    sf2 = sigma_f * sigma_f
    k = paciorek_2d(px[:, :, None] - px[:, None, :], py[:, :, None] - py[:, None, :],
                    pl[:, :, None], pl[:, None, :], sf2)
    a = np.where(valid[:, :, None] & valid[:, None, :], k, 0.0)
    a[:, np.arange(a.shape[1]), np.arange(a.shape[1])] += noise  # padding: identity rows
    border = np.full(edges.shape, float(default_height))
    has = valid.any(axis=1)
    if has.any():
        alpha = np.linalg.solve(a[has], (pz - mean)[has][:, :, None])[:, :, 0]
        phi = border_azimuths(m_count)[has][:, None]
        kx, ky = edges[has] * np.cos(phi), edges[has] * np.sin(phi)
        k_star = paciorek_2d(kx[:, :, None] - px[has][:, None, :],
                             ky[:, :, None] - py[has][:, None, :], knot_l[has][:, :, None],
                             pl[has][:, None, :], sf2)
        k_star = np.where(valid[has][:, None, :], k_star, 0.0)
        border[has] = mean + np.einsum('bkn,bn->bk', k_star, alpha)
    return np.stack([_left_borders(border, edges), border], axis=1)


def _knot_factors(d, training, d_flat):
    """(M, N + 1) d at border b's knots (segment b's bin edges): segment b's nearest training
    candidate's (as the per-segment prediction takes it), else segment b + 1's, else
    ``d_flat``."""
    rows = np.arange(training.shape[0])
    knot = factors_at_edges(d, training, rows, compiled=False)
    empty = ~training.any(axis=1)
    knot[empty] = knot[(rows[empty] + 1) % rows.size]
    knot[empty & empty[(rows + 1) % rows.size]] = d_flat
    return knot


def _left_borders(border, edges):
    """(M, N + 1) border s - 1 read at segment s's bin edges: linear between its knots
    (segment s - 1's edges), held beyond them."""
    m_count, n_knots = edges.shape
    left_row = (np.arange(m_count) - 1) % m_count
    low = edges[left_row, :1]
    width = (edges[left_row, -1:] - low) / (n_knots - 1)
    u = np.clip((edges - low) / np.where(width > 0, width, 1.0), 0.0, n_knots - 1.0)
    j = np.minimum(np.floor(u), n_knots - 2).astype(np.intp)
    rows = border[left_row]
    lo = np.take_along_axis(rows, j, axis=1)
    hi = np.take_along_axis(rows, j + 1, axis=1)
    return lo + (hi - lo) * (u - j)


def _borders_loop(x, y, candidate_index, candidate_z, d, training, edges, gain, d_flat,
                  sigma_f, sigma_n, mean, default_height, anchor_z, anchor_var, anchor_d,
                  anchor_on):
    """:func:`_borders_numpy` per border at its own size (compiled with numba): every
    segment's training candidates and their kernel gathered once (a segment lies on two
    borders), then per border its points, the kernel between its two segments, an in-place
    Cholesky, two triangular solves, the prediction at the knots, then every segment's left
    border read at its edges; a border whose matrix is not positive definite keeps the
    default height."""
    m_count, n_count = training.shape
    n_knots = n_count + 1
    n_max = 2 * n_count + 1
    a = np.empty((n_max, n_max))
    alpha, px, py, pl = np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max)
    knot_l = np.empty(n_knots)
    knot_row = np.empty(n_knots)  # one training point's kernel at the knots
    border = np.empty((m_count, n_knots))
    sf2 = sigma_f * sigma_f
    segment_xylz = np.empty((m_count, 4, n_count))
    seg_n = np.empty(m_count, dtype=np.int64)
    block_start = np.empty(m_count, dtype=np.int64)
    blocks = np.empty(m_count * (n_count * (n_count + 1) // 2))
    _segment_points(x, y, candidate_index, candidate_z, d, training, gain, d_flat, mean, sf2,
                    segment_xylz, seg_n, block_start, blocks)
    width = 2.0 * math.pi / m_count
    for b in range(m_count):
        nb = b + 1 if b + 1 < m_count else 0
        n = _gather_border(b, nb, segment_xylz, seg_n, gain, mean, anchor_z, anchor_d,
                           anchor_on, px, py, pl, alpha)
        for k in range(n_knots):
            border[b, k] = default_height
        if n == 0:
            continue
        _fill_knot_factors(b, nb, d, training, gain, d_flat, knot_l)
        _border_kernel(a, n, n - seg_n[b] - seg_n[nb], seg_n[b], seg_n[nb], blocks,
                       block_start[b], block_start[nb], px, py, pl, sf2)
        for i in range(n):
            a[i, i] += sigma_n * sigma_n
        if anchor_on[b] or anchor_on[nb]:
            a[0, 0] += anchor_var
        if not _cholesky_solve(a, alpha, n):
            continue
        phi = -math.pi + (b + 1.0) * width
        c, s = math.cos(phi), math.sin(phi)
        if _one_length_scale(pl, n, knot_l) and _finite_spacing(edges, b):
            _predict_stationary(border, b, edges, px, py, alpha, n, c, s,
                                2.0 * pl[0] * pl[0], sf2, mean, knot_row)
            continue
        for k in range(n_knots):
            kx, ky = edges[b, k] * c, edges[b, k] * s
            acc = 0.0
            for i in range(n):
                acc += paciorek_2d_compiled(kx - px[i], ky - py[i], knot_l[k], pl[i],
                                            sf2) * alpha[i]
            border[b, k] = mean + acc
    return _lattice(border, edges)


def _segment_points(x, y, candidate_index, candidate_z, d, training, gain, d_flat, mean, sf2,
                    segment_xylz, seg_n, block_start, blocks):
    """Every segment's training candidates into ``segment_xylz`` (M, 4, N: x, y, length scale
    a d, z minus the prior mean) and their number into ``seg_n``, and the kernel among them
    (lower triangle row by row, from ``block_start[m]``) into ``blocks``."""
    start = 0
    for m in range(training.shape[0]):
        n = 0
        for j in range(training.shape[1]):
            if training[m, j]:
                i = candidate_index[m, j]
                segment_xylz[m, 0, n] = np.float64(x[i])
                segment_xylz[m, 1, n] = np.float64(y[i])
                segment_xylz[m, 2, n] = gain * (d[m, j] if np.isfinite(d[m, j]) else d_flat)
                segment_xylz[m, 3, n] = candidate_z[m, j] - mean
                n += 1
        seg_n[m] = n
        block_start[m] = start
        sx, sy, sl = segment_xylz[m, 0], segment_xylz[m, 1], segment_xylz[m, 2]
        for i in range(n):
            for j in range(i + 1):
                blocks[start + j] = paciorek_2d_compiled(sx[i] - sx[j], sy[i] - sy[j], sl[i],
                                                         sl[j], sf2)
            start += i + 1


def _gather_border(b, nb, segment_xylz, seg_n, gain, mean, anchor_z, anchor_d, anchor_on, px,
                   py, pl, alpha):
    """Border b's training points into px, py, pl, alpha (z minus the prior mean): the anchor
    first when either segment has it (its length factor the mean of theirs), then segment b's
    and segment nb's training candidates (:func:`_segment_points`); returns their number."""
    n = 0
    if anchor_on[b] or anchor_on[nb]:
        if anchor_on[b] and anchor_on[nb]:
            pl[0] = gain * (0.5 * (anchor_d[b] + anchor_d[nb]))
        else:
            pl[0] = gain * (anchor_d[b] if anchor_on[b] else anchor_d[nb])
        px[0], py[0], alpha[0] = 0.0, 0.0, anchor_z - mean
        n = 1
    for m in (b, nb):
        for j in range(seg_n[m]):
            px[n], py[n] = segment_xylz[m, 0, j], segment_xylz[m, 1, j]
            pl[n], alpha[n] = segment_xylz[m, 2, j], segment_xylz[m, 3, j]
            n += 1
    return n


def _border_kernel(a, n, o, n1, n2, blocks, start1, start2, px, py, pl, sf2):
    """The lower triangle of border b's kernel (no noise) into a[:n, :n]: the anchor's row
    and column (when ``o`` is 1), the two segments' own blocks copied from ``blocks`` (from
    ``start1`` and ``start2``, :func:`_segment_points`) and the n2 x n1 block between them."""
    for i in range(o):
        for j in range(i + 1):
            a[i, j] = paciorek_2d_compiled(px[i] - px[j], py[i] - py[j], pl[i], pl[j], sf2)
    for i in range(o, n):
        for j in range(o):
            a[i, j] = paciorek_2d_compiled(px[i] - px[j], py[i] - py[j], pl[i], pl[j], sf2)
    s = start1
    for i in range(o, o + n1):
        for j in range(o, i + 1):
            a[i, j] = blocks[s]
            s += 1
    s = start2
    for i in range(o + n1, n):
        for j in range(o, o + n1):
            a[i, j] = paciorek_2d_compiled(px[i] - px[j], py[i] - py[j], pl[i], pl[j], sf2)
        for j in range(o + n1, i + 1):
            a[i, j] = blocks[s]
            s += 1


def _fill_knot_factors(b, nb, d, training, gain, d_flat, knot_l):
    """a d at border b's knots into ``knot_l`` (:func:`_knot_factors`' rule)."""
    n_count = training.shape[1]
    for m in (b, nb):
        first = -1
        for j in range(n_count):
            if training[m, j]:
                first = j
                break
        if first < 0:
            continue
        pick = first
        for k in range(n_count):
            if training[m, k]:
                pick = k
            value = d[m, pick]
            knot_l[k] = gain * (value if np.isfinite(value) else d_flat)
        knot_l[n_count] = knot_l[n_count - 1]
        return
    for k in range(n_count + 1):
        knot_l[k] = gain * d_flat


def _lattice(border, edges):
    """(M, 2, N + 1): border s - 1 read at segment s's edges (:func:`_left_borders`' rule) and
    border s, for every segment."""
    m_count, n_knots = edges.shape
    out = np.empty((m_count, 2, n_knots))
    for s in range(m_count):
        left = s - 1 if s > 0 else m_count - 1
        low = edges[left, 0]
        width = (edges[left, n_knots - 1] - low) / (n_knots - 1)
        for k in range(n_knots):
            u = (edges[s, k] - low) / (width if width > 0.0 else 1.0)
            u = min(max(u, 0.0), n_knots - 1.0)
            j = min(int(math.floor(u)), n_knots - 2)
            lo, hi = border[left, j], border[left, j + 1]
            out[s, 0, k] = lo + (hi - lo) * (u - j)
            out[s, 1, k] = border[s, k]
    return out


def _one_length_scale(pl, n, knot_l):
    """Whether the border's n training points and its knots share one length scale (the
    stationary kernel, ``use_nonstationary_length_scale`` off)."""
    for i in range(n):
        if pl[i] != pl[0]:
            return False
    for k in range(knot_l.size):
        if knot_l[k] != pl[0]:
            return False
    return True


def _finite_spacing(edges, b):
    """Whether border b's knot spacing squared is a finite number (absurdly far points make
    it overflow; the general prediction handles them)."""
    w = (edges[b, edges.shape[1] - 1] - edges[b, 0]) / (edges.shape[1] - 1)
    return w * w < 1e300


def _predict_stationary(out, b, knot_r, px, py, alpha, n, c, s, s2, sf2, mean, row):
    """The posterior mean at border b's knots for one length scale (prefactor 1, s2 = 2 L^2):
    the knots are equally spaced along the border (r_k = r_0 + k w), so each training point's
    exp(-|p_k - x_i|^2 / s2) comes by recurrence (``paciorek.stationary_along``, into the
    scratch ``row``): three exps a training point instead of one a knot."""
    n_knots = knot_r.shape[1]
    r0 = knot_r[b, 0]
    w = (knot_r[b, n_knots - 1] - r0) / (n_knots - 1)
    ratio = math.exp(-2.0 * w * w / s2)
    for k in range(n_knots):
        out[b, k] = 0.0
    for i in range(n):
        t = px[i] * c + py[i] * s  # along the border
        h = py[i] * c - px[i] * s  # across it (no difference of squares: no inf - inf)
        if stationary_along_compiled(row, t, h * h, r0, w, ratio, s2, alpha[i]):
            for k in range(n_knots):  # (False: 0 at every knot)
                out[b, k] += row[k]
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


# The borders' kernel may reassociate and contract its sums (LLVM's fast-math flags without
# the no-NaN / no-inf ones: d's NaN checks stay): it equals its reference to round-off only
# anyway, and the Cholesky's and prediction's dot products then vectorise (~10 % a frame).
_FAST = dict(fastmath={'reassoc', 'contract', 'nsz', 'arcp'})
_cholesky_solve = kernel(_cholesky_solve, inline='always', **_FAST) or _cholesky_solve
_one_length_scale = kernel(_one_length_scale, inline='always') or _one_length_scale
_finite_spacing = kernel(_finite_spacing, inline='always') or _finite_spacing
_gather_border = kernel(_gather_border, inline='always') or _gather_border
_segment_points = kernel(_segment_points, inline='always', **_FAST) or _segment_points
_border_kernel = kernel(_border_kernel, inline='always', **_FAST) or _border_kernel
_fill_knot_factors = kernel(_fill_knot_factors, inline='always') or _fill_knot_factors
_predict_stationary = kernel(_predict_stationary, **_FAST) or _predict_stationary
_lattice = kernel(_lattice) or _lattice


# ----------------------------------------------------------------------- the points' height

def _between_numpy(lattice, point_segment, point_bin, point_frac, point_angle, z, threshold):
    """The numpy reference of :func:`_between_loop` (the same values bit for bit)."""
    m_count, _, n_knots = lattice.shape
    flat = lattice.ravel().astype(point_frac.dtype)
    inner = point_segment.astype(np.intp) * (2 * n_knots) + point_bin
    left = _lerp(flat[inner], flat[inner + 1], point_frac)
    inner += n_knots
    right = _lerp(flat[inner], flat[inner + 1], point_frac)
    w = (point_angle + np.pi) * (m_count / (2.0 * np.pi)) - point_segment
    z_hat = _lerp(left, right, np.minimum(np.maximum(w, 0.0), 1.0).astype(point_frac.dtype))
    return z_hat, is_ground(z, z_hat, threshold)


def _lerp(low, high, frac):
    """low + (high - low) frac in the arrays' precision (a new array)."""
    step = high - low
    step *= frac
    step += low
    return step


def _between_loop(lattice, point_segment, point_bin, point_frac, point_angle, z, threshold):
    """Each point's ground on the two borders of its segment at its r (linear between the bin
    edges), then linear in azimuth between them, and the label rule, in one pass (compiled
    with numba)."""
    m_count, _, n_knots = lattice.shape
    flat = lattice.ravel().astype(point_frac.dtype)
    z_hat = np.empty(point_frac.size, dtype=point_frac.dtype)
    ground = np.empty(point_frac.size, dtype=np.bool_)
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
        height = (right - left) * w + left
        z_hat[i] = height
        ground[i] = is_ground_compiled(z[i], height, threshold)
    return z_hat, ground


def _borders_examples(_dtype):
    """Two segments of two bins, a training candidate each, the anchor in one; float32 points
    (the frames' own precision)."""
    return [(np.array([1.0, 2.0], dtype=dtype), np.array([-1.0, 0.5], dtype=dtype),
             np.array([[0, -1], [-1, 1]], dtype=np.int64),
             np.array([[-1.7, np.nan], [np.nan, -1.6]]),
             np.array([[2.0, np.nan], [np.nan, 2.0]]), np.array([[True, False], [False, True]]),
             np.array([[1.0, 2.0, 3.0], [1.5, 2.5, 3.5]]), 3.0, 2.0, 0.5, 0.05, -1.7, -1.7,
             -1.7, 0.09, np.ones(2), np.array([True, False]))
            for dtype in (np.float32, np.float64)]


def _between_examples(dtype):
    return [(np.zeros((2, 2, 3)), np.array([0, 1], dtype=np.int32),
             np.array([0, 1], dtype=np.int32), np.array([0.5, 0.25], dtype=dtype),
             np.array([-1.0, 1.0]), np.array([0.1, 0.3], dtype=dtype), np.dtype(dtype).type(0.25))]


# the borders' solve equals its reference to round-off (loops against LAPACK): compiled
# before use, like the GP step
BORDERS = Twin('coupled surface borders', _borders_numpy, kernel(_borders_loop, **_FAST),
               _borders_examples, exact=False)
BETWEEN = Twin('coupled surface points', _between_numpy, kernel(_between_loop),
               _between_examples)
STAGE = Stage('coupled_surface', 'ours', 'use_coupled_surface', (BORDERS, BETWEEN))
STAGES = (STAGE,)
