# SPDX-License-Identifier: Apache-2.0
"""The whole GP step compiled (numba): kernel, Cholesky, inverse, LML, gradient, prediction.

The GP solves one small SPD system per angular segment several times a frame. The numpy
reference (``gp.FrameGP`` with backend 'numpy') pads every segment to the largest one
(n <= N + 1 = 25 by default) and runs stacked LAPACK calls and (S, n, n) temporaries; on a
16-beam scan most segments hold a handful of training points, so nearly all of that work is
padding. Here each segment is processed at its own size n_s, in one pass that builds K from
(r, d), factorises A = K + diag(noise), inverts it and accumulates log|A|, alpha = A^-1 z and
the three gradient terms, without a Python-level temporary. The compiled functions
(``_resolve_into``, ``_predict_into``, ``_std_into``) fill arrays that the Python functions of
the same names without ``_into`` allocate (see ``_resolve_into`` for why), and release the GIL
(``nogil``) so that a ROS executor thread keeps running while a frame is solved.

The outputs equal the numpy reference to round-off (test/test_gp.py): padded slots hold what
numpy's identity rows give (A^-1 = I there, alpha = 0, K = 0).

First call of a process: numba compiles these functions (about 1-2 s) or loads them from its
on-disk cache (``cache=True``: ``__pycache__`` next to this file when that is writable, else
numba's user cache directory; ``NUMBA_CACHE_DIR`` overrides both). The cache is filled by the
first process that calls them, e.g. ``GroundSegmenter().warm_up()`` (the node does that at
start) or the first ``segment()``. The posterior std (``_std_into``, ~0.3 s of a first compile)
is a kernel of its own, not part of the prediction's: the labels need it only with
``ground_threshold_std_factor`` > 0 (and ``segment(details=True)`` reports it), so
:func:`warm_up` can leave it to the background compiler (core/compiled.py) and a new install's
first frame does not wait for it. A process that ends before the background compiler reaches
it leaves it for the next one to compile (the README's warm-up command waits for it).
"""

from __future__ import annotations

import numpy as np

from .compiled import (AVAILABLE, compile_later, failed, kernel,  # numba (cached, nogil)
                       mark_failed)


def solve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n):
    """Factorise A_s = K_s + diag(sigma_n^2 + noise_var) of every segment s at theta.

    r, d, z, noise_var: (S, n) padded training data, the first ``counts[s]`` slots of row s
    valid. Returns (ok (S,), logdet (S,), alpha (S, n), a_inv (S, n, n), gradient (3,),
    kernel (S, n, n), q (S, n, n)) where ``gradient`` is dJ/dlog(sigma_f, a, sigma_n) summed
    over the segments: 1/2 tr((alpha alpha^T - A^-1) dA/dlog theta); ``kernel`` and ``q`` hold
    K and (r_i - r_j)^2 / (d_i^2 + d_j^2) of each segment in their first counts[s] rows and
    columns (the rest is not written) for :func:`resolve_batched`. ``ok[s]`` is False
    when Cholesky meets a non-positive pivot; then that segment's outputs are meaningless and
    the caller falls back to jittered numpy.
    """
    nothing = np.zeros((0, 0, 0))
    return resolve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n,
                           np.ones(r.shape[0], dtype=np.bool_), np.zeros(0), np.zeros((0, 0)),
                           nothing, nothing, nothing)  # every segment changed: nothing known


def resolve_batched(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed,
                    known_logdet, known_alpha, known_a_inv, known_kernel, known_q):
    """:func:`solve_batched` when a solution at this theta of the same data with another
    noise in the ``changed`` (S,) segments is known: its K and q (independent of the noise)
    are used as they are and returned, and the log|A|, alpha and A^-1 of the unchanged
    segments are copied. The gradient terms are still summed over every segment in the same
    order, so the outputs are those of :func:`solve_batched` bit for bit; the kernel and the
    Cholesky factorisation and inverse (the O(n^3) part) run only where needed. With empty
    ``known_kernel`` and ``known_q`` (0, 0, 0), K and q are computed.
    """
    s_count, n = r.shape
    kernel_known = known_kernel.shape[0] > 0
    outputs = (np.empty(s_count, dtype=np.bool_), np.empty(s_count), np.empty((s_count, n)),
               np.empty((s_count, n, n)), np.empty(3),
               known_kernel if kernel_known else np.empty((s_count, n, n)),
               known_q if kernel_known else np.empty((s_count, n, n)))
    _resolve_into(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed, known_logdet,
                  known_alpha, known_a_inv, kernel_known, np.empty((2, n, n)), *outputs)
    return outputs


