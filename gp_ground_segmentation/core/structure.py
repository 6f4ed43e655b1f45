# SPDX-License-Identifier: Apache-2.0
"""Stage ``structure`` [ours, ``use_vertical_structure_test``]: ground-height points with a
column of returns right above them are the feet of walls, fences, cars, trunks and bushes.

The label rule cannot tell the lowest returns of a vertical surface from the road in front of it:
they lie a few cm above the predicted ground, inside the threshold. What gives them away is what
stands *above* them: a spinning LiDAR puts the next beams' returns on a vertical surface at
nearly the same xy, while on open ground the next beam lands metres further out. So a point
called ground is a foot when another point within a few cm horizontally stands more than
``rise_m`` above the predicted ground and more than ``step_m`` above the point itself (which
keeps a ramp's ground: neighbours a few cm apart on a slope differ by far less). Only points up
to ``max_height_m`` above the ground count (tree crowns, car roofs and signs overhanging visible
ground must not erase it). Curbs stay ground with ``rise_m`` above curb height.

"Within a few cm" is a fine polar grid: azimuth cells of ``cell_deg`` and radial cells of
``cell_m`` out to the range where an azimuth cell is ``cell_m`` wide, growing in proportion to
the range beyond (a far wall's beams are farther apart); a point's neighbourhood is its cell and
the 8 around it. Two compiled passes (the selection of column points and candidates with their
cells; the table of the highest column point per cell and the nine look-ups) have numpy twins
(masks and gathers; a dense table, ``np.maximum.at`` and nine gathers); only the far rings' log
is numpy's on both paths (numba's differs in the last bit).
"""

from __future__ import annotations

import numpy as np

from . import free_space as _free_space
from .compiled import Stage, Twin, kernel
from .free_space import FREE_SPACE
from .grid import _angle, _segment_of_angle

__all__ = ['vertical_structure_mask', 'structure_feet']


# Cells grow with range only up to this size (m): a wider neighbourhood is no longer "right
# above" a point. Points beyond the range where cells would be wider (115 m at 0.25 degrees)
# keep their height-test label; it also bounds the cell table however far points lie.
_MAX_CELL_M = 0.5


def _within(index, r, limit):
    """The entries of ``index`` whose points lie within ``limit`` of the sensor, and their r."""
    r = r[index]
    near = r <= limit
    return index[near], r[near]


def structure_feet(params, x, y, z, ground_z, candidate, *, r=None, angle=None,
                   compiled: bool = True):
    """:func:`vertical_structure_mask` with the sizes of ``params`` (SegmenterParams:
    structure_cell_m, structure_cell_deg, structure_rise_m, structure_max_height_m,
    structure_step_m), and the free-space stage's (free_space.py) when it is on: the stages
    ``structure`` and ``free_space`` of the segmenter, also for tools that apply them to other
    ground heights."""
    free_space = None
    if _free_space.STAGE.on(params):
        free_space = (params.free_space_clearance_m, params.free_space_beyond_m)
    return vertical_structure_mask(
        x, y, z, ground_z, candidate, cell_m=params.structure_cell_m,
        cell_deg=params.structure_cell_deg, rise_m=params.structure_rise_m,
        max_height_m=params.structure_max_height_m, step_m=params.structure_step_m, r=r,
        angle=angle, compiled=compiled, free_space=free_space)


def vertical_structure_mask(x: np.ndarray, y: np.ndarray, z: np.ndarray,
                            ground_z: np.ndarray, candidate: np.ndarray, *, cell_m: float,
                            cell_deg: float, rise_m: float, max_height_m: float,
                            step_m: float, r: np.ndarray | None = None,
                            angle: np.ndarray | None = None,
                            compiled: bool = True, free_space=None) -> np.ndarray:
    """Bool mask of the ``candidate`` points that stand at the foot of a vertical structure.

    x, y, z: (P,) finite coordinates (m); ground_z: (P,) predicted ground height under each
    point (m); candidate: (P,) bool, the points the height test called ground. cell_m: radial
    cell size (m) near the sensor; cell_deg: azimuth cell (deg); rise_m, max_height_m, step_m: a
    point of the neighbourhood between rise_m and max_height_m above the predicted ground (m)
    and more than step_m above the candidate itself (m) makes the candidate a structure foot.
    r: (P,) horizontal range sqrt(x^2 + y^2) (m) and angle: (P,) float64 azimuth
    arctan2(y, x) (rad, as ``grid._angle`` computes it) when the caller has them (the grid
    does). compiled: the numba passes when numba imports and they are compiled for these
    types (else their numpy twins, the same mask; False: the twins always). free_space:
    (clearance_m, beyond_m) to spare the feet under which the sensor saw free space
    (free_space.py), or None.
    Returns a (P,) bool mask, a subset of ``candidate``.
    """
    cell_rad = np.radians(cell_deg)
    limit = max(_MAX_CELL_M, cell_m) / cell_rad
    if r is None:
        r = np.hypot(x, y)
    if angle is None:
        angle = _angle(x, y)
    # the limits in the precision of what they are compared with, as numpy compares an array
    # with a Python float
    height_type = np.result_type(z, ground_z).type
    select = (angle, z, ground_z, candidate, r, height_type(rise_m), height_type(max_height_m),
              r.dtype.type(limit))
    # the step in z's precision, as numpy compares a float32 difference with a Python float
    return _mask_in_cells(select, cell_m, cell_rad, z.dtype.type(step_m), compiled,
                          free_space)


