# SPDX-License-Identifier: Apache-2.0
"""Unit tests of line extraction (lines.py): the Deming fit and Algorithm 1's critical points.

The Deming slope (the one function Algorithm 1 uses, from raw sums) is checked against
references that share no code with ``deming_fit``: the
maximum-likelihood problem over (alpha, beta, xi_1..xi_n) solved numerically with
scipy.optimize.least_squares, and principal-axis (eigenvector) regression after rescaling z by
1/sqrt(lambda). Critical points are checked on a hand-built segment whose every break has one
known cause; relaxing only that cause's threshold must remove only that break.
"""

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from gp_ground_segmentation.core.lines import deming_fit, extract_lines

NAN = np.nan
KW = dict(variance_ratio=1.0, max_slope=0.7, max_distance_m=0.15, max_gap_m=6.0,
          max_density_jump=8.0)


def moments(r, z):
    """Central second moments and means (for the OLS references)."""
    c = np.cov(np.stack([r, z]), ddof=0)
    return c[0, 0], c[1, 1], c[0, 1], r.mean(), z.mean()


def sums(r, z):
    """The raw sums deming_fit takes: n, sum r, sum z, sum r^2, sum z^2, sum r z."""
    return len(r), r.sum(), z.sum(), (r * r).sum(), (z * z).sum(), (r * z).sum()


def from_moments(s_rr, s_zz, s_rz, mean_r, mean_z):
    """Raw sums of a one-point-weight problem with the given central moments and means."""
    return (1.0, mean_r, mean_z, s_rr + mean_r * mean_r, s_zz + mean_z * mean_z,
            s_rz + mean_r * mean_z)


def ml_deming(r, z, lam):
    """Deming by its definition: minimise sum (z - a - b xi)^2 / s_z^2 + (r - xi)^2 / s_r^2,
    lambda = s_z^2 / s_r^2, over the line (a, b) and the true abscissae xi, numerically."""
    b0 = np.polyfit(r, z, 1)[0]
    p0 = np.concatenate([[z.mean() - b0 * r.mean(), b0], r])

    def residuals(p):
        a, b, xi = p[0], p[1], p[2:]
        return np.concatenate([z - a - b * xi, math.sqrt(lam) * (r - xi)])

    sol = least_squares(residuals, p0, method='lm', xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=20000)
    return sol.x[0], sol.x[1]


def principal_axis_slope(r, z, lam=1.0):
    """Orthogonal regression in (r, z / sqrt(lambda)): the covariance's largest-eigenvalue
    eigenvector is the line direction (its smallest is the normal)."""
    zs = z / math.sqrt(lam)
    w, v = np.linalg.eigh(np.cov(np.stack([r, zs])))
    normal = v[:, np.argmin(w)]
    return -normal[0] / normal[1] * math.sqrt(lam)


def noisy_line(rng, n, slope, sigma_r, sigma_z, r_lo=0.0, r_hi=10.0):
    xi = rng.uniform(r_lo, r_hi, n)
    return (xi + rng.normal(0, sigma_r, n), 0.3 + slope * xi + rng.normal(0, sigma_z, n))


# --------------------------------------------------------------------------------------------
# deming_fit
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('lam', [0.05, 0.5, 1.0, 4.0, 30.0])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_deming_matches_ml_and_principal_axis(seed, lam):
    rng = np.random.default_rng(seed)
    slope = rng.choice([-2.0, -0.3, 0.1, 0.8, 3.0])
    r, z = noisy_line(rng, 15, slope, 0.2, 0.2 * math.sqrt(lam))
    alpha, beta = deming_fit(*sums(r, z), lam)
    a_ml, b_ml = ml_deming(r, z, lam)
    assert float(beta) == pytest.approx(b_ml, rel=1e-7, abs=1e-9)
    assert float(alpha) == pytest.approx(a_ml, abs=1e-6)  # = beta error x mean r
    assert float(beta) == pytest.approx(principal_axis_slope(r, z, lam), rel=1e-9)
    # the line passes through the centroid
    assert float(alpha) + float(beta) * r.mean() == pytest.approx(z.mean(), abs=1e-12)


