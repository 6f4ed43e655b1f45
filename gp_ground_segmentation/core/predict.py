# SPDX-License-Identifier: Apache-2.0
"""Stage ``predict`` [paper, eqs. 5 and 13]: the GP posterior of the ground at the bin edges.

The posterior mean (and std) of every segment's ground height is evaluated at its N + 1 bin
edges, not at every point (a dense N x P kernel would cost far more); the ``labels`` stage
interpolates between them. Segments without a training point keep the prior: the ground under
the vehicle (or FrameGP's mean) with the prior std sigma_f.

The compiled prediction (:data:`PREDICT`) builds k* with the same kernel function as the
solve (``paciorek``) and accumulates the mean; the posterior std sqrt(sigma_f^2 - k*^T A^-1 k*)
is a kernel of its own (:data:`STD`, from the kept k*): the labels need it only with
``use_std_threshold``, so warm_up can leave it to the background compiler (``background``) and
a new install's first frame does not wait for it. Both equal their numpy references to
round-off and are compiled before use.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import math

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, failed, kernel, mark_failed
from .length_factors import EDGES, factors_at_edges
from .paciorek import paciorek, paciorek_compiled, stationary_along_compiled


class GroundModel(NamedTuple):
    """What the ``gp fit`` stage hands to ``predict`` (and the surface)."""

    gp: object  # the frame's FrameGP
    solution: Optional[object]  # its final GPSolution; None when no segment has a training point
    theta: np.ndarray  # (3,) sigma_f, a, sigma_n used for the frame
    training: np.ndarray  # (M, N) candidates that trained the GP
    outliers: np.ndarray  # (M, N) candidates rejected by the robust passes
    length_factor: np.ndarray  # (M, N) d_i
    default_height: float  # ground height of segments without a training point (m)


def ground_at_bin_edges(model: GroundModel, edges: np.ndarray, need_std: bool,
                        compiled: bool = True):
    """GP posterior mean (and std) at the (M, N + 1) bin ``edges``.

    Returns (mean, std, d at the edges of the GP's segments, k* there) with (M, N + 1) mean
    and std (None unless ``need_std``); k* is what :meth:`FrameGP.std_from_kernel` takes.
    """
    mean = np.full(edges.shape, model.default_height)
    std = np.full(edges.shape, model.theta[0]) if need_std else None  # None: not asked for
    d_star = k_star = None
    if model.solution is not None:
        rows = model.gp.segments
        d_star = factors_at_edges(model.length_factor, model.training, rows,
                                  compiled and model.gp.backend == 'numba')
        mean_b, std_b, k_star = model.gp.predict(model.solution, edges[rows], d_star,
                                                 with_std=need_std, return_kernel=True)
        mean[rows] = mean_b
        if need_std:
            std[rows] = std_b
    return mean, std, d_star, k_star


# --- the posterior, given a FrameGP's batch and solution ---------------------------------------

def posterior(gp, sol, r_star, d_star, with_std: bool, return_kernel: bool):
    """:meth:`FrameGP.predict`: the compiled prediction for a compiled solution of a numba
    FrameGP (on failure numpy, for good), else numpy."""
    sigma_f, gain, _ = (float(t) for t in sol.theta)
    if gp.backend == 'numba' and sol.gradient is not None:  # a compiled solution
        r_star, d_star = _prediction_points(r_star, d_star, gp.segments.size)
        try:
            mean, std, k_star = PREDICT.run(True, gp.r, gp.d, gp.counts, sol.alpha, sol.a_inv,
                                            r_star, d_star, sigma_f, gain, bool(with_std))
        except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
            gp.backend, gp.compiled_error = 'numpy', str(exc)
        else:
            out = (mean + gp.mean, (std if with_std else None))
            return out + (k_star,) if return_kernel else out
    mean, std, k_star = PREDICT.run(False, gp.r, gp.d, gp.counts, sol.alpha, sol.a_inv,
                                    r_star, d_star, sigma_f, gain, bool(with_std))
    out = (mean + gp.mean, (std if with_std else None))
    return out + (k_star,) if return_kernel else out


def std_from_kernel(gp, sol, k_star) -> np.ndarray:
    """:meth:`FrameGP.std_from_kernel`: the compiled std of a compiled solution (should it
    fail to compile, numpy's, the error kept in ``compiled_error``), else numpy's."""
    compiled_solution = gp.backend == 'numba' and sol.gradient is not None
    sigma_f = float(sol.theta[0])
    if compiled_solution:
        try:
            return STD.run(True, gp.counts, sol.a_inv, k_star, sigma_f)
        except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
            gp.compiled_error = str(exc)
    return STD.run(False, gp.counts, sol.a_inv, k_star, sigma_f)


def _is_plain_float64(a) -> bool:
    """A C-contiguous, writable, aligned float64 ndarray (what the compiled prediction is
    compiled for), as numpy flags say it."""
    return (type(a) is np.ndarray and a.dtype == np.float64
            and a.flags.num & 0x0501 == 0x0501)  # C-contiguous, aligned, writeable


def _prediction_points(r_star, d_star, s_count: int):
    """(r*, d*) as (S, k) float64 arrays for the compiled prediction: as given when both are
    that already (the segmenter's), else broadcast copies (a read-only array or another layout
    is another numba signature to load). The kernel only reads them."""
    if (_is_plain_float64(r_star) and _is_plain_float64(d_star) and r_star.ndim == 2
            and r_star.shape == d_star.shape and r_star.shape[0] == s_count):
        return r_star, d_star
    shape = np.broadcast_shapes(np.shape(r_star), np.shape(d_star), (s_count, 1))
    return tuple(np.broadcast_to(a, shape).astype(np.float64) for a in (r_star, d_star))


# --- the mean: compiled, and its numpy reference -----------------------------------------------

def predict_batched(r, d, counts, alpha, a_inv, r_star, d_star, sigma_f, gain, with_std):
    """Posterior mean (minus the prior mean) and std at r_star, d_star (S, k) of every segment,
    and k* (S, n, k) [segment, training point, prediction point] for a later std (compiled);
    std is all zeros unless ``with_std``."""
    s_count, k_count = r_star.shape
    mean, k_star = np.empty((s_count, k_count)), np.empty((s_count, r.shape[1], k_count))
    _predict_into(r, d, counts, alpha, r_star, d_star, sigma_f, gain, mean, k_star)
    std = (std_batched(counts, a_inv, k_star, sigma_f) if with_std
           else np.zeros((s_count, k_count)))
    return mean, std, k_star


def _predict_into(r, d, counts, alpha, r_star, d_star, sigma_f, gain, mean, k_star):
    """The loops of :func:`predict_batched` (compiled), into ``mean`` (S, k) and ``k_star``
    (S, n, k), neither initialised."""
    s_count, k_count = r_star.shape
    for s in range(s_count):  # padded slots are 0 (the others are written below)
        for j in range(counts[s], k_star.shape[1]):
            for c in range(k_count):
                k_star[s, j, c] = 0.0
    sf2 = sigma_f * sigma_f
    for s in range(s_count):
        m = counts[s]
        if _one_length_scale(d, d_star, s, m) and _equally_spaced(r_star, s):
            _predict_stationary(r, alpha, r_star, gain * d_star[s, 0], sf2, s, m, mean,
                                k_star)
            continue
        for c in range(k_count):
            l_star = gain * d_star[s, c]
            v = 0.0
            for j in range(m):
                kj = paciorek_compiled(r_star[s, c] - r[s, j], l_star, gain * d[s, j], sf2,
                                       1.0)[0]
                k_star[s, j, c] = kj
                v += kj * alpha[s, j]
            mean[s, c] = v


def _one_length_scale(d, d_star, s, m):
    """Whether segment s's m training points and its prediction points share one length
    factor (the defaults' stationary kernel: use_nonstationary_length_scale off)."""
    first = d_star[s, 0]
    for c in range(d_star.shape[1]):
        if d_star[s, c] != first:
            return False
    for j in range(m):
        if d[s, j] != first:
            return False
    return True


def _equally_spaced(r_star, s):
    """Whether segment s's prediction points are at least two, increasing and equally spaced
    (to 1e-9 of their span), as the bin edges are."""
    k_count = r_star.shape[1]
    if k_count < 2 or not r_star[s, k_count - 1] > r_star[s, 0]:
        return False
    step = (r_star[s, k_count - 1] - r_star[s, 0]) / (k_count - 1)
    tolerance = 1e-9 * (r_star[s, k_count - 1] - r_star[s, 0])
    for c in range(k_count):
        if abs(r_star[s, c] - (r_star[s, 0] + c * step)) > tolerance:
            return False
    return True


def _predict_stationary(r, alpha, r_star, length, sf2, s, m, mean, k_star):
    """:func:`_predict_into` for one segment whose kernel is stationary (one length scale:
    Paciorek's prefactor is 1) and whose k prediction points are equally spaced (the bin
    edges): each training point's k* row by recurrence (``paciorek.stationary_along``), three
    exps a training point instead of k."""
    k_count = r_star.shape[1]
    r0 = r_star[s, 0]
    w = (r_star[s, k_count - 1] - r0) / (k_count - 1)
    s2 = 2.0 * length * length
    ratio = math.exp(-2.0 * w * w / s2)
    for c in range(k_count):
        mean[s, c] = 0.0
    for j in range(m):
        row = k_star[s, j]
        if not stationary_along_compiled(row, r[s, j], 0.0, r0, w, ratio, s2, sf2):
            for c in range(k_count):  # 0 at its nearest edge: 0 at all of them
                row[c] = 0.0
            continue
        a = alpha[s, j]
        for c in range(k_count):
            mean[s, c] += row[c] * a


def _predict_numpy(r, d, counts, alpha, a_inv, r_star, d_star, sigma_f, gain, with_std):
    """The numpy reference of :func:`predict_batched` (r_star, d_star broadcastable to
    (S, k)); its k* is a (S, n, k) view of the (S, k, n) array it computes."""
    valid = np.arange(r.shape[1])[None, :] < counts[:, None]
    l_star = gain * np.asarray(d_star, dtype=np.float64)[:, :, None]
    k_star = paciorek(np.asarray(r_star, dtype=np.float64)[:, :, None] - r[:, None, :], l_star,
                      gain * d[:, None, :], sigma_f * sigma_f, 1.0)[0]
    k_star = np.where(valid[:, None, :], k_star, 0.0)
    mean = np.einsum('skn,sn->sk', k_star, alpha)
    std = _posterior_std(k_star, a_inv, sigma_f) if with_std else np.zeros(mean.shape)
    return mean, std, k_star.transpose(0, 2, 1)


def _predict_examples(_dtype):
    one, counts = np.ones((1, 2)), np.array([2], dtype=np.intp)
    return [(np.array([[0.0, 1.0]]), one, counts, one, np.ones((1, 2, 2)), one, one, 1.0, 1.0,
             False)]


PREDICT = Twin('GP prediction', _predict_numpy, predict_batched if AVAILABLE else None,
               _predict_examples, exact=False)


# --- the std: compiled, and its numpy reference ------------------------------------------------

def std_batched(counts, a_inv, k_star, sigma_f):
    """Posterior std sqrt(sigma_f^2 - k*^T A^-1 k*) (S, k) from the (S, n, k) k* of
    :func:`predict_batched` (compiled). Raises when the kernel cannot compile; the failure is
    remembered (compiled.failed), here or in the background compiler, so later calls raise at
    once instead of compiling again."""
    if failed(_std_into) or failed(std_batched):
        raise RuntimeError('the compiled GP std kernel failed to compile earlier')
    s_count, _, k_count = k_star.shape
    std = np.empty((s_count, k_count))
    try:
        _std_into(counts, a_inv, k_star, sigma_f, std, np.empty((2, k_count)))
    except Exception:
        mark_failed(_std_into)
        raise
    return std


def _std_into(counts, a_inv, k_star, sigma_f, std, work):
    """The loops of :func:`std_batched` (compiled), into ``std`` (S, k) with ``work`` (2, k)
    (neither initialised). All k prediction points of a segment are accumulated at once
    (innermost loop over them, which the compiler vectorises); A^-1 is symmetric, so
    k*^T A^-1 k* = sum_i k*_i (A^-1_ii k*_i + 2 sum_{j<i} A^-1_ij k*_j), half the
    multiplications of the full double sum, equal to it to round-off."""
    s_count, _, k_count = k_star.shape
    w = work[0]  # A^-1_ii k*_i + 2 sum_{j<i} A^-1_ij k*_j of every prediction point
    reduce = work[1]  # k*^T A^-1 k* of every prediction point
    sf2 = sigma_f * sigma_f
    for s in range(s_count):
        m = counts[s]
        ks = k_star[s]
        for c in range(k_count):
            reduce[c] = 0.0
        for i in range(m):
            for c in range(k_count):
                w[c] = 0.0
            for j in range(i):
                a = 2.0 * a_inv[s, i, j]
                for c in range(k_count):
                    w[c] += a * ks[j, c]
            a = a_inv[s, i, i]
            for c in range(k_count):
                reduce[c] += ks[i, c] * (w[c] + a * ks[i, c])
        for c in range(k_count):
            v = sf2 - reduce[c]
            std[s, c] = np.sqrt(v if v > 0.0 else 0.0)  # clamp round-off negatives


def _posterior_std(k_star, a_inv, sigma_f) -> np.ndarray:
    """numpy's posterior std sqrt(sigma_f^2 - k*^T A^-1 k*) (S, k) from k* (S, k, n)
    [segment, prediction point, training point] and A^-1 (S, n, n)."""
    reduce = np.einsum('skn,snm,skm->sk', k_star, a_inv, k_star, optimize=True)
    return np.sqrt(np.maximum(sigma_f * sigma_f - reduce, 0.0))  # clamp round-off


def _std_numpy(counts, a_inv, k_star, sigma_f):
    """The numpy reference of :func:`std_batched`."""
    return _posterior_std(k_star.transpose(0, 2, 1), a_inv, sigma_f)


if AVAILABLE:
    _one_length_scale = kernel(_one_length_scale, inline='always')
    _equally_spaced = kernel(_equally_spaced, inline='always')
    _predict_stationary = kernel(_predict_stationary, inline='always')
    _predict_into = kernel(_predict_into)
    _std_into = kernel(_std_into)

STD = Twin('GP posterior std', _std_numpy, std_batched if AVAILABLE else None,
           lambda _dtype: [(np.array([2], dtype=np.intp), np.zeros((1, 2, 2)),
                            np.zeros((1, 2, 2)), 1.0)], exact=False, background=True)

STAGES = (Stage('predict', 'paper', None, (EDGES, PREDICT, STD)),)
