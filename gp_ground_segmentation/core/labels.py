# SPDX-License-Identifier: Apache-2.0
"""Stage ``labels``: the ground height under every point and the label rule.

z_hat of a point is its segment's posterior mean at the bin edges interpolated linearly along r
within its bin. The label rule [paper: "close to the ground"] is :func:`is_ground`, one
definition for the numpy and the compiled pass: a point is ground when z - z_hat <= threshold.
The test is one-sided, as in the paper: anything below the predicted ground is ground
(below-ground noise included: it is no obstacle). There is no height or range cut-off.

The threshold is ``ground_threshold_m`` [the paper's, a number it leaves open], widened (ours):

* ``use_std_threshold``: by ``std_threshold_factor`` times the GP's posterior std, so it grows
  where the GP is unsure (far, sparse, between lines);
* ``use_cross_slope_threshold``: by the rise of the predicted ground across the segment where
  the neighbouring segments show a slope across the beams (:func:`cross_segment_rise`), so the
  high side of ground sloping across the beams stays ground;

and capped at ``max_threshold_m`` in total, so it never becomes a height cut-off.
"""

from __future__ import annotations

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, kernel


def is_ground(z, z_hat, threshold):
    """The label rule: ground when the point is at most ``threshold`` above the ground
    ``z_hat`` (scalars, compiled, or arrays)."""
    return z - z_hat <= threshold


def edge_thresholds(edges, mean, std, params, compiled: bool = True):
    """The ground threshold (m) at the (M, N + 1) bin ``edges``: a scalar, or (M, N + 1) when
    it varies (module docstring); ``mean`` and ``std`` are the GP's there (std None unless
    ``use_std_threshold``)."""
    p = params
    threshold = p.ground_threshold_m
    if STD_THRESHOLD.on(p):
        threshold = threshold + p.std_threshold_factor * std
    if CROSS_SLOPE.on(p):
        rise = cross_segment_rise(edges, mean, p.cross_slope_max, compiled=compiled)
        rise += threshold  # a new array: threshold + rise, in place (addition commutes)
        return np.minimum(rise, p.max_threshold_m, out=rise)
    return np.minimum(threshold, p.max_threshold_m)


def label_points(mean: np.ndarray, threshold, grid, z: np.ndarray, compiled: bool = True):
    """(z_hat, ground) of every point: the (M, N + 1) ``mean`` and ``threshold`` (or a scalar
    threshold) at the bin edges interpolated to the points of ``grid`` (a RadialGrid) and the
    label rule, in the points' precision."""
    if np.ndim(threshold) == 0:
        z_hat = interpolate_at_points(mean, grid)
        return z_hat, is_ground(z, z_hat, threshold)
    frac = grid.point_bin_fraction
    return LABELS.run(compiled, mean.ravel().astype(frac.dtype),
                      threshold.ravel().astype(frac.dtype), grid.point_segment, grid.point_bin,
                      frac, z, grid.num_bins + 1)


def interpolate_at_points(values: np.ndarray, grid) -> np.ndarray:
    """(M, N + 1) values at bin edges -> every point of ``grid``, linearly along r within its
    bin, in the points' precision (flat gathers: at 2 M points every float64 temporary is
    16 MB)."""
    frac = grid.point_bin_fraction
    inner = _inner_edge_index(grid.point_segment, grid.point_bin, grid.num_bins + 1)
    return _interpolate_flat(values.ravel().astype(frac.dtype), inner, frac)


def _inner_edge_index(point_segment, point_bin, row_length) -> np.ndarray:
    """Flat (M, N + 1) index of every point's inner bin edge (the outer one is the next)."""
    return point_segment * np.int32(row_length) + point_bin


