# SPDX-License-Identifier: Apache-2.0
"""How good is the GP ground surface (``SegmentationResult.ground_surface``)? Issue 11.

Usage::

    python benchmarks/bench_surface.py [--seeds N] [--no-write]

For every frame the segmenter runs twice on the same points (the second call warm-started, as in
a stream), then the surface is evaluated with ``height_at(x, y)`` at the true ground samples:

* synthetic scenes with exact ground (``scenes.synthetic``): flat, ramp10/15/20 (uphill ahead,
  downhill behind), hill, onslope15 (the whole scene on a 15 degree plane, a cross slope for most
  segments) and the randomised families crest, valley and cross_slope: truth = the analytic
  terrain height at the (x, y) of every point whose ray hit the terrain (curb faces left out);
* the real labelled scans (SemanticKITTI classes 40/44/48/49/60/72): truth = the z of every
  labelled ground point (a measurement, with the sensor's noise).

Columns: ``median |err|`` = median |z_hat - truth| (m); ``in +-2 z_std`` = fraction of samples
with |z_hat - truth| <= 2 z_std (z_std: std of the latent ground height, the GP's posterior std
and the spread across the segment, what the surface reports); for diagnosis, ``bias`` = median
signed z_hat - truth (m), ``in +-2 sqrt(z_std^2 + sigma_n^2)`` = the same fraction for the
predictive std of one measurement, and ``median z_std``; ``GP mean only`` = the same two figures
for the GP mean trained on the lowest points without the surface's ground offset (the labels'
z_hat), to show what the offset does. Samples outside the grid (height_at NaN) are counted in
``outside``.

On the real scans the truth points are the measurements the ground offset is averaged from (the
points labelled ground by the segmenter overlap the labelled ground), so those figures are
in-sample; the synthetic truth is the analytic terrain, independent of the measured points.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
SYNTHETIC_SCENES = ('flat', 'ramp10', 'ramp15', 'ramp20', 'hill', 'onslope15')
FAMILIES = ('crest', 'valley', 'cross_slope')


def frame_row(name, points, samples, truth, params):
    """Table row of one frame: the surface at the sample points (bool mask over ``points``)
    against ``truth``, after a warm-started second call; also the GP mean without the ground
    offset (the labels' z_hat, ``result.ground_height``) at the same points."""
    seg = GroundSegmenter(params)
    seg.segment(points)
    result = seg.segment(points)
    z_hat, z_std = result.ground_surface.height_at(points[samples, 0], points[samples, 1])
    err, sigma_n = z_hat - truth, result.hyperparameters.sigma_n
    inside = np.isfinite(err)
    e, s = err[inside], z_std[inside]
    e_gp = (result.ground_height[samples] - truth)[inside]
    return {'frame': name, 'samples': int(inside.sum()), 'outside': int((~inside).sum()),
            'median_abs': float(np.median(np.abs(e))), 'bias': float(np.median(e)),
            'in2': float(np.mean(np.abs(e) <= 2 * s)),
            'in2_pred': float(np.mean(np.abs(e) <= 2 * np.hypot(s, sigma_n))),
            'gp_median_abs': float(np.median(np.abs(e_gp))),
            'gp_in2': float(np.mean(np.abs(e_gp) <= 2 * s)),
            'median_std': float(np.median(s)), 'sigma_n': float(sigma_n)}


def synthetic_rows(seeds, params):
    from scenes import synthetic
    scans = [(name, synthetic.scan_scene(name)) for name in SYNTHETIC_SCENES]
    scans += [(f'{family}_{seed}', synthetic.family_scan(family, seed))
              for family in FAMILIES for seed in range(seeds)]
    rows = []
    for name, scan in scans:
        terrain = np.asarray(scan.kind) == synthetic.KIND_TERRAIN  # curb faces left out
        xy = scan.points[terrain, :2].astype(np.float64)
        truth = scan.terrain_z(xy[:, 0], xy[:, 1])
        rows.append(frame_row(name, np.ascontiguousarray(scan.points), terrain, truth, params))
    return rows


def real_rows(params):
    rows = []
    for ds in common.labelled_groups():
        for frame in ds.frames:
            keep = frame.truth & (frame.evaluated if frame.evaluated is not None else True)
            truth = frame.points[keep, 2].astype(np.float64)
            rows.append(frame_row(frame.name, frame.points, keep, truth, params))
    return rows


def table(rows):
    return common.markdown_table(
        ['frame', 'ground samples', 'outside grid', 'median abs err m', 'in +-2 z_std',
         'bias m', 'in +-2 sqrt(z_std^2+sigma_n^2)', 'GP mean only: median abs err m',
         'GP mean only: in +-2 z_std', 'median z_std m', 'sigma_n m'],
        [[r['frame'], f"{r['samples']:,}", f"{r['outside']:,}", f"{r['median_abs']:.4f}",
          f"{r['in2']:.3f}", f"{r['bias']:+.4f}", f"{r['in2_pred']:.3f}",
          f"{r['gp_median_abs']:.4f}", f"{r['gp_in2']:.3f}",
          f"{r['median_std']:.4f}", f"{r['sigma_n']:.3f}"] for r in rows])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, default=3, help='members per family (default 3)')
    ap.add_argument('--output', type=Path, default=RESULTS)
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    params = SegmenterParams()
    synthetic = synthetic_rows(args.seeds, params)
    real = real_rows(params)
    lines = ['## Ground surface: accuracy and calibration of z_hat, z_std (`bench_surface.py`)',
             '', common.machine_markdown(common.command_line()),
             '- SegmenterParams() defaults; second (warm-started) call on each frame; '
             'columns: see the script\'s docstring. Real-scan figures are in-sample (the '
             'ground offset is averaged from the measured ground points the truth is made of); '
             'synthetic truth is the exact terrain.', '',
             '### Synthetic scenes (truth: exact terrain height)', '', table(synthetic), '',
             '### Real labelled scans (truth: z of the labelled ground points)', '',
             table(real) if real else '(no labelled scan found)', '']
    text = '\n'.join(lines) + '\n'
    print(text)
    if not args.no_write:
        common.update_results_section(args.output, 'bench_surface', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
