# SPDX-License-Identifier: Apache-2.0
"""Unit tests of the whole-frame GP (paciorek.py, gp.py, predict.py) against formulas written out
directly.

References are computed per segment with scalar Python loops (the Paciorek kernel exactly as
printed in the paper), dense numpy linear algebra and scipy.stats.multivariate_normal, on
random padded problems: several segments of different lengths, masked-out candidates, a
segment with a single candidate and segments with none.
"""

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from gp_ground_segmentation.core import compiled, gp as gp_module, paciorek, predict
from gp_ground_segmentation.core.gp import FrameGP, GroundAnchor, solve_batched
from gp_ground_segmentation.core.length_factors import length_scale_factors
from gp_ground_segmentation.core.paciorek import paciorek_kernel

BOUNDS = [(0.01, 20.0), (0.05, 200.0), (0.005, 2.0)]


# --------------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------------
def k_paper(ri, li, rj, lj, sigma_f):
    """Paper eq. 6 term by term."""
    li2, lj2 = li * li, lj * lj
    return (sigma_f ** 2 * (li2 ** 0.25) * (lj2 ** 0.25) * ((li2 + lj2) / 2.0) ** -0.5
            * math.exp(-(ri - rj) ** 2 / (li2 + lj2)))


def k_matrix(r1, l1, r2, l2, sigma_f):
    return np.array([[k_paper(float(a), float(la), float(b), float(lb), sigma_f)
                      for b, lb in zip(r2, l2)] for a, la in zip(r1, l1)])


def random_problem(seed, m_count=5, n_count=9):
    """(r, z, d, mask) (M, N): sorted r, smooth sloped ground + noise, random mask; row 0 has
    no training candidate, row 1 exactly one, NaN where a bin is empty and masked out."""
    rng = np.random.default_rng(seed)
    r = np.sort(rng.uniform(2.0, 30.0, (m_count, n_count)), axis=1)
    z = (-1.7 + rng.uniform(-0.1, 0.2, (m_count, 1)) * r + 0.3 * np.sin(r / 3.0)
         + rng.normal(0, 0.05, (m_count, n_count)))
    d = rng.uniform(0.3, 4.0, (m_count, n_count))
    mask = rng.random((m_count, n_count)) < 0.75
    mask[0] = False
    mask[1] = False
    mask[1, rng.integers(n_count)] = True
    empty = ~mask & (rng.random((m_count, n_count)) < 0.5)
    r[empty] = np.nan
    z[empty] = np.nan
    return r, z, d, mask


def random_theta(rng):
    return np.exp(rng.uniform(np.log([0.1, 0.5, 0.02]), np.log([3.0, 20.0, 0.5])))


def dense_lml(r, z, d, mask, theta, mean, extra=None):
    """sum over segments of log N(z_m; mean, K_m + sigma_n^2 I) with scipy.stats."""
    sigma_f, gain, sigma_n = theta
    total = 0.0
    for m in range(r.shape[0]):
        idx = np.flatnonzero(mask[m])
        if idx.size == 0:
            continue
        ell = gain * d[m, idx]
        cov = k_matrix(r[m, idx], ell, r[m, idx], ell, sigma_f)
        noise = sigma_n ** 2 + (0.0 if extra is None else extra[m, idx])
        cov = cov + np.diag(np.broadcast_to(noise, idx.shape))
        total += multivariate_normal.logpdf(z[m, idx], mean=np.full(idx.size, mean), cov=cov)
    return total


def dense_posterior(r_train, z_train, l_train, noise, mean, sigma_f, r_star, l_star):
    """Textbook GP posterior mean and latent std (R&W eq. 2.23-2.24) with the paper kernel."""
    a = k_matrix(r_train, l_train, r_train, l_train, sigma_f) + np.diag(noise)
    ks = k_matrix(r_star, l_star, r_train, l_train, sigma_f)
    mu = mean + ks @ np.linalg.solve(a, z_train - mean)
    var = sigma_f ** 2 - np.einsum('ij,ji->i', ks, np.linalg.solve(a, ks.T))
    return mu, np.sqrt(np.maximum(var, 0.0))


def slot_of(gp, m, k):
    """Padded (s, j) slot of candidate (segment m, bin k)."""
    s = int(np.flatnonzero(gp.segments == m)[0])
    j = int(np.flatnonzero(gp.bins[s] == k)[0])
    assert gp.valid[s, j]
    return s, j