def test_deming_lambda_one_is_orthogonal_regression():
    rng = np.random.default_rng(11)
    for _ in range(20):
        r, z = noisy_line(rng, 30, rng.uniform(-4, 4), 0.3, 0.3)
        _, beta = deming_fit(*sums(r, z), 1.0)
        # smallest eigenvector of the covariance is the normal (-beta, 1) / norm
        w, v = np.linalg.eigh(np.cov(np.stack([r, z])))
        normal = v[:, 0]
        assert float(beta) == pytest.approx(-normal[0] / normal[1], rel=1e-9)
        # and it minimises the sum of squared perpendicular distances

        def perp(b):
            a = z.mean() - b * r.mean()
            return np.sum((z - a - b * r) ** 2) / (1 + b * b)
        assert perp(float(beta)) <= min(perp(float(beta) + 1e-4), perp(float(beta) - 1e-4))


def test_deming_limits_ols_and_inverse_regression():
    rng = np.random.default_rng(12)
    r, z = noisy_line(rng, 40, 1.2, 0.3, 0.3)
    s_rr, s_zz, s_rz, mr, mz = moments(r, z)
    ols = s_rz / s_rr
    inverse = s_zz / s_rz  # regression of r on z, inverted
    errors = [abs(float(deming_fit(*from_moments(s_rr, s_zz, s_rz, mr, mz), lam)[1]) - ols)
              for lam in (1.0, 1e2, 1e4, 1e6, 1e8)]
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 1e-7 * abs(ols)
    _, b_small = deming_fit(*from_moments(s_rr, s_zz, s_rz, mr, mz), 1e-8)
    assert float(b_small) == pytest.approx(inverse, rel=1e-6)
    # Deming lies between OLS and the inverse regression
    for lam in (0.1, 1.0, 10.0):
        b = float(deming_fit(*from_moments(s_rr, s_zz, s_rz, mr, mz), lam)[1])
        assert min(ols, inverse) < b < max(ols, inverse)


def test_deming_normalisation_swap_and_vectorisation():
    rng = np.random.default_rng(13)
    r, z = noisy_line(rng, 12, -0.7, 0.1, 0.2)
    a0, b0 = deming_fit(*sums(r, z), 2.0)
    a1, b1 = deming_fit(*(3.0 * np.array(sums(r, z))), 2.0)  # every point counted thrice
    assert float(b0) == pytest.approx(float(b1), rel=1e-12)
    assert float(a0) == pytest.approx(float(a1), rel=1e-12)
    # swapping the axes and inverting lambda inverts the slope
    _, b_swap = deming_fit(*sums(z, r), 0.5)
    assert float(b_swap) == pytest.approx(1.0 / float(b0), rel=1e-12)
    # vectorised over many problems at once == one at a time
    probs = [noisy_line(rng, 10, s, 0.1, 0.1) for s in (-3, -0.5, 0.0, 0.4, 2.0)]
    mom = np.array([sums(*p) for p in probs]).T
    alphas, betas = deming_fit(*mom, 1.5)
    for i, p in enumerate(probs):
        a, b = deming_fit(*sums(*p), 1.5)
        assert alphas[i] == pytest.approx(float(a), rel=1e-14)
        assert betas[i] == pytest.approx(float(b), rel=1e-14)


def test_deming_degenerate_cases():
    # all points equal: no direction at all -> horizontal through the point
    alpha, beta = deming_fit(*from_moments(0.0, 0.0, 0.0, 4.0, -1.5), 1.0)
    assert float(beta) == 0.0 and float(alpha) == -1.5
    # exactly horizontal points
    alpha, beta = deming_fit(*from_moments(2.0, 0.0, 0.0, 4.0, -1.5), 1.0)
    assert float(beta) == 0.0 and float(alpha) == -1.5
    # exactly vertical points (same r): infinite slope, no exception
    with np.errstate(all='raise'):
        _, beta = deming_fit(*from_moments(0.0, 3.0, 0.0, 4.0, -1.5), 1.0)
    assert np.isinf(beta)
    # exact collinear points of any slope are recovered exactly, for any lambda
    r = np.array([1.0, 2.0, 4.0, 7.0])
    for slope in (-5.0, -0.25, 0.0, 0.01, 1.0, 12.0):
        for lam in (1e-3, 1.0, 1e3):
            alpha, beta = deming_fit(*sums(r, 2.0 + slope * r), lam)
            assert float(beta) == pytest.approx(slope, rel=1e-9, abs=1e-12)
            assert float(alpha) == pytest.approx(2.0, abs=1e-9)