def _resolve_into(r, d, z, noise_var, counts, sigma_f, gain, sigma_n, changed,
                  known_logdet, known_alpha, known_a_inv, kernel_known, work,
                  ok, logdet, alpha, a_inv, gradient, kernel, q_all):
    """The loops of :func:`resolve_batched` (compiled with numba), writing into its arrays
    (allocated, not initialised): ``ok``, ``logdet``, ``alpha``, ``a_inv``, ``gradient`` (3,),
    ``kernel`` and ``q_all`` (S, n, n) (the known ones when ``kernel_known``), ``work`` (2, n, n).

    No array is allocated here: numba compiles its np.zeros / np.empty / np.array for every
    number of dimensions on first use in a process, ~0.9 s of a new install's first frame
    (the compiled code is cached on disk with the kernel, so only the first run pays). The
    arrays are zeroed here rather than by np.zeros (numpy's calloc hands large arrays fresh
    pages that fault on first write: +5 % on a KITTI frame's GP step), with element loops
    (a helper over a flat view compiled reshape for every number of dimensions: +0.45 s).
    """
    s_count, n = r.shape
    for i in range(n):  # zeroed with element loops: see above
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
    lower = work[0]
    inv_lower = work[1]
    sf2 = sigma_f * sigma_f
    inv_gain2 = 1.0 / (gain * gain)
    sn2 = sigma_n * sigma_n
    g_sf = 0.0
    g_gain = 0.0
    g_sn = 0.0
    for s in range(s_count):
        m = counts[s]
        ainv = a_inv[s]
        for i in range(m, n):
            ainv[i, i] = 1.0  # padded slots: identity rows, as in the numpy reference
        k = kernel[s]
        q = q_all[s]
        for i in range(0 if kernel_known else m):  # K, q = (r_i - r_j)^2 / (d_i^2 + d_j^2)
            di = d[s, i]
            for j in range(i + 1):
                dj = d[s, j]
                sd = di * di + dj * dj
                diff = r[s, i] - r[s, j]
                qij = diff * diff / sd
                kij = sf2 * np.sqrt(2.0 * di * dj / sd) * np.exp(-qij * inv_gain2)
                q[i, j] = qij
                q[j, i] = qij
                k[i, j] = kij
                k[j, i] = kij
        if not changed[s]:  # known: A^-1, alpha and log|A| of this segment at this theta
            for i in range(n):  # element loops: slice copies cost numba seconds to compile
                alpha[s, i] = known_alpha[s, i]
                for j in range(n):
                    ainv[i, j] = known_a_inv[s, i, j]
            logdet[s] = known_logdet[s]
        for j in range(m if changed[s] else 0):  # Cholesky of A = K + diag(noise), lower
            v = k[j, j] + sn2 + noise_var[s, j]
            for t in range(j):
                v -= lower[j, t] * lower[j, t]
            if not v > 0.0:
                ok[s] = False
                break
            ljj = np.sqrt(v)
            lower[j, j] = ljj
            logdet[s] += 2.0 * np.log(ljj)
            for i in range(j + 1, m):
                v = k[i, j]
                for t in range(j):
                    v -= lower[i, t] * lower[j, t]
                lower[i, j] = v / ljj
        if not ok[s]:
            continue
        for i in range(m if changed[s] else 0):  # L^-1, lower
            inv_lower[i, i] = 1.0 / lower[i, i]
            for j in range(i):
                v = 0.0
                for t in range(j, i):
                    v -= lower[i, t] * inv_lower[t, j]
                inv_lower[i, j] = v / lower[i, i]
        for i in range(m if changed[s] else 0):  # A^-1 = L^-T L^-1
            for j in range(i + 1):
                v = 0.0
                for t in range(i, m):
                    v += inv_lower[t, i] * inv_lower[t, j]
                ainv[i, j] = v
                ainv[j, i] = v
        for i in range(m if changed[s] else 0):
            v = 0.0
            for j in range(m):
                v += ainv[i, j] * z[s, j]
            alpha[s, i] = v
        for i in range(m):  # 1/2 tr(W dA), W = alpha alpha^T - A^-1
            ai = alpha[s, i]
            for j in range(m):
                wk = (ai * alpha[s, j] - ainv[i, j]) * k[i, j]
                g_sf += wk
                g_gain += wk * q[i, j]
            g_sn += ai * ai - ainv[i, i]
    gradient[0] = g_sf
    gradient[1] = g_gain * inv_gain2
    gradient[2] = g_sn * sn2