def _mask_in_cells(select, cell_m: float, cell_rad: float, step, compiled: bool,
                   free_space=None):
    """The mask in two passes, each compiled when ``compiled`` and ready (else its numpy
    twin, the same result): the selection and the points' polar cells, then the far rings,
    the table, the look-ups and the mask. Only the far rings' log is numpy's on both paths
    (numba's differs from numpy's in the last bit).

    The cells: azimuth cells of ``cell_rad`` (the grid's segments, only finer), and radial
    cells of ``cell_m`` out to r_square = cell_m / cell_rad, where an azimuth cell is cell_m
    wide, then cells growing with r: index r_square / cell_m + ln(r / r_square) / cell_rad,
    continuous at r_square. Float64 maths whatever the input precision: a float32 cloud and its
    float64 copy must put every point in the same cell. ``free_space``: (clearance_m,
    beyond_m) of the free-space stage (free_space.py), which then spares the feet it clears, or
    None."""
    n_az = max(1, int(np.ceil(2.0 * np.pi / cell_rad)))
    r_square = cell_m / cell_rad
    # the constants as _segment_of_angle computes them
    cells = (n_az, n_az / (2.0 * np.pi), 1.0 / cell_m, r_square, 1.0 / r_square)
    (az_col, ring_col, z_col, cand, az_cand, ring_cand, z_cand, far_index, n_far_col,
     far_ratio, r_cand) = SELECT_CELLS.run(compiled, *select, *cells)
    feet = CELLS_HITS.run(compiled, select[1].size, az_col, ring_col, z_col, cand, az_cand,
                          ring_cand, z_cand, far_index, n_far_col, np.log(far_ratio),
                          r_square / cell_m, 1.0 / cell_rad, n_az, step)
    if free_space is None or not feet.any():
        return feet
    clearance_m, beyond_m = free_space
    ground_z, rise_m = select[2], select[5]
    return FREE_SPACE.run(compiled, feet, cand, az_cand, r_cand, z_cand, ground_z,
                          float(rise_m), n_az, float(clearance_m), float(beyond_m))


def _cells_numpy(angle, r, n_az, inv_cell_m, r_square):
    """Azimuth cells, radial cells of the points within ``r_square`` (0 beyond) and the
    indices of those beyond (numpy; the far rings are :func:`_far_rings`')."""
    az = _segment_of_angle(angle, n_az)
    far = np.flatnonzero(r > r_square)
    ring = (r * inv_cell_m).astype(np.int32)
    ring[far] = 0
    return az, ring, far


def _select_cells_numpy(angle, z, ground_z, candidate, r, rise_m, max_height_m, limit, n_az,
                        az_factor, inv_cell_m, r_square, inv_r_square):
    """The numpy twin of :func:`_select_cells_loop` (while it compiles, or without numba)."""
    angle_col, z_col, r_col, cand, angle_cand, z_cand, r_cand = _select_numpy(
        angle, z, ground_z, candidate, r, rise_m, max_height_m, limit)
    az_col, ring_col, far_col = _cells_numpy(angle_col, r_col, n_az, inv_cell_m, r_square)
    az_cand, ring_cand, far_cand = _cells_numpy(angle_cand, r_cand, n_az, inv_cell_m, r_square)
    far_ratio = np.concatenate([r_col[far_col], r_cand[far_cand]]) * inv_r_square
    return (az_col, ring_col, z_col, cand, az_cand, ring_cand, z_cand,
            np.concatenate([far_col, far_cand]), far_col.size, far_ratio, r_cand)


