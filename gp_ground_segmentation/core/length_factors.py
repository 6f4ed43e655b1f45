# SPDX-License-Identifier: Apache-2.0
"""Stage ``length factors``: d_i of every candidate, L_i = a d_i in the GP kernel.

[paper, ``use_nonstationary_length_scale``] d_i from the candidate's line slope and rho~ (below),
which makes Paciorek's kernel non-stationary. Off: every candidate has the one length factor
``max_length_factor``, and with it the kernel is the stationary squared exponential of length
a d_max (a learned by the marginal likelihood as before); the leave-one-group-out choice of
benchmarks/bench_quality.py (benchmarks/RESULTS.md, "Ground quality").

Eq. 12 [paper]: d_i = log(1 / g_i) / rho_i for a candidate whose line has slope g_i >= g_d, and
log(1 / g_d) below the slope floor g_d. Guards of ours where the paper is silent: g is clipped to
[g_d, g_max] with g_max < 1 (g >= 1 would give log(1/g) <= 0, a non-positive length scale), a
one-point line (NaN slope) counts as flat, d is clipped to [d_min, d_max], and
``density_in_flat_branch`` (off: the paper's formula) also divides the flat branch by rho.
:func:`length_factor` is the one definition of eq. 12; the compiled pass calls it per candidate,
the numpy reference is its vectorised form :func:`factors_from_logs` (test_length_factors
checks them equal).

rho_i [ours, ``use_density_ring_normalisation``]: the grid's rho~ (a 2-D point density, see
``grid``) divided by its geometric mean over the training candidates in the same logarithmic
range ring (r within a factor RING_RATIO). A spinning LiDAR's density falls as 1/r^2 to 1/r^3,
so raw rho~ mostly encodes range (0.3 m length scales next to the sensor, 100 m ones far away);
relative to its ring, rho~ > 1 still marks points stacked above the candidate (obstacles, what
the paper wants from it), near and far and for any beam count. Off: rho_i = rho~ itself.

Smoothing [ours, ``use_length_factor_smoothing``]: ``length_factor_smoothing_passes`` rounds of
a (1, 2, 1) / 4 running mean of log d over each segment's training candidates (neighbours in bin
order, gaps skipped; a row's first and last average (2, 1) / 3 with their one neighbour, a lone
candidate keeps its d). Paciorek's kernel carries the prefactor sqrt(2 L_i L_j / (L_i^2 +
L_j^2)), below 1 whenever neighbouring length scales differ, which pulls the posterior towards
the prior mean; rho~ and with it d jumps from bin to bin with how many rings fall in each, and
where the ground is metres above the prior mean (high mounts, long ramps) that pull reaches
decimetres and the outlier test rejects clean ramp candidates. Averaging in log space keeps a
constant d and the slow variation with slope and density.

The compiled passes (the usable bins with the slope terms, the ring deviations, eq. 12, the
smoothing) leave every log and exp to numpy, on the arrays the reference takes them of: numpy's
SIMD log and exp differ from numba's in the last bit, and with them the outputs are equal bit
for bit. Also here: d at the bin edges for the prediction (:func:`factors_at_edges`).
"""

from __future__ import annotations

import numpy as np

from .compiled import AVAILABLE, Stage, Twin, kernel

RING_RATIO = 1.15  # the ring normalisation's range rings: r within this factor


# --- eq. 12 --------------------------------------------------------------------------------

def slope_term(slope, slope_floor, slope_ceiling):
    """(1 / g, flat) of one candidate: g = |slope| clipped to [slope_floor, slope_ceiling] (a
    NaN slope is flat, +inf steep); flat when |slope| < slope_floor."""
    raw = 0.0 if np.isnan(slope) else np.abs(slope)  # no slope = flat; +inf = steep
    return 1.0 / min(max(raw, slope_floor), slope_ceiling), raw < slope_floor


def slope_terms(slope, slope_floor, slope_ceiling):
    """:func:`slope_term` of every candidate (vectorised)."""
    slope = np.asarray(slope, dtype=np.float64)
    raw = np.where(np.isnan(slope), 0.0, np.abs(slope))  # no slope = flat; +inf = steep
    # np.minimum(np.maximum()) is np.clip without its Python-level overhead (same values)
    return 1.0 / np.minimum(np.maximum(raw, slope_floor), slope_ceiling), raw < slope_floor


