# SPDX-License-Identifier: Apache-2.0
"""How the cost of ``GroundSegmenter.segment`` grows with the number of points and the grid size.

Usage::

    python benchmarks/bench_scaling.py [--quick] [--repeats N] [--sizes 10000,30000,...]
                                       [--grids 120x32,240x64,...] [--no-write]

Points: 10k ... 2M. Clouds smaller than a frame are random subsets of the labelled real KITTI
scan; bigger ones stack the real KITTI frames (labelled scan + the 6 bag frames), every repeat of
a frame turned by a random yaw about the vertical axis and jittered by 1 cm, so the structure stays
real (ground is still ground) while the density grows. Per size: a fresh segmenter, 2 untimed
calls (the first learns theta cold), then ``--repeats`` timed calls on the same cloud (streaming,
warm-started theta); median ms total and per stage (``timings_ms``).

Memory, in separate untimed calls (measuring slows the call):

* ``tracemalloc peak``: peak of the memory traced by tracemalloc during one ``segment()`` call,
  started just before it. numpy reports its array buffers to tracemalloc, so this is the peak of
  numpy (and Python) allocations made by the call, results included, input excluded.
* ``RSS delta``: peak resident set size during the call (Linux VmHWM, reset through
  /proc/self/clear_refs just before) minus the RSS before it. Includes BLAS/LAPACK workspaces
  and anything not traced; can be lower than the tracemalloc peak when freed memory is reused.

The slope of log(time) against log(points) is fitted by least squares (1 = linear cost), for the
total and per stage, over all sizes and over >= 100k points.

Grid: on the labelled ~120k-point frame, (M segments x N bins) over a few settings, same timing,
with the number of ground candidates and the labelled-frame F1 (the grid also changes accuracy).
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402
from gp_ground_segmentation.core import compiled  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
STAGES = ('grid', 'lines', 'gp_fit', 'predict', 'label', 'structure')
DEFAULT_SIZES = (10_000, 30_000, 100_000, 300_000, 1_000_000, 2_000_000)
DEFAULT_GRIDS = ((60, 32), (120, 32), (240, 32), (120, 16), (120, 64), (240, 64), (360, 96))
MB = 1024 * 1024


def measure_memory(seg, points):
    """(tracemalloc peak bytes, RSS delta bytes or None) of one segment() call."""
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    try:
        seg.segment(points)
        traced_peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    gc.collect()
    rss_delta = None
    if common.reset_peak_rss():
        before, _ = common.rss_bytes()
        seg.segment(points)
        _, peak = common.rss_bytes()
        rss_delta = max(peak - before, 0)
    return traced_peak, rss_delta


def time_segmenter(params, points, repeats, warmup=2):
    """Fresh segmenter, warm-up calls, timed calls -> (segmenter, wall ms, stage ms, last)."""
    seg = GroundSegmenter(params)
    for _ in range(warmup):
        last = seg.segment(points)
    wall, stages = [], {}
    for _ in range(repeats):
        last, dt = common.timed(seg.segment, points)
        wall.append(dt * 1e3)
        for k, v in last.timings_ms.items():
            stages.setdefault(k, []).append(v)
    return seg, wall, stages, last


def slope(xs, ys):
    """Least-squares slope of log(y) vs log(x); NaN with < 2 usable points."""
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = (xs > 0) & (ys > 0) & np.isfinite(ys)
    if ok.sum() < 2:
        return float('nan')
    return float(np.polyfit(np.log(xs[ok]), np.log(ys[ok]), 1)[0])


def linear_fit(xs, ys):
    """Least-squares ys = a + b xs; returns (a, b, largest |residual| / y)."""
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = np.isfinite(ys)
    if ok.sum() < 2:
        return float('nan'), float('nan'), float('nan')
    b, a = np.polyfit(xs[ok], ys[ok], 1)
    worst = float(np.max(np.abs(a + b * xs[ok] - ys[ok]) / ys[ok]))
    return float(a), float(b), worst


def parse_grids(text):
    out = []
    for item in text.split(','):
        m, n = item.lower().split('x')
        out.append((int(m), int(n)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--repeats', type=int, default=None,
                    help='timed calls per setting (default 7; 5 from 1M points; --quick 2)')
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--sizes', default=','.join(str(s) for s in DEFAULT_SIZES))
    ap.add_argument('--grids', default=','.join(f'{m}x{n}' for m, n in DEFAULT_GRIDS),
                    help='M x N settings, e.g. 120x32,240x64 (empty: skip)')
    ap.add_argument('--no-memory', action='store_true', help='skip the memory measurement')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--output', type=Path, default=RESULTS)
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    command = common.command_line()
    t_start = time.perf_counter()
    sizes = [int(float(s)) for s in args.sizes.split(',') if s.strip()]
    grids = parse_grids(args.grids) if args.grids.strip() else []

    frames = common.real_frames()
    if not frames:
        print('no real frames found under', common.DATA_DIR, file=sys.stderr)
        return 1
    params = SegmenterParams()
    # every compiled stage loaded (or compiled) before the first timed call: otherwise the
    # first size's calls take the numpy path of the stages still loading in the background
    GroundSegmenter(params).warm_up()
    compiled.wait(300.0)
    size_text = size_section(args, frames, sizes, params)
    labeled = common.load_labeled_kitti()
    gframe = labeled.frames[0] if labeled else frames[0]
    grid_rows = [grid_row(args, params, gframe, m, nb) for m, nb in grids]

    lines = ['## Scaling (`bench_scaling.py`)', '', common.machine_markdown(command),
             f'- Clouds from real KITTI frames ({len(frames)} frames: subsets below one frame, '
             f'stacked copies with random yaw + 1 cm jitter above); SegmenterParams() defaults '
             f'(grid {params.num_segments} x {params.num_bins}); per size a fresh segmenter, '
             f'2 untimed calls, then timed streaming calls (7, or 5 from 1M points, unless '
             f'--repeats/--quick). Memory in separate untimed calls (see the script docstring).',
             '', '### Cost vs number of points', '', size_text, '']
    if grid_rows:
        lines += [f'### Cost vs grid size (M segments x N bins) on {gframe.name} '
                  f'({len(gframe):,} points)', '',
                  common.markdown_table(['M x N', 'total ms median'] + [f'{k} ms' for k in STAGES]
                                        + ['candidates', 'F1', 'recall'], grid_rows), '']
    lines.append(f'Total wall time of the run: {time.perf_counter() - t_start:.0f} s.')
    text = '\n'.join(lines) + '\n'
    print(text)
    if not args.no_write:
        common.update_results_section(args.output, 'bench_scaling', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


def repeats_for(args, n: int) -> int:
    """Timed calls per setting: --repeats, else 2 with --quick, 5 from 1M points, else 7."""
    if args.repeats is not None:
        return args.repeats
    if args.quick:
        return 2
    return 5 if n >= 1_000_000 else 7


def size_section(args, frames, sizes, params) -> str:
    """The cost-vs-points table, the slope table and the linear fit (markdown)."""
    rng = np.random.default_rng(args.seed)
    rows, totals, stage_meds = [], [], {k: [] for k in STAGES}
    for n in sizes:
        pts = common.make_cloud_of_size(frames, n, rng)
        seg, wall, stages, last = time_segmenter(params, pts, repeats_for(args, n))
        traced = rss = None
        if not args.no_memory:
            traced, rss = measure_memory(seg, pts)
        med = common.median(stages.get('total', wall))
        totals.append(med)
        for k in STAGES:
            stage_meds[k].append(common.median(stages.get(k, [])))
        rows.append([common.fmt(n), common.fmt(med), common.fmt(float(np.percentile(wall, 95))),
                     common.fmt(med * 1e6 / n, 0)]
                    + [common.fmt(common.median(stages.get(k, [])), 1) for k in STAGES]
                    + [common.fmt(last.stats.get('candidates'), 0),
                       common.fmt(traced / MB if traced is not None else None, 1),
                       common.fmt(rss / MB if rss is not None else None, 1)])
        print(f'{n:>9,} points: {med:8.1f} ms', file=sys.stderr)
        del pts, seg, last
        gc.collect()
    size_table = common.markdown_table(
        ['points', 'total ms median', 'wall ms p95', 'ns / point'] + [f'{k} ms' for k in STAGES]
        + ['candidates', 'tracemalloc peak MB', 'RSS delta MB'], rows)
    big = [i for i, n in enumerate(sizes) if n >= 100_000]
    slope_rows = [['total', common.fmt(slope(sizes, totals), 2),
                   common.fmt(slope([sizes[i] for i in big], [totals[i] for i in big]), 2)]]
    for k in STAGES:
        slope_rows.append([k, common.fmt(slope(sizes, stage_meds[k]), 2),
                           common.fmt(slope([sizes[i] for i in big],
                                            [stage_meds[k][i] for i in big]), 2)])
    slope_table = common.markdown_table(
        ['stage', 'slope of log(ms) vs log(points), all sizes', 'slope, >= 100k points'],
        slope_rows)
    fixed, per_point, worst = linear_fit(sizes, totals)
    print(slope_table)  # every stage's slope printed; RESULTS.md keeps the total's
    return (f'{size_table}\n\nSlope of log(total ms) vs log(points): {slope_rows[0][1]} over all '
            f'sizes, {slope_rows[0][2]} from 100k points (1 = cost linear in the points).\n\n'
            f'Linear fit total ms = a + b * points over all '
            f'sizes: a = {common.fmt(fixed, 1)} ms (per-frame fixed cost), b = '
            f'{common.fmt(per_point * 1e6, 1)} ns per point; largest relative residual '
            f'{common.fmt(100 * worst, 0)} % (small = cost linear in the points).')


def grid_row(args, params, frame, m: int, nb: int) -> list:
    """One row of the cost-vs-grid table: M x N on ``frame``."""
    try:
        gp = params.replace(num_segments=m, num_bins=nb)
    except ValueError as exc:
        return [f'{m} x {nb}', f'invalid: {exc}'] + ['-'] * 9
    _, wall, stages, last = time_segmenter(gp, frame.points, repeats_for(args, len(frame)))
    met = common.score(last.ground_mask, frame)
    is_default = (m, nb) == (params.num_segments, params.num_bins)
    print(f'grid {m}x{nb}: {common.median(stages.get("total", wall)):.1f} ms', file=sys.stderr)
    return ([f'{m} x {nb}' + (' (default)' if is_default else ''),
             common.fmt(common.median(stages.get('total', wall)))]
            + [common.fmt(common.median(stages.get(k, [])), 1) for k in STAGES]
            + [common.fmt(last.stats.get('candidates'), 0),
               common.fmt(met['f1'], 3) if met else '-',
               common.fmt(met['recall'], 3) if met else '-'])


if __name__ == '__main__':
    sys.exit(main())