def test_deming_beats_ols_on_steep_noisy_lines():
    rng = np.random.default_rng(2021)
    slope, sigma = 1.5, 0.1
    dem_err, ols_err = [], []
    for _ in range(200):
        r, z = noisy_line(rng, 200, slope, sigma, sigma, 0.0, 2.0)
        s_rr, s_zz, s_rz, mr, mz = moments(r, z)
        dem_err.append(float(deming_fit(*sums(r, z), 1.0)[1]) - slope)
        ols_err.append(s_rz / s_rr - slope)
    dem_err, ols_err = np.array(dem_err), np.array(ols_err)
    assert np.mean(np.abs(dem_err)) < 0.7 * np.mean(np.abs(ols_err))
    # why: OLS is attenuated (biased flat) by the noise in r, Deming is not
    assert np.mean(ols_err) < -3 * np.std(ols_err) / math.sqrt(200)
    assert abs(np.mean(dem_err)) < 3 * np.std(dem_err) / math.sqrt(200)


# --------------------------------------------------------------------------------------------
# extract_lines on a hand-built segment
# --------------------------------------------------------------------------------------------
def hand_segment():
    """(r, z, rho) of one segment, 17 bins (one empty), five lines with known breaks:

    bins 0-5   line A: z = 0.05 r, r = 2..6, bin 2 empty
    bin  6     0.5 m step up                        -> critical by distance
    bins 6-8   line B: z = 0.15 + 0.1 r, r = 7..9
    bin  9     r = 16, on line B's extension       -> critical by radial gap (7 m)
    bins 9-11  line C: same equation, r = 16..18
    bin 12     r = 19, on the same line, rho x10   -> critical by density jump
    bin 12     line D: one point (no slope)
    bin 13     1 m above: chord slope 1.0          -> critical by slope
    bins 13-16 line E: z = 7.05 - 0.2 r, r = 20..23
    """
    r = np.array([2, 3, NAN, 4, 5, 6, 7, 8, 9, 16, 17, 18, 19, 20, 21, 22, 23], dtype=float)
    z = np.full_like(r, NAN)
    z[:6] = 0.05 * r[:6]
    z[6:13] = 0.15 + 0.1 * r[6:13]
    z[13:] = 7.05 - 0.2 * r[13:]
    rho = np.ones_like(r)
    rho[12:] = 10.0
    rho[2] = 0.0  # empty bin, as the grid reports it
    return r, z, rho


def run(r, z, rho, **overrides):
    kw = dict(KW, **overrides)
    return extract_lines(np.atleast_2d(r), np.atleast_2d(z), np.atleast_2d(rho), **kw)


