# SPDX-License-Identifier: Apache-2.0
"""Median ms per stage of ``GroundSegmenter.segment`` on ~120k-point real KITTI frames.

Usage::

    python benchmarks/bench_core.py [--runs N] [--quick] [--frames all|labeled|bag] [--no-write]

Stages are the keys of ``SegmentationResult.timings_ms`` (grid, lines, gp_fit, predict, label,
total); ``wall`` is time.perf_counter around the whole ``segment()`` call (it includes input
conversion and result assembly that the stages may not cover).

* streaming: one segmenter fed the real frames in sequence (the labelled SemanticKITTI scan and
  the 6 frames of the KITTI 00 bag, cycled), so theta is warm-started as in the node; warm-up
  calls are not timed.
* cold: ``reset()`` before every call, so each frame pays the first-frame theta learning.
* first call in process: the very first ``segment()`` of this process (imports done, nothing
  else warmed), i.e. what a node pays on its first message (compiled kernels would show here).

Also prints ground precision/recall/F1 on the labelled frame (streaming and cold), so that a
speed-up that costs accuracy is visible in the same run.
"""

from __future__ import annotations

import argparse
import sys
import time
import timeit
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
STAGE_ORDER = ('grid', 'lines', 'gp_fit', 'predict', 'label', 'structure')


def load_frames(which):
    frames = []
    if which in ('all', 'labeled'):
        ds = common.load_labeled_kitti()
        if ds:
            frames += ds.frames
    if which in ('all', 'bag'):
        ds = common.load_bag_frames() or common.load_unlabeled_kitti()
        if ds:
            frames += ds.frames
    return frames


def make_reference():
    """Patchwork++ (defaults, KITTI height) as a load yardstick, or None when not installed."""
    try:
        import pypatchworkpp
    except ImportError:
        return None
    p = pypatchworkpp.Parameters()
    p.sensor_height = common.KITTI_SENSOR_HEIGHT_M
    p.verbose = False
    with common.quiet_stdout():  # its constructor prints to std::cout
        impl = pypatchworkpp.patchworkpp(p)

    def run_reference(points):
        impl.estimateGround(points)
        return impl.getGroundIndices()
    return run_reference


def run(frames, runs, warmup, cold, params, reference=None):
    """Per-stage ms lists, wall ms list, stats and labelled-frame metrics over ``runs`` calls.

    ``reference`` (a callable on the points) is timed right after each segment() call on the same
    frame, so that the ratio of the two is insensitive to the load of the shared machine.
    """
    seg = GroundSegmenter(params)
    stages, wall, iters, metrics, ref, surface = {}, [], [], [], [], {}
    for i in range(warmup + runs):
        frame = frames[i % len(frames)]
        if cold:
            seg.reset()
        res, dt = common.timed(seg.segment, frame.points)
        if reference is not None:
            ref_dt = common.timed(reference, frame.points)[1]
        surface_dt = time_surface_reads(res) if not cold else {}
        if i < warmup:
            continue
        for k, v in surface_dt.items():
            surface.setdefault(k, []).append(v)
        if reference is not None:
            ref.append(ref_dt * 1e3)
        wall.append(dt * 1e3)
        for k, v in res.timings_ms.items():
            stages.setdefault(k, []).append(v)
        iters.append(res.stats.get('optimizer_iterations', 0))
        m = common.score(res.ground_mask, frame)
        if m is not None:
            metrics.append(m)
    return {'stages': stages, 'wall': wall, 'iterations': iters, 'metrics': common.pool(metrics),
            'theta': getattr(seg, 'hyperparameters', None), 'reference': ref,
            'surface': surface}


def time_surface_reads(res) -> dict:
    """ms of reading what segment() leaves lazy: the surface as the node publishes it (z_std at
    the bin edges, then the supported points as float32) and height_above_ground per point."""
    t0 = time.perf_counter()
    res.ground_surface.points()
    t1 = time.perf_counter()
    res.height_above_ground
    t2 = time.perf_counter()
    return {'surface': (t1 - t0) * 1e3, 'height_above_ground': (t2 - t1) * 1e3}


def surface_construction_us(frame, params) -> float:
    """Median microseconds of the only surface work segment() does eagerly: building the lazy
    GroundSurface object from arrays it already has (timed apart: it is too small to see in a
    whole segment() call on a shared machine)."""
    from gp_ground_segmentation.core.surface import GroundSurface
    s = GroundSegmenter(params).segment(frame.points).ground_surface
    m = s.num_segments
    args = (s.r[:, 0], s.r[:, 1] - s.r[:, 0], np.ones(m, bool), s.z, np.ones(m, bool), None,
            lambda: s.z_std)
    counts = np.ones((m, s.num_bins), np.int64)
    training = np.ones((m, s.num_bins), bool)
    times = timeit.repeat(lambda: (counts.sum(axis=1) > 0, training.any(axis=1),
                                   GroundSurface(*args)), number=200, repeat=7)
    return min(times) / 200 * 1e6


