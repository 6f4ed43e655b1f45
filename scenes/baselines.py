# SPDX-License-Identifier: Apache-2.0
"""Flat-ground baselines, to show what the GP's slope handling buys (tests and benchmarks).

Neither is meant for use on a vehicle: they are the simplest honest references.
"""

from __future__ import annotations

import numpy as np


def constant_height_ground(points: np.ndarray, threshold_m: float = 0.2) -> np.ndarray:
    """Ground = within ``threshold_m`` above the frame's ground level (a level plane).

    The ground level is the 5th percentile of the points nearest the sensor (r < 10 m), so no
    sensor height has to be known.
    """
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    near = xyz[r < 10.0, 2]
    level = np.percentile(near if near.size else xyz[:, 2], 5)
    return np.abs(xyz[:, 2] - level) <= threshold_m


def ransac_plane_ground(points: np.ndarray, threshold_m: float = 0.2, iterations: int = 200,
                        seed: int = 0) -> np.ndarray:
    """Ground = within ``threshold_m`` of the single plane with most inliers (RANSAC)."""
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    rng = np.random.default_rng(seed)
    # bias the samples towards low points, as ground-plane RANSAC implementations do
    low = xyz[xyz[:, 2] <= np.percentile(xyz[:, 2], 50)]
    best, best_count = None, -1
    sample = low[rng.integers(0, len(low), size=(iterations, 3))]
    normals = np.cross(sample[:, 1] - sample[:, 0], sample[:, 2] - sample[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals, sample = normals[ok] / norms[ok, None], sample[ok]
    subset = xyz[rng.integers(0, len(xyz), size=min(len(xyz), 20000))]
    for normal, p0 in zip(normals, sample[:, 0]):
        count = np.count_nonzero(np.abs((subset - p0) @ normal) <= threshold_m)
        if count > best_count:
            best, best_count = (normal, p0), count
    normal, p0 = best
    return np.abs((xyz - p0) @ normal) <= threshold_m