def std_batched(counts, a_inv, k_star, sigma_f):
    """Posterior std sqrt(sigma_f^2 - k*^T A^-1 k*) (S, k) from the (S, n, k) k* of
    :func:`predict_batched`.

    Raises when the kernel cannot compile; the failure is remembered (compiled.failed), here
    or in the background compiler, so later calls raise at once instead of compiling again.
    """
    if failed(_std_into):
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
    (neither initialised).

    All k prediction points of a segment are accumulated at once (innermost loop over them,
    which the compiler vectorises). A^-1 is symmetric, so k*^T A^-1 k* = sum_i k*_i (A^-1_ii
    k*_i + 2 sum_{j<i} A^-1_ij k*_j): half the multiplications of the full double sum (0.2 of
    the 0.4 ms of a 124k-point frame's surface std), equal to it to round-off.
    """
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


def predict_batched(r, d, counts, alpha, a_inv, r_star, d_star, sigma_f, gain, with_std):
    """Posterior mean (minus the prior mean) and std at r_star, d_star (S, k) of every segment,
    and k* (S, n, k) [segment, training point, prediction point] for a later std_batched.

    std is all zeros when ``with_std`` is False (and :func:`std_batched` is not called).
    """
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
        for c in range(k_count):
            l1 = gain * d_star[s, c]
            v = 0.0
            for j in range(m):
                l2 = gain * d[s, j]
                sl = l1 * l1 + l2 * l2
                diff = r_star[s, c] - r[s, j]
                kj = sf2 * np.sqrt(2.0 * l1 * l2 / sl) * np.exp(-diff * diff / sl)
                k_star[s, j, c] = kj
                v += kj * alpha[s, j]
            mean[s, c] = v


if AVAILABLE:
    _resolve_into = kernel(_resolve_into)
    _std_into = kernel(_std_into)
    _predict_into = kernel(_predict_into)


def warm_up(std_now: bool = True) -> None:
    """Compile (or load from numba's cache) the kernels now instead of inside the first frame.

    The node's worker thread calls this before it waits for clouds, so the first frame does not
    pay the compilation and drop the frames that arrive meanwhile. ``std_now`` False (for labels
    that do not use the std) queues the posterior std's kernel for the background compiler
    instead (:func:`queue_std`). A no-op without numba.
    """
    if AVAILABLE:
        one = np.ones((1, 2))
        counts = np.array([2], dtype=np.intp)
        _, logdet, alpha, a_inv, _, k, q = solve_batched(np.array([[0.0, 1.0]]), one, one,
                                                         one * 0.0, counts, 1.0, 1.0, 0.1)
        resolve_batched(np.array([[0.0, 1.0]]), one, one, one * 0.0, counts, 1.0, 1.0, 0.1,
                        np.zeros(1, dtype=np.bool_), logdet, alpha, a_inv, k, q)
        predict_batched(np.array([[0.0, 1.0]]), one, counts, alpha, a_inv, one, one, 1.0, 1.0,
                        std_now)
        if not std_now:
            queue_std()


def queue_std() -> None:
    """Have the background compiler (core/compiled.py) compile, or load from the cache, the
    posterior std's kernel. Its numpy twin differs in round-off, so nothing runs it meanwhile:
    a std asked for before it is ready compiles it in the asking thread (after the compilation
    running then: numba's compiler lock). A no-op without numba or when it is ready."""
    if AVAILABLE:
        k = 2
        compile_later(_std_into, np.array([2], dtype=np.intp), np.zeros((1, k, k)),
                      np.zeros((1, k, k)), 1.0, np.empty((1, k)), np.empty((2, k)))