# --------------------------------------------------------------------------------------------
# Kernel
# --------------------------------------------------------------------------------------------
def test_paciorek_kernel_equals_paper_formula():
    rng = np.random.default_rng(0)
    r1, r2 = rng.uniform(0, 40, 7), rng.uniform(0, 40, 5)
    l1, l2 = rng.uniform(0.05, 10, 7), rng.uniform(0.05, 10, 5)
    for sigma_f in (0.01, 0.7, 4.0):
        got = paciorek_kernel(r1[:, None], l1[:, None], r2[None, :], l2[None, :], sigma_f)
        np.testing.assert_allclose(got, k_matrix(r1, l1, r2, l2, sigma_f), rtol=1e-13,
                                   atol=1e-300)
    # batched (S, n, 1) x (S, 1, m)
    rb, lb = rng.uniform(0, 40, (3, 6)), rng.uniform(0.1, 5, (3, 6))
    got = paciorek_kernel(rb[:, :, None], lb[:, :, None], rb[:, None, :], lb[:, None, :], 1.3)
    for s in range(3):
        np.testing.assert_allclose(got[s], k_matrix(rb[s], lb[s], rb[s], lb[s], 1.3),
                                   rtol=1e-13, atol=1e-300)


def test_paciorek_kernel_symmetric_psd():
    rng = np.random.default_rng(1)
    for _ in range(10):
        n = 40
        r = np.sort(rng.uniform(0, 50, n))
        ell = np.exp(rng.uniform(np.log(0.1), np.log(20), n))
        k = paciorek_kernel(r[:, None], ell[:, None], r[None, :], ell[None, :], 1.7)
        np.testing.assert_array_equal(k, k.T)
        np.testing.assert_allclose(np.diag(k), 1.7 ** 2, rtol=1e-14)
        w = np.linalg.eigvalsh(k)
        assert w.min() > -1e-10 * w.max()
        # a random draw's quadratic form is non-negative
        v = rng.normal(size=n)
        assert v @ k @ v > -1e-9


def test_paciorek_constant_length_scale_is_squared_exponential():
    rng = np.random.default_rng(2)
    r1, r2 = rng.uniform(0, 20, 9), rng.uniform(0, 20, 9)
    for ell in (0.3, 2.0, 15.0):
        got = paciorek_kernel(r1[:, None], np.full((9, 1), ell), r2[None, :],
                              np.full((1, 9), ell), 0.8)
        se = 0.8 ** 2 * np.exp(-(r1[:, None] - r2[None, :]) ** 2 / (2.0 * ell ** 2))
        np.testing.assert_allclose(got, se, rtol=1e-13, atol=1e-300)


def test_one_paciorek_kernel_on_every_path():
    """paciorek() is the one definition: its compiled copy (what the compiled solve and
    prediction call), the numpy solve's geometry form (q and prefactor kept across thetas)
    and the compiled solve's K agree with it, and q gives its log-gradient in a
    (dk/dlog a = 2 k q / a^2, against finite differences)."""
    rng = np.random.default_rng(4)
    r, z, d, mask = random_problem(4)
    theta = (0.8, 1.7, 0.05)
    gp = FrameGP(r, z, d, mask, backend='numpy')
    valid = gp.valid[:, :, None] & gp.valid[:, None, :]
    diff = gp.r[:, :, None] - gp.r[:, None, :]
    k, q = paciorek.paciorek(diff, gp.d[:, :, None], gp.d[:, None, :], theta[0] ** 2,
                             1.0 / theta[1] ** 2)
    np.testing.assert_allclose(np.where(valid, k, 0.0), gp.kernel(theta), rtol=1e-14, atol=0)
    np.testing.assert_array_equal(np.where(valid, q, 0.0), gp._pair_geometry()[0])
    if compiled.AVAILABLE:
        one = [paciorek.paciorek_compiled(a, b, c, 1.3, 0.7)
               for a, b, c in rng.uniform(0.05, 30.0, (200, 3))]
        many = paciorek.paciorek(*rng.uniform(0.05, 30.0, (200, 3)).T, 1.3, 0.7)
        assert len(one) == 200 and np.all(np.isfinite(many))
        rng = np.random.default_rng(4)  # the same draws, one by one
        for (a, b, c), (k1, q1) in zip(rng.uniform(0.05, 30.0, (200, 3)), one):
            k2, q2 = paciorek.paciorek(a, b, c, 1.3, 0.7)
            assert q1 == q2 and k1 == pytest.approx(k2, rel=1e-15)
        fast = FrameGP(r, z, d, mask, backend='numba')
        sol = fast.solve(theta)
        for s_, count in enumerate(fast.counts):
            np.testing.assert_allclose(sol.pair_terms[0][s_, :count, :count],
                                       k[s_, :count, :count], rtol=1e-14)
    # the gradient factor: d k / d log a = 2 k q / a^2
    step = 1e-6
    k_up = paciorek.paciorek(diff, gp.d[:, :, None], gp.d[:, None, :], theta[0] ** 2,
                             1.0 / (theta[1] * math.exp(step)) ** 2)[0]
    np.testing.assert_allclose(np.where(valid, (k_up - k) / step, 0.0),
                               np.where(valid, 2.0 * k * q / theta[1] ** 2, 0.0),
                               rtol=1e-4, atol=1e-9)


