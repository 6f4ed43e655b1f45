# SPDX-License-Identifier: Apache-2.0
"""Probe (issues 10, 14): the labelled real scans made to look like other sensors and pipelines.

Usage::

    python benchmarks/probe_perturbed.py [--no-write]

The defaults were chosen on the shared labelled scans; clouds nobody tuned on come from other
LiDARs (fewer beams), other drivers and filters (voxel grids, dropped returns) and noisier
units. This script derives such clouds from the labelled scans themselves, so that their
labels still hold, and scores this project (``SegmenterParams()`` defaults, no mount height)
and Patchwork++ (bench_quality's settings: its defaults with the mount height, RNR on the
KITTI scans) on each, cold, in one run:

* ``as recorded``;
* ``voxel grid 6 cm``: the first point of every 6 cm voxel (an xyz-only voxel filter);
* ``every 2nd ring`` / ``every 4th ring``: a 32- and a 16-beam sensor with the same field of
  view. The ring of a point is its row in RELLIS-3D's organised cloud (64 x 2048) and, in a
  KITTI scan (stored ring after ring), the number of times the azimuth wrapped around before
  it (a few spurious wraps make a ring ~65-69; close enough to thin the beams);
* ``half the returns``: every point kept with probability 1/2 (seed 0);
* ``range noise 3 cm``: every point moved along its ray by a N(0, 3 cm) error (seed 0).

Pooled P / R / F1 per data set (SemanticKITTI: the 4 labelled scans; RELLIS-3D: its scan);
scoring as bench_quality.py. Nothing here changes the core or chooses a default.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_quality  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation.tools.evaluation import pooled_metrics  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
SECTION = 'probe_perturbed'
VOXEL_M = 0.06
RANGE_NOISE_M = 0.03
RELLIS_COLUMNS = 2048  # RELLIS-3D's Ouster OS1-64 clouds: 64 rows of 2048 columns


def rings(points: np.ndarray, organised_columns: int | None = None) -> np.ndarray:
    """Ring (beam) index of every point (module docstring): the row of an organised cloud of
    ``organised_columns`` columns, else the azimuth wraps counted along a KITTI-ordered scan."""
    n_points = len(points)
    if organised_columns:
        return np.arange(n_points) // organised_columns
    step = np.diff(np.arctan2(points[:, 1], points[:, 0]))
    wrapped = step < -np.pi  # a KITTI ring runs from -pi to pi ...
    if np.count_nonzero(step > np.pi) > np.count_nonzero(wrapped):
        wrapped = step > np.pi  # ... or the other way round
    out = np.zeros(n_points, dtype=np.int64)
    out[1:] = np.cumsum(wrapped)
    return out


def voxel_first(points: np.ndarray, voxel_m: float = VOXEL_M) -> np.ndarray:
    """Sorted indices of the first point of every ``voxel_m`` voxel (x, y, z)."""
    key = np.floor(points[:, :3] / voxel_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def with_range_noise(points: np.ndarray, std_m: float = RANGE_NOISE_M, seed: int = 0):
    """A copy of ``points`` with each moved along its ray by N(0, std_m); (0, 0, 0) stays."""
    rng = np.random.default_rng(seed)
    out = points.copy()
    xyz = points[:, :3].astype(np.float64)
    norm = np.linalg.norm(xyz, axis=1)
    scale = np.where(norm > 0, 1.0 + rng.normal(0.0, std_m, norm.size) / np.maximum(norm, 1e-9),
                     1.0)
    out[:, :3] = (xyz * scale[:, None]).astype(points.dtype)
    return out


def _frame_rings(frame):
    return rings(frame.points, RELLIS_COLUMNS if frame.name.startswith('rellis') else None)


def _subset(frame, keep: np.ndarray):
    return dataclasses.replace(frame, points=np.ascontiguousarray(frame.points[keep]),
                               truth=frame.truth[keep], evaluated=frame.evaluated[keep])


def every_nth_ring(n: int):
    def thin(frame):
        return _subset(frame, _frame_rings(frame) % n == 0)
    return thin


def half_the_returns(frame):
    return _subset(frame, np.random.default_rng(0).random(len(frame.points)) < 0.5)


PERTURBATIONS = (('as recorded', lambda frame: frame),
                 (f'voxel grid {VOXEL_M * 100:.0f} cm',
                  lambda frame: _subset(frame, voxel_first(frame.points))),
                 ('every 2nd ring', every_nth_ring(2)),
                 ('every 4th ring', every_nth_ring(4)),
                 ('half the returns', half_the_returns),
                 (f'range noise {RANGE_NOISE_M * 100:.0f} cm',
                  lambda frame: dataclasses.replace(frame,
                                                    points=with_range_noise(frame.points))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args(argv)
    data = [('SemanticKITTI (4 scans)', [f for ds in (common.load_labeled_kitti(),
                                                      common.load_kitti00_labeled()) if ds
                                         for f in ds.frames]),
            ('RELLIS-3D (1 scan)', [f for ds in (common.load_rellis(),) if ds for f in ds.frames])]
    data = [(name, frames) for name, frames in data if frames]
    if not data:
        sys.exit('probe_perturbed: no labelled scans found in ../shared/data')
    rows = []
    for label, perturb in PERTURBATIONS:
        for data_name, frames in data:
            changed = [perturb(frame) for frame in frames]
            # cold: a fresh instance per scan, bench_quality's settings for each method
            ours, theirs = (pooled_metrics(bench_quality.run_frames(key, changed))
                            for key in ('gp', 'patchworkpp'))
            points = [len(frame.points) for frame in changed]
            rows.append([label, data_name, f'{int(np.mean(points)):,}',
                         *(f'{m["precision"]:.3f} / {m["recall"]:.3f} / {m["f1"]:.3f}'
                           for m in (ours, theirs)),
                         f'{ours["f1"] - theirs["f1"]:+.3f}'])
            print(' | '.join(rows[-1]), flush=True)
    table = common.markdown_table(
        ['cloud', 'data', 'points per scan', 'this project P / R / F1',
         'Patchwork++ P / R / F1', 'F1 ours - Patchwork++'], rows)
    text = ('## Labelled scans made to look like other sensors (`probe_perturbed.py`)\n\n'
            + common.machine_markdown(common.command_line()) + '\n'
            + 'Cold (a fresh instance per scan), pooled per data set; this project with '
              '`SegmenterParams()` defaults, Patchwork++ with bench_quality.py\'s settings. '
              'What each cloud is: the script\'s docstring. Not used to choose any default.\n\n'
            + table + '\n')
    print(text)
    if not args.no_write:
        common.update_results_section(RESULTS, SECTION, text)


if __name__ == '__main__':
    main()
