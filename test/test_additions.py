# SPDX-License-Identifier: Apache-2.0
"""Unit tests of our additions to the paper (additions.py), with hand-computed expectations,
and of the switches that turn each one off in the segmenter."""

import numpy as np
import pytest

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core.additions import (elevated_plateaus, ground_under_sensor,
                                                   outlier_candidates, steep_line_candidates)
from scenes.synthetic import make_scene, simulate_scan

NAN = np.nan
PLATEAU = dict(step_up_m=0.3, max_slope=0.7, max_gap_m=6.0)


def plateaus(rows):
    """rows: (r, z, slope_before or None) per segment, padded with NaN to one (M, N) array."""
    n = max(len(r) for r, _, _ in rows)

    def pad(a):
        return np.concatenate([np.asarray(a, float), np.full(n - len(a), NAN)])
    cand_r = np.stack([pad(r) for r, _, _ in rows])
    cand_z = np.stack([pad(z) for _, z, _ in rows])
    slope = np.stack([pad(s if s is not None else [NAN] * len(r)) for r, _, s in rows])
    return elevated_plateaus(cand_r, cand_z, slope, **PLATEAU)


# (r, z, slope_before, expected elevated): each row one rule of the state machine
CASES = {
    # enter on a 1.5 m step up (chord 1.5 > 0.7), stay while high, leave on a 1.5 m drop
    'enter, stay, drop': ([2, 3, 4, 5, 6, 7, 8], [0, 0, 0, 1.5, 1.5, 1.5, 0.0], None,
                          [0, 0, 0, 1, 1, 1, 0]),
    # a 0.5 m rise over 1 m is a ramp (chord 0.5 < 0.7), a 0.2 m step a curb (rise < 0.3)
    'ramp and curb do not enter': ([2, 3, 4, 5, 5.1, 6], [0, 0, 0, 0.5, 0.7, 0.7], None,
                                   [0, 0, 0, 0, 0, 0]),
    # ground rising at 0.1 before the step (slope_before 0.1 at the step): the plateau comes
    # down slowly (no 0.3 m drop); it ends where z <= 0.4 + 0.1 (r - 4) + 0.3, at r = 10
    'back down to the extrapolated ground': (
        [2, 3, 4, 5, 6, 7, 8, 9, 10, 11], [0.2, 0.3, 0.4, 2.0, 2.0, 1.8, 1.6, 1.4, 1.2, 1.0],
        [NAN, NAN, 0.1, 0.1, NAN, NAN, NAN, NAN, NAN, NAN], [0, 0, 0, 1, 1, 1, 1, 1, 0, 0]),
    # the same heights with a flat line before the step: ground 0.4 + 0.3, still high at r = 10
    'flat ground before the step': (
        [2, 3, 4, 5, 6, 7, 8, 9, 10, 11], [0.2, 0.3, 0.4, 2.0, 2.0, 1.8, 1.6, 1.4, 1.2, 1.0],
        None, [0, 0, 0, 1, 1, 1, 1, 1, 1, 1]),
    # a radial gap of 8 m > zeta_m ends the plateau even though the next candidate is high
    'gap': ([2, 3, 4, 12, 13], [0, 0, 1.5, 1.6, 3.0], None, [0, 0, 1, 0, 1]),
    # empty bins inside the plateau do not end it
    'empty bins': ([2, 3, NAN, 5, NAN, 6], [0, 1.0, NAN, 1.0, NAN, 1.1], None,
                   [0, 1, 0, 1, 0, 1]),
}


@pytest.mark.parametrize('name', CASES)
def test_plateau_state_machine(name):
    r, z, slope, expected = CASES[name]
    got = plateaus([(r, z, slope)])[0, :len(r)]
    np.testing.assert_array_equal(got, np.asarray(expected, bool))


def test_plateau_segments_advance_independently():
    rows = [CASES[name][:3] for name in CASES]
    together = plateaus(rows)
    for i, name in enumerate(CASES):
        expected = np.asarray(CASES[name][3], bool)
        np.testing.assert_array_equal(together[i, :len(expected)], expected)
        assert not together[i, len(expected):].any()


