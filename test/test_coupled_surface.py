# SPDX-License-Identifier: Apache-2.0
"""The coupled surface (core/coupled_surface.py): the borders' GP against hand-computed values
and its compiled twin, the points' heights between the borders, and ground sloping across the
beams."""

import math

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core import compiled
from gp_ground_segmentation.core.coupled_surface import (BETWEEN, BORDERS, border_azimuths,
                                                         segment_borders)
from gp_ground_segmentation.core.paciorek import paciorek_2d

SIGMA_F, SIGMA_N, MEAN = 0.5, 0.05, -1.7


def _one_candidate(m_count=8, n_bins=3):
    """One training candidate in segment 0 (bin 1), no anchor; knots at r = 2, 4, 6, 8."""
    shape = (m_count, n_bins)
    cand = [np.zeros(shape) for _ in range(3)]
    phi = -np.pi + 0.5 * 2 * np.pi / m_count  # segment 0's centre
    cand[0][0, 1], cand[1][0, 1], cand[2][0, 1] = 5 * math.cos(phi), 5 * math.sin(phi), -1.5
    training = np.zeros(shape, dtype=bool)
    training[0, 1] = True
    knots = np.tile([2.0, 4.0, 6.0, 8.0], (m_count, 1))
    return (cand[0], cand[1], cand[2], np.full(shape, 3.0), training, knots,
            np.full(knots.shape, 4.0), SIGMA_F, SIGMA_N, MEAN, 0.0, 0.0, np.ones(m_count),
            np.zeros(m_count, dtype=bool))


def test_one_candidate_border_is_the_closed_form():
    args = _one_candidate()
    out = BORDERS.reference(*args)
    # border 0 (between segments 0 and 1) and border 7 (between 7 and 0) see the candidate;
    # m + k(p, c) (z - m) / (sigma_f^2 + sigma_n^2): k(c, c) = sigma_f^2 (equal L's)
    cx, cy = args[0][0, 1], args[1][0, 1]
    for b in (0, 7):
        phi = border_azimuths(8)[b]
        for k, r in enumerate([2.0, 4.0, 6.0, 8.0]):
            d2 = (r * math.cos(phi) - cx) ** 2 + (r * math.sin(phi) - cy) ** 2
            kernel = SIGMA_F ** 2 * (2 * 4.0 * 3.0 / 25.0) * math.exp(-d2 / 25.0)
            want = MEAN + kernel * (-1.5 - MEAN) / (SIGMA_F ** 2 + SIGMA_N ** 2)
            assert out[b, k] == pytest.approx(want, rel=1e-12)
    # the other borders have no training point: no model (the caller's default height)
    assert np.isnan(out[1:7]).all()


def test_kernel_is_the_2d_paciorek():
    # l_i = l_j: the prefactor is 1 and k = sigma_f^2 exp(-d^2 / 2 l^2)
    assert paciorek_2d(3.0, 4.0, 2.0, 2.0, 0.25) == pytest.approx(0.25 * math.exp(-25 / 8))
    # the prefactor is the 1-D one squared: 2 l_i l_j / (l_i^2 + l_j^2)
    assert paciorek_2d(0.0, 0.0, 1.0, 3.0, 1.0) == pytest.approx(0.6)


def _random_frame(rng, m_count=16, n_bins=6):
    shape = (m_count, n_bins)
    phi = -np.pi + (np.arange(m_count)[:, None] + rng.random(shape)) * 2 * np.pi / m_count
    r = np.sort(rng.uniform(2.0, 40.0, shape), axis=1)
    training = rng.random(shape) < 0.7
    training[3] = False  # a segment without candidates
    training[9:11] = False  # two in a row without the anchor: a border without a model
    knots = np.sort(rng.uniform(1.0, 45.0, (m_count, n_bins + 1)), axis=1)
    anchor_on = rng.random(m_count) < 0.8
    anchor_on[9:11] = False
    return (r * np.cos(phi), r * np.sin(phi), -1.7 + 0.2 * rng.standard_normal(shape),
            rng.uniform(1.0, 10.0, shape), training, knots,
            rng.uniform(1.0, 10.0, knots.shape), 0.6, 0.05, -1.6, -1.72, 0.09,
            rng.uniform(1.0, 10.0, m_count), anchor_on)


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
def test_borders_twins_agree_to_round_off():
    args = _random_frame(np.random.default_rng(7))
    reference, got = BORDERS.reference(*args), BORDERS.kernel(*args)
    assert np.array_equal(np.isnan(reference), np.isnan(got))
    assert np.isnan(reference[9]).all() and np.isfinite(reference[8]).all()
    np.testing.assert_allclose(got, reference, rtol=1e-10, atol=1e-10)


def test_segment_borders_reads_the_left_border_at_its_own_edges():
    border = np.array([[0.0, 1.0, 2.0], [10.0, 20.0, 30.0], [5.0, 5.0, 5.0]])
    edges = np.array([[1.0, 2.0, 3.0], [0.5, 1.5, 2.5], [2.0, 4.0, 6.0]])
    lattice = segment_borders(border, edges)
    # segment 1's left border is border 0 (knots at segment 0's edges 1, 2, 3): at 0.5 held at
    # its first knot, at 1.5 halfway between 0 and 1, at 2.5 halfway between 1 and 2
    np.testing.assert_allclose(lattice[1, 0], [0.0, 0.5, 1.5])
    np.testing.assert_allclose(lattice[1, 1], border[1])  # its right border is border 1
    # segment 0's left border is border 2 (they wrap around), constant 5
    np.testing.assert_allclose(lattice[0, 0], [5.0, 5.0, 5.0])


def _between_args(dtype):
    """Two segments of two bins; segment 0: left border 0 everywhere, right border 1 at its
    inner edges and 3 at the outer one."""
    lattice = np.zeros((2, 2, 3))
    lattice[0, 1] = [1.0, 1.0, 3.0]
    width = np.pi  # two segments: segment 0 spans [-pi, 0)
    angle = np.array([-np.pi, -np.pi + 0.5 * width, -np.pi + 0.25 * width, -1e-9, -np.pi])
    return (lattice, np.zeros(5, dtype=np.int32), np.array([0, 0, 1, 0, 1], dtype=np.int32),
            np.array([0.5, 0.5, 0.5, 0.0, 1.0], dtype=dtype), angle)


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_points_between_borders_by_hand(dtype):
    z = BETWEEN.reference(*_between_args(dtype))
    assert z.dtype == dtype
    # at the left border: the left border's 0; halfway in azimuth: half the right border's 1;
    # a quarter of the way in bin 1 halfway along r (right border 2 there): 0.5; at the right
    # border's inner edge: 1; at the left border, end of bin 1: 0
    np.testing.assert_allclose(z, [0.0, 0.5, 0.5, 1.0, 0.0], atol=1e-6)


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_between_twins_agree_bit_for_bit(dtype):
    rng = np.random.default_rng(11)
    m_count, n_bins, n_points = 12, 5, 5000
    segment = rng.integers(0, m_count, n_points).astype(np.int32)
    angle = -np.pi + (segment + rng.random(n_points)) * 2 * np.pi / m_count
    args = (rng.standard_normal((m_count, 2, n_bins + 1)), segment,
            rng.integers(0, n_bins, n_points).astype(np.int32),
            rng.random(n_points).astype(dtype), angle)
    reference = BETWEEN.reference(*args)
    assert np.array_equal(BETWEEN.kernel(*args), reference)
    assert BETWEEN.kernel(*args).dtype == reference.dtype


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