def length_factor(log_inverse_slope, rho, flat, flat_value, density_in_flat_branch, d_min,
                  d_max):
    """Eq. 12 for one candidate from log(1 / g): divided by rho (1 where rho is not positive),
    ``flat_value`` = log(1 / g_d) on a flat candidate unless ``density_in_flat_branch``,
    clipped to [d_min, d_max] (NaN stays NaN, as np.maximum / np.minimum keep it)."""
    value = log_inverse_slope / (rho if rho > 0 else 1.0)
    if flat and not density_in_flat_branch:
        value = flat_value
    if value < d_min:
        value = d_min
    if value > d_max:
        value = d_max
    return value


def factors_from_logs(log_inverse_slope, density_rel, flat, *, flat_value,
                      density_in_flat_branch, d_min, d_max):
    """:func:`length_factor` of every candidate (vectorised)."""
    d = log_inverse_slope / np.where(density_rel > 0, density_rel, 1.0)
    if not density_in_flat_branch:
        d = np.where(flat, flat_value, d)
    return np.minimum(np.maximum(d, d_min), d_max)


def length_scale_factors(slope, density_rel, *, slope_floor, slope_ceiling,
                         density_in_flat_branch=True, d_min=0.05, d_max=50.0):
    """Eq. 12 of every candidate from its line's slope and its rho (vectorised)."""
    inverse_slope, flat = slope_terms(slope, slope_floor, slope_ceiling)
    return factors_from_logs(np.log(inverse_slope), density_rel, flat,
                             flat_value=float(np.log(1.0 / slope_floor)),
                             density_in_flat_branch=density_in_flat_branch, d_min=d_min,
                             d_max=d_max)


# --- the frame's length factors: the stage ----------------------------------------------------

def frame_length_factors(slope, density, candidate_r, training, params, compiled: bool = True):
    """d_i of every candidate (M, N) from its line's ``slope``, the grid's rho~ ``density``
    and ranges, with the training candidates' ``training`` mask and the SegmenterParams
    ``params`` (module docstring)."""
    p = params
    if not NONSTATIONARY.on(p):  # one length factor for every candidate: NaN where none
        return np.where(np.isnan(candidate_r), np.nan, float(p.max_length_factor))
    training = np.ascontiguousarray(training, dtype=bool)
    usable, r_usable, rho_usable, inverse_slope, flat = USABLE.run(
        compiled, density, candidate_r, training, slope, float(p.slope_floor),
        float(p.slope_ceiling))
    rho = rho_usable
    if NORMALISATION.on(p):
        rho = np.exp(RING.run(compiled, np.log(r_usable), np.log(rho_usable),
                              float(np.log(RING_RATIO))))
    d, smoothing_input = EQ12.run(
        compiled, np.log(inverse_slope), rho, usable, flat, training,
        bool(p.density_in_flat_branch), float(np.log(1.0 / p.slope_floor)),
        float(p.min_length_factor), float(p.max_length_factor))
    if not SMOOTHING.on(p):
        return d
    return _smoothed(d, smoothing_input, training, p.length_factor_smoothing_passes, compiled)


def _smoothed(d, smoothing_input, training, passes, compiled):
    """``d`` with the smoothing's passes over log(``smoothing_input``) (d where training,
    else 1) on the training candidates."""
    log_d = SMOOTH.run(compiled, np.log(smoothing_input), training, int(passes))
    return np.where(training, np.exp(log_d), d)


def smooth_length_factors(d: np.ndarray, training: np.ndarray, passes: int,
                          compiled: bool = True) -> np.ndarray:
    """(M, N) ``d`` after ``passes`` rounds of the smoothing (module docstring) over each
    segment's ``training`` candidates; other entries unchanged."""
    if passes <= 0:  # the paper's d
        return d
    training = np.ascontiguousarray(training, dtype=bool)
    return _smoothed(d, np.where(training, d, 1.0), training, passes, compiled)


