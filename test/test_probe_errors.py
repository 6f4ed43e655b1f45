# SPDX-License-Identifier: Apache-2.0
"""The helpers of benchmarks/probe_errors.py (where the defaults' errors lie on real scans)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
import probe_errors  # noqa: E402


def test_auc_is_the_chance_a_positive_exceeds_a_negative():
    # pairs (p, n): 3 > 1, 3 > 2, 0 < 1, 0 < 2 -> 2 of 4 pairs; ties count one half
    assert probe_errors.auc(np.array([3.0, 0.0]), np.array([1.0, 2.0])) == pytest.approx(0.5)
    assert probe_errors.auc(np.array([3.0, 4.0]), np.array([1.0, 2.0])) == pytest.approx(1.0)
    assert probe_errors.auc(np.array([1.0]), np.array([1.0])) == pytest.approx(0.5)
    assert np.isnan(probe_errors.auc(np.array([]), np.array([1.0])))


def test_top_classes_names_the_most_frequent_first():
    classes = np.array([70, 70, 70, 51, 51, 999])
    assert probe_errors.top_classes(classes, probe_errors.SEMANTIC_KITTI_NAMES, 2) == (
        'vegetation 3, fence 2')
    assert probe_errors.top_classes(np.array([999]), {}, 3) == '999 1'


def test_spread_is_median_and_10th_90th_percentiles():
    assert probe_errors.spread(np.arange(11, dtype=float)) == '5.00 [1.00, 9.00]'
    assert probe_errors.spread(np.array([])) == '-'


def test_real_scans_skip_missing_files(tmp_path, capsys):
    assert probe_errors.real_scans(tmp_path) == []
    assert 'skipped kitti_spvnas' in capsys.readouterr().err


def test_ground_beyond_feet_counts_low_points_farther_out_along_the_ray():
    # the foot at 10 m, azimuth 0; ground 1 m beyond (counted), ground 0.05 m beyond (too
    # close), 3 m beyond (too far), 1 m beyond but 0.3 m up (not ground) or 1 deg aside (another
    # ray), and 1 m nearer (not beyond)
    points = np.array([[10.0, 0.0], [11.0, 0.0], [10.05, 0.0], [13.0, 0.0], [11.0, 0.0],
                       [11.0 * np.cos(np.radians(1.0)), 11.0 * np.sin(np.radians(1.0))],
                       [9.0, 0.0]])
    h = np.array([0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0])
    counts = probe_errors.ground_beyond_feet(points, h, np.array([0]))
    assert counts.tolist() == [1]
    h[1] = np.nan  # no height: not ground
    assert probe_errors.ground_beyond_feet(points, h, np.array([0])).tolist() == [0]
    assert probe_errors.ground_beyond_feet(points, h, np.array([], dtype=int)).size == 0
