# SPDX-License-Identifier: Apache-2.0
"""Ground quality on every labelled real scan and the synthetic scenes, cold, vs Patchwork++.

Usage::

    python benchmarks/quality_quick.py [--no-write] [--set name=value ...]
                                       [--baseline name=value ...] [--cv name=v1,v2,...]

Scans (``../shared/data``, README sections 1 and 6), grouped into the independent *scenes* that
cross-validation holds out:

* ``spvnas``  the SemanticKITTI scan of spvnas (1 frame);
* ``kitti00`` KITTI 00 frames 0-2 with SemanticKITTI labels (3 consecutive frames = 1 scene);
* ``rellis``  the RELLIS-3D off-road scan (Ouster OS1-64, organised, RELLIS ontology);
* the synthetic groups of ``common.synthetic_datasets`` (flat, sloped, mixed; exact truth).
(loaders of ``common``; bench_quality.py is the full evaluation with more families and peers.)

Every frame is segmented cold (a new ``GroundSegmenter`` per frame) by this project with
``--set`` changes over the defaults, by the ``--baseline`` parameter set (default: the defaults)
and by Patchwork++ (``pypatchworkpp`` defaults, a fresh instance per frame, ``sensor_height``
= the frame's mount height: 1.73 m on KITTI, on RELLIS minus the median z of its labelled
ground 3-10 m away, 1.27 m; RNR off where intensity is not KITTI remission).
Scores: ``gp_ground_segmentation.tools.evaluation``, pooled TP/FP/FN.

``--cv name=v1,v2,... [name2=...]`` picks parameter values (a joint grid) by leave-one-scene-out:
for each held-out real scene the values with the highest mean F1 over the *other* units (real
scenes and synthetic groups, each unit's pooled F1 weighted equally) are chosen, and their
held-out score reported.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
from bench_peers import PatchworkPPMethod  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'


def load_units():
    """[(unit name, is_real, Dataset)]: the real scenes whose files exist, synthetic groups."""
    units = []
    for name, loader in (('spvnas', common.load_labeled_kitti),
                         ('kitti00', common.load_kitti00_labeled), ('rellis', common.load_rellis)):
        ds = loader()
        if ds is not None:
            units.append((name, True, ds))
    units += [(ds.name, False, ds) for ds in common.synthetic_datasets(seed=0)]
    return units


def run_gp(params: SegmenterParams, units) -> dict:
    """{frame name: (metrics, result)} of a cold segmenter per frame."""
    out = {}
    for _, _, ds in units:
        for frame in ds.frames:
            result = GroundSegmenter(params).segment(frame.points)
            out[frame.name] = (common.score(result.ground_mask, frame), result)
    return out


def run_patchworkpp(units) -> dict:
    """{frame name: metrics} of Patchwork++ with a fresh instance per frame (cold)."""
    out = {}
    for _, _, ds in units:
        for frame in ds.frames:
            method = PatchworkPPMethod(frame.mount_height_m or common.KITTI_SENSOR_HEIGHT_M)
            method.start(common.Dataset(ds.name, [frame]))
            out[frame.name] = common.score(method.run(frame), frame)
    return out


def _metrics(value) -> dict:
    """The metrics of a per-frame entry: run_gp's (metrics, result) or run_patchworkpp's."""
    return value[0] if isinstance(value, tuple) else value


def unit_f1(units, per_frame: dict) -> dict:
    """{unit: pooled F1} from per-frame metrics (dict values may be (metrics, extra))."""
    return {name: common.pool([_metrics(per_frame[f.name]) for f in ds.frames])['f1']
            for name, _, ds in units}


def _prf(m) -> str:
    return ' / '.join(common.fmt(m[k], 3) for k in ('precision', 'recall', 'f1'))


def report(units, ours, base, pwpp, ours_label, base_label) -> str:
    """Per-frame and pooled tables (markdown)."""
    headers = ['frame', 'points', f'{base_label} P / R / F1', f'{ours_label} P / R / F1',
               'Patchwork++ P / R / F1', 'ours - PW++ F1']
    rows = []
    pooled = {}

    def add(label, npts, b, o, p):
        rows.append([label, npts, _prf(b), _prf(o), _prf(p), common.fmt(o['f1'] - p['f1'], 3)])

    for name, is_real, ds in units:
        if is_real:
            for f in ds.frames:
                add(f.name, common.fmt(len(f)), base[f.name][0], ours[f.name][0], pwpp[f.name])
        b, o, p = (common.pool([_metrics(r[f.name]) for f in ds.frames])
                   for r in (base, ours, pwpp))
        pooled[name] = (b, o, p)
        add(f'**{name}** pooled ({len(ds.frames)} frames)', '-', b, o, p)
    groups = (('real SemanticKITTI (4 scans)', ('spvnas', 'kitti00')),
              ('all synthetic', tuple(n for n, real, _ in units if not real)))
    for label, names in groups:
        frames = [f for n, _, ds in units if n in names for f in ds.frames]
        if not frames:
            continue
        b, o, p = (common.pool([_metrics(r[f.name]) for f in frames]) for r in (base, ours, pwpp))
        add(f'**{label}** pooled', '-', b, o, p)
    return common.markdown_table(headers, rows)


def stage_ms(ours: dict) -> str:
    """Median ms per stage over the real frames."""
    stages = {}
    for metrics, result in ours.values():
        if result.valid_mask.size > 100_000:
            for k, v in result.timings_ms.items():
                stages.setdefault(k, []).append(v)
    return ', '.join(f'{k} {common.fmt(common.median(v), 1)}' for k, v in stages.items())


def cross_validate(units, grid: dict, base_params: SegmenterParams) -> str:
    """Leave-one-real-scene-out choice of the parameters in ``grid`` (name -> values, searched
    jointly); markdown tables."""
    names = list(grid)
    combos = list(itertools.product(*grid.values()))
    f1 = {}
    for combo in combos:
        per_frame = run_gp(base_params.replace(**dict(zip(names, combo))), units)
        f1[combo] = unit_f1(units, per_frame)
        print(f'[cv] {combo}: ' + ', '.join(f'{u} {s:.4f}' for u, s in f1[combo].items()),
              file=sys.stderr)
    all_units = [u for u, _, _ in units]
    rows = []
    for held, is_real, _ in units:
        if not is_real:
            continue
        others = [u for u in all_units if u != held]
        best = max(combos, key=lambda c: np.mean([f1[c][u] for u in others]))
        rows.append([held, ', '.join(map(repr, best)),
                     common.fmt(np.mean([f1[best][u] for u in others]), 4),
                     common.fmt(f1[best][held], 4),
                     common.fmt(max(f1[c][held] for c in combos), 4)])
    table = common.markdown_table(
        ['held-out scene', f'{", ".join(names)} chosen on the others', 'mean F1 on the others',
         'held-out F1', 'best held-out F1 of any value'], rows)
    per_value = common.markdown_table(
        [', '.join(names)] + all_units,
        [[', '.join(map(repr, c))] + [common.fmt(f1[c][u], 4) for u in all_units]
         for c in combos])
    return table + '\n\nF1 per unit and value:\n\n' + per_value


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--set', nargs='*', default=[], help='name=value over the defaults (ours)')
    ap.add_argument('--baseline', nargs='*', default=[], help='name=value of the baseline set')
    ap.add_argument('--cv', nargs='*', default=[],
                    help='name=v1,v2,... (several: a joint grid): leave-one-scene-out')
    ap.add_argument('--no-write', action='store_true', help='print only, keep RESULTS.md')
    args = ap.parse_args(argv)
    units = load_units()
    ours_params = SegmenterParams().replace(**common.parse_param_values(args.set))
    base_params = SegmenterParams().replace(**common.parse_param_values(args.baseline))
    ours = run_gp(ours_params, units)
    base = run_gp(base_params, units)
    pwpp = run_patchworkpp(units)
    ours_label = 'ours' + (f' ({", ".join(args.set)})' if args.set else ' (defaults)')
    base_label = 'baseline' + (f' ({", ".join(args.baseline)})' if args.baseline
                               else ' (defaults)')
    text = [common.machine_markdown(common.command_line()),
            report(units, ours, base, pwpp, ours_label, base_label), '',
            f'Ours, median ms per stage on the real frames (cold): {stage_ms(ours)}.']
    if args.cv:
        grid = {}
        for item in args.cv:
            name, _, values = item.partition('=')
            grid[name] = [common.parse_param_values([f'{name}={v}'])[name]
                          for v in values.split(',')]
        text += ['', f'Leave-one-scene-out choice of {", ".join(f"`{n}`" for n in grid)} '
                 '(searched jointly):', '', cross_validate(units, grid, ours_params)]
    out = '\n'.join(text) + '\n'
    print(out)
    if not args.no_write:
        common.update_results_section(RESULTS, 'quality_quick', '## Ground quality, quick '
                                      '(benchmarks/quality_quick.py)\n\n' + out)


if __name__ == '__main__':
    main()