# --------------------------------------------------------------------------------------------
# FrameGP: layout, LML and gradient
# --------------------------------------------------------------------------------------------
def test_frame_gp_layout():
    r, z, d, mask = random_problem(3)
    gp = FrameGP(r, z, d, mask)
    np.testing.assert_array_equal(gp.segments, np.flatnonzero(mask.any(axis=1)))
    assert gp.n_max == mask.sum(axis=1).max() and gp.num_points == mask.sum()
    assert gp.mean == np.median(z[mask])
    for s, m in enumerate(gp.segments):
        k = gp.bins[s][gp.valid[s]]
        np.testing.assert_array_equal(k, np.flatnonzero(mask[m]))  # bin order
        np.testing.assert_array_equal(gp.r[s][gp.valid[s]], r[m, k])
        np.testing.assert_allclose(gp.z[s][gp.valid[s]], z[m, k] - gp.mean, rtol=1e-15)
    assert np.isfinite(gp.r).all() and np.isfinite(gp.z).all()
    assert FrameGP(r, z, d, mask, mean=0.25).mean == 0.25
    assert not gp.is_anchor.any()
    np.testing.assert_array_equal(gp.to_grid(gp.valid, False), mask)  # and back


def test_frame_gp_anchor_is_an_explicit_first_point():
    """The anchor enters the segments it names before their candidates, with its own noise
    and d, counts in the prior mean once per segment, and never shows up on the grid."""
    r, z, d, mask = random_problem(4)
    segments = mask.any(axis=1)
    segments[0] = True  # a segment with the anchor only
    anchor = GroundAnchor(-1.5, 0.09, segments, np.linspace(1.0, 2.0, mask.shape[0]))
    gp = FrameGP(r, z, d, mask, anchor=anchor)
    np.testing.assert_array_equal(gp.segments, np.flatnonzero(segments))
    assert gp.num_points == mask.sum() + segments.sum()
    assert gp.mean == np.median(np.concatenate([z[mask], np.full(segments.sum(), -1.5)]))
    for s, m in enumerate(gp.segments):
        assert gp.is_anchor[s, 0] and not gp.is_anchor[s, 1:].any() and gp.bins[s, 0] == -1
        assert gp.r[s, 0] == 0.0 and gp.z[s, 0] == -1.5 - gp.mean
        assert gp.d[s, 0] == anchor.length_factor[m] and gp.noise_var[s, 0] == 0.09
        np.testing.assert_array_equal(gp.bins[s, 1:][gp.valid[s, 1:]], np.flatnonzero(mask[m]))
    np.testing.assert_array_equal(gp.to_grid(gp.valid, False), mask)
    # slot values land on their own bins (the anchor's nowhere), also from a with_noise copy
    for frame in (gp, gp.with_noise(np.full(mask.shape, 0.5))):
        np.testing.assert_array_equal(frame.to_grid(frame.r, np.nan), np.where(mask, r, np.nan))
    # the LML is that of the dense problem with the anchor as one more point
    theta = np.array([0.6, 2.0, 0.1])
    r2, z2, d2, mask2 = (np.concatenate([col, a], axis=1) for col, a in (
        (np.zeros((5, 1)), r), (np.full((5, 1), -1.5), z), (anchor.length_factor[:, None], d),
        (segments[:, None], mask)))
    extra = np.zeros_like(r2)
    extra[:, 0] = 0.09
    assert gp.solve(theta).lml == pytest.approx(
        dense_lml(r2, z2, d2, mask2, theta, gp.mean, extra), rel=1e-10)
    # new noise leaves the anchor's own and the original object alone
    noisier = gp.with_noise(np.full(mask.shape, 0.5))
    assert np.all(noisier.noise_var[gp.is_anchor] == 0.09)
    assert np.all(noisier.noise_var[gp.valid & ~gp.is_anchor] == 0.5)
    assert np.all(gp.noise_var[gp.valid & ~gp.is_anchor] == 0.0)


