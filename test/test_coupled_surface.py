# SPDX-License-Identifier: Apache-2.0
"""The coupled surface (core/coupled_surface.py): the borders' GP against hand-computed values
and its compiled twin, the points' heights between the borders, and ground sloping across the
beams."""

import math

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core import compiled
from gp_ground_segmentation.core.coupled_surface import (BETWEEN, BORDERS, _left_borders,
                                                         border_azimuths)
from gp_ground_segmentation.core.paciorek import paciorek_2d

SIGMA_F, SIGMA_N, MEAN, DEFAULT = 0.5, 0.05, -1.7, -1.75


def _one_candidate(m_count=8, n_bins=3):
    """One training candidate (point 0) in segment 0, bin 1, length factor 3 (gain 1), no
    anchor; every segment's edges at r = 2, 4, 6, 8."""
    phi = -np.pi + 0.5 * 2 * np.pi / m_count  # segment 0's centre
    x, y = np.array([5 * math.cos(phi)]), np.array([5 * math.sin(phi)])
    index = np.full((m_count, n_bins), -1, dtype=np.intp)
    index[0, 1] = 0
    cand_z = np.full((m_count, n_bins), np.nan)
    cand_z[0, 1] = -1.5
    d = np.full((m_count, n_bins), np.nan)
    d[0, 1] = 3.0
    edges = np.tile([2.0, 4.0, 6.0, 8.0], (m_count, 1))
    return (x, y, index, cand_z, d, index >= 0, edges, 1.0, 2.0, SIGMA_F, SIGMA_N, MEAN,
            DEFAULT, 0.0, 0.0, np.ones(m_count), np.zeros(m_count, dtype=bool))


@pytest.mark.parametrize('use_compiled', [False, True])
def test_one_candidate_border_is_the_closed_form(use_compiled):
    if use_compiled and not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    args = _one_candidate()
    lattice = BORDERS.run(use_compiled, *args)
    # borders 0 (segments 0 | 1) and 7 (7 | 0) see the candidate, with one length scale 3 m:
    # m + k(p, c) (z - m) / (sigma_f^2 + sigma_n^2), k(p, c) = sigma_f^2 exp(-|p - c|^2 / 18)
    for b in (0, 7):
        phi = border_azimuths(8)[b]
        want = []
        for r in (2.0, 4.0, 6.0, 8.0):
            d2 = (r * math.cos(phi) - args[0][0]) ** 2 + (r * math.sin(phi) - args[1][0]) ** 2
            kernel = SIGMA_F ** 2 * math.exp(-d2 / 18.0)
            want.append(MEAN + kernel * (-1.5 - MEAN) / (SIGMA_F ** 2 + SIGMA_N ** 2))
        right_of, left_of = b, (b + 1) % 8  # border b is segment b's right, b + 1's left
        np.testing.assert_allclose(lattice[right_of, 1], want, rtol=1e-12)
        np.testing.assert_allclose(lattice[left_of, 0], want, rtol=1e-12)
    # the other borders have no training point: the default height
    assert (lattice[2:7] == DEFAULT).all() and (lattice[1, 1] == DEFAULT).all()


def test_kernel_is_the_2d_paciorek():
    # l_i = l_j: the prefactor is 1 and k = sigma_f^2 exp(-d^2 / 2 l^2)
    assert paciorek_2d(3.0, 4.0, 2.0, 2.0, 0.25) == pytest.approx(0.25 * math.exp(-25 / 8))
    # the prefactor is the 1-D one squared: 2 l_i l_j / (l_i^2 + l_j^2)
    assert paciorek_2d(0.0, 0.0, 1.0, 3.0, 1.0) == pytest.approx(0.6)


def _random_frame(rng, m_count=16, n_bins=6, one_length=False):
    """A random frame's arguments: 70 % of the bins train, segment 3 and segments 9-10 none
    (9 | 10 without the anchor: a border without a model)."""
    shape = (m_count, n_bins)
    phi = -np.pi + (np.arange(m_count)[:, None] + rng.random(shape)) * 2 * np.pi / m_count
    r = np.sort(rng.uniform(2.0, 40.0, shape), axis=1)
    x, y = (r * np.cos(phi)).ravel(), (r * np.sin(phi)).ravel()
    index = np.arange(r.size, dtype=np.intp).reshape(shape)
    training = rng.random(shape) < 0.7
    training[3] = False
    training[9:11] = False
    d = np.full(shape, 2.0) if one_length else rng.uniform(0.3, 3.0, shape)
    r_min = rng.uniform(1.0, 3.0, m_count)
    edges = r_min[:, None] + np.arange(n_bins + 1) * rng.uniform(3.0, 7.0, m_count)[:, None]
    anchor_on = rng.random(m_count) < 0.8
    anchor_on[9:11] = False
    return (x, y, index, -1.7 + 0.2 * rng.standard_normal(shape), d, training, edges, 3.0, 2.0,
            0.6, 0.05, -1.6, -1.65, -1.72, 0.09,
            np.full(m_count, 2.0) if one_length else rng.uniform(0.3, 3.0, m_count), anchor_on)


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('one_length', [False, True])
def test_borders_twins_agree_to_round_off(one_length):
    args = _random_frame(np.random.default_rng(7), one_length=one_length)
    reference, got = BORDERS.reference(*args), BORDERS.kernel(*args)
    # border 9 (segments 9 | 10) has no training point: both take the default height there
    assert (reference[9, 1] == -1.65).all() and (reference[10, 0] == -1.65).all()
    assert np.isfinite(reference).all()
    np.testing.assert_allclose(got, reference, rtol=1e-10, atol=1e-10)


