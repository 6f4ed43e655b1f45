# SPDX-License-Identifier: Apache-2.0
"""Stage ``free_space`` [ours, ``use_free_space_feet``]: a structure foot that the sensor sees
*under* the structure is ground.

The structure test (structure.py) turns a ground-height point into an obstacle when a point a
few cm away horizontally stands between ``structure_rise_m`` and ``structure_max_height_m``
above the predicted ground: the lowest returns of walls, fences, cars and bushes. It also
condemns the flat ground under a car's sill or bumper, a bush's canopy or a hedge's overhang:
something stands above it, but does not reach down to it.

What tells the two apart is free space, and the sensor itself shows it: a ray that passed over
the foot through the band where a structure standing on it would have to be -- above the foot,
below ``structure_rise_m`` over the ground -- and went on to hit the ground farther out. Under
a wall, or a car side that reaches the ground, no ray can: it would have hit the structure. So
a foot is spared when some height-test ground point of its azimuth cell lies more than
``free_space_beyond_m`` farther out and its ray passed the foot's range more than
``free_space_clearance_m`` above the foot and as far below ground + ``structure_rise_m``. The
sensor is at the origin of the levelled frame, so the ray to (r_b, z_b) passes range r at
height z_b r / r_b: the test is lo < z_b / r_b < hi with lo = (z_foot + clearance) / r_foot
and hi = (z_hat + rise - clearance) / r_foot. No beam spacing or sensor model enters: it holds
for any scan pattern.

The structure test hands over its candidates (azimuth cell, range, height), which are feet and
the predicted ground; this stage clears the spared feet. Both twins give the same mask, bit for
bit.
"""

from __future__ import annotations

import numpy as np

from .compiled import Stage, Twin, kernel


def spared_numpy(feet, cand, az_cand, r_cand, z_cand, ground_z, rise_m, n_az, clearance_m,
                 beyond_m):
    """``feet`` (P,) without the spared ones (a new array): the numpy reference.

    cand: (C,) indices into the points of the candidates (the height test's ground points
    within the structure test's range); az_cand (C,) their azimuth cells in [0, n_az); r_cand
    (C,) float64 range (m); z_cand (C,) height (m); ground_z (P,) the predicted ground under
    every point (m); rise_m: the structure test's column height over the ground (m).
    """
    out = feet.copy()
    foot = np.flatnonzero(feet[cand])
    if foot.size == 0:
        return out
    z64 = z_cand.astype(np.float64)
    lo = (z64[foot] + clearance_m) / r_cand[foot]
    hi = ((ground_z[cand[foot]].astype(np.float64) + rise_m) - clearance_m) / r_cand[foot]
    order = np.argsort(az_cand, kind='stable')
    start = np.searchsorted(az_cand[order], np.arange(n_az + 1))
    row = az_cand[foot]
    count = start[row + 1] - start[row]
    owner = np.repeat(np.arange(foot.size), count)
    first = np.repeat(start[row] - (np.cumsum(count) - count), count)
    other = order[first + np.arange(owner.size)]
    # the ray's slope z / r between lo and hi, without a division per candidate: r > 0
    ray = ((r_cand[other] > r_cand[foot][owner] + beyond_m)
           & (z64[other] > lo[owner] * r_cand[other]) & (z64[other] < hi[owner] * r_cand[other]))
    spared = np.zeros(foot.size, dtype=bool)
    spared[owner[ray]] = True
    out[cand[foot[spared]]] = False
    return out


def _spared_loop(feet, cand, az_cand, r_cand, z_cand, ground_z, rise_m, n_az, clearance_m,
                 beyond_m):
    """:func:`spared_numpy` as loops (compiled with numba): the candidates' ranges and heights
    counted into their azimuth cells once (contiguous per cell, so each foot scans its cell in
    order), then each foot's cell scanned until a ray is found."""
    out = feet.copy()
    start = np.zeros(n_az + 1, dtype=np.int64)
    for j in range(az_cand.size):
        start[az_cand[j] + 1] += 1
    for a in range(n_az):
        start[a + 1] += start[a]
    fill = start[:n_az].copy()
    cell_r = np.empty(az_cand.size)
    cell_z = np.empty(az_cand.size)
    for j in range(az_cand.size):
        k = fill[az_cand[j]]
        cell_r[k] = r_cand[j]
        cell_z[k] = np.float64(z_cand[j])
        fill[az_cand[j]] = k + 1
    for i in range(cand.size):
        if not feet[cand[i]]:
            continue
        lo = (np.float64(z_cand[i]) + clearance_m) / r_cand[i]
        hi = ((np.float64(ground_z[cand[i]]) + rise_m) - clearance_m) / r_cand[i]
        if not hi > lo:
            continue
        beyond = r_cand[i] + beyond_m
        a = az_cand[i]
        for k in range(start[a], start[a + 1]):
            if cell_r[k] > beyond and cell_z[k] > lo * cell_r[k] and cell_z[k] < hi * cell_r[k]:
                out[cand[i]] = False
                break
    return out


def _examples(dtype):
    """A foot (0) on ground at -1.7 m, a ground return 0.4 m farther out whose ray passed over
    it below the column height (0.2 m), and a third point that is no candidate."""
    feet = np.array([True, False, False])
    return [(feet, np.array([0, 1], dtype=np.intp), np.array([5, 5], dtype=np.int32),
             np.array([8.0, 8.4]), np.array([-1.7, -1.7], dtype=dtype),
             np.full(3, -1.7, dtype=dtype), 0.2, 1440, 0.03, 0.1)]


FREE_SPACE = Twin('free space under structures', spared_numpy, kernel(_spared_loop), _examples)
STAGE = Stage('free_space', 'ours', 'use_free_space_feet', (FREE_SPACE,))
STAGES = (STAGE,)
