# SPDX-License-Identifier: Apache-2.0
"""Probe (issue 10): would a local roughness test after ``structure`` raise precision robustly?

Usage::

    python benchmarks/probe_local_roughness.py

Segments every frame of quality_quick.py's units cold with the defaults, then, as a
post-process on the labels (nothing here is in the core), relabels as obstacle the ground
points of small polar cells (``deg`` of azimuth x ``dr`` m of range) whose ground points
spread more than ``s`` m, either about their mean height above the predicted ground
(``std``) or about a plane fitted to them (``plane``, like Patchwork++'s flatness test; the
smallest eigenvalue's direction replaced by a least-squares z(x, y) plane). ``all`` drops
the whole cell, ``upper`` only its points above the cell's mean / plane. Prints the pooled F1
per unit and its change vs the defaults. A test is a robust gain only when no unit loses.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import quality_quick  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402


def rough_points(x, y, h, ground, deg, dr, spread_m, kind, mode, min_count=4):
    """Bool mask of the ``ground`` points in rough cells (see the module docstring)."""
    idx = np.flatnonzero(ground)
    azimuth = ((np.arctan2(y[idx], x[idx]) + np.pi) / np.radians(deg)).astype(np.int64)
    ring = (np.hypot(x[idx], y[idx]) / dr).astype(np.int64)
    _, cell, count = np.unique(azimuth * 100000 + ring, return_inverse=True, return_counts=True)
    residual = h[idx] - (np.bincount(cell, h[idx]) / count)[cell]
    if kind == 'plane':
        dx = x[idx] - (np.bincount(cell, x[idx]) / count)[cell]
        dy = y[idx] - (np.bincount(cell, y[idx]) / count)[cell]
        normal = np.empty((count.size, 2, 2))
        normal[:, 0, 0] = np.bincount(cell, dx * dx) + 1e-3
        normal[:, 0, 1] = normal[:, 1, 0] = np.bincount(cell, dx * dy)
        normal[:, 1, 1] = np.bincount(cell, dy * dy) + 1e-3
        rhs = np.stack([np.bincount(cell, dx * residual), np.bincount(cell, dy * residual)], 1)
        coef = np.linalg.solve(normal, rhs[..., None])[..., 0]
        residual = residual - coef[cell, 0] * dx - coef[cell, 1] * dy
    spread = np.sqrt(np.bincount(cell, residual * residual) / count)
    bad = (spread[cell] > spread_m) & (count[cell] >= min_count)
    if mode == 'upper':
        bad &= residual > 0
    out = np.zeros(ground.shape, dtype=bool)
    out[idx[bad]] = True
    return out


def main():
    frames = []  # (unit, frame, ground mask, height above ground, x, y)
    for unit, _, ds in quality_quick.load_units():
        for frame in ds.frames:
            result = GroundSegmenter(SegmenterParams()).segment(frame.points)
            frames.append((unit, frame, result.ground_mask, result.height_above_ground,
                           frame.points[:, 0].astype(float), frame.points[:, 1].astype(float)))
    units = list(dict.fromkeys(f[0] for f in frames))

    def pooled_f1(test):
        per_unit = {u: [] for u in units}
        for unit, frame, ground, h, x, y in frames:
            kept = ground if test is None else ground & ~test(x, y, h, ground)
            per_unit[unit].append(common.score(kept, frame))
        return np.array([common.pool(per_unit[u])['f1'] for u in units])

    base = pooled_f1(None)
    print('| test | ' + ' | '.join(units) + ' | mean | worst change |')
    print('| :--- |' + ' ---: |' * (len(units) + 2))
    print('| defaults | ' + ' | '.join(f'{v:.4f}' for v in base) + f' | {base.mean():.4f} | - |')
    for kind, deg, dr, spread_m, mode in itertools.product(
            ('std', 'plane'), (1.0, 2.0), (0.5, 1.0), (0.02, 0.03, 0.045, 0.06), ('all', 'upper')):
        f1 = pooled_f1(lambda x, y, h, g: rough_points(x, y, h, g, deg, dr, spread_m, kind, mode))
        change = f1 - base
        print(f'| {kind} {deg:g} deg x {dr:g} m, s {spread_m:g} m, {mode} | '
              + ' | '.join(f'{v:.4f} ({d:+.4f})' for v, d in zip(f1, change))
              + f' | {f1.mean():.4f} | {change.min():+.4f} |', flush=True)


if __name__ == '__main__':
    main()