def stage_rows(stream, cold):
    keys = [k for k in STAGE_ORDER if k in stream['stages'] or k in cold['stages']]
    keys += [k for k in list(stream['stages']) + list(cold['stages'])
             if k not in keys and k != 'total']
    keys = list(dict.fromkeys(keys)) + ['total']
    rows = []
    total_med = common.median(stream['stages'].get('total', []))
    for k in keys:
        s = common.summary_ms(np.asarray(stream['stages'].get(k, []), float) / 1e3)
        c = common.summary_ms(np.asarray(cold['stages'].get(k, []), float) / 1e3)
        share = s['median'] / total_med * 100 if total_med else float('nan')
        rows.append([k, common.fmt(s['median'], 2), common.fmt(s['p95'], 2),
                     common.fmt(share, 0), common.fmt(c['median'], 2), common.fmt(c['p95'], 2)])

    def unstaged(r):  # total minus the named stages: validity mask, conversions, bookkeeping
        named = [k for k in r['stages'] if k != 'total']
        return [r['stages']['total'][i] - sum(r['stages'][k][i] for k in named)
                for i in range(len(r['stages'].get('total', [])))]
    s = common.summary_ms(np.asarray(unstaged(stream)) / 1e3)
    c = common.summary_ms(np.asarray(unstaged(cold)) / 1e3)
    rows.insert(-1, ['(total - stages)', common.fmt(s['median'], 2), common.fmt(s['p95'], 2),
                     common.fmt(s['median'] / total_med * 100 if total_med else None, 0),
                     common.fmt(c['median'], 2), common.fmt(c['p95'], 2)])
    s = common.summary_ms(np.asarray(stream['wall']) / 1e3)
    c = common.summary_ms(np.asarray(cold['wall']) / 1e3)
    rows.append(['wall (perf_counter around segment())', common.fmt(s['median'], 2),
                 common.fmt(s['p95'], 2), '', common.fmt(c['median'], 2), common.fmt(c['p95'], 2)])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--runs', type=int, default=None, help='timed calls per mode (default 21, '
                    '--quick 7)')
    ap.add_argument('--warmup', type=int, default=2, help='untimed calls first (default 2)')
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--frames', choices=('all', 'labeled', 'bag'), default='all')
    ap.add_argument('--no-reference', action='store_true',
                    help='do not time Patchwork++ alongside (it gives a load-independent ratio)')
    ap.add_argument('--output', type=Path, default=RESULTS)
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    runs = args.runs if args.runs is not None else (7 if args.quick else 21)
    command = common.command_line()
    frames = load_frames(args.frames)
    if not frames:
        print('no real frames found under', common.DATA_DIR, file=sys.stderr)
        return 1
    params = SegmenterParams()

    # First call of this process on the first frame (nothing warmed yet).
    first_res, first_dt = common.timed(GroundSegmenter(params).segment, frames[0].points)

    reference = None if args.no_reference else make_reference()
    stream = run(frames, runs, args.warmup, cold=False, params=params, reference=reference)
    cold = run(frames, runs, args.warmup, cold=True, params=params)

    npts = np.mean([len(f) for f in frames])
    th = stream['theta']
    lines = ['## Core stages (`bench_core.py`)', '', common.machine_markdown(command),
             f'- Frames: {len(frames)} real KITTI frames ({", ".join(f.name for f in frames)}), '
             f'{npts:,.0f} points on average; {runs} timed calls per mode after {args.warmup} '
             f'warm-up calls; SegmenterParams() defaults.',
             f'- First segment() call of the process ({frames[0].name}, cold theta, nothing '
             f'warmed): {first_dt * 1e3:,.1f} ms (stages: '
             + ', '.join(f'{k} {v:.1f}' for k, v in first_res.timings_ms.items()) + ').',
             '', common.markdown_table(
                 ['stage', 'streaming median ms', 'streaming p95 ms', '% of total',
                  'cold median ms', 'cold p95 ms'], stage_rows(stream, cold)), '']
    for name, r in (('streaming', stream), ('cold', cold)):
        m = r['metrics']
        acc = (f'labelled frame P/R/F1 {m["precision"]:.3f}/{m["recall"]:.3f}/{m["f1"]:.3f}'
               if m else 'no labelled frame in the set')
        lines.append(f'- {name}: optimizer iterations per frame median '
                     f'{common.fmt(common.median(r["iterations"]), 0)}; {acc}.')
    surf = stream['surface']
    if surf:
        wall_med = common.median(stream['wall'])
        build_us = surface_construction_us(frames[0], params)
        read = {k: common.summary_ms(np.asarray(v) / 1e3) for k, v in surf.items()}
        lines.append(
            f"- Ground surface, same streaming run: segment() builds only a lazy "
            f"GroundSurface ({build_us:.1f} us, timeit, = {build_us / 1e3 / wall_med * 100:.3f}"
            f" % of the median segment() wall time, below this machine's noise); reading it "
            f"after segment() as the node publishes it (z_std + supported points) median "
            f"{read['surface']['median']:.2f} ms (p95 {read['surface']['p95']:.2f}), "
            f"height_above_ground {read['height_above_ground']['median']:.2f} ms "
            f"(p95 {read['height_above_ground']['p95']:.2f}), i.e. segment() + surface = "
            f"{(wall_med + read['surface']['median']) / wall_med:.3f}x segment() alone.")
    if th is not None:
        lines.append(f'- theta after the stream: sigma_f {th.sigma_f:.3g} m, a {th.gain:.3g}, '
                     f'sigma_n {th.sigma_n:.3g} m.')
    if stream['reference']:
        ref = common.median(stream['reference'])
        ratio = common.median(stream['wall']) / ref
        lines.append(f'- Yardstick: Patchwork++ (pypatchworkpp defaults, sensor height '
                     f'{common.KITTI_SENSOR_HEIGHT_M} m) timed right after each streaming call on '
                     f'the same frame: median {ref:.1f} ms; streaming wall / Patchwork++ = '
                     f'{ratio:.2f}x.')
    text = '\n'.join(lines) + '\n'
    print(text)
    if not args.no_write:
        common.update_results_section(args.output, 'bench_core', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
