# SPDX-License-Identifier: Apache-2.0
"""The helpers of benchmarks/probes.py: error analysis, scans made to look like other sensors,
ring-less scans."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
import probes  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402
from gp_ground_segmentation.tools.evaluation import truth_metrics  # noqa: E402


# ------------------------------------------------------------------------------------ errors

def test_auc_is_the_chance_a_positive_exceeds_a_negative():
    # pairs (p, n): 3 > 1, 3 > 2, 0 < 1, 0 < 2 -> 2 of 4 pairs; ties count one half
    assert probes.auc(np.array([3.0, 0.0]), np.array([1.0, 2.0])) == pytest.approx(0.5)
    assert probes.auc(np.array([3.0, 4.0]), np.array([1.0, 2.0])) == pytest.approx(1.0)
    assert probes.auc(np.array([1.0]), np.array([1.0])) == pytest.approx(0.5)
    assert np.isnan(probes.auc(np.array([]), np.array([1.0])))


def test_top_classes_names_the_most_frequent_first():
    classes = np.array([70, 70, 70, 51, 51, 999])
    assert probes.top_classes(classes, probes.SEMANTIC_KITTI_NAMES, 2) == (
        'vegetation 3, fence 2')
    assert probes.top_classes(np.array([999]), {}, 3) == '999 1'


def test_spread_is_median_and_10th_90th_percentiles():
    assert probes.spread(np.arange(11, dtype=float)) == '5.00 [1.00, 9.00]'
    assert probes.spread(np.array([])) == '-'


def test_real_scans_skip_missing_files(tmp_path, capsys):
    assert probes.real_scans(tmp_path) == []
    assert 'skipped kitti00_000000' in capsys.readouterr().err


def test_ground_beyond_feet_counts_low_points_farther_out_along_the_ray():
    # the foot at 10 m, azimuth 0; ground 1 m beyond (counted), ground 0.05 m beyond (too
    # close), 3 m beyond (too far), 1 m beyond but 0.3 m up (not ground) or 1 deg aside (another
    # ray), and 1 m nearer (not beyond)
    points = np.array([[10.0, 0.0], [11.0, 0.0], [10.05, 0.0], [13.0, 0.0], [11.0, 0.0],
                       [11.0 * np.cos(np.radians(1.0)), 11.0 * np.sin(np.radians(1.0))],
                       [9.0, 0.0]])
    h = np.array([0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0])
    counts = probes.ground_beyond_feet(points, h, np.array([0]))
    assert counts.tolist() == [1]
    h[1] = np.nan  # no height: not ground
    assert probes.ground_beyond_feet(points, h, np.array([0])).tolist() == [0]
    assert probes.ground_beyond_feet(points, h, np.array([], dtype=int)).size == 0


# ------------------------------------------------------------------------------------ perturbed

def _kitti_ordered(n_rings, per_ring):
    """Points stored ring after ring, each ring sweeping the azimuth from -pi to pi."""
    azimuth = np.tile(np.linspace(-np.pi + 0.01, np.pi - 0.01, per_ring), n_rings)
    r = np.repeat(np.arange(n_rings) + 5.0, per_ring)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), np.zeros_like(r)], 1)


def test_rings_count_the_azimuth_wraps_of_a_kitti_ordered_scan():
    points = _kitti_ordered(3, 50)
    np.testing.assert_array_equal(probes.rings(points), np.repeat([0, 1, 2], 50))
    # a sensor sweeping the other way round
    np.testing.assert_array_equal(probes.rings(points[::-1]), np.repeat([0, 1, 2], 50))


def test_rings_of_an_organised_cloud_are_its_rows():
    np.testing.assert_array_equal(probes.rings(np.zeros((6, 3)), organised_columns=2),
                                  [0, 0, 1, 1, 2, 2])


def test_voxel_first_keeps_the_first_point_of_each_voxel():
    points = np.array([[0.01, 0.01, 0.0], [0.02, 0.03, 0.01], [0.07, 0.0, 0.0],
                       [-0.01, 0.0, 0.0], [0.03, 0.05, 0.05]])
    # voxels of 6 cm: points 0, 1, 4 share one; 2 and 3 have their own
    np.testing.assert_array_equal(probes.voxel_first(points, 0.06), [0, 2, 3])


def test_range_noise_moves_points_along_their_ray_and_keeps_no_returns():
    points = np.array([[10.0, 0.0, 0.0], [0.0, 0.0, 0.0], [3.0, 4.0, 0.0]], dtype=np.float32)
    noisy = probes.with_range_noise(points, std_m=0.5, seed=1)
    assert noisy.dtype == points.dtype
    np.testing.assert_array_equal(noisy[1], 0.0)
    for i in (0, 2):
        direction = points[i] / np.linalg.norm(points[i])
        moved = noisy[i] / np.linalg.norm(noisy[i])
        np.testing.assert_allclose(moved, direction, atol=1e-6)
        assert np.linalg.norm(noisy[i]) != np.linalg.norm(points[i])


# ------------------------------------------------------------------------------------ rings

def test_ringless_scan_keeps_random_returns_inside_the_field_of_view():
    points, is_ground, returned = probes.ringless_scan('flat', 35.0, -35.0, 35.0)
    assert 0 < len(points) <= probes.POINTS_PER_SCAN
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    assert np.abs(azimuth).max() <= 35.0 and returned.all() and is_ground.any()
    # no regular rings: many elevations, irregularly spaced (a spinning sensor's are even)
    elevation = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    levels = np.unique(np.round(elevation, 2))
    gaps = np.diff(levels)
    assert levels.size > 100 and gaps.std() > 0.5 * gaps.mean()
    # the same seed gives the same scan
    again, _, _ = probes.ringless_scan('flat', 35.0, -35.0, 35.0)
    np.testing.assert_array_equal(points, again)


# (scene, minimum F1) in the forward 70 deg pattern; measured 0.998 and 0.985 (Patchwork++
# with the mount height: 0.933, 0.715)
@pytest.mark.parametrize('scene,min_f1', [('flat', 0.993), ('onslope15', 0.98)])
def test_ringless_forward_scans_are_segmented(scene, min_f1):
    points, is_ground, returned = probes.ringless_scan(scene, 35.0, -35.0, 35.0)
    result = GroundSegmenter(SegmenterParams()).segment(points[:, :3])
    assert truth_metrics(result.ground_mask, is_ground, returned)['f1'] >= min_f1
