# SPDX-License-Identifier: Apache-2.0
"""Compiled batched SPD factorisation for the GP (numba), with the numpy path as the reference.

The GP solves one small SPD system per angular segment (n <= N + 1 = 25 by default) several
times a frame, and ``np.linalg.inv`` costs ~2 ms for 120 such matrices because it runs a general
LU per matrix. This kernel does Cholesky, the triangular inverse and L^-T L^-1 in one pass per
matrix: ~0.75 ms for the same batch (benchmarks/RESULTS.md). It is used when numba imports;
``gp.FrameGP.solve`` falls back to numpy (and to its jitter retries) when it does not, or when a
matrix is not positive definite.

The first call of a process compiles the kernel (about 1 s) or loads it from numba's on-disk
cache (about 0.3 s when the package directory is writable).
"""

from __future__ import annotations

import numpy as np

try:  # numba is a regular dependency, but the package must still work without it
    import numba
except ImportError:  # pragma: no cover - exercised by the fallback tests via AVAILABLE
    numba = None

AVAILABLE = numba is not None


def _spd_inverse_batched(a, z):
    """For every s: A_s -> A_s^-1 in place; returns (ok (S,), logdet (S,), alpha = A^-1 z (S, n)).

    ``ok[s]`` is False when Cholesky meets a non-positive pivot; that matrix is left unchanged
    and the caller falls back to jittered numpy.
    """
    s_count, n, _ = a.shape
    logdet = np.zeros(s_count)
    alpha = np.zeros((s_count, n))
    ok = np.ones(s_count, dtype=np.bool_)
    lower = np.zeros((n, n))
    inv_lower = np.zeros((n, n))
    for s in range(s_count):
        m = a[s]
        for j in range(n):  # Cholesky, lower
            d = m[j, j]
            for k in range(j):
                d -= lower[j, k] * lower[j, k]
            if not d > 0.0:
                ok[s] = False
                break
            ljj = np.sqrt(d)
            lower[j, j] = ljj
            logdet[s] += 2.0 * np.log(ljj)
            for i in range(j + 1, n):
                v = m[i, j]
                for k in range(j):
                    v -= lower[i, k] * lower[j, k]
                lower[i, j] = v / ljj
        if not ok[s]:
            continue
        for i in range(n):  # L^-1, lower
            inv_lower[i, i] = 1.0 / lower[i, i]
            for j in range(i):
                v = 0.0
                for k in range(j, i):
                    v -= lower[i, k] * inv_lower[k, j]
                inv_lower[i, j] = v / lower[i, i]
            for j in range(i + 1, n):
                inv_lower[i, j] = 0.0
        for i in range(n):  # A^-1 = L^-T L^-1
            for j in range(i + 1):
                v = 0.0
                for k in range(i, n):
                    v += inv_lower[k, i] * inv_lower[k, j]
                m[i, j] = v
                m[j, i] = v
        for i in range(n):
            v = 0.0
            for j in range(n):
                v += m[i, j] * z[s, j]
            alpha[s, i] = v
    return ok, logdet, alpha


spd_inverse_batched = (numba.njit(cache=True)(_spd_inverse_batched) if AVAILABLE
                       else _spd_inverse_batched)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now instead of inside the first frame.

    The node's worker thread calls this before it waits for clouds, so the first frame does not
    pay the 0.2-1 s and drop the frames that arrive meanwhile. A no-op without numba.
    """
    if AVAILABLE:
        spd_inverse_batched(np.eye(2)[None].copy(), np.zeros((1, 2)))
