# SPDX-License-Identifier: Apache-2.0
"""Stage ``gp fit`` [paper, sections III-IV]: the whole-frame GP over the ground candidates.

Paper: every segment's training candidates (r_i, z_i) with length scales L_i = a d_i (eq. 12,
``length_factors``) form one GP with the kernel of eq. 7 (``paciorek``); theta = (sigma_f, a,
sigma_n) is shared by all segments and learned by maximising the whole-frame objective
J(theta) = sum_m log p(z_m | r_m, theta) (eq. 14).

Ours, where the paper is silent:

* the prior mean is a constant m0 (the paper's eq. 6 uses zero), so sigma_f describes the
  ground's deviations from a level plane at m0: the anchor height (``prior_mean_at_anchor``)
  or the median height of the training points;
* each training point may carry extra noise variance on top of sigma_n^2 (the anchor, rejected
  outliers: :meth:`FrameGP.with_noise`);
* theta is learned with scipy's L-BFGS-B on log theta within bounds, under a cap on objective
  evaluations (each one factorisation of the frame), with the analytic gradient
  dJ/dlog theta = 1/2 sum_m tr((alpha alpha^T - A_m^-1) dA_m/dlog theta).

All segments are solved as one padded (S, n) batch. The numpy reference factorises it with
stacked LAPACK calls, padded slots being identity rows with z = 0 that add nothing to J or its
gradient; it is also the fallback (non-PD matrices: jittered retries; a numba failure: numpy
for the rest of that object's life). The compiled solve (:data:`SOLVE`) processes each segment
at its own size n_s in one pass (kernel, Cholesky, inverse, log|A|, alpha, gradient terms)
without a Python-level temporary, and releases the GIL. The two agree to round-off (LAPACK
against loops), so the compiled one is compiled before use, never swapped in mid-stream.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import minimize
from threadpoolctl import ThreadpoolController

from . import predict
from .anchor import GroundAnchor
from .compiled import AVAILABLE, Stage, Twin, kernel
from .paciorek import paciorek_compiled

LOG_2PI = float(np.log(2.0 * np.pi))


# Failures of one marginal-likelihood evaluation that mean "theta is numerically bad here", not a
# bug: LinAlgError is a ValueError; ArithmeticError covers Overflow/ZeroDivision/FloatingPoint.
_NUMERICAL_ERRORS = (ValueError, ArithmeticError)


BACKENDS = ('auto', 'numba', 'numpy')


def resolve_backend(backend: str) -> str:
    """'auto' -> 'numba' when numba imports, else 'numpy'; raise ValueError on other names."""
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == 'auto':
        return 'numba' if AVAILABLE else 'numpy'
    if backend == 'numba' and not AVAILABLE:
        raise ValueError("backend 'numba' requested but numba is not installed")
    return backend


_blas = None  # threadpoolctl controller, made on first use (after scipy has loaded its BLAS)


def numpy_blas_limit():
    """One BLAS thread while the numpy GP runs (a context manager). It factorises many tiny
    (n <= N + 1) matrices, on which OpenBLAS threads only spin: the same wall time, half the
    CPU time, which leaves the other core to the ROS executor. The compiled GP calls no BLAS."""
    global _blas
    if _blas is None:
        _blas = ThreadpoolController()
    return _blas.limit(limits=1, user_api='blas')


# solutions each FrameGP keeps (the start and the last point of a theta search: whichever
# wins is solved again, and the robust pass re-solves at it)
_CACHED_SOLUTIONS = 2


class _BudgetExhausted(Exception):
    """Raised inside the objective to stop L-BFGS-B exactly at the evaluation cap."""


@dataclass
class GPSolution:
    """Factorisation of A = K + sigma_n^2 I for every segment at one theta."""

    theta: np.ndarray  # (3,) sigma_f, a, sigma_n
    alpha: np.ndarray  # (S, n) A^-1 (z - m0)
    a_inv: np.ndarray  # (S, n, n)
    lml: float  # J(theta)
    jitter: float  # diagonal jitter that had to be added (m^2), 0 if none
    kernel: Optional[np.ndarray]  # (S, n, n) K at theta (padded slots 0); None when compiled
    gradient: Optional[np.ndarray] = None  # (3,) dJ/dlog(theta) when the solver gave it
    logdets: Optional[np.ndarray] = None  # (S,) log|A| of each segment when compiled
    pair_terms: tuple = ()  # compiled: (K, q) (S, n, n), see solve_batched


def _pad_numpy(r, z, d, mask, noise_var, has_anchor, anchor_segments, anchor_d,
               anchor_height, anchor_var, mean):
    """The numpy reference of FrameGP's padding: (M, N) candidate arrays -> the (S, n) batch.

    Rows of ``mask`` with a training point (or the anchor) enter the batch; in each, the anchor
    (when ``has_anchor`` and its segment has it) comes first, then the training candidates in
    bin order, then padding slots (r 0, z 0, d 1, noise 0). Returns (segments (S,), valid,
    bins (-1: the anchor), r, z - mean, d, noise_var (S, n), counts (S,)).
    """
    if has_anchor:  # the anchor becomes column 0 of the padded input
        m_count = mask.shape[0]
        r = np.concatenate([np.zeros((m_count, 1)), r], axis=1)
        z = np.concatenate([np.full((m_count, 1), anchor_height), z], axis=1)
        d = np.concatenate([anchor_d[:, None], d], axis=1)
        mask = np.concatenate([anchor_segments[:, None], mask], axis=1)
        noise_var = np.concatenate([np.full((m_count, 1), anchor_var), noise_var], axis=1)
    counts = mask.sum(axis=1)
    segments = np.flatnonzero(counts > 0)
    n_max = int(counts.max()) if counts.size else 0
    sub = mask[segments]
    # stable order: training points of each segment first (the anchor first of all)
    order = np.argsort(~sub, axis=1, kind='stable')[:, :n_max]
    # (S, n) flat index into the padded (M, N[+1]) input of every slot: one gather per
    # array instead of a row subset and take_along_axis (same values)
    flat = segments[:, None] * mask.shape[1] + order
    valid = mask.reshape(-1)[flat]
    bins = order - 1 if has_anchor else order
    return (segments, valid, bins, np.where(valid, r.reshape(-1)[flat], 0.0),
            np.where(valid, z.reshape(-1)[flat] - mean, 0.0),
            np.where(valid, d.reshape(-1)[flat], 1.0),
            np.where(valid, noise_var.reshape(-1)[flat], 0.0), valid.sum(axis=1))


def _pad_loop(r, z, d, mask, noise_var, has_anchor, anchor_segments, anchor_d, anchor_height,
              anchor_var, mean):
    """:func:`_pad_numpy` as one pass over the rows (compiled with numba): the same arrays,
    without the concatenations, the sort and the ten gathers of the reference."""
    m_count, n_count = mask.shape
    row_counts = np.zeros(m_count, dtype=np.intp)
    for m in range(m_count):
        c = 1 if has_anchor and anchor_segments[m] else 0
        for j in range(n_count):
            if mask[m, j]:
                c += 1
        row_counts[m] = c
    s_count = 0
    n_max = 0
    for m in range(m_count):
        if row_counts[m] > 0:
            s_count += 1
            n_max = max(n_max, row_counts[m])
    segments = np.empty(s_count, dtype=np.intp)
    valid = np.zeros((s_count, n_max), dtype=np.bool_)
    bins = np.empty((s_count, n_max), dtype=np.intp)
    r_out = np.zeros((s_count, n_max))
    z_out = np.zeros((s_count, n_max))
    d_out = np.ones((s_count, n_max))
    noise_out = np.zeros((s_count, n_max))
    counts = np.empty(s_count, dtype=np.intp)
    s = 0
    for m in range(m_count):
        if row_counts[m] == 0:
            continue
        segments[s] = m
        counts[s] = row_counts[m]
        k = 0
        if has_anchor and anchor_segments[m]:
            valid[s, 0] = True
            bins[s, 0] = -1
            z_out[s, 0] = anchor_height - mean
            d_out[s, 0] = anchor_d[m]
            noise_out[s, 0] = anchor_var
            k = 1
        for j in range(n_count):
            if mask[m, j]:
                valid[s, k] = True
                bins[s, k] = j
                r_out[s, k] = r[m, j]
                z_out[s, k] = z[m, j] - mean
                d_out[s, k] = d[m, j]
                noise_out[s, k] = noise_var[m, j]
                k += 1
        if has_anchor and not anchor_segments[m] and k < n_max:
            bins[s, k] = -1  # padding slots: the columns left, in order, as the stable sort
            k += 1
        for j in range(n_count):
            if k >= n_max:
                break
            if not mask[m, j]:
                bins[s, k] = j
                k += 1
        s += 1
    return segments, valid, bins, r_out, z_out, d_out, noise_out, counts


def _pad_examples(_dtype):
    grid, row = np.ones((2, 2)), np.ones(2)
    return [(grid, grid, grid, np.ones((2, 2), bool), grid, True, np.ones(2, bool), row, 0.0,
             0.1, 0.0)]


PAD = Twin('GP batch padding', _pad_numpy, kernel(_pad_loop), _pad_examples)


def _slot_noise_loop(noise_var, old_noise_var, valid, is_anchor, segments, bins, anchor_var):
    """(S, n) noise variance of the batch's slots from the (M, N) ``noise_var`` of the grid
    candidates (the anchor's slots ``anchor_var``, padding 0), and (S,) whether a segment's
    differ from ``old_noise_var`` (compiled with numba; ``FrameGP.with_noise``): the same
    values as its numpy reference, in one pass."""
    s_count, n_slots = valid.shape
    slot_noise = np.empty((s_count, n_slots))
    changed = np.zeros(s_count, dtype=np.bool_)
    for s in range(s_count):
        m = segments[s]
        for i in range(n_slots):
            if is_anchor[s, i]:
                value = anchor_var
            elif valid[s, i]:
                value = noise_var[m, bins[s, i]]
            else:
                value = 0.0
            slot_noise[s, i] = value
            if value != old_noise_var[s, i]:
                changed[s] = True
    return slot_noise, changed


def _slot_noise_numpy(noise_var, old_noise_var, valid, is_anchor, segments, bins, anchor_var):
    """The numpy reference of :func:`_slot_noise_loop`."""
    keep = valid & ~is_anchor
    grid_index = (segments[:, None] * noise_var.shape[1] + bins)[keep]
    slot_noise = np.where(is_anchor, anchor_var, 0.0)
    slot_noise[keep] = noise_var.reshape(-1)[grid_index]
    return slot_noise, np.any(slot_noise != old_noise_var, axis=1)


def _slot_examples(_dtype):
    slots, flags = np.ones((2, 2)), np.ones((2, 2), bool)
    return [(slots, slots, flags, flags, np.zeros(2, np.intp), np.zeros((2, 2), np.intp), 0.1)]


SLOT_NOISE = Twin('GP slot noise', _slot_noise_numpy, kernel(_slot_noise_loop), _slot_examples)


# --- the solve: compiled, and its numpy reference ---------------------------------------------

def solve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n):
    """Factorise A_s = K_s + diag(sigma_n^2 + noise_var) of every segment s at theta (compiled).

    r, d, z, noise_var: (S, n) padded training data, the first ``counts[s]`` slots of row s
    valid. Returns (ok (S,), logdet (S,), alpha (S, n), a_inv (S, n, n), gradient (3,),
    kernel (S, n, n), q (S, n, n)): ``gradient`` is dJ/dlog(sigma_f, a, sigma_n) summed over
    the segments; ``kernel`` and ``q`` hold K and (r_i - r_j)^2 / (d_i^2 + d_j^2) in each
    segment's first counts[s] rows and columns (the rest is not written) for
    :func:`resolve_batched`. ``ok[s]`` is False when Cholesky meets a non-positive pivot (that
    segment's outputs are then meaningless; the caller falls back to jittered numpy).
    """
    nothing = np.zeros((0, 0, 0))
    return resolve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n,
                           np.ones(r.shape[0], dtype=np.bool_), np.zeros(0), np.zeros((0, 0)),
                           nothing, nothing, nothing)  # every segment changed: nothing known


def resolve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed,
                    known_logdet, known_alpha, known_a_inv, known_kernel, known_q):
    """:func:`solve_batched` when a solution at this theta of the same data with another
    noise in the ``changed`` (S,) segments is known: its K and q are reused and returned, the
    unchanged segments' log|A|, alpha and A^-1 copied; the gradient is still summed over every
    segment in order, so the outputs are :func:`solve_batched`'s bit for bit. Empty
    ``known_kernel`` and ``known_q`` (0, 0, 0): K and q are computed."""
    s_count, n = r.shape
    kernel_known = known_kernel.shape[0] > 0
    outputs = (np.empty(s_count, dtype=np.bool_), np.empty(s_count), np.empty((s_count, n)),
               np.empty((s_count, n, n)), np.empty(3),
               known_kernel if kernel_known else np.empty((s_count, n, n)),
               known_q if kernel_known else np.empty((s_count, n, n)))
    _resolve_into(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed, known_logdet,
                  known_alpha, known_a_inv, kernel_known, np.empty((2, n, n)), *outputs)
    return outputs


def _resolve_into(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed, known_logdet,
                  known_alpha, known_a_inv, kernel_known, work, ok, logdet, alpha, a_inv,
                  gradient, k_all, q_all):
    """The loops of :func:`resolve_batched` (compiled), into its outputs (allocated, not
    initialised) with ``work`` (2, n, n). No array is allocated here: numba compiles
    np.zeros / np.empty for every number of dimensions on first use in a process (most of a
    new install's first frame); outputs are zeroed with element loops instead of np.zeros,
    whose fresh pages would fault on first write."""
    s_count, n = r.shape
    _zero_solution(work, ok, logdet, alpha, a_inv)
    sf2 = sigma_f * sigma_f
    inv_gain2 = 1.0 / (gain * gain)
    sn2 = sigma_n * sigma_n
    g_sf = 0.0
    g_gain = 0.0
    g_sn = 0.0
    for s in range(s_count):
        m = counts[s]
        for i in range(m, n):
            a_inv[s, i, i] = 1.0  # padded slots: identity rows, as in the numpy reference
        if not kernel_known:
            _pair_terms(r[s], d[s], m, sf2, inv_gain2, k_all[s], q_all[s])
        if changed[s]:
            ok[s], logdet[s] = _factorise(k_all[s], noise_var[s], z[s], m, sn2, work[0],
                                          work[1], a_inv[s], alpha[s])
        else:  # known: A^-1, alpha and log|A| of this segment at this theta
            for i in range(n):  # element loops: slice copies cost numba seconds to compile
                alpha[s, i] = known_alpha[s, i]
                for j in range(n):
                    a_inv[s, i, j] = known_a_inv[s, i, j]
            logdet[s] = known_logdet[s]
        if ok[s]:
            g_sf, g_gain, g_sn = _add_gradient(alpha[s], a_inv[s], k_all[s], q_all[s], m,
                                               g_sf, g_gain, g_sn)
    gradient[0] = g_sf
    gradient[1] = g_gain * inv_gain2
    gradient[2] = g_sn * sn2


def _zero_solution(work, ok, logdet, alpha, a_inv):
    """ok True, the rest 0 (element loops: see :func:`_resolve_into`)."""
    s_count, n = alpha.shape
    for i in range(n):
        for j in range(n):
            work[0, i, j] = 0.0
            work[1, i, j] = 0.0
    for s in range(s_count):
        ok[s] = True
        logdet[s] = 0.0
        for i in range(n):
            alpha[s, i] = 0.0
            for j in range(n):
                a_inv[s, i, j] = 0.0


def _pair_terms(r, d, m, sf2, inv_gain2, k, q):
    """K and q of one segment's first ``m`` points (symmetric), with the kernel of eq. 7."""
    for i in range(m):
        for j in range(i + 1):
            kij, qij = paciorek_compiled(r[i] - r[j], d[i], d[j], sf2, inv_gain2)
            q[i, j] = qij
            q[j, i] = qij
            k[i, j] = kij
            k[j, i] = kij


def _factorise(k, noise_var, z, m, sn2, lower, inv_lower, a_inv, alpha):
    """Cholesky of one segment's A = K + diag(sn2 + noise_var) (first ``m`` slots), L^-1,
    A^-1 = L^-T L^-1 and alpha = A^-1 z into ``a_inv`` and ``alpha``: (ok, log|A|); ok False
    at a non-positive pivot (nothing after it is written)."""
    logdet = 0.0
    for j in range(m):  # Cholesky, lower
        v = k[j, j] + sn2 + noise_var[j]
        for t in range(j):
            v -= lower[j, t] * lower[j, t]
        if not v > 0.0:
            return False, logdet
        ljj = np.sqrt(v)
        lower[j, j] = ljj
        logdet += 2.0 * np.log(ljj)
        for i in range(j + 1, m):
            v = k[i, j]
            for t in range(j):
                v -= lower[i, t] * lower[j, t]
            lower[i, j] = v / ljj
    for i in range(m):  # L^-1, lower
        inv_lower[i, i] = 1.0 / lower[i, i]
        for j in range(i):
            v = 0.0
            for t in range(j, i):
                v -= lower[i, t] * inv_lower[t, j]
            inv_lower[i, j] = v / lower[i, i]
    for i in range(m):  # A^-1 = L^-T L^-1
        for j in range(i + 1):
            v = 0.0
            for t in range(i, m):
                v += inv_lower[t, i] * inv_lower[t, j]
            a_inv[i, j] = v
            a_inv[j, i] = v
    for i in range(m):
        v = 0.0
        for j in range(m):
            v += a_inv[i, j] * z[j]
        alpha[i] = v
    return True, logdet


def _add_gradient(alpha, a_inv, k, q, m, g_sf, g_gain, g_sn):
    """The running sums of 1/2 tr(W dA/dlog theta), W = alpha alpha^T - A^-1, with one
    segment's terms added (dK/dlog sigma_f = 2K, dK/dlog a = 2 K q / a^2: ``paciorek``)."""
    for i in range(m):
        ai = alpha[i]
        for j in range(m):
            wk = (ai * alpha[j] - a_inv[i, j]) * k[i, j]
            g_sf += wk
            g_gain += wk * q[i, j]
        g_sn += ai * ai - a_inv[i, i]
    return g_sf, g_gain, g_sn


if AVAILABLE:  # the callees before their callers, inlined into them (numba IR: no call)
    _zero_solution = kernel(_zero_solution, inline='always')
    _pair_terms = kernel(_pair_terms, inline='always')
    _factorise = kernel(_factorise, inline='always')
    _add_gradient = kernel(_add_gradient, inline='always')
    _resolve_into = kernel(_resolve_into)


def _pair_geometry(r, d, valid):
    """(q, prefactor) (S, n, n) of a padded batch, 0 on padded pairs (``paciorek``'s terms
    that do not depend on theta): q = (r_i - r_j)^2 / (d_i^2 + d_j^2), prefactor =
    sqrt(2 d_i d_j / (d_i^2 + d_j^2))."""
    pair = valid[:, :, None] & valid[:, None, :]
    di, dj = d[:, :, None], d[:, None, :]
    sd = di * di + dj * dj
    diff = r[:, :, None] - r[:, None, :]
    return (np.where(pair, diff * diff / sd, 0.0),
            np.where(pair, np.sqrt(2.0 * di * dj / sd), 0.0))


def _kernel_from_geometry(q, prefactor, sigma_f, gain):
    """K (S, n, n) at (sigma_f, gain) from the batch's :func:`_pair_geometry` (numpy)."""
    k = np.multiply(q, -1.0 / (gain * gain))  # in place from here: one temporary
    np.exp(k, out=k)
    k *= prefactor
    k *= sigma_f * sigma_f
    return k


def _with_noise_diagonal(k, valid, noise_var, sigma_n):
    """(A = K + diag(sigma_n^2 + noise_var), a writable view of A's diagonals); padded slots
    get 1 there (identity rows: K is 0 there)."""
    a = k.copy()
    a_diag = a.reshape(a.shape[0], -1)[:, ::a.shape[-1] + 1]  # a view of every diagonal
    a_diag += np.where(valid, sigma_n ** 2 + noise_var, 1.0)
    return a, a_diag


def _numpy_gradient(alpha, a_inv, k, q, valid, theta):
    """dJ/dlog theta (3,) of a numpy solution: 1/2 tr(W dA/dlog theta), W = alpha alpha^T -
    A^-1. K (and so W K) is 0 on padded slots and the noise term takes the valid diagonal."""
    wk = (alpha[:, :, None] * alpha[:, None, :] - a_inv) * k
    grad_sigma_f = float(wk.sum())  # 1/2 tr(W * 2K)
    grad_gain = float(np.vdot(wk, q)) / theta[1] ** 2  # 1/2 tr(W * K * 2q/a^2)
    w_diag = alpha * alpha - np.diagonal(a_inv, axis1=1, axis2=2)
    grad_sigma_n = float(w_diag[valid].sum()) * theta[2] ** 2  # 1/2 tr(W * 2 sn^2 I)
    return np.array([grad_sigma_f, grad_gain, grad_sigma_n])


def _resolve_numpy(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed, known_logdet,
                   known_alpha, known_a_inv, known_kernel, known_q):
    """The numpy reference of :func:`resolve_batched` (FrameGP's numpy arithmetic, without its
    jittered retries): the full solve (what is known changes no number, to round-off); ok all
    False when a matrix is not PD."""
    valid = np.arange(r.shape[1])[None, :] < counts[:, None]
    q, prefactor = _pair_geometry(r, d, valid)
    k = _kernel_from_geometry(q, prefactor, sigma_f, gain)
    a, _ = _with_noise_diagonal(k, valid, noise_var, sigma_n)
    try:
        chol = np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        return (np.zeros(r.shape[0], dtype=bool),) + (None,) * 6
    a_inv = np.linalg.inv(a)
    alpha = np.einsum('sij,sj->si', a_inv, z)
    logdets = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    gradient = _numpy_gradient(alpha, a_inv, k, q, valid, (sigma_f, gain, sigma_n))
    return np.ones(r.shape[0], dtype=bool), logdets, alpha, a_inv, gradient, k, q


def _solve_examples(_dtype):
    r, counts = np.array([[0.0, 1.0]]), np.array([2], dtype=np.intp)
    one, nothing = np.ones((1, 2)), np.zeros((0, 0, 0))
    return [(r, one, one, one * 0.0, counts, 1.0, 1.0, 0.1, np.ones(1, dtype=np.bool_),
             np.zeros(0), np.zeros((0, 0)), nothing, nothing, nothing)]


def _solve_outputs(args, outputs):
    """What of a solve the twin tests compare: K and q only in each segment's first counts
    rows and columns (the kernel leaves the rest unwritten)."""
    counts = args[4]
    ok, logdets, alpha, a_inv, gradient, k, q = outputs
    return (ok, logdets, alpha, a_inv, gradient) + tuple(
        [a[s, :c, :c] for s, c in enumerate(counts)] for a in (k, q))


SOLVE = Twin('GP solve', _resolve_numpy, resolve_batched if AVAILABLE else None,
             _solve_examples, exact=False, outputs=_solve_outputs)


def slots_to_grid(values, valid, is_anchor, segments, bins, shape, fill=np.nan):
    """(S, n) values of a batch's slots -> the (M, N) ``shape`` grid of its candidates,
    ``fill`` where no grid candidate trains (the anchor dropped)."""
    keep = valid & ~is_anchor
    out = np.full(shape, fill, dtype=values.dtype)
    out.reshape(-1)[(segments[:, None] * shape[1] + bins)[keep]] = values[keep]
    return out


def leave_one_out(alpha, a_inv, valid):
    """(S, n) leave-one-out residuals z_i - mean_{-i} = alpha_i / [A^-1]_ii and predictive stds
    sqrt(1 / [A^-1]_ii), sensor noise included (R&W eq. 5.12), of a solution's slots; 0 on
    padding."""
    diag = np.diagonal(a_inv, axis1=1, axis2=2)
    return np.where(valid, alpha / diag, 0.0), np.where(valid, np.sqrt(1.0 / diag), 0.0)


class FrameGP:
    """Training data of one frame, padded to (S, n) over the segments that have training points.

    Immutable after construction: a different noise assignment is a new object
    (:meth:`with_noise`), so a solution cached for one theta can never belong to other data.
    """

    def __init__(self, r, z, d, mask, noise_var=None, anchor: GroundAnchor | None = None,
                 mean=None, backend='auto'):
        """r, z, d, mask, noise_var: (M, N) candidate arrays; mask marks training candidates.

        ``noise_var`` (m^2, default 0) is added to sigma_n^2 on each candidate's diagonal.
        ``anchor`` adds its point before the first candidate of every segment it names.
        The prior mean is ``mean``, by default the median height of all training points (the
        anchor counted once per segment that has it), so sigma_f describes deviations of the
        ground from a level plane at that height.
        ``backend``: 'numba' (compiled factorisation), 'numpy', or 'auto' (numba if it imports).
        """
        mask = np.asarray(mask, dtype=bool)
        self.anchor = anchor
        self.shape = mask.shape  # (M, N) of the grid
        self.backend = resolve_backend(backend)
        m_count = mask.shape[0]
        has_anchor = anchor is not None
        anchor_segments = (np.asarray(anchor.segments, dtype=bool) if has_anchor
                           else np.zeros(m_count, dtype=bool))
        if mean is None:  # the median over all training points, the anchor once per segment
            seen = np.asarray(z)[mask]  # in z's precision, as the heights it is the median of
            if has_anchor:
                anchors = np.full(np.count_nonzero(anchor_segments), float(anchor.height_m))
                seen = np.concatenate([anchors, seen])
            mean = float(np.median(seen)) if seen.size else 0.0
        self.mean = float(mean)
        as_float = (lambda a: np.ascontiguousarray(a, dtype=np.float64))
        args = (as_float(r), as_float(z), as_float(d), np.ascontiguousarray(mask),
                as_float(np.zeros(mask.shape) if noise_var is None else noise_var),
                has_anchor, anchor_segments,
                as_float(anchor.length_factor if has_anchor else np.ones(m_count)),
                float(anchor.height_m) if has_anchor else 0.0,
                float(anchor.noise_var) if has_anchor else 0.0, self.mean)
        # segments: rows of (M, N) that enter the batch; per (S, n) slot: valid, grid bin (-1
        # for the anchor), r, z - mean, d, noise_var; counts: training points of each row
        (self.segments, self.valid, self.bins, self.r, self.z, self.d, self.noise_var,
         self.counts) = PAD.run(self.backend == 'numba', *args)
        self.n_max = self.valid.shape[1]
        self.is_anchor = self.valid & (self.bins < 0)
        self.num_points = int(self.counts.sum())
        self._geometry = None  # (q, prefactor) (S, n, n) of the numpy path, made on first use
        self.compiled_error = None  # why the numba kernel failed, if it did (then numpy)
        self.cholesky_fallbacks = 0  # jittered retries of this object and those it came from
        self.factorisations = 0  # uncached solves of this object (the unit of fitting cost)
        self._cache = []  # [(theta bytes, GPSolution)]: the last _CACHED_SOLUTIONS solves
        self._known = None  # ([(theta bytes, compiled solution)], changed (S,)): with_noise

    def _pair_geometry(self):
        """(q, prefactor) (S, n, n) of the numpy path (:func:`_pair_geometry`), made once."""
        if self._geometry is None:
            self._geometry = _pair_geometry(self.r, self.d, self.valid)
        return self._geometry

    def with_noise(self, noise_var) -> 'FrameGP':
        """The same data with another per-candidate noise variance (M, N) (m^2).

        Shares the geometry (kernel distances, prefactors) with this object; the anchor keeps
        its own noise. Cheap: no re-padding, no new distance matrices.
        """
        if self.backend == 'numpy':
            self._pair_geometry()  # made once here, shared by the copy
        other = copy.copy(self)
        anchor_var = float(self.anchor.noise_var) if self.anchor is not None else 0.0
        # the grid candidates' slots get ``noise_var``, the anchor's its own, padding 0; and
        # the segments whose noise changed
        other.noise_var, changed = SLOT_NOISE.run(
            self.backend == 'numba',
            np.ascontiguousarray(noise_var, dtype=np.float64).reshape(self.shape),
            self.noise_var, self.valid, self.is_anchor, self.segments, self.bins, anchor_var)
        other._cache = []  # cholesky_fallbacks carries on: it counts the whole chain
        other.factorisations = 0
        # this object's cached solutions stay valid for the copy's segments whose noise is
        # unchanged: a solve at their theta recomputes only the others (bit for bit the same)
        compiled_solutions = [(key, sol) for key, sol in self._cache if sol.logdets is not None]
        other._known = (compiled_solutions, changed) if compiled_solutions else None
        return other

    def to_grid(self, slot_values, fill) -> np.ndarray:
        """(S, n) values of the training slots -> (M, N) over the grid's bins (anchor dropped)."""
        return slots_to_grid(np.asarray(slot_values), self.valid, self.is_anchor, self.segments,
                             self.bins, self.shape, fill)

    # -- core linear algebra ---------------------------------------------------------------
    def kernel(self, theta):
        """K (S, n, n) at theta, zero on padded slots (numpy reference)."""
        sigma_f, gain, _ = theta
        return _kernel_from_geometry(*self._pair_geometry(), sigma_f, gain)

    def solve(self, theta) -> GPSolution:
        """Factorise A at theta, adding growing diagonal jitter if Cholesky fails.

        The diagonal of A is sigma_n^2 plus each point's ``noise_var``; the data are fixed at
        construction, so the cached solution is keyed on theta alone.
        """
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        for cached_key, cached in self._cache:
            if cached_key == key:  # L-BFGS-B re-evaluates its start and end points
                return cached
        self.factorisations += 1
        sol = self._solve_compiled(theta, key) if self.backend == 'numba' else None
        if sol is None:
            sol = self._solve_numpy(theta)
        self._cache = self._cache[1 - _CACHED_SOLUTIONS:] + [(key, sol)]
        return sol

    def _lml(self, logdet, alpha):
        return -0.5 * (float(np.einsum('si,si->', self.z, alpha)) + logdet
                       + self.num_points * LOG_2PI)

    def _solve_compiled(self, theta, key: bytes) -> Optional[GPSolution]:
        """The whole step in numba (``key``: theta's bytes, as :meth:`solve` caches it); None
        when a matrix is not PD or numba fails (then numpy)."""
        known_solutions, changed = self._known if self._known is not None else ([], None)
        known = next((sol for known_key, sol in known_solutions if known_key == key), None)
        if known is None:  # every segment changed: nothing known
            empty = np.zeros((0, 0, 0))
            changed = np.ones(self.segments.size, dtype=np.bool_)
            known_parts = (np.zeros(0), np.zeros((0, 0)), empty, empty, empty)
        else:
            known_parts = (known.logdets, known.alpha, known.a_inv, *known.pair_terms)
        try:
            ok, logdets, alpha, a_inv, gradient, *pair_terms = SOLVE.run(
                True, self.r, self.d, self.z, self.noise_var, self.counts,
                *(float(t) for t in theta), changed, *known_parts)
        except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
            self.backend, self.compiled_error = 'numpy', str(exc)  # numpy from now on
            return None
        if not ok.all():
            return None
        logdet = float(logdets.sum())
        return GPSolution(theta, alpha, a_inv, self._lml(logdet, alpha), 0.0, None, gradient,
                          logdets, tuple(pair_terms))

    def _solve_numpy(self, theta) -> GPSolution:
        """The numpy reference (and fallback): stacked factorisation of the padded batch."""
        k = self.kernel(theta)
        a, a_diag = _with_noise_diagonal(k, self.valid, self.noise_var, theta[2])
        a_inv, logdet, alpha, jitter = self._numpy_factorise(a, a_diag, theta)
        return GPSolution(theta, alpha, a_inv, self._lml(logdet, alpha), jitter, k)

    def _numpy_factorise(self, a, a_diag, theta):
        """Stacked numpy Cholesky (for PD check and log|A|) and inverse, with jitter retries.

        ``a_diag`` is a writable view of the diagonals of ``a``; jitter grows x100 per retry
        and every retry is counted in ``cholesky_fallbacks``.
        Returns (A^-1, log|A| summed over segments, alpha = A^-1 z, jitter added).
        """
        jitter = 0.0
        for _ in range(6):
            try:
                chol = np.linalg.cholesky(a)
                break
            except np.linalg.LinAlgError:
                step = max(jitter * 99.0, 1e-8 * theta[0] ** 2 + 1e-10)
                a_diag += step
                jitter += step
                self.cholesky_fallbacks += 1
        else:
            raise np.linalg.LinAlgError('kernel matrix not positive definite even with jitter')
        logdet = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum()
        a_inv = np.linalg.inv(a)
        return a_inv, logdet, np.einsum('sij,sj->si', a_inv, self.z), jitter

    def lml_and_gradient(self, log_theta):
        """J and dJ/dlog(theta) (3,), the objective of the hyperparameter search."""
        theta = np.exp(np.asarray(log_theta, dtype=np.float64))
        sol = self.solve(theta)
        if sol.gradient is not None:
            return sol.lml, sol.gradient.copy()
        q, _ = self._pair_geometry()
        return sol.lml, _numpy_gradient(sol.alpha, sol.a_inv, sol.kernel, q, self.valid, theta)

    # -- learning ------------------------------------------------------------------------
    def fit(self, theta0, bounds, max_evaluations):
        """Maximise J from theta0 within bounds ((lo, hi) x 3); returns (theta, info dict).

        The cap is on objective evaluations (each one factorisation of the whole frame), the
        unit of cost; L-BFGS-B's own iteration count is reported in ``info``.
        """
        theta0 = np.asarray(theta0, dtype=np.float64)
        if theta0.shape == (len(bounds),):  # np.clip's values without its ~5 us of set-up
            theta0 = np.array([min(max(t, lo), hi)  # NaN stays NaN, as in np.clip
                               for t, (lo, hi) in zip(theta0.tolist(), bounds)],
                              dtype=np.float64)
        else:
            theta0 = np.clip(theta0, [b[0] for b in bounds], [b[1] for b in bounds])
        info = {'iterations': 0, 'evaluations': 0, 'failed': False}
        if max_evaluations <= 0 or self.num_points == 0:
            return theta0, info

        values, points = [], []

        def objective(log_theta):
            if info['evaluations'] >= max_evaluations:
                raise _BudgetExhausted  # scipy checks maxfun only between iterations
            info['evaluations'] += 1
            points.append(np.array(log_theta, dtype=np.float64))
            try:
                lml, grad = self.lml_and_gradient(log_theta)
            except _NUMERICAL_ERRORS:  # a bad point, not a bad frame: L-BFGS-B backs off
                lml, grad = -np.inf, np.zeros(3)
            if not np.isfinite(lml) or not np.all(np.isfinite(grad)):
                values.append(np.inf)
                return 1e30, np.zeros(3)
            values.append(-lml)
            return -lml, -grad

        log_bounds = np.log(np.asarray(bounds, dtype=np.float64))
        try:
            res = minimize(objective, np.log(theta0), jac=True, method='L-BFGS-B',
                           bounds=log_bounds, options={'maxfun': int(max_evaluations),
                                                       'maxiter': int(max_evaluations)})
            info['iterations'] = int(res.nit)
        except _BudgetExhausted:
            pass
        except _NUMERICAL_ERRORS + (RuntimeError,):  # RuntimeError: scipy's own failures
            info['failed'] = True
            return theta0, info
        if not values or not np.isfinite(min(values)):
            info['failed'] = True  # never move to an undefined theta: keep the last good one
            return theta0, info
        best = int(np.argmin(values))  # values[0] is theta0: the result is never worse
        return np.exp(points[best]), info

    # -- the leave-one-out view and the prediction ------------------------------------------
    def loo_residuals(self, sol: GPSolution) -> np.ndarray:
        """(S, n) z_i - mean_{-i}: leave-one-out residual alpha_i / [A^-1]_ii (R&W eq. 5.12)."""
        return leave_one_out(sol.alpha, sol.a_inv, self.valid)[0]

    def loo_std(self, sol: GPSolution) -> np.ndarray:
        """(S, n) leave-one-out predictive std sqrt(1 / [A^-1]_ii) of each slot, sensor noise
        included (R&W eq. 5.12); 0 on padded slots."""
        return leave_one_out(sol.alpha, sol.a_inv, self.valid)[1]

    def predict(self, sol: GPSolution, r_star, d_star, with_std=True, return_kernel=False):
        """Posterior mean (absolute z) and std at r_star, d_star (S, k) of the batch segments
        (``predict`` stage). ``with_std=False`` skips the variance (the costlier half) and
        returns std = None; ``return_kernel`` also returns k* (S, n, k) for a later
        :meth:`std_from_kernel` (the std without recomputing k*)."""
        return predict.posterior(self, sol, r_star, d_star, with_std, return_kernel)

    def std_from_kernel(self, sol: GPSolution, k_star) -> np.ndarray:
        """Posterior std (S, k) from the k* that ``predict(..., return_kernel=True)`` returned
        for ``sol``: the numbers ``predict(..., with_std=True)`` gives. The compiled std may be
        compiled only now (warm_up leaves it to the background when the labels do not use it);
        should that fail, numpy computes it (equal to round-off), the error in
        ``compiled_error``."""
        return predict.std_from_kernel(self, sol, k_star)


STAGES = (Stage('gp fit', 'paper', None, (PAD, SLOT_NOISE, SOLVE)),)
