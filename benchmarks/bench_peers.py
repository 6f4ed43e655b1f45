# SPDX-License-Identifier: Apache-2.0
"""This project vs Patchwork++, Patchwork and linefit: same process, same frames, same scoring.

Usage::

    python benchmarks/bench_peers.py [--quick] [--repeats N] [--warmup N] [--no-write]
                                     [--datasets kitti_labeled,synthetic-sloped,...]
                                     [--methods gp,patchworkpp,patchwork,linefit]

Peers (optional, never runtime dependencies of the package): ``pip install pypatchworkpp linefit``.
A peer that cannot be imported or constructed is reported as such in the output, not faked.

Every method is fed the same ``(N, 4)`` float32 array (x, y, z, intensity) of each frame and must
return a boolean ground mask over all N input points; the timed call includes each method's own
Python wrapper and turning its output into that mask (Patchwork: ``estimateGround`` +
``getGroundIndices``; linefit: ``run``; this project: ``GroundSegmenter.segment``). Points a peer
leaves out of both its ground and non-ground outputs (out of its range) count as non-ground.

Protocol per data set: each method gets a fresh instance (stateful ones -- this project's theta
warm start, Patchwork++'s adaptive thresholds -- then run as a stream over the data set's frames,
as in the node); ``--warmup`` rounds over all frames are run untimed, then ``--repeats`` timed
rounds.
Within a round the methods take turns frame by frame (the order rotates each round) so that load
from other jobs on this shared machine hits all methods alike. Accuracy is taken from the last
round. This project's *cold* first-frame latency (a new segmenter, theta not yet learned) is
timed separately on the first frame of every data set.

Configuration ("documented defaults for a KITTI-mounted sensor", sensor height 1.73 m):

* Patchwork++: ``pypatchworkpp.Parameters()`` defaults (they are the KITTI defaults of the paper),
  ``sensor_height = 1.73``. Reflected-noise removal needs intensity: it is disabled on clouds that
  have none (Patchwork++ would skip it anyway, printing a warning per frame).
* Patchwork: ``pypatchworkpp.PatchworkParams()`` defaults, ``sensor_height = 1.73``.
* linefit: the repository's KITTI config ``assets/config/kitti.toml`` (Kin-Zhang/linefit @ 8923861)
  verbatim except ``verbose`` false, so its ``height`` is 1.78 m: the file tunes the height with an
  offset for KITTI, and 1.73 m costs linefit about 8 F1 points on the labelled frame (0.877 vs
  0.958 in one run), which would not be a fair use of its defaults (``--linefit-height``).
  Its ``n_threads = 8`` is capped by the library to hardware_concurrency - 1, i.e. 1 thread here.
* This project: ``SegmenterParams()`` defaults (no sensor height is needed).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'

# linefit: Kin-Zhang/linefit assets/config/kitti.toml (commit 892386191be2), height set by caller.
LINEFIT_KITTI_TOML = """\
[important]
height = {height}
[segments]
r_min = 0.1
r_max = 80
n_segments = 360
n_bins = 160
[ground]
min_slope = -0.1
max_slope = 0.1
long_threshold = 2.0
max_long_height = 0.2
max_start_height = 0.2
max_fit_error = 0.2
max_dist_to_line = 0.2
line_search_angle = 0.33
[general]
n_threads = 8
verbose = false
"""


# ------------------------------------------------------------------------------------ methods

class Method:
    """A ground segmenter: ``start(dataset)`` makes a fresh instance; ``run(frame)`` -> mask."""

    key = ''
    label = ''

    def start(self, dataset):
        raise NotImplementedError

    def run(self, frame) -> np.ndarray:
        raise NotImplementedError


class GPMethod(Method):
    key, label = 'gp', 'this project (GP)'

    def __init__(self, params: SegmenterParams | None = None):
        self.params = params or SegmenterParams()
        self.seg = None
        self.last = None

    def start(self, dataset):
        self.seg = GroundSegmenter(self.params)

    def run(self, frame):
        self.last = self.seg.segment(frame.points)
        return self.last.ground_mask


class PatchworkPPMethod(Method):
    key, label = 'patchworkpp', 'Patchwork++'

    def __init__(self, sensor_height):
        import pypatchworkpp
        self.mod = pypatchworkpp
        self.sensor_height = sensor_height
        self.impl = None
        self.columns = 4

    def _params(self, has_intensity):
        p = self.mod.Parameters()
        p.sensor_height = self.sensor_height
        p.verbose = False
        p.enable_RNR = bool(has_intensity)
        return p

    def start(self, dataset):
        has_intensity = all(f.has_intensity for f in dataset.frames)
        self.columns = 4 if has_intensity else 3
        with common.quiet_stdout():
            self.impl = self.mod.patchworkpp(self._params(has_intensity))

    def run(self, frame):
        pts = frame.points if self.columns == 4 else frame.points[:, :3]
        self.impl.estimateGround(pts)
        mask = np.zeros(len(pts), dtype=bool)
        mask[self.impl.getGroundIndices()] = True
        return mask


class PatchworkMethod(PatchworkPPMethod):
    key, label = 'patchwork', 'Patchwork'

    def _params(self, has_intensity):
        p = self.mod.PatchworkParams()
        p.sensor_height = self.sensor_height
        p.verbose = False
        return p

    def start(self, dataset):
        self.columns = 4
        with common.quiet_stdout():
            self.impl = self.mod.patchwork(self._params(True))


class LinefitMethod(Method):
    key, label = 'linefit', 'linefit'

    def __init__(self, sensor_height):
        import linefit  # noqa: F401 - fail here, not in start(), when it is missing
        self.mod = linefit
        self.sensor_height = sensor_height
        self.impl = None

    def start(self, dataset):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / 'kitti.toml'
            path.write_text(LINEFIT_KITTI_TOML.format(height=self.sensor_height))
            with common.quiet_stdout():
                self.impl = self.mod.ground_seg(str(path))

    def run(self, frame):
        return np.asarray(self.impl.run(frame.points[:, :3])).astype(bool)


def build_methods(keys, sensor_height, linefit_height=1.78):
    """(methods, unavailable) where unavailable maps label -> the exact reason."""
    factories = {
        'gp': lambda: GPMethod(),
        'patchworkpp': lambda: PatchworkPPMethod(sensor_height),
        'patchwork': lambda: PatchworkMethod(sensor_height),
        'linefit': lambda: LinefitMethod(linefit_height),
    }
    labels = {'gp': GPMethod.label, 'patchworkpp': PatchworkPPMethod.label,
              'patchwork': PatchworkMethod.label, 'linefit': LinefitMethod.label}
    methods, unavailable = [], {}
    for key in keys:
        try:
            m = factories[key]()
            if key == 'patchwork' and not hasattr(m.mod, 'patchwork'):
                raise ImportError(f'pypatchworkpp {common._package_version("pypatchworkpp")} '
                                  'has no `patchwork` (original Patchwork) binding')
            methods.append(m)
        except Exception as exc:  # noqa: BLE001 - report any failure verbatim
            unavailable[labels[key]] = f'{type(exc).__name__}: {exc}'
    return methods, unavailable


# ------------------------------------------------------------------------------------ running

def run_dataset(ds, methods, repeats, warmup):
    """Time and score every method on one data set; returns a result dict."""
    res = {m.key: {'times': [], 'metrics': [None] * len(ds.frames),
                   'ground_frac': [0.0] * len(ds.frames), 'error': None} for m in methods}
    gp_stages, gp_iters = {}, []

    # Cold first-frame latency of this project: a new segmenter, theta not yet learned.
    cold = None
    if any(m.key == 'gp' for m in methods):
        seg = GroundSegmenter(SegmenterParams())
        f0 = ds.frames[0]
        out, dt = common.timed(seg.segment, f0.points)
        cold = {'ms': dt * 1e3, 'metrics': common.score(out.ground_mask, f0),
                'ground_frac': float(out.ground_mask.mean()), 'frame': f0.name}

    active = []
    for m in methods:
        try:
            m.start(ds)
            active.append(m)
        except Exception as exc:  # noqa: BLE001
            res[m.key]['error'] = f'{type(exc).__name__}: {exc}'
    rounds = warmup + repeats
    for rnd in range(rounds):
        order = active[rnd % len(active):] + active[:rnd % len(active)] if active else []
        for fi, frame in enumerate(ds.frames):
            for m in order:
                r = res[m.key]
                if r['error']:
                    continue
                try:
                    mask, dt = common.timed(m.run, frame)
                except Exception as exc:  # noqa: BLE001
                    r['error'] = f'{type(exc).__name__}: {exc}'
                    continue
                if rnd >= warmup:
                    r['times'].append(dt)
                    if m.key == 'gp':
                        for k, v in m.last.timings_ms.items():
                            gp_stages.setdefault(k, []).append(v)
                        gp_iters.append(m.last.stats.get('optimizer_iterations', 0))
                if rnd == rounds - 1:
                    r['metrics'][fi] = common.score(mask, frame)
                    r['ground_frac'][fi] = float(mask.mean()) if len(mask) else float('nan')
    theta = None
    for m in active:
        if m.key == 'gp' and m.seg is not None:
            theta = getattr(m.seg, 'hyperparameters', None)
    return {'dataset': ds, 'methods': res, 'cold': cold, 'gp_stages': gp_stages,
            'gp_iterations': gp_iters, 'theta': theta}


# ------------------------------------------------------------------------------------ output

def ratio(a, b):
    """'2.35x' for a / b, '-' when either is missing."""
    r = a / b if b else float('nan')
    return common.fmt(r, 2) + 'x' if np.isfinite(r) else '-'


def _prf(m):
    if m is None:
        return '-', '-', '-'
    return (common.fmt(m['precision'], 3), common.fmt(m['recall'], 3), common.fmt(m['f1'], 3))


def dataset_markdown(result, methods):
    ds = result['dataset']
    npts = ds.points_per_frame
    lines = [f'### {ds.name}: {ds.description}',
             f'{len(ds.frames)} frame(s), {npts:,.0f} points per frame on average.', '']
    ref = result['methods'].get('patchworkpp')
    ref_ms = common.summary_ms(ref['times'])['median'] if ref and ref['times'] else float('nan')
    headers = ['method', 'ms median', 'ms p95', 'Mpts/s', 'precision', 'recall', 'F1',
               'ground %', 'time / Patchwork++']
    rows = []
    for m in methods:
        r = result['methods'][m.key]
        if r['error']:
            rows.append([m.label, f'failed: {r["error"]}'] + ['-'] * 7)
            continue
        s = common.summary_ms(r['times'])
        pooled = common.pool(r['metrics'])
        gfrac = 100 * np.mean(r['ground_frac'])
        rows.append([m.label, common.fmt(s['median']), common.fmt(s['p95']),
                     common.fmt(npts / s['median'] / 1e3, 2), *_prf(pooled), common.fmt(gfrac),
                     ratio(s['median'], ref_ms)])
    cold = result['cold']
    if cold:
        rows.append([f'this project, cold first frame ({cold["frame"]})', common.fmt(cold['ms']),
                     '-', common.fmt(len(ds.frames[0]) / cold['ms'] / 1e3, 2),
                     *_prf(cold['metrics']), common.fmt(100 * cold['ground_frac']),
                     ratio(cold['ms'], ref_ms)])
    lines.append(common.markdown_table(headers, rows))
    if result['gp_stages']:
        st = ', '.join(f'{k} {common.fmt(common.median(v), 1)}'
                       for k, v in result['gp_stages'].items())
        th = result['theta']
        theta = (f'; theta after the stream: sigma_f {th.sigma_f:.3g} m, a {th.gain:.3g}, '
                 f'sigma_n {th.sigma_n:.3g} m' if th else '')
        lines += ['', f'This project, median ms per stage (streaming): {st}; optimizer iterations '
                      f'per frame median {common.fmt(common.median(result["gp_iterations"]), 0)}'
                      f'{theta}.']
    if len(ds.frames) > 1 and ds.labeled:
        headers = ['scene', 'points'] + [f'{m.label} P / R / F1' for m in methods]
        rows = []
        for fi, frame in enumerate(ds.frames):
            row = [frame.name, common.fmt(len(frame))]
            for m in methods:
                met = result['methods'][m.key]['metrics'][fi]
                row.append(' / '.join(_prf(met)) if met else '-')
            rows.append(row)
        lines += ['', 'Per frame:', '', common.markdown_table(headers, rows)]
    return '\n'.join(lines) + '\n'


def summary_markdown(results, methods):
    """One row per data set: times as ratios to Patchwork++ and F1 of every method."""
    keys = [m.key for m in methods]
    headers = ['data set', 'points/frame'] + [f'{m.label} ms' for m in methods]
    if 'patchworkpp' in keys and 'gp' in keys:
        headers.append('GP / Patchwork++ time')
    headers += [f'{m.label} F1' for m in methods]
    rows = []
    for result in results:
        ds = result['dataset']
        meds = {}
        for m in methods:
            r = result['methods'][m.key]
            meds[m.key] = (common.summary_ms(r['times'])['median'] if r['times'] and not r['error']
                           else float('nan'))
        row = [ds.name, common.fmt(ds.points_per_frame, 0)] + [common.fmt(meds[k]) for k in keys]
        if 'patchworkpp' in keys and 'gp' in keys:
            row.append(ratio(meds['gp'], meds['patchworkpp']))
        for m in methods:
            pooled = common.pool(result['methods'][m.key]['metrics'])
            row.append(common.fmt(pooled['f1'], 3) if pooled else '-')
        rows.append(row)
    return common.markdown_table(headers, rows) + '\n'


def load_datasets(selected, quick):
    datasets = []
    ds = common.load_labeled_kitti()
    if ds:
        datasets.append(ds)
    ds = common.load_bag_frames() or common.load_unlabeled_kitti()
    if ds:
        datasets.append(ds)
    datasets += common.load_sensor_pcds()
    datasets += common.synthetic_datasets()
    if selected:
        datasets = [d for d in datasets if d.name in selected]
    return datasets


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--repeats', type=int, default=None,
                    help='timed rounds over each data set (default 15, --quick 3)')
    ap.add_argument('--warmup', type=int, default=1, help='untimed rounds first (default 1)')
    ap.add_argument('--quick', action='store_true', help='3 timed rounds (about 1-2 min)')
    ap.add_argument('--datasets', default='',
                    help='comma list (kitti_labeled, kitti00_bag, vlp16, vlp32, xt32, '
                         'synthetic-flat, synthetic-sloped, synthetic-mixed); default all')
    ap.add_argument('--methods', default='gp,patchworkpp,patchwork,linefit')
    ap.add_argument('--sensor-height', type=float, default=common.KITTI_SENSOR_HEIGHT_M,
                    help='sensor height given to the peers (m, default 1.73 = KITTI)')
    ap.add_argument('--linefit-height', type=float, default=1.78,
                    help='linefit height (m, default 1.78 = its kitti.toml)')
    ap.add_argument('--output', type=Path, default=RESULTS, help='RESULTS.md to update')
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    repeats = args.repeats if args.repeats is not None else (3 if args.quick else 15)
    if repeats < 1 or args.warmup < 0:
        ap.error('--repeats must be >= 1 and --warmup >= 0')
    command = common.command_line()
    keys = [k.strip() for k in args.methods.split(',') if k.strip()]
    unknown = set(keys) - {'gp', 'patchworkpp', 'patchwork', 'linefit'}
    if unknown or not keys:
        ap.error(f'--methods: unknown {", ".join(sorted(unknown)) or "(empty)"}; choose from '
                 'gp, patchworkpp, patchwork, linefit')

    t_start = time.perf_counter()
    methods, unavailable = build_methods(keys, args.sensor_height, args.linefit_height)
    selected = {s.strip() for s in args.datasets.split(',') if s.strip()}
    datasets = load_datasets(selected, args.quick)
    print(f'loaded {len(datasets)} data sets in {time.perf_counter() - t_start:.1f} s; methods: '
          + ', '.join(m.label for m in methods), file=sys.stderr)
    for label, why in unavailable.items():
        print(f'UNAVAILABLE {label}: {why}', file=sys.stderr)

    results = []
    for ds in datasets:
        t0 = time.perf_counter()
        results.append(run_dataset(ds, methods, repeats, args.warmup))
        print(f'{ds.name}: {time.perf_counter() - t0:.1f} s', file=sys.stderr)

    parts = ['## Peers: this project vs Patchwork++, Patchwork, linefit (`bench_peers.py`)', '',
             common.machine_markdown(command),
             '- Protocol: one process; every method gets the same float32 (N, 4) frames; '
             f'{args.warmup} untimed warm-up round(s), then {repeats} timed rounds over each data '
             f'set\'s frames, methods taking turns frame by frame; stateful methods run as a '
             f'stream (new instance per data set). Times are wall-clock per frame '
             f'(time.perf_counter) including each method\'s Python wrapper; accuracy from the '
             f'last round, pooled over a data set\'s frames (sum of TP/FP/FN).',
             '- Scoring (everyone alike): SemanticKITTI ground = 40, 44, 48, 49, 60, 72; 0 and 1 '
             'ignored; 70 vegetation non-ground. Synthetic truth = terrain hit (curb faces '
             'ground). Positive = ground.',
             f'- Peer configuration: Patchwork++ and Patchwork with their pypatchworkpp default '
             f'parameters and sensor_height {args.sensor_height} m (RNR off on clouds without '
             f'intensity); linefit with its repository\'s KITTI config kitti.toml, height '
             f'{args.linefit_height} m (the file\'s 1.78 m is the default; 1 thread here). '
             f'This project: SegmenterParams() defaults, no sensor height needed.',
             '- kitti00_bag frame 0 is byte-for-byte the unlabeled KITTI .bin in ../shared/data, '
             'so that file is not run on its own (it is used only when the bag cannot be read).',
             '- Sensor PCDs (vlp16/vlp32/xt32) are indoor, floor near z = -0.5 m, and have no '
             'labels: the peers are configured for the KITTI height, so only their times mean '
             'something there; ground % is shown as a plausibility hint.', '']
    for label, why in unavailable.items():
        parts.append(f'- **{label} not run**: {why}')
    if unavailable:
        parts.append('')
    parts += ['### Summary (median ms per frame; F1 pooled per data set)', '',
              summary_markdown(results, methods),
              '(Per data set: ms p95, points/s, precision and recall, ground share, this '
              "project's cold first frame and stages, per frame: the script's printed output.)",
              '', f'Total wall time of the run: {time.perf_counter() - t_start:.0f} s.']
    text = '\n'.join(parts)
    for result in results:
        print(dataset_markdown(result, methods))
    print(text)
    if not args.no_write:
        common.update_results_section(args.output, 'bench_peers', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