def relative_density(density: np.ndarray, candidate_r: np.ndarray, mask: np.ndarray,
                     ring_ratio: float = RING_RATIO) -> np.ndarray:
    """rho~ over its geometric mean among the ``mask`` candidates of its log-range ring (r
    within a factor ``ring_ratio``); 1 outside ``mask``, for rho~ <= 0 and r not finite or
    <= 0 (the ring normalisation of the module docstring, numpy)."""
    out = np.ones_like(density, dtype=np.float64)
    usable = usable_bins(density, candidate_r, mask)
    if not usable.any():
        return out
    out[usable] = np.exp(ring_log_deviation(np.log(candidate_r[usable]),
                                            np.log(density[usable]), np.log(ring_ratio)))
    return out


def usable_bins(density, candidate_r, mask) -> np.ndarray:
    """The bins the ring normalisation compares: in ``mask``, with rho~ > 0 and a finite
    range > 0."""
    return mask & (density > 0) & np.isfinite(candidate_r) & (candidate_r > 0)


def ring_log_deviation(log_r: np.ndarray, log_rho: np.ndarray, log_ratio: float) -> np.ndarray:
    """log rho~ minus its mean over the log-range ring of width ``log_ratio`` it falls in
    (:func:`relative_density`'s arithmetic on its usable bins; the numpy twin of
    :func:`_ring_deviation_loop`)."""
    if log_r.size == 0:
        return np.empty(0)
    ring = np.floor(log_r / log_ratio).astype(np.intp)
    ring -= ring.min()
    sums = np.bincount(ring, weights=log_rho)
    counts = np.bincount(ring)
    return log_rho - sums[ring] / counts[ring]


def _ring_deviation_loop(log_r, log_rho, log_ratio):
    """``grid.ring_log_deviation`` (compiled with numba): log rho~ minus the mean of its range
    ring, the ring sums accumulated in the order np.bincount sums them."""
    count = log_r.size
    deviation = np.empty(count)
    if count == 0:
        return deviation
    ring = np.empty(count, dtype=np.intp)
    ring_min = 0
    for i in range(count):
        ring[i] = np.intp(np.floor(log_r[i] / log_ratio))
        if i == 0 or ring[i] < ring_min:
            ring_min = ring[i]
    ring_max = 0
    for i in range(count):
        ring[i] -= ring_min
        ring_max = max(ring_max, ring[i])
    sums = np.zeros(ring_max + 1)
    counts = np.zeros(ring_max + 1, dtype=np.intp)
    for i in range(count):
        sums[ring[i]] += log_rho[i]
        counts[ring[i]] += 1
    for i in range(count):
        deviation[i] = log_rho[i] - sums[ring[i]] / np.float64(counts[ring[i]])
    return deviation


def _usable_bins_loop(density, candidate_r, training, slope, slope_floor, slope_ceiling):
    """The bins ``relative_density`` uses and, of every bin, the slope part of
    ``length_scale_factors`` (compiled with numba): (usable (M, N), their r and rho~ in row
    order (as a boolean index gathers them), 1 / g, whether the slope is below the floor)."""
    m_count, n_count = density.shape
    usable = np.empty((m_count, n_count), dtype=np.bool_)
    r_usable = np.empty(m_count * n_count)
    rho_usable = np.empty(m_count * n_count)
    inverse_slope = np.empty((m_count, n_count))
    flat = np.empty((m_count, n_count), dtype=np.bool_)
    count = 0
    for m in range(m_count):
        for k in range(n_count):
            r = candidate_r[m, k]
            ok = training[m, k] and density[m, k] > 0 and np.isfinite(r) and r > 0
            usable[m, k] = ok
            if ok:
                r_usable[count] = r
                rho_usable[count] = density[m, k]
                count += 1
            inverse_slope[m, k], flat[m, k] = _slope_term(slope[m, k], slope_floor,
                                                          slope_ceiling)
    return usable, r_usable[:count], rho_usable[:count], inverse_slope, flat