def _select_cells_loop(angle, z, ground_z, candidate, r, rise_m, max_height_m, limit, n_az,
                       az_factor, inv_cell_m, r_square, inv_r_square):
    """The compiled selection (:func:`_select_loop`) and the cells of the points it selects
    (compiled with numba): azimuth cell, radial cell out to ``r_square`` (0 beyond), and of
    the points beyond it their index (column points first, then candidates; ``n_far_col`` of
    the former) and r / r_square, whose log numpy takes (:func:`_mask_in_cells`' cells,
    the same float64 operations as :func:`_cells_numpy`), and the candidates' r."""
    angle_col, z_col, r_col, cand, angle_cand, z_cand, r_cand = _select_compiled(
        angle, z, ground_z, candidate, r, rise_m, max_height_m, limit)
    n_col, n_cand = z_col.size, z_cand.size
    az_col = np.empty(n_col, dtype=np.int32)
    ring_col = np.empty(n_col, dtype=np.int32)
    az_cand = np.empty(n_cand, dtype=np.int32)
    ring_cand = np.empty(n_cand, dtype=np.int32)
    far_index = np.empty(n_col + n_cand, dtype=np.intp)
    far_ratio = np.empty(n_col + n_cand)
    n_far = 0
    n_far_col = 0
    for part in range(2):
        angles, ranges = (angle_col, r_col) if part == 0 else (angle_cand, r_cand)
        az, ring = (az_col, ring_col) if part == 0 else (az_cand, ring_cand)
        for i in range(ranges.size):
            az[i] = min(np.int32((angles[i] + np.pi) * az_factor), n_az - 1)
            if ranges[i] > r_square:
                ring[i] = 0
                far_index[n_far] = i
                far_ratio[n_far] = ranges[i] * inv_r_square
                n_far += 1
            else:
                ring[i] = np.int32(ranges[i] * inv_cell_m)
        if part == 0:
            n_far_col = n_far
    return (az_col, ring_col, z_col, cand, az_cand, ring_cand, z_cand, far_index[:n_far],
            n_far_col, far_ratio[:n_far], r_cand)


def _far_rings(ring_col, ring_cand, far_index, n_far_col, log_ratio, ring_base,
               inv_cell_rad):
    """Radial cells of the points beyond r_square (ring_base + ln(r / r_square) / cell_rad,
    as :func:`_mask_in_cells` defines them) into ``ring_col`` and ``ring_cand``, in place."""
    ring = (ring_base + log_ratio * inv_cell_rad).astype(np.int32)
    ring_col[far_index[:n_far_col]] = ring[:n_far_col]
    ring_cand[far_index[n_far_col:]] = ring[n_far_col:]


def _cells_hits_numpy(n_points, az_col, ring_col, z_col, cand, az_cand, ring_cand, z_cand,
                      far_index, n_far_col, log_ratio, ring_base, inv_cell_rad, n_az, step):
    """The numpy twin of :func:`_cells_hits_loop` (while it compiles, or without numba)."""
    out = np.zeros(n_points, dtype=bool)
    if cand.size == 0 or z_col.size == 0:
        return out
    ring_col, ring_cand = ring_col.copy(), ring_cand.copy()
    _far_rings(ring_col, ring_cand, far_index, n_far_col, log_ratio, ring_base, inv_cell_rad)
    width = int(max(ring_col.max(), ring_cand.max())) + 3
    out[cand] = _structure_hits_numpy(az_col, ring_col, z_col, az_cand, ring_cand, z_cand,
                                      n_az, width, step)
    return out


def _cells_hits_loop(n_points, az_col, ring_col, z_col, cand, az_cand, ring_cand, z_cand,
                     far_index, n_far_col, log_ratio, ring_base, inv_cell_rad, n_az, step):
    """The far rings (written into ``ring_col`` and ``ring_cand``), the compiled table and
    look-ups (:func:`_structure_hits_loop`) and the (P,) mask of the ``cand`` points that
    hit, in one compiled call: the same mask as :func:`_cells_hits_numpy`."""
    out = np.zeros(n_points, dtype=np.bool_)
    if cand.size == 0 or z_col.size == 0:
        return out
    for f in range(far_index.size):
        ring = np.int32(ring_base + log_ratio[f] * inv_cell_rad)
        if f < n_far_col:
            ring_col[far_index[f]] = ring
        else:
            ring_cand[far_index[f]] = ring
    hit = _structure_hits_compiled(az_col, ring_col, z_col, az_cand, ring_cand, z_cand, n_az,
                                   0, step)
    for i in range(cand.size):
        out[cand[i]] = hit[i]
    return out


