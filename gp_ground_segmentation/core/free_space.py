# SPDX-License-Identifier: Apache-2.0
"""Stage ``free_space`` [ours, ``use_free_space_feet``]: a structure foot that the sensor sees
*under* the structure is ground.

The structure test (structure.py) turns a ground-height point into an obstacle when a point a
few cm away horizontally stands well above the ground: the lowest returns of walls, fences, cars
and bushes. It also condemns the flat ground under a car's sill or bumper, a bush's canopy or a
hedge's overhang, because something stands above it, although that something does not reach
down to it.

What tells the two apart is free space, and the sensor itself shows it: a ray that passed
between the foot and the lowest column point above it, and went on to hit the ground farther
out. Under a wall, or a car side that reaches the ground, no ray can: it would have hit the
structure. So a foot is spared when some height-test ground point of its azimuth cell lies more
than ``free_space_beyond_m`` farther out and its ray passed the foot's range more than
``free_space_clearance_m`` above the foot and as far below the column's lowest point. The sensor
is at the origin of the levelled frame, so the ray to (r_b, z_b) passes range r at height
z_b r / r_b: the test is lo < z_b / r_b < hi with lo = (z_foot + clearance) / r_foot and
hi = (z_column - clearance) / r_foot. No beam spacing or sensor model enters: it holds for any
scan pattern.

The structure look-ups (structure.py) hand over every candidate's azimuth cell, range and
height, whether it is a foot, and the lowest column point of its neighbourhood; this stage
clears the spared feet. Both twins give the same mask, bit for bit.
"""

from __future__ import annotations

import numpy as np

from .compiled import Stage, Twin, kernel


def spared_numpy(feet, cand, az_cand, r_cand, z_cand, column_low, n_az, clearance_m,
                 beyond_m):
    """``feet`` (P,) without the spared ones (a new array): the numpy reference.

    cand: (C,) indices into the points of the candidates (the height test's ground points
    within the structure test's range); az_cand (C,) their azimuth cells in [0, n_az); r_cand
    (C,) float64 range (m); z_cand (C,) height (m); column_low (C,) the lowest column point of
    each candidate's neighbourhood (m; +inf where none).
    """
    out = feet.copy()
    is_foot = feet[cand]
    foot = np.flatnonzero(is_foot)
    if foot.size == 0:
        return out
    z64 = z_cand.astype(np.float64)
    lo = (z64[foot] + clearance_m) / r_cand[foot]
    hi = (column_low[foot].astype(np.float64) - clearance_m) / r_cand[foot]
    order = np.argsort(az_cand, kind='stable')
    start = np.searchsorted(az_cand[order], np.arange(n_az + 1))
    row = az_cand[foot]
    count = start[row + 1] - start[row]
    owner = np.repeat(np.arange(foot.size), count)
    first = np.repeat(start[row] - (np.cumsum(count) - count), count)
    other = order[first + np.arange(owner.size)]
    slope = z64[other] / r_cand[other]
    ray = ((r_cand[other] > r_cand[foot][owner] + beyond_m) & (slope > lo[owner])
           & (slope < hi[owner]))
    spared = np.zeros(foot.size, dtype=bool)
    spared[owner[ray]] = True
    out[cand[foot[spared]]] = False
    return out


def _spared_loop(feet, cand, az_cand, r_cand, z_cand, column_low, n_az, clearance_m,
                 beyond_m):
    """:func:`spared_numpy` as loops (compiled with numba): the candidates counted into their
    azimuth cells once, then each foot's cell scanned until a ray is found."""
    out = feet.copy()
    start = np.zeros(n_az + 1, dtype=np.int64)
    for j in range(az_cand.size):
        start[az_cand[j] + 1] += 1
    for a in range(n_az):
        start[a + 1] += start[a]
    fill = start[:n_az].copy()
    order = np.empty(az_cand.size, dtype=np.int64)
    for j in range(az_cand.size):
        order[fill[az_cand[j]]] = j
        fill[az_cand[j]] += 1
    for i in range(cand.size):
        if not feet[cand[i]]:
            continue
        lo = (np.float64(z_cand[i]) + clearance_m) / r_cand[i]
        hi = (np.float64(column_low[i]) - clearance_m) / r_cand[i]
        beyond = r_cand[i] + beyond_m
        a = az_cand[i]
        for k in range(start[a], start[a + 1]):
            j = order[k]
            if r_cand[j] > beyond:
                slope = np.float64(z_cand[j]) / r_cand[j]
                if slope > lo and slope < hi:
                    out[cand[i]] = False
                    break
    return out


def _examples(dtype):
    """A foot (0) with the column's lowest point 0.3 m above it and a ground return 0.4 m
    farther out whose ray passed between them; a second candidate and point for the tables."""
    feet = np.array([True, False, False])
    cand = np.array([0, 1], dtype=np.intp)
    return [(feet, cand, np.array([5, 5], dtype=np.int32), np.array([8.0, 8.4]),
             np.array([-1.7, -1.7], dtype=dtype), np.array([-1.4, np.inf], dtype=dtype), 1440,
             0.03, 0.1)]


FREE_SPACE = Twin('free space under structures', spared_numpy, kernel(_spared_loop), _examples)
STAGE = Stage('free_space', 'ours', 'use_free_space_feet', (FREE_SPACE,))
STAGES = (STAGE,)
