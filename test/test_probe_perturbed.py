# SPDX-License-Identifier: Apache-2.0
"""The helpers of benchmarks/probe_perturbed.py that turn a labelled scan into another sensor's."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
import probe_perturbed as pp  # noqa: E402


def _kitti_ordered(n_rings, per_ring):
    """Points stored ring after ring, each ring sweeping the azimuth from -pi to pi."""
    azimuth = np.tile(np.linspace(-np.pi + 0.01, np.pi - 0.01, per_ring), n_rings)
    r = np.repeat(np.arange(n_rings) + 5.0, per_ring)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), np.zeros_like(r)], 1)


def test_rings_count_the_azimuth_wraps_of_a_kitti_ordered_scan():
    points = _kitti_ordered(3, 50)
    np.testing.assert_array_equal(pp.rings(points), np.repeat([0, 1, 2], 50))
    # a sensor sweeping the other way round
    np.testing.assert_array_equal(pp.rings(points[::-1]), np.repeat([0, 1, 2], 50))


def test_rings_of_an_organised_cloud_are_its_rows():
    np.testing.assert_array_equal(pp.rings(np.zeros((6, 3)), organised_columns=2),
                                  [0, 0, 1, 1, 2, 2])


def test_voxel_first_keeps_the_first_point_of_each_voxel():
    points = np.array([[0.01, 0.01, 0.0], [0.02, 0.03, 0.01], [0.07, 0.0, 0.0],
                       [-0.01, 0.0, 0.0], [0.03, 0.05, 0.05]])
    # voxels of 6 cm: points 0, 1, 4 share one; 2 and 3 have their own
    np.testing.assert_array_equal(pp.voxel_first(points, 0.06), [0, 2, 3])


def test_range_noise_moves_points_along_their_ray_and_keeps_no_returns():
    points = np.array([[10.0, 0.0, 0.0], [0.0, 0.0, 0.0], [3.0, 4.0, 0.0]], dtype=np.float32)
    noisy = pp.with_range_noise(points, std_m=0.5, seed=1)
    assert noisy.dtype == points.dtype
    np.testing.assert_array_equal(noisy[1], 0.0)
    for i in (0, 2):
        direction = points[i] / np.linalg.norm(points[i])
        moved = noisy[i] / np.linalg.norm(noisy[i])
        np.testing.assert_allclose(moved, direction, atol=1e-6)
        assert np.linalg.norm(noisy[i]) != np.linalg.norm(points[i])