def _usable_bins_numpy(density, candidate_r, training, slope, slope_floor, slope_ceiling):
    """The numpy reference of :func:`_usable_bins_loop`."""
    usable = usable_bins(density, candidate_r, training)
    inverse_slope, flat = slope_terms(slope, slope_floor, slope_ceiling)
    return usable, candidate_r[usable], density[usable], inverse_slope, flat


def _eq12_loop(log_inverse_slope, rho_usable, usable, flat, training, density_in_flat_branch,
               log_flat, d_min, d_max):
    """Eq. 12 of every bin (compiled with numba; :func:`length_factor` per bin), given
    log(1 / g) of every bin and rho of the ``usable`` ones in row order (1 elsewhere): (d, and
    d where ``training`` else 1, whose log the smoothing takes)."""
    m_count, n_count = flat.shape
    d = np.empty((m_count, n_count))
    smoothing_input = np.empty((m_count, n_count))
    i = 0
    for m in range(m_count):
        for k in range(n_count):
            rho = 1.0
            if usable[m, k]:
                rho = rho_usable[i]
                i += 1
            value = _length_factor(log_inverse_slope[m, k], rho, flat[m, k], log_flat,
                                   density_in_flat_branch, d_min, d_max)
            d[m, k] = value
            smoothing_input[m, k] = value if training[m, k] else 1.0
    return d, smoothing_input


def _eq12_numpy(log_inverse_slope, rho_usable, usable, flat, training, density_in_flat_branch,
                log_flat, d_min, d_max):
    """The numpy reference of :func:`_eq12_loop`."""
    rho = np.ones(flat.shape)
    rho[usable] = rho_usable
    d = factors_from_logs(log_inverse_slope, rho, flat, flat_value=log_flat,
                          density_in_flat_branch=density_in_flat_branch, d_min=d_min,
                          d_max=d_max)
    return d, np.where(training, d, 1.0)


def _smooth_numpy(log_d, training, passes):
    """The numpy reference of :func:`smooth_length_factors`' passes over log d."""
    m_count, n_count = log_d.shape
    columns = np.arange(n_count)
    # the previous and the next training candidate of every bin in its row (-1 / N: none)
    before = np.maximum.accumulate(np.where(training, columns, -1), axis=1)
    before = np.concatenate([np.full((m_count, 1), -1), before[:, :-1]], axis=1)
    after = np.minimum.accumulate(np.where(training, columns, n_count)[:, ::-1], axis=1)[:, ::-1]
    after = np.concatenate([after[:, 1:], np.full((m_count, 1), n_count)], axis=1)
    has_before, has_after = before >= 0, after < n_count
    rows = np.arange(m_count)[:, None]
    before, after = np.maximum(before, 0), np.minimum(after, n_count - 1)
    for _ in range(passes):
        prev, nxt = log_d[rows, before], log_d[rows, after]
        smoothed = np.where(has_before & has_after, 0.25 * prev + 0.5 * log_d + 0.25 * nxt,
                            np.where(has_before, (2.0 * log_d + prev) / 3.0,
                                     np.where(has_after, (2.0 * log_d + nxt) / 3.0, log_d)))
        log_d = np.where(training, smoothed, log_d)
    return log_d


def _smooth_loop(log_d, training, passes):
    """:func:`_smooth_numpy` row by row (compiled with numba): the same arithmetic in the same
    order on each row's training candidates, gathered into a short buffer."""
    m_count, n_count = log_d.shape
    out = log_d.copy()
    index = np.empty(n_count, dtype=np.int64)
    values = np.empty(n_count)
    smoothed = np.empty(n_count)
    for m in range(m_count):
        k = 0
        for j in range(n_count):
            if training[m, j]:
                index[k] = j
                values[k] = log_d[m, j]
                k += 1
        if k < 2:  # a lone candidate keeps its d
            continue
        for _ in range(passes):
            smoothed[0] = (2.0 * values[0] + values[1]) / 3.0
            for i in range(1, k - 1):
                smoothed[i] = 0.25 * values[i - 1] + 0.5 * values[i] + 0.25 * values[i + 1]
            smoothed[k - 1] = (2.0 * values[k - 1] + values[k - 2]) / 3.0
            for i in range(k):
                values[i] = smoothed[i]
        for i in range(k):
            out[m, index[i]] = values[i]
    return out