def _select_numpy(angle, z, ground_z, candidate, r, rise_m, max_height_m, limit):
    """The points within ``limit`` of the sensor that are column points (between ``rise_m`` and
    ``max_height_m`` above the predicted ground) and those that are ``candidate``s: (azimuth,
    z, r of the column points, then the candidates' indices, azimuth, z, r), r in float64 for
    the cells (:func:`_mask_in_cells`)."""
    height = z - ground_z
    selected = []
    for index in (np.flatnonzero((height > rise_m) & (height <= max_height_m)),
                  np.flatnonzero(candidate)):
        index, r_in = _within(index, r, limit)
        selected += [index, angle[index], z[index], np.asarray(r_in, dtype=np.float64)]
    return tuple(selected[1:])


def _select_loop(angle, z, ground_z, candidate, r, rise_m, max_height_m, limit):
    """:func:`_select_numpy` in two passes over the points (compiled with numba): the same
    comparisons in the same precision and the same values, without the reference's masks,
    gathers and conversions."""
    n_points = z.size
    kind = np.zeros(n_points, dtype=np.uint8)  # bit 0: column point, bit 1: candidate
    n_column = 0
    n_cand = 0
    for i in range(n_points):
        if not r[i] <= limit:
            continue
        height = z[i] - ground_z[i]
        if height > rise_m and height <= max_height_m:
            kind[i] = 1
            n_column += 1
        if candidate[i]:
            kind[i] |= 2
            n_cand += 1
    angle_col, r_col = np.empty(n_column, dtype=angle.dtype), np.empty(n_column)
    z_col = np.empty(n_column, dtype=z.dtype)
    cand = np.empty(n_cand, dtype=np.intp)
    angle_cand, r_cand = np.empty(n_cand, dtype=angle.dtype), np.empty(n_cand)
    z_cand = np.empty(n_cand, dtype=z.dtype)
    c = 0
    k = 0
    for i in range(n_points):
        if kind[i] & 1:
            angle_col[c], z_col[c], r_col[c] = angle[i], z[i], r[i]
            c += 1
        if kind[i] & 2:
            cand[k] = i
            angle_cand[k], z_cand[k], r_cand[k] = angle[i], z[i], r[i]
            k += 1
    return angle_col, z_col, r_col, cand, angle_cand, z_cand, r_cand


_select_compiled = kernel(_select_loop)


def _structure_hits_numpy(az_col, ring_col, z_col, az_cand, ring_cand, z_cand, n_az, width,
                          step):
    """Candidates with a column point in their 3 x 3 cells more than ``step`` above them."""
    # highest column point per cell; one spare cell on every side: row 0 repeats the last
    # azimuth row and row n_az + 1 the first (azimuth wraps around), so each of the 9
    # neighbours is a constant offset in the flat table
    top = np.full((n_az + 2, width), -np.inf, dtype=z_col.dtype)
    np.maximum.at(top.ravel(), (az_col + 1).astype(np.intp) * width + (ring_col + 1), z_col)
    top[0] = top[n_az]
    top[n_az + 1] = top[1]
    top = top.ravel()
    base = (az_cand + 1).astype(np.intp) * width + (ring_cand + 1)
    highest = np.full(az_cand.size, -np.inf, dtype=z_col.dtype)
    for offset in (-width - 1, -width, -width + 1, -1, 0, 1, width - 1, width, width + 1):
        np.maximum(highest, top.take(base + offset), out=highest)
    return highest - z_cand > step