def test_left_border_is_read_at_the_segments_own_edges():
    border = np.array([[0.0, 1.0, 2.0], [10.0, 20.0, 30.0], [5.0, 5.0, 5.0]])
    edges = np.array([[1.0, 2.0, 3.0], [0.5, 1.5, 2.5], [2.0, 4.0, 6.0]])
    left = _left_borders(border, edges)
    # segment 1's left border is border 0 (knots at segment 0's edges 1, 2, 3): at 0.5 held at
    # its first knot, at 1.5 halfway between 0 and 1, at 2.5 halfway between 1 and 2
    np.testing.assert_allclose(left[1], [0.0, 0.5, 1.5])
    # segment 0's left border is border 2 (they wrap around), constant 5
    np.testing.assert_allclose(left[0], [5.0, 5.0, 5.0])


def _between_args(dtype, threshold=0.25):
    """Two segments of two bins; segment 0: left border 0 everywhere, right border 1 at its
    inner edges and 3 at the outer one."""
    lattice = np.zeros((2, 2, 3))
    lattice[0, 1] = [1.0, 1.0, 3.0]
    width = np.pi  # two segments: segment 0 spans [-pi, 0)
    angle = np.array([-np.pi, -np.pi + 0.5 * width, -np.pi + 0.25 * width, -1e-9, -np.pi])
    z = np.array([0.2, 0.8, 0.5, 1.3, 0.0], dtype=dtype)
    return (lattice, np.zeros(5, dtype=np.int32), np.array([0, 0, 1, 0, 1], dtype=np.int32),
            np.array([0.5, 0.5, 0.5, 0.0, 1.0], dtype=dtype), angle, z,
            np.dtype(dtype).type(threshold))


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_points_between_borders_by_hand(dtype):
    z_hat, ground = BETWEEN.reference(*_between_args(dtype))
    assert z_hat.dtype == dtype
    # at the left border: the left border's 0; halfway in azimuth: half the right border's 1;
    # a quarter of the way in bin 1 halfway along r (right border 2 there): 0.5; at the right
    # border's inner edge: 1; at the left border, end of bin 1: 0
    np.testing.assert_allclose(z_hat, [0.0, 0.5, 0.5, 1.0, 0.0], atol=1e-6)
    # the label rule: z - z_hat <= 0.25 (0.2, 0.3, 0.0, 0.3, 0.0 above the ground)
    assert ground.tolist() == [True, False, True, False, True]


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_between_twins_agree_bit_for_bit(dtype):
    rng = np.random.default_rng(11)
    m_count, n_bins, n_points = 12, 5, 5000
    segment = rng.integers(0, m_count, n_points).astype(np.int32)
    angle = -np.pi + (segment + rng.random(n_points)) * 2 * np.pi / m_count
    args = (rng.standard_normal((m_count, 2, n_bins + 1)), segment,
            rng.integers(0, n_bins, n_points).astype(np.int32),
            rng.random(n_points).astype(dtype), angle,
            rng.standard_normal(n_points).astype(dtype), np.dtype(dtype).type(0.25))
    reference = BETWEEN.reference(*args)
    for a, b in zip(BETWEEN.kernel(*args), reference):
        assert np.array_equal(a, b) and a.dtype == b.dtype


def _cross_slope_scan(slope=0.25, mount=1.73):
    """Flat-ring returns of an HDL-64E-like fan on a plane rising across the beams:
    z = slope * y - mount (exact truth: every return is ground)."""
    points = []
    for elev in np.radians(np.linspace(-24.8, -1.0, 48)):
        for az in np.radians(np.arange(-180.0, 180.0, 0.2)):
            # the ray (cos e cos a, cos e sin a, sin e) t meets z = slope y - mount at t
            denominator = math.sin(elev) - slope * math.cos(elev) * math.sin(az)
            if denominator >= -1e-6:
                continue
            t = -mount / denominator
            if t * math.cos(elev) < 60.0:
                points.append((t * math.cos(elev) * math.cos(az),
                               t * math.cos(elev) * math.sin(az), t * math.sin(elev)))
    return np.asarray(points, dtype=np.float32)


def test_ground_sloping_across_the_beams_is_followed():
    points = _cross_slope_scan()
    truth_z = 0.25 * points[:, 1] - 1.73
    errors, recall = {}, {}
    for on in (False, True):
        # the threshold of the first versions (0.2 m): the contrast in recall is clearer
        params = SegmenterParams(use_coupled_surface=on, use_cross_slope_threshold=False,
                                 ground_threshold_m=0.2)
        result = GroundSegmenter(params).segment(points)
        errors[on] = np.abs(result.ground_height - truth_z)
        recall[on] = result.ground_mask.mean()
    # the per-segment height is off by up to the rise across a segment (measured: median
    # 0.020 m, 90 % within 0.078 m, recall 0.988); the coupled one follows the plane between
    # the borders (0.002 m, 0.004 m, recall 1.000): the high side of each segment is found
    assert np.median(errors[True]) < 0.2 * np.median(errors[False])
    assert np.quantile(errors[True], 0.9) < 0.25 * np.quantile(errors[False], 0.9)
    assert recall[False] < 0.99 < 0.998 < recall[True]
