# SPDX-License-Identifier: Apache-2.0
"""Is interpolating the GP between bin edges as good as evaluating it at every point? (issue 3)

The segmenter evaluates the GP posterior mean at the N + 1 bin edges of each segment and
interpolates linearly along r for every raw point. This script evaluates the same posterior
directly at every valid point (a dense (points x candidates) kernel per segment, with the
length-scale factor of the point's bin) on the real frames and compares: height difference,
labels that change, and the time of the two ways. Both label sets go through the same
height test and the same vertical-structure test (its column heights measured from each way's
ground height), so only the interpolation differs.

    python benchmarks/bench_interpolation.py [--no-write]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from common import (REPO, command_line, load_labeled_kitti, machine_markdown, markdown_table,
                    real_frames, update_results_section)

from gp_ground_segmentation import GroundSegmenter  # noqa: E402 (path via common)
from gp_ground_segmentation.core.labels import is_ground  # noqa: E402
from gp_ground_segmentation.core.structure import structure_feet  # noqa: E402
from gp_ground_segmentation.tools.evaluation import truth_metrics  # noqa: E402


def direct_heights(result):
    """Posterior mean at every valid point, straight from the frame's GP."""
    d = result.details
    gp, sol, grid = d.gp, d.gp_solution, d.grid
    row_of = np.full(grid.num_segments, -1)
    row_of[gp.segments] = np.arange(gp.segments.size)
    rows = row_of[grid.point_segment]
    z_hat = np.full(grid.point_r.size, np.nan)
    order = np.argsort(rows, kind='stable')
    bounds = np.searchsorted(rows[order], np.arange(gp.segments.size + 1))
    start = time.perf_counter()
    for s in range(gp.segments.size):  # one dense GP evaluation per segment
        idx = order[bounds[s]:bounds[s + 1]]
        if idx.size == 0:
            continue
        r_star = grid.point_r[idx].astype(np.float64)[None, :]
        d_star = d.length_factor_at_edges[s][grid.point_bin[idx]][None, :]
        sub = _one_segment(gp, s)
        mean, _ = sub.predict(_one_solution(sol, s), r_star, d_star, with_std=False)
        z_hat[idx] = mean[0]
    elapsed_ms = (time.perf_counter() - start) * 1e3
    return z_hat, elapsed_ms


class _Row:
    """A one-segment view of a FrameGP batch, enough for FrameGP.predict."""

    def __init__(self, gp, s):
        self.d, self.r, self.valid = gp.d[s:s + 1], gp.r[s:s + 1], gp.valid[s:s + 1]
        self.counts = gp.counts[s:s + 1]
        self.mean = gp.mean
        self.backend = 'numpy'  # the dense reference prediction, whatever the frame used


def _one_segment(gp, s):
    from gp_ground_segmentation.core.gp import FrameGP
    row = _Row(gp, s)
    row.predict = FrameGP.predict.__get__(row)
    return row


def _one_solution(sol, s):
    from gp_ground_segmentation.core.gp import GPSolution
    return GPSolution(sol.theta, sol.alpha[s:s + 1], sol.a_inv[s:s + 1], sol.lml, sol.jitter,
                      None if sol.kernel is None else sol.kernel[s:s + 1])


def with_structure_test(seg, points, valid_index, ground_height, ground):
    """``ground`` minus the feet the segmenter's vertical-structure test finds with
    ``ground_height`` as the predicted ground (as segment() applies it after the height test)."""
    p = seg.params
    if not p.use_vertical_structure_test:
        return ground
    xyz = points[valid_index]
    feet = structure_feet(p, xyz[:, 0], xyz[:, 1], xyz[:, 2], ground_height.astype(xyz.dtype),
                          ground)
    return ground & ~feet


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    frames = real_frames()
    labeled = load_labeled_kitti()
    rows = []
    for frame in frames:
        seg = GroundSegmenter()
        seg.segment(frame.points)
        result = seg.segment(frame.points, details=True)
        d = result.details
        z = frame.points[d.valid_index, 2].astype(np.float64)
        interp = result.ground_height[d.valid_index]
        direct, direct_ms = direct_heights(result)
        diff = np.abs(direct - interp)
        ground_direct = with_structure_test(seg, frame.points, d.valid_index, direct,
                                            is_ground(z, direct, d.threshold))
        ground_interp = result.ground_mask[d.valid_index]
        changed = int(np.count_nonzero(ground_direct != ground_interp))
        f1 = '-'
        if labeled is not None and frame.name == labeled.frames[0].name:
            full = np.zeros(len(frame.points), bool)
            full[d.valid_index] = ground_direct
            m_direct = truth_metrics(full, frame.truth, frame.evaluated)['f1']
            m_interp = truth_metrics(result.ground_mask, frame.truth, frame.evaluated)['f1']
            f1 = f'{m_interp:.4f} / {m_direct:.4f}'
        rows.append([frame.name, f'{len(frame.points):,}', f'{np.median(diff) * 100:.2f}',
                     f'{np.percentile(diff, 99) * 100:.1f}', f'{diff.max() * 100:.1f}',
                     f'{changed:,} ({changed / len(z):.2%})',
                     f"{result.timings_ms['predict'] + result.timings_ms['label']:.1f}",
                     f'{direct_ms:.0f}', f1])
    table = markdown_table(['frame', 'points', 'abs(direct - interpolated) median cm', 'p99 cm',
                            'max cm', 'labels that change', 'edges + interpolation ms',
                            'direct ms', 'F1 interpolated / direct'], rows)
    print(table)
    if args.no_write:
        return 0
    text = ('## GP at every point vs interpolation between bin edges '
            '(`bench_interpolation.py`)\n\n' + machine_markdown(command_line()) + '\n'
            + 'Both label sets: the height test, then the vertical-structure test with that '
            "way's ground height.\n\n" + table + '\n')
    update_results_section(REPO / 'benchmarks' / 'RESULTS.md', 'bench_interpolation', text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