def test_hand_built_segment_lines_and_critical_points():
    r, z, rho = hand_segment()
    out = run(r, z, rho)
    np.testing.assert_array_equal(out.line_id[0],
                                  [0, 0, -1, 0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 4, 4, 4, 4])
    np.testing.assert_array_equal(np.flatnonzero(out.is_critical[0]), [6, 9, 12, 13])
    expected_slope = np.array([0.05] * 6 + [0.1] * 6 + [NAN] + [0.2] * 4)
    expected_slope[2] = NAN
    np.testing.assert_allclose(out.slope[0], expected_slope, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(out.line_slope, [0.05, 0.1, 0.1, NAN, -0.2], rtol=1e-9,
                               equal_nan=True)
    np.testing.assert_allclose(out.intercept, [0.0, 0.15, 0.15, NAN, 7.05], atol=1e-9,
                               equal_nan=True)
    np.testing.assert_array_equal(out.line_count, [5, 3, 3, 1, 4])
    np.testing.assert_array_equal(out.line_r_range,
                                  [[2, 6], [7, 9], [16, 18], [19, 19], [20, 23]])
    # slope of the current line just before each candidate joins: NaN until it has 2 points
    np.testing.assert_allclose(
        out.slope_before[0], [NAN, NAN, NAN, 0.05, 0.05, 0.05, 0.05, NAN, 0.1, 0.1, NAN, 0.1,
                              0.1, NAN, NAN, -0.2, -0.2], rtol=1e-9, equal_nan=True)


@pytest.mark.parametrize('bin_index,relaxed', [
    (6, dict(max_distance_m=1.0)),  # step of 0.5 m
    (9, dict(max_gap_m=8.0)),  # gap of 7 m
    (12, dict(max_density_jump=20.0)),  # jump x10
    (13, dict(max_slope=1.5)),  # chord slope 1.0
])
def test_each_critical_point_has_the_designed_cause(bin_index, relaxed):
    r, z, rho = hand_segment()
    base = run(r, z, rho).is_critical[0]
    out = run(r, z, rho, **relaxed).is_critical[0]
    assert base[bin_index] and not out[bin_index]
    # the breaks before it are untouched
    np.testing.assert_array_equal(out[:bin_index], base[:bin_index])


def test_tightened_thresholds_add_breaks():
    r, z, rho = hand_segment()
    # slope 0.05 lines break everywhere when zeta_b is below it
    out = run(r, z, rho, max_slope=0.04)
    assert out.is_critical[0, [1, 3, 4, 5]].all()
    # a 0.5 m gap limit breaks at every 1 m step; the gap over the empty bin 2 is measured
    # between the present candidates (r 3 -> 4), so bin 3 breaks like the others
    out = run(r, z, rho, max_gap_m=0.5)
    assert out.is_critical[0, [1, 3, 4, 5]].all()
    # a 1.5 m gap limit keeps line A whole across the empty bin
    out = run(r, z, rho, max_gap_m=1.5)
    assert not out.is_critical[0, :6].any()


def canonical(line_id):
    """Line ids renumbered by first appearance (ids are frame-global)."""
    mapping, out = {}, np.full_like(line_id, -1)
    for k, v in enumerate(line_id):
        if v >= 0:
            out[k] = mapping.setdefault(int(v), len(mapping))
    return out


def ramp_segment(rng, n=32, angle_deg=15.0, sigma=0.02):
    r_true = np.linspace(3.0, 40.0, n) + rng.uniform(-0.3, 0.3, n)
    r = r_true + rng.normal(0, sigma, n)
    z = -1.7 + math.tan(math.radians(angle_deg)) * r_true + rng.normal(0, sigma, n)
    rho = 100.0 / r ** 2 * rng.lognormal(0, 0.3, n)
    return r, z, rho


def test_segments_advance_independently():
    rng = np.random.default_rng(4)
    n = 17
    hr, hz, hrho = hand_segment()
    rows = [hand_segment()]
    rows.append(ramp_segment(rng, n))
    # the hand pattern shifted two bins outwards (different columns break)
    sr, sz, srho = (np.concatenate([[NAN, NAN], a[:-2]]) for a in (hr, hz, hrho))
    rows.append((sr, sz, srho))
    rows.append((np.full(n, NAN), np.full(n, NAN), np.zeros(n)))  # empty segment
    noisy_r = np.sort(rng.uniform(1, 60, n))
    noisy = (noisy_r, rng.normal(0, 0.5, n) + 0.2 * noisy_r, rng.lognormal(0, 1.5, n))
    holes = rng.random(n) < 0.3
    noisy[0][holes] = NAN
    noisy[1][holes] = NAN
    rows.append(noisy)
    cand_r = np.stack([row[0] for row in rows])
    cand_z = np.stack([row[1] for row in rows])
    rho = np.stack([row[2] for row in rows])
    together = extract_lines(cand_r, cand_z, rho, **KW)
    # ids are unique across the frame
    ids = [set(together.line_id[i][together.line_id[i] >= 0]) for i in range(len(rows))]
    assert sum(len(s) for s in ids) == len(set().union(*ids)) == together.line_count.size
    for i, (r, z, rr) in enumerate(rows):
        alone = extract_lines(r[None], z[None], rr[None], **KW)
        np.testing.assert_array_equal(canonical(together.line_id[i]),
                                      canonical(alone.line_id[0]))
        np.testing.assert_array_equal(together.is_critical[i], alone.is_critical[0])
        np.testing.assert_allclose(together.slope[i], alone.slope[0], rtol=1e-12,
                                   equal_nan=True)
        # per-line parameters match through the id mapping
        for k in np.flatnonzero(together.line_id[i] >= 0):
            a, b = together.line_id[i, k], alone.line_id[0, k]
            np.testing.assert_allclose([together.intercept[a], together.line_slope[a]],
                                       [alone.intercept[b], alone.line_slope[b]], rtol=1e-12,
                                       atol=1e-12, equal_nan=True)
            assert together.line_count[a] == alone.line_count[b]
    assert not together.is_critical[3].any() and (together.line_id[3] == -1).all()


@pytest.mark.parametrize('seed', range(5))
def test_noisy_15_degree_ramp_is_one_line(seed):
    rng = np.random.default_rng(100 + seed)
    r, z, rho = ramp_segment(rng)
    out = run(r, z, rho)
    assert not out.is_critical.any()
    assert np.unique(out.line_id).size == 1
    assert out.line_count.tolist() == [32]
    np.testing.assert_allclose(out.slope, math.tan(math.radians(15.0)), atol=0.005)
    assert out.intercept[0] == pytest.approx(-1.7, abs=0.1)


# --- compiled growing loop == numpy reference (bit for bit) ---------------------------------

def _assert_same_lines(a, b):
    for name in a.__dataclass_fields__:
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name


def _both(cand_r, cand_z, density, **kw):
    from conftest import compiled_and_reference
    return compiled_and_reference(extract_lines, cand_r, cand_z, density, **dict(KW, **kw))


@pytest.mark.parametrize('seed', range(6))
def test_compiled_growing_equals_the_numpy_reference_on_random_candidates(seed):
    rng = np.random.default_rng(seed)
    m, n = 40, 24
    r = np.sort(rng.uniform(2.0, 60.0, (m, n)), axis=1)
    # ground rising with r, steps, spikes and noise; empty bins, empty segments and columns;
    # zero densities (ratio inf / NaN) and equal r (vertical chords)
    z = 0.05 * r + rng.choice([0.0, 0.4, -0.3, 2.0], (m, n), p=[.7, .1, .1, .1]) \
        + rng.normal(0, 0.03, (m, n))
    r[:, 5] = r[:, 4]
    density = rng.choice([0.0, 1.0, 20.0, 300.0], (m, n)) * rng.uniform(0.5, 2.0, (m, n))
    empty = rng.random((m, n)) < 0.3
    empty[3] = True
    empty[:, 7] = True
    r[empty], z[empty] = np.nan, np.nan
    compiled, reference = _both(r, z, density, max_gap_m=float(rng.uniform(1.0, 8.0)))
    assert reference.intercept.size > m  # many lines: every kind of break happens
    _assert_same_lines(compiled, reference)


@pytest.mark.parametrize('source', ['sensors/velodyne_vlp16.pcd', 'sensors/hesai_xt32.pcd',
                                    'kitti_sequnknown_spvnas_000000.bin', 'mixed'])
def test_compiled_growing_equals_the_numpy_reference_on_real_candidates(source):
    from conftest import candidate_grid
    g, p = candidate_grid(source)
    compiled, reference = _both(
        g.candidate_r, g.candidate_z, g.density, variance_ratio=p.deming_variance_ratio,
        max_slope=p.line_max_slope, max_distance_m=p.line_max_distance_m,
        max_gap_m=p.line_max_gap_m, max_density_jump=p.line_max_density_jump)
    _assert_same_lines(compiled, reference)