def _structure_hits_loop(az_col, ring_col, z_col, az_cand, ring_cand, z_cand, n_az, width,
                         step):
    """:func:`_structure_hits_numpy` as loops (compiled with numba): the same mask.

    The table holds, per azimuth row, only the rings between that row's nearest and farthest
    column point (rows one after the other, as in a sparse row matrix) instead of the dense
    (n_az + 2) x ``width`` table: filling that with -inf every frame cost more than the
    look-ups (the dense table has many times the cells in use). A cell outside its
    row's range holds no column point, -inf in the reference; the highest of the nine cells is
    the same value, so the mask is too. ``width`` is not needed.
    """
    # plain loops rather than np.full and slice copies: they compile in a third of the time
    ring_lo = np.empty(n_az, dtype=np.int64)  # per azimuth row: first and last ring in use
    ring_hi = np.empty(n_az, dtype=np.int64)
    for a in range(n_az):
        ring_lo[a] = 0
        ring_hi[a] = -1  # an empty row
    for i in range(az_col.size):
        a = az_col[i]
        ring = np.int64(ring_col[i])
        if ring_hi[a] < ring_lo[a]:
            ring_lo[a] = ring
            ring_hi[a] = ring
        elif ring < ring_lo[a]:
            ring_lo[a] = ring
        elif ring > ring_hi[a]:
            ring_hi[a] = ring
    row_start = np.empty(n_az + 1, dtype=np.int64)
    row_start[0] = 0
    for a in range(n_az):
        row_start[a + 1] = row_start[a] + ring_hi[a] - ring_lo[a] + 1
    # one spare cell at the end: -inf in z's precision, where every look-up starts (so that
    # highest - z is computed in that precision, as in the reference)
    top = np.empty(row_start[n_az] + 1, dtype=z_col.dtype)
    for cell in range(top.size):
        top[cell] = -np.inf
    for i in range(az_col.size):
        a = az_col[i]
        cell = row_start[a] + ring_col[i] - ring_lo[a]
        if z_col[i] > top[cell]:
            top[cell] = z_col[i]
    hit = np.zeros(az_cand.size, dtype=np.bool_)
    for i in range(az_cand.size):
        highest = top[top.size - 1]
        ring = np.int64(ring_cand[i])
        row = np.int64(az_cand[i])
        before = row - 1 if row > 0 else n_az - 1  # the azimuth rows around, wrapping around
        after = row + 1 if row < n_az - 1 else 0
        for a in (before, row, after):
            first = max(ring - 1, ring_lo[a])
            last = min(ring + 1, ring_hi[a])
            for cell in range(row_start[a] + first - ring_lo[a],
                              row_start[a] + last - ring_lo[a] + 1):
                if top[cell] > highest:
                    highest = top[cell]
        hit[i] = highest - z_cand[i] > step
    return hit


_structure_hits_compiled = kernel(_structure_hits_loop)
_select_cells_compiled = _cells_hits_compiled = None
if _structure_hits_compiled is not None:  # these passes call the compiled ones above
    _select_cells_compiled = kernel(_select_cells_loop)
    _cells_hits_compiled = kernel(_cells_hits_loop)


# the examples' cells: 1 degree azimuth, 0.5 m radial (as _mask_in_cells makes the constants)
_EXAMPLE_CELL_RAD, _EXAMPLE_CELL_M = float(np.radians(1.0)), 0.5
_EXAMPLE_N_AZ, _EXAMPLE_R_SQUARE = 360, _EXAMPLE_CELL_M / _EXAMPLE_CELL_RAD


def _select_examples(dtype):
    """A ground point with a column point right above it (reaches every compiled part)."""
    z = np.array([0.0, 0.5], dtype)
    scalar = np.dtype(dtype).type
    return [(np.zeros(2), z, np.zeros(2, dtype), np.array([True, False]), np.ones(2, dtype),
             scalar(0.2), scalar(0.7), scalar(100.0), _EXAMPLE_N_AZ,
             _EXAMPLE_N_AZ / (2.0 * np.pi), 1.0 / _EXAMPLE_CELL_M, _EXAMPLE_R_SQUARE,
             1.0 / _EXAMPLE_R_SQUARE)]


def _hits_examples(dtype):
    cells = _select_cells_numpy(*_select_examples(dtype)[0])
    return [(2, *cells[:-2], np.log(cells[-2]), _EXAMPLE_R_SQUARE / _EXAMPLE_CELL_M,
             1.0 / _EXAMPLE_CELL_RAD, _EXAMPLE_N_AZ, np.dtype(dtype).type(0.05))]


SELECT_CELLS = Twin('structure selection and cells', _select_cells_numpy,
                    _select_cells_compiled, _select_examples)
CELLS_HITS = Twin('structure look-ups', _cells_hits_numpy, _cells_hits_compiled,
                  _hits_examples)
STAGE = Stage('structure', 'ours', 'use_vertical_structure_test', (SELECT_CELLS, CELLS_HITS))
STAGES = (STAGE,)
