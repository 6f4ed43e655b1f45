# SPDX-License-Identifier: Apache-2.0
"""The GP kernel [paper, eq. 7]: Paciorek & Schervish's non-stationary squared exponential in 1-D.

    k(r_i, r_j) = sigma_f^2 (L_i^2)^(1/4) (L_j^2)^(1/4) ((L_i^2 + L_j^2) / 2)^(-1/2)
                  * exp(-(r_i - r_j)^2 / (L_i^2 + L_j^2)),        L_i = a d_i

:func:`paciorek` is its one definition. The compiled GP solve and prediction call its compiled
copy per pair of points; the numpy prediction calls it on arrays. The numpy solve keeps the
pair geometry (q, prefactor below) of a frame across the thetas of a search and multiplies the
kernel out of it (``gp._kernel_from_geometry``); test_gp checks that equals this function.

With d fixed per frame, L = a d and the kernel of the d's is the kernel of the L's: the
prefactor sqrt(2 d_i d_j / (d_i^2 + d_j^2)) does not depend on a, and
(r_i - r_j)^2 / (L_i^2 + L_j^2) = q / a^2 with q = (r_i - r_j)^2 / (d_i^2 + d_j^2). So the
solve passes (d_i, d_j, 1 / a^2) and the prediction (L_i, L_j, 1). The log-gradient of the
marginal likelihood needs dk / dlog sigma_f = 2 k and dk / dlog a = 2 k q / a^2: q is returned
for it.

The same kernel in two dimensions (:func:`paciorek_2d`, ours: the coupled surface,
coupled_surface.py) has an isotropic length scale L_i per point: Paciorek's prefactor
|L_i^2 I|^(1/4) |L_j^2 I|^(1/4) |(L_i^2 + L_j^2) I / 2|^(-1/2) is then the 1-D one squared.

With one length scale for every point the kernel is stationary (prefactor 1);
:func:`stationary_along` evaluates it at equally spaced points by recurrence, for the
per-segment prediction at the bin edges (predict.py) and the border GPs' knots
(coupled_surface.py).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import kernel


def paciorek(diff, l_i, l_j, sigma_f2, inv_scale2):
    """(k, q) of points ``diff`` = r_i - r_j apart with length scales (or factors) l_i, l_j:
    k = sigma_f2 sqrt(2 l_i l_j / s) exp(-q inv_scale2), q = diff^2 / s, s = l_i^2 + l_j^2
    (module docstring). Scalars (compiled) or broadcastable arrays (numpy)."""
    s = l_i * l_i + l_j * l_j
    prefactor = np.sqrt(2.0 * l_i * l_j / s)
    q = diff * diff / s
    return sigma_f2 * prefactor * np.exp(-q * inv_scale2), q


def paciorek_kernel(r1, l1, r2, l2, sigma_f):
    """k(r1_i, r2_j) for broadcastable arrays: r1, l1 (..., n, 1) against r2, l2 (..., 1, m)."""
    return paciorek(r1 - r2, l1, l2, sigma_f * sigma_f, 1.0)[0]


def paciorek_2d(dx, dy, l_i, l_j, sigma_f2):
    """k of points (dx, dy) apart in the plane with isotropic length scales l_i, l_j:
    sigma_f2 (2 l_i l_j / s) exp(-(dx^2 + dy^2) / s), s = l_i^2 + l_j^2 (module docstring).
    Scalars (compiled) or broadcastable arrays (numpy)."""
    s = l_i * l_i + l_j * l_j
    return sigma_f2 * (2.0 * l_i * l_j / s) * np.exp(-(dx * dx + dy * dy) / s)


def stationary_along(row, t, h2, r0, w, ratio, s2, scale) -> bool:
    """row[k] = scale exp(-((r0 + k w - t)^2 + h2) / s2) at the row.size equally spaced points
    r0 + k w (w >= 0) of a line, for a point at t along it and sqrt(h2) off it; s2 = 2 L^2
    (the stationary kernel, prefactor 1) and ratio = exp(-2 w^2 / s2). The value at the
    nearest point, then outwards by one ratio per point that itself shrinks by ``ratio``: three
    exps instead of row.size, every factor <= 1 towards the row's ends (far values underflow to
    0 as the direct formula's do). Returns False, writing nothing, when the value at the
    nearest point is 0 (then it is 0 at all of them)."""
    n = row.size
    peak = int(min(max(round((t - r0) / w) if w > 0.0 else 0.0, 0.0), n - 1.0))
    u = r0 + peak * w - t
    value = math.exp(-(u * u + h2) / s2) * scale
    if value == 0.0:
        return False
    row[peak] = value
    up, step = value, math.exp(-(2.0 * w * u + w * w) / s2)
    for k in range(peak + 1, n):  # farther out: the exponent falls by step / ratio
        up *= step
        row[k] = up
        step *= ratio
    down, step = value, math.exp((2.0 * w * u - w * w) / s2)
    for k in range(peak - 1, -1, -1):
        down *= step
        row[k] = down
        step *= ratio
    return True


# inlined into their compiled callers (numba IR: no call per pair of points)
paciorek_compiled = kernel(paciorek, inline='always') or paciorek  # numpy's without numba
paciorek_2d_compiled = kernel(paciorek_2d, inline='always') or paciorek_2d
stationary_along_compiled = kernel(stationary_along, inline='always') or stationary_along