_usable_bins_compiled = _eq12_compiled = None
if AVAILABLE:  # these passes call the compiled slope term and eq. 12, inlined per bin
    _slope_term = kernel(slope_term, inline='always')
    _length_factor = kernel(length_factor, inline='always')
    _usable_bins_compiled = kernel(_usable_bins_loop)
    _eq12_compiled = kernel(_eq12_loop)


def _grids(*dtypes):
    return tuple(np.ones((2, 2), dtype) for dtype in dtypes)


USABLE = Twin('usable bins and slope terms', _usable_bins_numpy, _usable_bins_compiled,
              lambda _dtype: [(*_grids(float, float, bool, float), 0.1, 0.9)])
RING = Twin('ring deviations', ring_log_deviation, kernel(_ring_deviation_loop),
            lambda _dtype: [(np.ones(2), np.ones(2), 0.1)])
EQ12 = Twin('eq. 12', _eq12_numpy, _eq12_compiled,
            lambda _dtype: [(np.ones((2, 2)), np.ones(4), *_grids(bool, bool, bool), False,
                             1.0, 0.05, 2.0)])
SMOOTH = Twin('length-factor smoothing', _smooth_numpy, kernel(_smooth_loop),
              lambda _dtype: [(*_grids(float, bool), 1)])


# --- d at the bin edges (the prediction's) ----------------------------------------------------

def factors_at_edges(d: np.ndarray, training: np.ndarray, rows: np.ndarray,
                     compiled: bool = True) -> np.ndarray:
    """(len(rows), N + 1) d at the bin edges of the GP's ``rows``: each edge takes the d of
    the nearest training candidate at or before it in its row (else after it), the last
    column repeated for the outer edge."""
    return EDGES.run(compiled, d, training, rows)


def _fill_along_rows(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill unknown entries of each row with the nearest known entry to their left (else right)."""
    n = values.shape[1]
    idx = np.where(known, np.arange(n), -1)
    left = np.maximum.accumulate(idx, axis=1)
    idx_r = np.where(known, np.arange(n), n)
    right = np.minimum.accumulate(idx_r[:, ::-1], axis=1)[:, ::-1]
    pick = np.where(left >= 0, left, right)
    pick = np.clip(pick, 0, n - 1)
    return np.take_along_axis(values, pick, axis=1)


def _fill_rows_to_edges(values: np.ndarray, known: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows), N + 1): ``_fill_along_rows(values, known)`` of ``rows``, its last column
    repeated for the outer edge; the numpy reference of :func:`_fill_rows_to_edges_loop`."""
    filled = _fill_along_rows(values, known)
    return np.concatenate([filled, filled[:, -1:]], axis=1)[rows]


def _fill_rows_to_edges_loop(values, known, rows):
    """:func:`_fill_rows_to_edges` in one pass (compiled with numba): only the rows asked for,
    without the reference's two accumulations, three where and the gather (the same values).
    """
    n = values.shape[1]
    out = np.empty((rows.size, n + 1), dtype=values.dtype)
    for s in range(rows.size):
        m = rows[s]
        pick = n - 1  # a row without a known entry takes its last one
        for j in range(n):
            if known[m, j]:
                pick = j  # the first known entry fills the entries before it
                break
        for j in range(n):
            if known[m, j]:
                pick = j
            out[s, j] = values[m, pick]
        out[s, n] = out[s, n - 1]
    return out


EDGES = Twin('length factors at the bin edges', _fill_rows_to_edges,
             kernel(_fill_rows_to_edges_loop),
             lambda _dtype: [(*_grids(float, bool), np.zeros(1, np.intp))])

NORMALISATION = Stage('ring normalisation', 'ours', 'use_density_ring_normalisation', (RING,))
SMOOTHING = Stage('length-factor smoothing', 'ours', 'use_length_factor_smoothing', (SMOOTH,))
NONSTATIONARY = Stage('length factors', 'paper', 'use_nonstationary_length_scale',
                      (USABLE, EQ12))
STAGES = (NONSTATIONARY, NORMALISATION, SMOOTHING)
