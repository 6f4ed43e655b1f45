# SPDX-License-Identifier: Apache-2.0
"""Whole-frame Gaussian process over the ground candidates of all segments (paper sections III-IV).

Paper: kernel (eq. 7, Paciorek & Schervish non-stationary squared exponential in 1-D):

    k(r_i, r_j) = sigma_f^2 (L_i^2)^(1/4) (L_j^2)^(1/4) ((L_i^2 + L_j^2) / 2)^(-1/2)
                  * exp(-(r_i - r_j)^2 / (L_i^2 + L_j^2)),        L_i = a d_i

length-scale factor (eqs. 8 and 12): d_i = log(1/g_i) / rho_i, with g the slope of the
candidate's line-segment and rho the density-like value, and d_i = log(1/g_d) below the slope
floor g_d; prediction (eqs. 5 and 13); hyperparameters theta = (sigma_f, a, sigma_n) shared by
all segments and learned by maximising the whole-frame objective
J(theta) = sum_m log p(z_m | r_m, theta) (eq. 14).

Ours, where the paper is silent:

* g is clipped to [g_d, g_max] with g_max < 1: g >= 1 (steeper than 45 deg) would give
  log(1/g) <= 0, a non-positive length scale; one-point lines (no slope) count as flat (g_d).
* rho is the bin's rho~ relative to the typical rho~ at the same range
  (``grid.relative_density``), so that ``a`` means the same near and far and for a 16-beam and a
  128-beam sensor; rho~ > 0 for every bin that holds a candidate, so d is finite.
* ``density_in_flat_branch=True`` also divides the flat branch by rho (continuous in g at g_d);
  the default (False) is the paper's eq. 12.
* d is clipped to [d_min, d_max] so that no candidate gets a vanishing or unbounded length scale;
  with d fixed per frame, L = a d exactly and the prefactor of k is independent of ``a``.
* The prior mean is a constant m0 (the paper's eq. 6 uses a zero mean), so sigma_f describes
  deviations of the ground from a level plane at m0: the segmenter passes the anchor height
  (``prior_mean_at_anchor``, default), clipped to the candidates' range; without one,
  FrameGP takes the median height of the training points.
* Each training point may carry its own extra noise variance on top of sigma_n^2 (the anchor
  at r = 0, rejected outliers: see ``additions``).
* theta is learned with L-BFGS-B on log theta within bounds, using the analytic gradient

      dJ/dtheta = 1/2 sum_m tr((alpha alpha^T - A_m^-1) dA_m/dtheta),   A_m = K_m + diag(noise),

  under a cap on objective evaluations.

All segments are solved together as one padded (S, n, n) batch. Backend 'numba' runs the whole
step compiled, each segment at its own size (gp_compiled.py: kernel, Cholesky, inverse, J, its
gradient, prediction); backend 'numpy' is the reference: numpy's stacked Cholesky and inverse
over the padded batch, where padded rows are identity rows with z = 0, which add nothing to J
or its gradient. numpy is also the fallback (non-PD matrices: jittered retries; a numba
failure: numpy for the rest of that object's life).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import minimize

from . import gp_compiled
from .compiled import kernel, run

LOG_2PI = float(np.log(2.0 * np.pi))


# Failures of one marginal-likelihood evaluation that mean "theta is numerically bad here", not a
# bug: LinAlgError is a ValueError; ArithmeticError covers Overflow/ZeroDivision/FloatingPoint.
_NUMERICAL_ERRORS = (ValueError, ArithmeticError)


BACKENDS = ('auto', 'numba', 'numpy')


def resolve_backend(backend: str) -> str:
    """'auto' -> 'numba' when numba imports, else 'numpy'; raise ValueError on other names."""
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == 'auto':
        return 'numba' if gp_compiled.AVAILABLE else 'numpy'
    if backend == 'numba' and not gp_compiled.AVAILABLE:
        raise ValueError("backend 'numba' requested but numba is not installed")
    return backend


# solutions each FrameGP keeps (the start and the last point of a theta search: whichever
# wins is solved again, and the robust pass re-solves at it)
_CACHED_SOLUTIONS = 2


class _BudgetExhausted(Exception):
    """Raised inside the objective to stop L-BFGS-B exactly at the evaluation cap."""


def length_scale_factors(slope, density_rel, *, slope_floor, slope_ceiling,
                         density_in_flat_branch=True, d_min=0.05, d_max=50.0):
    """d_i = log(1/g_i) / rho_i with the guards listed in the module docstring."""
    inverse_slope, flat = slope_terms(slope, slope_floor, slope_ceiling)
    return factors_from_logs(np.log(inverse_slope), density_rel, flat,
                             flat_value=float(np.log(1.0 / slope_floor)),
                             density_in_flat_branch=density_in_flat_branch, d_min=d_min,
                             d_max=d_max)


def slope_terms(slope, slope_floor, slope_ceiling):
    """(1 / g, flat) of :func:`length_scale_factors`: g = |slope| clipped to [slope_floor,
    slope_ceiling] (a NaN slope is flat, +inf steep); flat where |slope| < slope_floor."""
    slope = np.asarray(slope, dtype=np.float64)
    raw = np.where(np.isnan(slope), 0.0, np.abs(slope))  # no slope = flat; +inf = steep
    # np.minimum(np.maximum()) is np.clip without its Python-level overhead (same values)
    return 1.0 / np.minimum(np.maximum(raw, slope_floor), slope_ceiling), raw < slope_floor


def factors_from_logs(log_inverse_slope, density_rel, flat, *, flat_value,
                      density_in_flat_branch, d_min, d_max):
    """The rest of :func:`length_scale_factors` from log(1 / g): divided by rho~ (1 where it
    is not positive), ``flat_value`` = log(1 / slope_floor) on flat bins unless
    ``density_in_flat_branch``, clipped to [d_min, d_max] (NaN stays NaN)."""
    d = log_inverse_slope / np.where(density_rel > 0, density_rel, 1.0)
    if not density_in_flat_branch:
        d = np.where(flat, flat_value, d)
    return np.minimum(np.maximum(d, d_min), d_max)


def paciorek_kernel(r1, l1, r2, l2, sigma_f):
    """k(r1_i, r2_j) for broadcastable arrays: r1, l1 (..., n, 1) against r2, l2 (..., 1, m)."""
    s = l1 * l1 + l2 * l2
    prefactor = np.sqrt(2.0 * l1 * l2 / s)
    diff = r1 - r2
    return sigma_f * sigma_f * prefactor * np.exp(-diff * diff / s)


def _posterior_std(k_star, a_inv, sigma_f) -> np.ndarray:
    """numpy's posterior std sqrt(sigma_f^2 - k*^T A^-1 k*) (S, k) from k* (S, k, n)
    [segment, prediction point, training point] and A^-1 (S, n, n)."""
    reduce = np.einsum('skn,snm,skm->sk', k_star, a_inv, k_star, optimize=True)
    return np.sqrt(np.maximum(sigma_f * sigma_f - reduce, 0.0))  # clamp round-off


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


@dataclass
class GPSolution:
    """Factorisation of A = K + sigma_n^2 I for every segment at one theta."""

    theta: np.ndarray  # (3,) sigma_f, a, sigma_n
    alpha: np.ndarray  # (S, n) A^-1 (z - m0)
    a_inv: np.ndarray  # (S, n, n)
    lml: float  # J(theta)
    jitter: float  # diagonal jitter that had to be added (m^2), 0 if none
    kernel: Optional[np.ndarray]  # (S, n, n) K at theta (padded slots 0); None when compiled
    gradient: Optional[np.ndarray] = None  # (3,) dJ/dlog(theta) when the solver gave it
    logdets: Optional[np.ndarray] = None  # (S,) log|A| of each segment when compiled
    pair_terms: tuple = ()  # compiled: (K, q) (S, n, n), see gp_compiled.solve_batched


@dataclass(frozen=True)
class GroundAnchor:
    """One extra training point at r = 0 in chosen segments: the ground under the vehicle."""

    height_m: float  # z of the point (m)
    noise_var: float  # its noise variance on top of sigma_n^2 (m^2)
    segments: np.ndarray  # (M,) bool: segments that get it
    length_factor: np.ndarray  # (M,) d of the point in each segment


def _pad_numpy(r, z, d, mask, noise_var, has_anchor, anchor_segments, anchor_d,
               anchor_height, anchor_var, mean):
    """The numpy reference of FrameGP's padding: (M, N) candidate arrays -> the (S, n) batch.

    Rows of ``mask`` with a training point (or the anchor) enter the batch; in each, the anchor
    (when ``has_anchor`` and its segment has it) comes first, then the training candidates in
    bin order, then padding slots (r 0, z 0, d 1, noise 0). Returns (segments (S,), valid,
    bins (-1: the anchor), r, z - mean, d, noise_var (S, n), counts (S,)).
    """
    if has_anchor:  # the anchor becomes column 0 of the padded input
        m_count = mask.shape[0]
        r = np.concatenate([np.zeros((m_count, 1)), r], axis=1)
        z = np.concatenate([np.full((m_count, 1), anchor_height), z], axis=1)
        d = np.concatenate([anchor_d[:, None], d], axis=1)
        mask = np.concatenate([anchor_segments[:, None], mask], axis=1)
        noise_var = np.concatenate([np.full((m_count, 1), anchor_var), noise_var], axis=1)
    counts = mask.sum(axis=1)
    segments = np.flatnonzero(counts > 0)
    n_max = int(counts.max()) if counts.size else 0
    sub = mask[segments]
    # stable order: training points of each segment first (the anchor first of all)
    order = np.argsort(~sub, axis=1, kind='stable')[:, :n_max]
    # (S, n) flat index into the padded (M, N[+1]) input of every slot: one gather per
    # array instead of a row subset and take_along_axis (same values)
    flat = segments[:, None] * mask.shape[1] + order
    valid = mask.reshape(-1)[flat]
    bins = order - 1 if has_anchor else order
    return (segments, valid, bins, np.where(valid, r.reshape(-1)[flat], 0.0),
            np.where(valid, z.reshape(-1)[flat] - mean, 0.0),
            np.where(valid, d.reshape(-1)[flat], 1.0),
            np.where(valid, noise_var.reshape(-1)[flat], 0.0), valid.sum(axis=1))


def _pad_loop(r, z, d, mask, noise_var, has_anchor, anchor_segments, anchor_d, anchor_height,
              anchor_var, mean):
    """:func:`_pad_numpy` as one pass over the rows (compiled with numba): the same arrays,
    without the concatenations, the sort and the ten gathers of the reference."""
    m_count, n_count = mask.shape
    row_counts = np.zeros(m_count, dtype=np.intp)
    for m in range(m_count):
        c = 1 if has_anchor and anchor_segments[m] else 0
        for j in range(n_count):
            if mask[m, j]:
                c += 1
        row_counts[m] = c
    s_count = 0
    n_max = 0
    for m in range(m_count):
        if row_counts[m] > 0:
            s_count += 1
            n_max = max(n_max, row_counts[m])
    segments = np.empty(s_count, dtype=np.intp)
    valid = np.zeros((s_count, n_max), dtype=np.bool_)
    bins = np.empty((s_count, n_max), dtype=np.intp)
    r_out = np.zeros((s_count, n_max))
    z_out = np.zeros((s_count, n_max))
    d_out = np.ones((s_count, n_max))
    noise_out = np.zeros((s_count, n_max))
    counts = np.empty(s_count, dtype=np.intp)
    s = 0
    for m in range(m_count):
        if row_counts[m] == 0:
            continue
        segments[s] = m
        counts[s] = row_counts[m]
        k = 0
        if has_anchor and anchor_segments[m]:
            valid[s, 0] = True
            bins[s, 0] = -1
            z_out[s, 0] = anchor_height - mean
            d_out[s, 0] = anchor_d[m]
            noise_out[s, 0] = anchor_var
            k = 1
        for j in range(n_count):
            if mask[m, j]:
                valid[s, k] = True
                bins[s, k] = j
                r_out[s, k] = r[m, j]
                z_out[s, k] = z[m, j] - mean
                d_out[s, k] = d[m, j]
                noise_out[s, k] = noise_var[m, j]
                k += 1
        if has_anchor and not anchor_segments[m] and k < n_max:
            bins[s, k] = -1  # padding slots: the columns left, in order, as the stable sort
            k += 1
        for j in range(n_count):
            if k >= n_max:
                break
            if not mask[m, j]:
                bins[s, k] = j
                k += 1
        s += 1
    return segments, valid, bins, r_out, z_out, d_out, noise_out, counts


_pad_compiled = kernel(_pad_loop)


def _slot_noise_loop(noise_var, old_noise_var, valid, is_anchor, segments, bins, anchor_var):
    """(S, n) noise variance of the batch's slots from the (M, N) ``noise_var`` of the grid
    candidates (the anchor's slots ``anchor_var``, padding 0), and (S,) whether a segment's
    differ from ``old_noise_var`` (compiled with numba; ``FrameGP.with_noise``): the same
    values as its numpy reference, in one pass."""
    s_count, n_slots = valid.shape
    slot_noise = np.empty((s_count, n_slots))
    changed = np.zeros(s_count, dtype=np.bool_)
    for s in range(s_count):
        m = segments[s]
        for i in range(n_slots):
            if is_anchor[s, i]:
                value = anchor_var
            elif valid[s, i]:
                value = noise_var[m, bins[s, i]]
            else:
                value = 0.0
            slot_noise[s, i] = value
            if value != old_noise_var[s, i]:
                changed[s] = True
    return slot_noise, changed


_slot_noise_compiled = kernel(_slot_noise_loop)


class FrameGP:
    """Training data of one frame, padded to (S, n) over the segments that have training points.

    Immutable after construction: a different noise assignment is a new object
    (:meth:`with_noise`), so a solution cached for one theta can never belong to other data.
    """

    def __init__(self, r, z, d, mask, noise_var=None, anchor: GroundAnchor | None = None,
                 mean=None, backend='auto'):
        """r, z, d, mask, noise_var: (M, N) candidate arrays; mask marks training candidates.

        ``noise_var`` (m^2, default 0) is added to sigma_n^2 on each candidate's diagonal.
        ``anchor`` adds its point before the first candidate of every segment it names.
        The prior mean is ``mean``, by default the median height of all training points (the
        anchor counted once per segment that has it), so sigma_f describes deviations of the
        ground from a level plane at that height.
        ``backend``: 'numba' (compiled factorisation), 'numpy', or 'auto' (numba if it imports).
        """
        mask = np.asarray(mask, dtype=bool)
        self.anchor = anchor
        self.shape = mask.shape  # (M, N) of the grid
        self.backend = resolve_backend(backend)
        m_count = mask.shape[0]
        has_anchor = anchor is not None
        anchor_segments = (np.asarray(anchor.segments, dtype=bool) if has_anchor
                           else np.zeros(m_count, dtype=bool))
        if mean is None:  # the median over all training points, the anchor once per segment
            seen = np.asarray(z)[mask]  # in z's precision, as the heights it is the median of
            if has_anchor:
                anchors = np.full(np.count_nonzero(anchor_segments), float(anchor.height_m))
                seen = np.concatenate([anchors, seen])
            mean = float(np.median(seen)) if seen.size else 0.0
        self.mean = float(mean)
        as_float = (lambda a: np.ascontiguousarray(a, dtype=np.float64))
        args = (as_float(r), as_float(z), as_float(d), np.ascontiguousarray(mask),
                as_float(np.zeros(mask.shape) if noise_var is None else noise_var),
                has_anchor, anchor_segments,
                as_float(anchor.length_factor if has_anchor else np.ones(m_count)),
                float(anchor.height_m) if has_anchor else 0.0,
                float(anchor.noise_var) if has_anchor else 0.0, self.mean)
        # segments: rows of (M, N) that enter the batch; per (S, n) slot: valid, grid bin (-1
        # for the anchor), r, z - mean, d, noise_var; counts: training points of each row
        (self.segments, self.valid, self.bins, self.r, self.z, self.d, self.noise_var,
         self.counts) = run(self.backend == 'numba', _pad_compiled, _pad_numpy, *args)
        self.n_max = self.valid.shape[1]
        self.is_anchor = self.valid & (self.bins < 0)
        self.num_points = int(self.counts.sum())
        self._geometry = None  # (q, prefactor) (S, n, n) of the numpy path, made on first use
        self._grid_slot_index = None  # to_grid's index, made on first use (shared by copies)
        self.compiled_error = None  # why the numba kernel failed, if it did (then numpy)
        self.cholesky_fallbacks = 0  # jittered retries of this object and those it came from
        self.factorisations = 0  # uncached solves of this object (the unit of fitting cost)
        self._cache = []  # [(theta bytes, GPSolution)]: the last _CACHED_SOLUTIONS solves
        self._known = None  # ([(theta bytes, compiled solution)], changed (S,)): with_noise

    def _pair_geometry(self):
        """(q, prefactor) (S, n, n) of the numpy path, 0 on padded pairs; computed once.

        q = (r_i - r_j)^2 / (d_i^2 + d_j^2), prefactor = sqrt(2 d_i d_j / (d_i^2 + d_j^2)).
        """
        if self._geometry is None:
            pair = self.valid[:, :, None] & self.valid[:, None, :]
            di, dj = self.d[:, :, None], self.d[:, None, :]
            sd = di * di + dj * dj
            diff = self.r[:, :, None] - self.r[:, None, :]
            self._geometry = (np.where(pair, diff * diff / sd, 0.0),
                              np.where(pair, np.sqrt(2.0 * di * dj / sd), 0.0))
        return self._geometry

    def with_noise(self, noise_var) -> 'FrameGP':
        """The same data with another per-candidate noise variance (M, N) (m^2).

        Shares the geometry (kernel distances, prefactors) with this object; the anchor keeps
        its own noise. Cheap: no re-padding, no new distance matrices.
        """
        if self.backend == 'numpy':
            self._pair_geometry()  # made once here, shared by the copy
        other = copy.copy(self)
        anchor_var = float(self.anchor.noise_var) if self.anchor is not None else 0.0
        # the grid candidates' slots get ``noise_var``, the anchor's its own, padding 0; and
        # the segments whose noise changed
        other.noise_var, changed = run(
            self.backend == 'numba', _slot_noise_compiled, self._slot_noise,
            np.ascontiguousarray(noise_var, dtype=np.float64).reshape(self.shape),
            self.noise_var, self.valid, self.is_anchor, self.segments, self.bins, anchor_var)
        other._cache = []  # cholesky_fallbacks carries on: it counts the whole chain
        other.factorisations = 0
        # this object's cached solutions stay valid for the copy's segments whose noise is
        # unchanged: a solve at their theta recomputes only the others (bit for bit the same)
        compiled_solutions = [(key, sol) for key, sol in self._cache if sol.logdets is not None]
        other._known = (compiled_solutions, changed) if compiled_solutions else None
        return other

    def _slot_noise(self, noise_var, old_noise_var, valid, is_anchor, segments, bins,
                    anchor_var):
        """The numpy reference of :func:`_slot_noise_loop` (``with_noise``'s slots)."""
        keep, grid_index = self._grid_slots()
        slot_noise = np.where(is_anchor, anchor_var, 0.0)
        slot_noise[keep] = noise_var.reshape(-1)[grid_index]
        return slot_noise, np.any(slot_noise != old_noise_var, axis=1)

    def to_grid(self, slot_values, fill) -> np.ndarray:
        """(S, n) values of the training slots -> (M, N) over the grid's bins (anchor dropped)."""
        slot_values = np.asarray(slot_values)
        out = np.full(self.shape, fill, dtype=slot_values.dtype)
        keep, grid_index = self._grid_slots()
        out.reshape(-1)[grid_index] = slot_values[keep]
        return out

    def _grid_slots(self):
        """(keep (S, n) bool: slots of grid candidates, their flat (M * N) grid indices)."""
        if self._grid_slot_index is None:
            keep = self.valid & ~self.is_anchor
            self._grid_slot_index = (keep, (self.segments[:, None] * self.shape[1]
                                            + self.bins)[keep])
        return self._grid_slot_index

    # -- core linear algebra ---------------------------------------------------------------
    def kernel(self, theta):
        """K (S, n, n) at theta, zero on padded slots (numpy reference)."""
        sigma_f, gain, _ = theta
        q, prefactor = self._pair_geometry()
        k = np.multiply(q, -1.0 / (gain * gain))  # in place from here: one temporary
        np.exp(k, out=k)
        k *= prefactor
        k *= sigma_f * sigma_f
        return k

    def solve(self, theta) -> GPSolution:
        """Factorise A at theta, adding growing diagonal jitter if Cholesky fails.

        The diagonal of A is sigma_n^2 plus each point's ``noise_var``; the data are fixed at
        construction, so the cached solution is keyed on theta alone.
        """
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        for cached_key, cached in self._cache:
            if cached_key == key:  # L-BFGS-B re-evaluates its start and end points
                return cached
        self.factorisations += 1
        sol = self._solve_compiled(theta, key) if self.backend == 'numba' else None
        if sol is None:
            sol = self._solve_numpy(theta)
        self._cache = self._cache[1 - _CACHED_SOLUTIONS:] + [(key, sol)]
        return sol

    def _lml(self, logdet, alpha):
        return -0.5 * (float(np.einsum('si,si->', self.z, alpha)) + logdet
                       + self.num_points * LOG_2PI)

    def _solve_compiled(self, theta, key: bytes) -> Optional[GPSolution]:
        """The whole step in numba (``key``: theta's bytes, as :meth:`solve` caches it); None
        when a matrix is not PD or numba fails (then numpy)."""
        args = (self.r, self.d, self.z, self.noise_var, self.counts,
                *(float(t) for t in theta))
        known_solutions, changed = self._known if self._known is not None else ([], None)
        known = next((sol for known_key, sol in known_solutions if known_key == key), None)
        try:
            if known is not None:
                ok, logdets, alpha, a_inv, gradient, *pair_terms = gp_compiled.resolve_batched(
                    *args, changed, known.logdets, known.alpha, known.a_inv, *known.pair_terms)
            else:
                ok, logdets, alpha, a_inv, gradient, *pair_terms = gp_compiled.solve_batched(
                    *args)
        except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
            self.backend, self.compiled_error = 'numpy', str(exc)  # numpy from now on
            return None
        if not ok.all():
            return None
        logdet = float(logdets.sum())
        return GPSolution(theta, alpha, a_inv, self._lml(logdet, alpha), 0.0, None, gradient,
                          logdets, tuple(pair_terms))

    def _solve_numpy(self, theta) -> GPSolution:
        """The numpy reference (and fallback): stacked factorisation of the padded batch."""
        k = self.kernel(theta)
        # A = K + noise on the diagonal; padded slots get 1 there (identity rows, K is 0 there)
        diagonal = np.where(self.valid, theta[2] ** 2 + self.noise_var, 1.0)
        a = k.copy()
        a_diag = a.reshape(a.shape[0], -1)[:, ::a.shape[-1] + 1]  # a view of every diagonal
        a_diag += diagonal
        a_inv, logdet, alpha, jitter = self._numpy_factorise(a, a_diag, theta)
        return GPSolution(theta, alpha, a_inv, self._lml(logdet, alpha), jitter, k)

    def _numpy_factorise(self, a, a_diag, theta):
        """Stacked numpy Cholesky (for PD check and log|A|) and inverse, with jitter retries.

        ``a_diag`` is a writable view of the diagonals of ``a``; jitter grows x100 per retry
        and every retry is counted in ``cholesky_fallbacks``.
        Returns (A^-1, log|A| summed over segments, alpha = A^-1 z, jitter added).
        """
        jitter = 0.0
        for _ in range(6):
            try:
                chol = np.linalg.cholesky(a)
                break
            except np.linalg.LinAlgError:
                step = max(jitter * 99.0, 1e-8 * theta[0] ** 2 + 1e-10)
                a_diag += step
                jitter += step
                self.cholesky_fallbacks += 1
        else:
            raise np.linalg.LinAlgError('kernel matrix not positive definite even with jitter')
        logdet = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum()
        a_inv = np.linalg.inv(a)
        return a_inv, logdet, np.einsum('sij,sj->si', a_inv, self.z), jitter

    def lml_and_gradient(self, log_theta):
        """J and dJ/dlog(theta) (3,), the objective of the hyperparameter search."""
        theta = np.exp(np.asarray(log_theta, dtype=np.float64))
        sol = self.solve(theta)
        if sol.gradient is not None:
            return sol.lml, sol.gradient.copy()
        k = sol.kernel
        q, _ = self._pair_geometry()
        # W = alpha alpha^T - A^-1; K (and so W*K) is zero on padded slots, and the noise
        # derivative only involves the valid diagonal, so no full-size mask is needed.
        wk = (sol.alpha[:, :, None] * sol.alpha[:, None, :] - sol.a_inv) * k
        grad_sigma_f = float(wk.sum())  # 1/2 tr(W * 2K)
        grad_gain = float(np.vdot(wk, q)) / theta[1] ** 2  # 1/2 tr(W * K * 2q/a^2)
        w_diag = sol.alpha * sol.alpha - np.diagonal(sol.a_inv, axis1=1, axis2=2)
        grad_sigma_n = float(w_diag[self.valid].sum()) * theta[2] ** 2  # 1/2 tr(W * 2 sn^2 I)
        return sol.lml, np.array([grad_sigma_f, grad_gain, grad_sigma_n])

    # -- learning ------------------------------------------------------------------------
    def fit(self, theta0, bounds, max_evaluations):
        """Maximise J from theta0 within bounds ((lo, hi) x 3); returns (theta, info dict).

        The cap is on objective evaluations (each one factorisation of the whole frame), the
        unit of cost; L-BFGS-B's own iteration count is reported in ``info``.
        """
        theta0 = np.asarray(theta0, dtype=np.float64)
        if theta0.shape == (len(bounds),):  # np.clip's values without its ~5 us of set-up
            theta0 = np.array([min(max(t, lo), hi)  # NaN stays NaN, as in np.clip
                               for t, (lo, hi) in zip(theta0.tolist(), bounds)],
                              dtype=np.float64)
        else:
            theta0 = np.clip(theta0, [b[0] for b in bounds], [b[1] for b in bounds])
        info = {'iterations': 0, 'evaluations': 0, 'failed': False}
        if max_evaluations <= 0 or self.num_points == 0:
            return theta0, info

        values, points = [], []

        def objective(log_theta):
            if info['evaluations'] >= max_evaluations:
                raise _BudgetExhausted  # scipy checks maxfun only between iterations
            info['evaluations'] += 1
            points.append(np.array(log_theta, dtype=np.float64))
            try:
                lml, grad = self.lml_and_gradient(log_theta)
            except _NUMERICAL_ERRORS:  # a bad point, not a bad frame: L-BFGS-B backs off
                lml, grad = -np.inf, np.zeros(3)
            if not np.isfinite(lml) or not np.all(np.isfinite(grad)):
                values.append(np.inf)
                return 1e30, np.zeros(3)
            values.append(-lml)
            return -lml, -grad

        log_bounds = np.log(np.asarray(bounds, dtype=np.float64))
        try:
            res = minimize(objective, np.log(theta0), jac=True, method='L-BFGS-B',
                           bounds=log_bounds, options={'maxfun': int(max_evaluations),
                                                       'maxiter': int(max_evaluations)})
            info['iterations'] = int(res.nit)
        except _BudgetExhausted:
            pass
        except _NUMERICAL_ERRORS + (RuntimeError,):  # RuntimeError: scipy's own failures
            info['failed'] = True
            return theta0, info
        if not values or not np.isfinite(min(values)):
            info['failed'] = True  # never move to an undefined theta: keep the last good one
            return theta0, info
        best = int(np.argmin(values))  # values[0] is theta0: the result is never worse
        return np.exp(points[best]), info

    # -- prediction ----------------------------------------------------------------------
    def loo_residuals(self, sol: GPSolution) -> np.ndarray:
        """(S, n) z_i - mean_{-i}: leave-one-out residual alpha_i / [A^-1]_ii (R&W eq. 5.12)."""
        diag = np.diagonal(sol.a_inv, axis1=1, axis2=2)
        return np.where(self.valid, sol.alpha / diag, 0.0)

    def loo_std(self, sol: GPSolution) -> np.ndarray:
        """(S, n) leave-one-out predictive std sqrt(1 / [A^-1]_ii) of each slot, sensor noise
        included (R&W eq. 5.12); 0 on padded slots."""
        diag = np.diagonal(sol.a_inv, axis1=1, axis2=2)
        return np.where(self.valid, np.sqrt(1.0 / diag), 0.0)

    def predict(self, sol: GPSolution, r_star, d_star, with_std=True, return_kernel=False):
        """Posterior mean (absolute z) and std at r_star, d_star (S, k) of the batch segments.

        ``with_std=False`` skips the variance (the costlier half) and returns std = None.
        ``return_kernel``: also return k* (S, n, k) for a later :meth:`std_from_kernel` (the
        std without recomputing k*), or None when the compiled backend did not run.
        """
        sigma_f, gain, _ = sol.theta
        if self.backend == 'numba' and sol.gradient is not None:  # a compiled solution
            r_star, d_star = _prediction_points(r_star, d_star, self.segments.size)
            try:
                mean, std, k_star = gp_compiled.predict_batched(
                    self.r, self.d, self.counts, sol.alpha, sol.a_inv, r_star, d_star,
                    float(sigma_f), float(gain), bool(with_std))
            except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
                self.backend, self.compiled_error = 'numpy', str(exc)
            else:
                out = (mean + self.mean, (std if with_std else None))
                return out + (k_star,) if return_kernel else out
        l_star = gain * np.asarray(d_star, dtype=np.float64)[:, :, None]
        l_train = gain * self.d[:, None, :]
        k_star = paciorek_kernel(np.asarray(r_star, dtype=np.float64)[:, :, None], l_star,
                                 self.r[:, None, :], l_train, sigma_f)
        k_star = np.where(self.valid[:, None, :], k_star, 0.0)
        mean = np.einsum('skn,sn->sk', k_star, sol.alpha) + self.mean
        std = _posterior_std(k_star, sol.a_inv, sigma_f) if with_std else None
        return (mean, std, None) if return_kernel else (mean, std)

    def std_from_kernel(self, sol: GPSolution, k_star) -> np.ndarray:
        """Posterior std (S, k) from the k* that ``predict(..., return_kernel=True)`` returned
        for ``sol``: the same numbers as ``predict(..., with_std=True)`` gives.

        The std's kernel may be compiled only now (the segmenter's warm_up leaves it to the
        background when the labels do not use it); should that fail, numpy computes it (equal
        to round-off) and the error is kept in ``compiled_error``.
        """
        sigma_f = float(sol.theta[0])
        try:
            return gp_compiled.std_batched(self.counts, sol.a_inv, k_star, sigma_f)
        except Exception as exc:  # noqa: BLE001 - numba compile/runtime failure
            self.compiled_error = str(exc)
        # the compiled prediction's k* is (S, n, k): [segment, training point, prediction point]
        return _posterior_std(k_star.transpose(0, 2, 1), sol.a_inv, sigma_f)