@pytest.mark.parametrize('seed', range(4))
def test_lml_equals_sum_of_multivariate_normal_logpdf(seed):
    r, z, d, mask = random_problem(10 + seed)
    gp = FrameGP(r, z, d, mask)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        theta = random_theta(rng)
        lml, _ = gp.lml_and_gradient(np.log(theta))
        assert lml == pytest.approx(dense_lml(r, z, d, mask, theta, gp.mean), rel=1e-10)
    # with per-candidate extra noise, given at construction or derived
    extra = np.zeros_like(r)
    pick = np.argwhere(mask)[rng.choice(mask.sum(), 3, replace=False)]
    for m, k in pick:
        extra[m, k] = rng.uniform(0.01, 5.0)
    theta = random_theta(rng)
    lml, _ = FrameGP(r, z, d, mask, noise_var=extra).lml_and_gradient(np.log(theta))
    assert lml == pytest.approx(dense_lml(r, z, d, mask, theta, gp.mean, extra), rel=1e-10)
    lml, _ = gp.with_noise(extra).lml_and_gradient(np.log(theta))
    assert lml == pytest.approx(dense_lml(r, z, d, mask, theta, gp.mean, extra), rel=1e-10)


@pytest.mark.parametrize('seed', range(6))
def test_lml_gradient_matches_finite_differences(seed):
    r, z, d, mask = random_problem(20 + seed, m_count=4, n_count=8)
    rng = np.random.default_rng(100 + seed)
    gp = FrameGP(r, z, d, mask, noise_var=rng.uniform(0, 0.2, r.shape) if seed % 2 else None)
    log_theta = np.log(random_theta(rng))
    _, grad = gp.lml_and_gradient(log_theta)
    h = 1e-5
    for i in range(3):
        step = np.zeros(3)
        step[i] = h
        fd = (gp.lml_and_gradient(log_theta + step)[0]
              - gp.lml_and_gradient(log_theta - step)[0]) / (2 * h)
        assert abs(fd - grad[i]) < 1e-5 * abs(grad[i]), (i, fd, grad[i])