def _interpolate_flat(flat: np.ndarray, inner: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """``flat[inner]`` moved ``frac`` of the way to ``flat[inner + 1]``, in ``flat``'s dtype."""
    out = flat[inner]
    step = flat[inner + 1]
    step -= out
    step *= frac
    out += step
    return out


def _label_numpy(mean, threshold, point_segment, point_bin, frac, z, row_length):
    """The numpy reference of :func:`_label_loop`: flat (M * (N + 1)) ``mean`` and
    ``threshold`` at the bin edges, each point's segment, bin and position in the bin ->
    (z_hat, ground)."""
    inner = _inner_edge_index(point_segment, point_bin, row_length)
    z_hat = _interpolate_flat(mean, inner, frac)
    return z_hat, is_ground(z, z_hat, _interpolate_flat(threshold, inner, frac))


def _label_loop(mean, threshold, point_segment, point_bin, frac, z, row_length):
    """:func:`_label_numpy` in one pass over the points (compiled with numba): the same
    operations in the same precision for each point, without the reference's six gathers and
    per-point temporaries."""
    z_hat = np.empty(z.size, dtype=frac.dtype)
    ground = np.empty(z.size, dtype=np.bool_)
    for i in range(z.size):
        inner = point_segment[i] * row_length + point_bin[i]
        f = frac[i]
        low = mean[inner]
        height = low + (mean[inner + 1] - low) * f
        low = threshold[inner]
        z_hat[i] = height
        ground[i] = _is_ground(z[i], height, low + (threshold[inner + 1] - low) * f)
    return z_hat, ground


_is_ground = is_ground
_label_compiled = None
if AVAILABLE:  # the pass calls the compiled label rule, inlined per point
    _is_ground = kernel(is_ground, inline='always')
    _label_compiled = kernel(_label_loop)
is_ground_compiled = _is_ground  # for other stages' compiled passes (coupled_surface.py)


def _label_examples(dtype):
    edges, points = np.zeros(6, dtype), np.zeros(2, dtype)
    index = np.zeros(2, np.int32)
    return [(edges, edges, index, index, points, points, 3)]


LABELS = Twin('label pass', _label_numpy, _label_compiled, _label_examples)


def cross_segment_rise(edges: np.ndarray, mean: np.ndarray, max_slope: float,
                       compiled: bool = True) -> np.ndarray:
    """(M, N + 1) how much the predicted ground rises across one segment at each bin edge (m).

    The GP models z(r) per segment, and a bin's candidate is its lowest point: where the ground
    rises *across* the beams (an embankment beside the road), the candidate follows the
    segment's low side and the high side sits above z_hat by up to the rise across the
    segment. The rise is estimated from the neighbouring segments' ground at the same r
    (segments wrap around): only where the ground rises on one side of the segment and falls on
    the other (a slope across it), by the smaller of the two steps, |z_hat[m + 1] - z_hat[m]|
    and |z_hat[m] - z_hat[m - 1]|. A single raised neighbour (a fit bent up by an obstacle, a
    car beside the road) is no slope. The rise is
    capped at what a slope of ``max_slope`` gives over the segment's width 2 pi r / M there: a
    steeper rise is structure (or a poor fit next to it), not ground, and must not widen the
    threshold more.

    ``edges``: (M, N + 1) r of every segment's bin edges (increasing along each row);
    ``mean``: z_hat there. ``compiled``: one numba pass when numba imports (else the numpy
    reference); both give the same values.
    """
    return RISE.run(compiled, edges, mean, float(max_slope))


def _rise_numpy(edges, mean, max_slope):
    """The numpy reference of :func:`cross_segment_rise`."""
    span = float(np.nanmax(edges)) + 1.0  # more than any r
    m_count = edges.shape[0]
    # one sorted 1-D table of all rows (row offset by a span larger than any r): np.interp
    # then looks up every segment's edges in its neighbour's row at once
    offset = np.arange(m_count)[:, None] * span
    flat_r = (edges + offset).ravel()
    flat_z = mean.ravel()

    def neighbour(shift):
        rows = (np.arange(m_count) + shift) % m_count
        query = np.clip(edges, edges[rows, :1], edges[rows, -1:]) + offset[rows]
        return np.interp(query, flat_r, flat_z)

    ahead = neighbour(1) - mean
    behind = mean - neighbour(-1)
    rise = np.where(ahead * behind > 0, np.minimum(np.abs(ahead), np.abs(behind)), 0.0)
    cap = max_slope * (2.0 * np.pi / m_count) * edges
    return np.minimum(rise, cap)


def _rise_loop(edges, mean, max_slope):
    """:func:`_rise_numpy` in one pass (compiled with numba): each edge looked up in its
    neighbours' rows with np.interp's own arithmetic (the slope of the interval, then
    slope * (x - x_j) + z_j, the other end if that is NaN, z_j where x = x_j), the same
    query and table values, so the same numbers without the reference's (M, N + 1)
    temporaries. A row's edges increase, so the interval of the next edge is found by
    walking on from the last one. The span is the reference's np.nanmax + 1 (a max is
    exact), without its Python overhead."""
    m_count, n_edges = edges.shape
    span = np.nan  # np.nanmax: NaN when every edge is NaN
    for m in range(m_count):
        for k in range(n_edges):
            x = edges[m, k]
            if not np.isnan(x) and (np.isnan(span) or x > span):
                span = x
    span = span + 1.0
    rise = np.empty((m_count, n_edges))
    neighbour = np.empty((2, n_edges))  # ground of the segment ahead and behind at each edge
    factor = max_slope * (2.0 * np.pi / m_count)
    for m in range(m_count):
        for side in range(2):
            n = m + 1 if side == 0 else m - 1
            if n == m_count:
                n = 0
            elif n < 0:
                n = m_count - 1
            offset = n * span
            j = 0  # the last table entry of row n at or before x
            for k in range(n_edges):
                x = edges[m, k]  # np.clip(edges, first, last) + offset, then np.interp
                if x < edges[n, 0]:
                    x = edges[n, 0]
                if x > edges[n, n_edges - 1]:
                    x = edges[n, n_edges - 1]
                x = x + offset
                if np.isnan(x):
                    neighbour[side, k] = x
                    continue
                if edges[n, j] + offset > x:
                    j = 0  # edges not increasing after all: search the row from its start
                while j + 1 < n_edges and edges[n, j + 1] + offset <= x:
                    j += 1
                x_j = edges[n, j] + offset
                if j == n_edges - 1 or x_j == x:
                    value = mean[n, j]
                else:
                    x_next = edges[n, j + 1] + offset
                    slope = (mean[n, j + 1] - mean[n, j]) / (x_next - x_j)
                    value = slope * (x - x_j) + mean[n, j]
                    if np.isnan(value):
                        value = slope * (x - x_next) + mean[n, j + 1]
                        if np.isnan(value) and mean[n, j] == mean[n, j + 1]:
                            value = mean[n, j]
                neighbour[side, k] = value
        for k in range(n_edges):
            step_ahead = neighbour[0, k] - mean[m, k]
            step_behind = mean[m, k] - neighbour[1, k]
            value = 0.0
            if step_ahead * step_behind > 0:
                value = abs(step_ahead)  # np.minimum: NaN if either is NaN
                if not (np.isnan(value) or value <= abs(step_behind)):
                    value = abs(step_behind)
            cap = factor * edges[m, k]
            rise[m, k] = value if np.isnan(value) or value <= cap else cap
    return rise


_rise_compiled = kernel(_rise_loop)
RISE = Twin('cross-segment rise', _rise_numpy, _rise_compiled,
            lambda _dtype: [(np.ones((2, 3)), np.ones((2, 3)), 1.0)])

STD_THRESHOLD = Stage('std threshold', 'ours', 'use_std_threshold')
CROSS_SLOPE = Stage('cross-slope threshold', 'ours', 'use_cross_slope_threshold', (RISE,))
STAGES = (Stage('labels', 'paper', None, (LABELS,)), STD_THRESHOLD, CROSS_SLOPE)