def test_plateau_heights_far_from_the_sensor():
    """Heights are taken relative to each segment's first candidate: a plateau 500 m up the
    road (absolute z = 300 m) is found as at the origin."""
    r, z, slope, expected = CASES['back down to the extrapolated ground']
    got = plateaus([(np.add(r, 500.0), np.add(z, 300.0), slope)])[0]
    np.testing.assert_array_equal(got, np.asarray(expected, bool))


# --- ground under the sensor -----------------------------------------------------------------
def anchor_problem():
    """3 segments x 3 bins; lines 0..4 with intercepts and counts set by hand."""
    cand_z = np.array([[-1.7, -1.6, NAN], [2.0, -1.5, -1.4], [-1.6, NAN, NAN]])
    training = np.isfinite(cand_z)
    training[1, 0] = False  # a steep-line candidate: the segment's first *training* one is bin 1
    line_id = np.array([[0, 0, -1], [1, 2, 2], [3, -1, -1]])
    line_count = np.array([2, 1, 2, 1])
    intercept = np.array([-1.75, 2.0, -1.55, -1.6])
    return cand_z, training, line_id, line_count, intercept


def test_anchor_is_median_of_first_lines_intercepts():
    cand_z, training, line_id, line_count, intercept = anchor_problem()
    # segment 0: line 0 (-1.75); segment 1: line 2 (-1.55), not the steep line 1;
    # segment 2: line 3 has one candidate, no intercept estimate -> median(-1.75, -1.55)
    assert ground_under_sensor(cand_z, training, line_id, line_count,
                               intercept) == pytest.approx(-1.65)
    line_count[3] = 2
    assert ground_under_sensor(cand_z, training, line_id, line_count,
                               intercept) == pytest.approx(-1.6)


def test_anchor_fallbacks():
    cand_z, training, line_id, line_count, intercept = anchor_problem()
    # no first line with two candidates: median of the training candidates
    single = np.ones_like(line_count)
    assert ground_under_sensor(cand_z, training, line_id, single, intercept) == pytest.approx(
        np.median([-1.7, -1.6, -1.5, -1.4, -1.6]))
    # no training candidate: median of all candidates; no candidate: 0
    none = np.zeros_like(training)
    assert ground_under_sensor(cand_z, none, line_id, line_count,
                               intercept) == pytest.approx(-1.55)
    assert ground_under_sensor(np.full((2, 2), NAN), none[:2, :2], line_id, line_count,
                               intercept) == 0.0


# --- leave-one-out outliers and steep lines --------------------------------------------------
def test_outlier_thresholds_are_one_sided_each():
    loo = np.array([0.9, 0.7, -1.1, -0.9, NAN])
    np.testing.assert_array_equal(outlier_candidates(loo, above_m=0.8, below_m=1.0),
                                  [True, False, True, False, False])


def test_steep_line_mask():
    np.testing.assert_array_equal(steep_line_candidates(np.array([0.8, 0.7, NAN, 0.1]), 0.7),
                                  [True, False, False, False])


# --- switches in the segmenter ---------------------------------------------------------------
@pytest.fixture(scope='module')
def mixed_scan():
    return simulate_scan(make_scene('mixed'))


def run(points, **switches):
    params = SegmenterParams(optimizer_first_frame_evaluations=0, **switches)
    return GroundSegmenter(params).segment(points)


def test_each_switch_turns_its_addition_off(mixed_scan):
    pts = mixed_scan.points
    base = run(pts)
    assert base.stats['elevated_candidates'] > 0 and base.stats['outlier_candidates'] > 0
    assert 'anchor_height_m' in base.stats
    no_plateaus = run(pts, use_elevated_plateaus=False)
    assert no_plateaus.stats['elevated_candidates'] == 0
    assert no_plateaus.stats['training_candidates'] > base.stats['training_candidates']
    no_outliers = run(pts, use_outlier_rejection=False)
    assert no_outliers.stats['outlier_candidates'] == 0
    no_anchor = run(pts, use_anchor=False)
    assert 'anchor_height_m' not in no_anchor.stats
    for res in (no_plateaus, no_outliers, no_anchor):
        assert not np.array_equal(res.ground_mask, base.ground_mask)  # each one matters here
        assert res.ground_mask.any() and res.obstacle_mask.any()
