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
    """:func:`spared_numpy` as loops (compiled with numba): the feet counted into their
    azimuth cells with their ray bounds (:func:`_feet_by_cell`), the candidates that lie
    beyond their cell's nearest foot counted into the cells too (:func:`_rays_by_cell`; a few
    percent of them on a street scan: feet are mostly far out), then each foot tests its
    cell's rays until one passes under its column (a dense cloud's feet stop early)."""
    out = feet.copy()
    start, owner, lo, hi, beyond, near = _feet_by_cell(feet, cand, az_cand, r_cand, z_cand,
                                                       ground_z, rise_m, n_az, clearance_m,
                                                       beyond_m)
    ray_start, ray_r, ray_z = _rays_by_cell(az_cand, r_cand, z_cand, near, n_az)
    for a in range(n_az):
        for k in range(start[a], start[a + 1]):
            if beyond[k] == np.inf:  # no ray can pass between the foot and its column
                continue
            for q in range(ray_start[a], ray_start[a + 1]):
                r = ray_r[q]
                if r > beyond[k] and ray_z[q] > lo[k] * r and ray_z[q] < hi[k] * r:
                    out[owner[k]] = False
                    break
    return out


def _rays_by_cell(az_cand, r_cand, z_cand, near, n_az):
    """The candidates beyond their cell's nearest foot (``near``), contiguous per azimuth cell
    (cell a's from ray_start[a] to ray_start[a + 1]): their ranges and heights."""
    ray_start = np.zeros(n_az + 1, dtype=np.int64)
    for j in range(az_cand.size):
        if r_cand[j] > near[az_cand[j]]:
            ray_start[az_cand[j] + 1] += 1
    for a in range(n_az):
        ray_start[a + 1] += ray_start[a]
    fill = ray_start[:n_az].copy()
    ray_r = np.empty(ray_start[n_az])
    ray_z = np.empty(ray_start[n_az])
    for j in range(az_cand.size):
        a = az_cand[j]
        if r_cand[j] > near[a]:
            ray_r[fill[a]] = r_cand[j]
            ray_z[fill[a]] = np.float64(z_cand[j])
            fill[a] += 1
    return ray_start, ray_r, ray_z


def _feet_by_cell(feet, cand, az_cand, r_cand, z_cand, ground_z, rise_m, n_az, clearance_m,
                  beyond_m):
    """The feet among the candidates, contiguous per azimuth cell (cell a's from start[a] to
    start[a + 1]): their point index, ray slope bounds lo and hi and range beyond which a
    return spares them (inf where hi <= lo: none can), and per cell the nearest of those
    ranges (inf: no foot to spare)."""
    foot = np.empty(cand.size, dtype=np.int64)
    start = np.zeros(n_az + 1, dtype=np.int64)
    n_foot = 0
    for i in range(cand.size):
        if feet[cand[i]]:
            foot[n_foot] = i
            n_foot += 1
            start[az_cand[i] + 1] += 1
    for a in range(n_az):
        start[a + 1] += start[a]
    fill = start[:n_az].copy()
    near = np.full(n_az, np.inf)
    owner = np.empty(n_foot, dtype=np.int64)
    lo, hi, beyond = np.empty(n_foot), np.empty(n_foot), np.empty(n_foot)
    for f in range(n_foot):
        i = foot[f]
        a = az_cand[i]
        k = fill[a]
        fill[a] = k + 1
        owner[k] = cand[i]
        lo[k] = (np.float64(z_cand[i]) + clearance_m) / r_cand[i]
        hi[k] = ((np.float64(ground_z[cand[i]]) + rise_m) - clearance_m) / r_cand[i]
        beyond[k] = r_cand[i] + beyond_m
        if not hi[k] > lo[k]:
            beyond[k] = np.inf
        elif beyond[k] < near[a]:
            near[a] = beyond[k]
    return start, owner, lo, hi, beyond, near


def _examples(dtype):
    """A foot (0) on ground at -1.7 m, a ground return 0.4 m farther out whose ray passed over
    it below the column height (0.2 m), and a third point that is no candidate."""
    feet = np.array([True, False, False])
    return [(feet, np.array([0, 1], dtype=np.intp), np.array([5, 5], dtype=np.int32),
             np.array([8.0, 8.4]), np.array([-1.7, -1.7], dtype=dtype),
             np.full(3, -1.7, dtype=dtype), 0.2, 1440, 0.03, 0.1)]


_feet_by_cell = kernel(_feet_by_cell, inline='always') or _feet_by_cell
_rays_by_cell = kernel(_rays_by_cell, inline='always') or _rays_by_cell
FREE_SPACE = Twin('free space under structures', spared_numpy, kernel(_spared_loop), _examples)
STAGE = Stage('free_space', 'ours', 'use_free_space_feet', (FREE_SPACE,))
STAGES = (STAGE,)