# --------------------------------------------------------------------------------------------
# Prediction, leave-one-out, extra noise
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('seed', range(3))
def test_predict_equals_textbook_posterior(seed):
    r, z, d, mask = random_problem(30 + seed)
    gp = FrameGP(r, z, d, mask)
    rng = np.random.default_rng(seed)
    theta = random_theta(rng)
    sigma_f, gain, sigma_n = theta
    sol = gp.solve(theta)
    r_star = rng.uniform(0, 35, (gp.segments.size, 6))
    d_star = rng.uniform(0.3, 4.0, (gp.segments.size, 6))
    mean, std = gp.predict(sol, r_star, d_star)
    for s, m in enumerate(gp.segments):
        idx = np.flatnonzero(mask[m])
        mu, sd = dense_posterior(r[m, idx], z[m, idx], gain * d[m, idx],
                                 np.full(idx.size, sigma_n ** 2), gp.mean, sigma_f,
                                 r_star[s], gain * d_star[s])
        np.testing.assert_allclose(mean[s], mu, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(std[s], sd, rtol=1e-7, atol=1e-7)


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('seed', range(3))
def test_std_from_the_kept_kernel_equals_the_std_of_predict(seed):
    r, z, d, mask = random_problem(50 + seed)
    gp = FrameGP(r, z, d, mask, backend='numba')
    rng = np.random.default_rng(seed)
    sol = gp.solve(random_theta(rng))
    r_star = rng.uniform(0, 35, (gp.segments.size, 7))
    d_star = rng.uniform(0.3, 4.0, (gp.segments.size, 7))
    mean, std = gp.predict(sol, r_star, d_star, with_std=True)
    mean_only, no_std, k_star = gp.predict(sol, r_star, d_star, with_std=False,
                                           return_kernel=True)
    assert no_std is None and k_star.shape == (gp.segments.size, gp.n_max, 7)
    # the surface's deferred z_std: the same numbers, bit for bit
    assert np.array_equal(mean_only, mean)
    assert np.array_equal(gp.std_from_kernel(sol, k_star), std)


@pytest.mark.parametrize('seed', range(3))
def test_loo_residuals_equal_explicit_refits(seed):
    r, z, d, mask = random_problem(40 + seed)
    gp = FrameGP(r, z, d, mask)
    rng = np.random.default_rng(seed)
    theta = random_theta(rng)
    sigma_f, gain, sigma_n = theta
    loo = gp.loo_residuals(gp.solve(theta))
    assert np.all(loo[~gp.valid] == 0)
    checked = 0
    for s, m in enumerate(gp.segments):
        idx = np.flatnonzero(mask[m])
        for i, k in enumerate(idx):
            rest = np.delete(idx, i)
            if rest.size == 0:
                # no other candidate: the LOO prediction is the prior mean
                expected = z[m, k] - gp.mean
            else:
                mu, _ = dense_posterior(r[m, rest], z[m, rest], gain * d[m, rest],
                                        np.full(rest.size, sigma_n ** 2), gp.mean, sigma_f,
                                        r[m, [k]], gain * d[m, [k]])
                expected = z[m, k] - mu[0]
            assert loo[slot_of(gp, m, k)] == pytest.approx(expected, rel=1e-8, abs=1e-10)
            checked += 1
    assert checked == mask.sum()


def test_noise_var_removes_a_candidates_influence():
    r, z, d, mask = random_problem(50)
    m = int(np.argmax(mask.sum(axis=1)))
    k = np.flatnonzero(mask[m])[mask[m].sum() // 2]
    z = z.copy()
    z[m, k] += 3.0  # an obstacle top among the ground candidates
    theta = np.array([0.8, 3.0, 0.05])
    mean0 = float(np.median(z[mask]))
    with_it = FrameGP(r, z, d, mask, mean=mean0)
    s, j = slot_of(with_it, m, k)
    mask_without = mask.copy()
    mask_without[m, k] = False
    without = FrameGP(r, z, d, mask_without, mean=mean0)
    s2 = int(np.flatnonzero(without.segments == m)[0])
    r_star = np.linspace(2, 30, 15)[None, :]
    d_star = np.full_like(r_star, 1.5)
    ref, ref_std = without.predict(without.solve(theta), r_star, d_star)
    pulled, _ = with_it.predict(with_it.solve(theta), r_star, d_star)
    assert np.max(np.abs(pulled[s] - ref[s2])) > 0.1  # the outlier does pull the plain fit
    noise = np.zeros_like(r)
    noise[m, k] = 1e8
    ignored = with_it.with_noise(noise)
    sol = ignored.solve(theta)
    mean, std = ignored.predict(sol, r_star, d_star)
    np.testing.assert_allclose(mean[s], ref[s2], atol=1e-6)
    np.testing.assert_allclose(std[s], ref_std[s2], atol=1e-6)
    assert abs(sol.alpha[s, j]) < 1e-7


# --------------------------------------------------------------------------------------------
# Length-scale factors
# --------------------------------------------------------------------------------------------
LS = dict(slope_floor=0.02, slope_ceiling=0.9, d_min=0.05, d_max=50.0)


def test_length_scale_factors_regular_branch_and_guards():
    g = np.array([0.05, 0.3, 0.8, 0.9, 1.0, 2.5, np.nan, 0.001, 0.0])
    rho = np.array([1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    d = length_scale_factors(g, rho, **LS)
    expected = [math.log(1 / 0.05), math.log(1 / 0.3) / 2.0, math.log(1 / 0.8) / 0.5,
                math.log(1 / 0.9), math.log(1 / 0.9), math.log(1 / 0.9),  # g >= 1 -> ceiling
                math.log(1 / 0.02), math.log(1 / 0.02), math.log(1 / 0.02)]  # NaN / flat -> g_d
    np.testing.assert_allclose(d, expected, rtol=1e-14)
    assert np.all(d > 0)
    # density 0 (or negative, or NaN) counts as an ordinary bin (rho = 1)
    d0 = length_scale_factors(np.array([0.3, 0.3, 0.3, np.nan]),
                              np.array([0.0, -2.0, np.nan, 0.0]), **LS)
    np.testing.assert_allclose(d0, [math.log(1 / 0.3)] * 3 + [math.log(1 / 0.02)], rtol=1e-14)
    # clipping to [d_min, d_max]
    dc = length_scale_factors(np.array([0.3, 0.3]), np.array([1e-6, 1e6]), **LS)
    np.testing.assert_array_equal(dc, [50.0, 0.05])


def test_length_scale_factors_flat_branch_switch():
    g = np.array([0.001, 0.01, np.nan, 0.05, 0.5])
    rho = np.array([4.0, 0.25, 2.0, 4.0, 0.5])
    with_rho = length_scale_factors(g, rho, density_in_flat_branch=True, **LS)
    without = length_scale_factors(g, rho, density_in_flat_branch=False, **LS)
    log_gd = math.log(1 / 0.02)
    np.testing.assert_allclose(with_rho, [log_gd / 4, log_gd / 0.25, log_gd / 2,
                                          math.log(1 / 0.05) / 4, math.log(1 / 0.5) / 0.5],
                               rtol=1e-14)
    # the paper's flat branch: g < g_d -> log(1/g_d), no density; steeper slopes unchanged
    np.testing.assert_allclose(without, [log_gd, log_gd, log_gd, math.log(1 / 0.05) / 4,
                                         math.log(1 / 0.5) / 0.5], rtol=1e-14)
    # with the density in the flat branch L is continuous in g at g_d
    eps = 1e-9
    lo = length_scale_factors(np.array([0.02 - eps]), np.array([3.0]), **LS)
    hi = length_scale_factors(np.array([0.02 + eps]), np.array([3.0]), **LS)
    assert lo[0] == pytest.approx(hi[0], rel=1e-6)


def test_length_scale_factor_at_exactly_g_d_uses_density():
    d = length_scale_factors(np.array([0.02]), np.array([4.0]), density_in_flat_branch=False,
                             **LS)
    assert d[0] == pytest.approx(math.log(1 / 0.02) / 4.0)


def test_length_scale_factor_infinite_slope_is_steep():
    d = length_scale_factors(np.array([np.inf]), np.array([1.0]), **LS)
    assert d[0] == pytest.approx(math.log(1 / 0.9))


# --------------------------------------------------------------------------------------------
# Learning
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('seed', range(4))
def test_fit_never_worse_than_start_and_within_bounds(seed):
    r, z, d, mask = random_problem(60 + seed, m_count=5, n_count=10)
    gp = FrameGP(r, z, d, mask)
    rng = np.random.default_rng(seed)
    lo, hi = np.array(BOUNDS).T
    starts = [random_theta(rng), lo, hi, np.array([100.0, 1e-3, 50.0])]  # last: out of bounds
    for theta0 in starts:
        start = np.clip(theta0, lo, hi)
        start_lml = gp.solve(start).lml
        for cap in (1, 3, 40):
            theta, info = gp.fit(theta0, BOUNDS, cap)
            assert np.all(theta >= lo * (1 - 1e-12)) and np.all(theta <= hi * (1 + 1e-12))
            assert gp.solve(theta).lml >= start_lml - 1e-9 * abs(start_lml)
            assert info['evaluations'] >= 1
    # a real improvement from a poor start with enough evaluations
    theta, info = gp.fit([5.0, 100.0, 1.0], BOUNDS, 60)
    assert not info['failed']
    assert gp.solve(theta).lml > gp.solve([5.0, 100.0, 1.0]).lml + 1.0


def test_fit_zero_cap_and_empty_frame_return_clipped_start():
    r, z, d, mask = random_problem(70)
    gp = FrameGP(r, z, d, mask)
    theta, info = gp.fit([100.0, 1.0, 0.1], BOUNDS, 0)
    np.testing.assert_array_equal(theta, [20.0, 1.0, 0.1])
    assert info['evaluations'] == 0
    empty = FrameGP(r, z, d, np.zeros_like(mask))
    assert empty.num_points == 0
    theta, info = empty.fit([0.5, 2.0, 0.05], BOUNDS, 10)
    np.testing.assert_array_equal(theta, [0.5, 2.0, 0.05])


def test_fit_respects_evaluation_cap():
    worst = {}
    for seed in range(8):
        r, z, d, mask = random_problem(80 + seed, m_count=5, n_count=12)
        gp = FrameGP(r, z, d, mask)
        rng = np.random.default_rng(seed)
        theta0 = np.exp(rng.uniform(np.log([0.05, 0.2, 0.01]), np.log([5.0, 50.0, 0.5])))
        for cap in (1, 2, 3, 5):
            gp.solve(theta0)  # the segmenter has always factorised the start already
            before = gp.factorisations
            gp.fit(theta0, BOUNDS, cap)
            worst[cap] = max(worst.get(cap, 0), gp.factorisations - before)
    assert all(worst[cap] <= cap for cap in worst), worst


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('seed', range(4))
def test_resolve_with_known_segments_equals_full_solve(seed, monkeypatch):
    """A with_noise copy solved at a theta its parent has solved reuses the parent's segments
    whose noise is unchanged (gp.resolve_batched): the solution, J and gradient equal
    a fresh FrameGP's full solve bit for bit, and segments with new noise do change."""
    r, z, d, mask = random_problem(110 + seed, m_count=6, n_count=12)
    rng = np.random.default_rng(seed)
    theta = random_theta(rng)
    parent = FrameGP(r, z, d, mask, backend='numba')
    parent.solve(theta)
    noise = np.zeros(mask.shape)
    noise[np.argmax(mask.sum(axis=1)), :] = 4.0  # the fullest row's candidates: more noise
    calls = []
    real = gp_module.SOLVE.kernel

    def counting(*args):
        if args[9].size:  # a re-solve with known segments (a full solve passes none)
            calls.append(int(args[8].sum()))
        return real(*args)

    monkeypatch.setattr(gp_module, 'SOLVE', dataclasses.replace(gp_module.SOLVE, kernel=counting))
    reused = parent.with_noise(noise).solve(theta)
    fresh = FrameGP(r, z, d, mask, noise_var=noise, backend='numba', mean=parent.mean)
    full = fresh.solve(theta)
    assert calls == [1]  # the copy did reuse all but the one noisier row
    for name in ('alpha', 'a_inv', 'gradient', 'logdets'):
        np.testing.assert_array_equal(getattr(reused, name), getattr(full, name))
    assert reused.lml == full.lml
    assert not np.array_equal(reused.alpha, parent.solve(theta).alpha)  # that row did change


def test_cholesky_failure_falls_back_without_raising():
    # eight candidates at the same r and d: K is rank one, sigma_n at a 1e-9 m bound
    r = np.full((2, 8), 5.0)
    r[1] = np.linspace(3, 10, 8)
    rng = np.random.default_rng(9)
    z = rng.normal(0, 0.1, (2, 8))
    d = np.ones((2, 8))
    mask = np.ones((2, 8), dtype=bool)
    gp = FrameGP(r, z, d, mask)
    sol = gp.solve([1.0, 1.0, 1e-9])
    assert gp.cholesky_fallbacks >= 1
    assert sol.jitter > 0 and np.isfinite(sol.lml)
    lml, grad = gp.lml_and_gradient(np.log([1.0, 1.0, 1e-9]))
    assert np.isfinite(lml) and np.all(np.isfinite(grad))
    before = gp.cholesky_fallbacks
    theta, info = gp.fit([1.0, 1.0, 1e-9], [(0.01, 20.0), (0.05, 200.0), (1e-9, 2.0)], 20)
    assert np.all(np.isfinite(theta))
    assert gp.cholesky_fallbacks >= before
    mean, std = gp.predict(gp.solve(theta), np.full((2, 3), 5.0), np.ones((2, 3)))
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('anchor', [False, True])
def test_compiled_step_equals_numpy(seed, anchor):
    """The compiled GP step and the numpy reference: same solution, LML, gradient, prediction."""
    r, z, d, mask = random_problem(seed)
    m_count = mask.shape[0]
    ground = (GroundAnchor(-1.7, 0.01, np.arange(m_count) % 3 > 0, np.full(m_count, 2.0))
              if anchor else None)
    noise = np.where(np.random.default_rng(seed).random(mask.shape) < 0.1, 1e4, 0.0)
    theta = np.log([0.7, 1.5, 0.08])
    ref_gp = FrameGP(r, z, d, mask, noise, anchor=ground, backend='numpy')
    fast_gp = FrameGP(r, z, d, mask, noise, anchor=ground, backend='numba')
    assert fast_gp.counts.min() < fast_gp.n_max  # segments of different sizes in the batch
    ref_lml, ref_grad = ref_gp.lml_and_gradient(theta)
    lml, grad = fast_gp.lml_and_gradient(theta)
    ref, fast = ref_gp.solve(np.exp(theta)), fast_gp.solve(np.exp(theta))
    assert fast.gradient is not None and ref.gradient is None  # really two paths
    assert lml == pytest.approx(ref_lml, rel=1e-10)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-9)
    np.testing.assert_allclose(fast.a_inv, ref.a_inv, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.alpha, ref.alpha, rtol=1e-9, atol=1e-12)
    r_star = np.linspace(0.0, 40.0, 7)[None, :].repeat(fast_gp.segments.size, axis=0)
    d_star = np.full_like(r_star, 1.3)
    ref_mean, ref_std = ref_gp.predict(ref, r_star, d_star)
    mean, std = fast_gp.predict(fast, r_star, d_star)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(std, ref_std, rtol=1e-7, atol=1e-9)
    assert fast_gp.predict(fast, r_star, d_star, with_std=False)[1] is None


def test_compiled_step_reports_non_pd_matrices():
    r = np.array([[0.0, 1.0, 2.0], [5.0, 5.0, 0.0]])
    d = np.ones((2, 3))
    z = np.ones((2, 3))
    counts = np.array([3, 2])
    noise = np.array([[0.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])  # negative variance: not PD
    ok, logdet, alpha, a_inv, *_ = solve_batched(r, d, z, noise, counts, 1.0, 1.0, 0.1)
    assert ok.tolist() == [True, False]
    k = np.exp(-np.subtract.outer(r[0], r[0]) ** 2 / 2.0) + 0.01 * np.eye(3)
    assert logdet[0] == pytest.approx(np.linalg.slogdet(k)[1], rel=1e-12)
    np.testing.assert_allclose(a_inv[0], np.linalg.inv(k), rtol=1e-10)
    np.testing.assert_allclose(alpha[0], np.linalg.solve(k, z[0]), rtol=1e-10)


def test_broken_compiled_kernel_falls_back_to_numpy(monkeypatch):
    """If numba cannot compile or run on a platform, the frame is still solved (numpy)."""
    def broken(*args):
        raise RuntimeError('no LLVM here')
    monkeypatch.setattr(gp_module, 'AVAILABLE', True)
    monkeypatch.setattr(gp_module, 'SOLVE', dataclasses.replace(gp_module.SOLVE, kernel=broken))
    r, z, d, mask = random_problem(1)
    gp = FrameGP(r, z, d, mask, backend='numba')
    ref = FrameGP(r, z, d, mask, backend='numpy').solve((0.7, 1.5, 0.08))
    sol = gp.solve((0.7, 1.5, 0.08))
    assert sol.lml == ref.lml
    assert gp.backend == 'numpy' and 'no LLVM here' in gp.compiled_error
    assert gp.with_noise(np.zeros_like(r)).backend == 'numpy'  # derived objects keep numpy


def test_backend_names():
    r, z, d, mask = random_problem(2)
    assert FrameGP(r, z, d, mask).backend == ('numba' if compiled.AVAILABLE else 'numpy')
    with pytest.raises(ValueError, match='backend'):
        FrameGP(r, z, d, mask, backend='cuda')


@pytest.mark.parametrize('with_anchor', [False, True])
@pytest.mark.parametrize('seed', range(6))
def test_compiled_padding_equals_the_numpy_reference(seed, with_anchor):
    """FrameGP's (M, N) -> (S, n) padding: the compiled pass gives the reference's arrays bit
    for bit (dtypes, shapes, padding slots), with rows empty, full and in between, and
    segments with the anchor alone."""
    if gp_module.PAD.kernel is None:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(seed)
    m_count, n_count = 9, 6
    r = rng.uniform(0.0, 40.0, (m_count, n_count))
    z = rng.normal(0.0, 1.0, (m_count, n_count))
    d = rng.uniform(0.1, 3.0, (m_count, n_count))
    mask = rng.random((m_count, n_count)) < rng.uniform(0.1, 0.9)
    mask[0] = False
    mask[1] = True
    noise_var = rng.uniform(0.0, 1.0, (m_count, n_count))
    anchor_segments = rng.random(m_count) < 0.7
    args = (r, z, d, mask, noise_var, with_anchor, anchor_segments,
            rng.uniform(0.1, 2.0, m_count), -1.7, 0.01, float(rng.normal()))
    for ours, reference in zip(gp_module.PAD.kernel(*args), gp_module._pad_numpy(*args)):
        assert ours.dtype == reference.dtype and ours.shape == reference.shape
        np.testing.assert_array_equal(ours, reference)


def test_a_failed_std_kernel_is_remembered_not_compiled_again(monkeypatch):
    """std_batched calls its kernel directly (not through compiled.run): a compile failure,
    here or in the background compiler, must not be retried at every surface read."""
    calls = []

    def broken(*args):
        calls.append(1)
        raise RuntimeError('no LLVM here')
    monkeypatch.setattr(predict, '_std_into', broken)
    args = (np.array([2], dtype=np.intp), np.zeros((1, 2, 2)), np.zeros((1, 2, 2)), 1.0)
    try:
        for _ in range(3):
            with pytest.raises(RuntimeError):
                predict.std_batched(*args)
        assert calls == [1] and compiled.failed(broken)
    finally:  # the set of failed kernels is the process's: other tests check it is empty
        compiled._failed.discard(broken)


@pytest.mark.parametrize('with_anchor', [False, True])
def test_compiled_slot_noise_equals_the_numpy_reference(with_anchor):
    """with_noise's slots: the compiled pass gives the reference's (S, n) noise (the anchor's
    own, padding 0) and the segments whose noise changed; a compiled copy solves as a numpy
    copy does."""
    module = gp_module
    if module.SLOT_NOISE.kernel is None:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(3)
    m_count, n_bins = 20, 10
    r = np.sort(rng.uniform(1.0, 30.0, (m_count, n_bins)), axis=1)
    z = rng.normal(0.0, 0.2, (m_count, n_bins))
    d = rng.uniform(0.3, 3.0, (m_count, n_bins))
    mask = rng.random((m_count, n_bins)) < 0.6
    mask[:2] = False
    anchor = (GroundAnchor(0.0, 0.01, rng.random(m_count) < 0.8, rng.uniform(0.3, 3.0, m_count))
              if with_anchor else None)
    gp = FrameGP(r, z, d, mask, anchor=anchor, backend='numba')
    noise = np.where(mask & (rng.random(mask.shape) < 0.2), 1e4, 0.0)
    anchor_var = 0.01 if with_anchor else 0.0
    args = (noise, gp.noise_var, gp.valid, gp.is_anchor, gp.segments, gp.bins, anchor_var)
    ours = module.SLOT_NOISE.kernel(*args)
    reference = module.SLOT_NOISE.reference(*args)
    for a, b in zip(ours, reference):
        np.testing.assert_array_equal(a, b)
    assert 0 < np.count_nonzero(reference[1]) < gp.segments.size
    theta = np.array([0.5, 2.0, 0.1])
    gp.solve(theta)
    numpy_gp = FrameGP(r, z, d, mask, anchor=anchor, backend='numpy')
    np.testing.assert_array_equal(gp.with_noise(noise).noise_var,
                                  numpy_gp.with_noise(noise).noise_var)
