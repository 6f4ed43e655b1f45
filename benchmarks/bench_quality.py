# SPDX-License-Identifier: Apache-2.0
"""Ground quality on every labelled scan and synthetic family, under both scoring protocols.

Usage::

    python benchmarks/bench_quality.py [--quick] [--real-only] [--seeds N] [--families a,b]
                                       [--methods gp,patchworkpp,patchwork,linefit]
                                       [--modes cold,streamed] [--variant NAME:key=value,...]
                                       [--grid name=v1,v2,...] [--ablation] [--timing-rounds N]
                                       [--no-write]

Data (``common.labelled_groups`` and ``scenes.synthetic``; an absent file is skipped with a
printed reason): every labelled real scan, grouped for cross-validation by sequence -- KITTI
00 (frames 0-2, one scene), 02, 04, 05, 06, 08 (the spvnas scan) and 10 with SemanticKITTI
labels, RELLIS-3D with its own -- the eight classic synthetic scenes (``classic``) and every
randomised family of ``scenes.synthetic.FAMILY_NAMES`` with seeds 0..N-1 (3; ``--quick`` 1),
each family its own group.

Methods, fed the same (N, 4) float32 frames: this project (``SegmenterParams()`` defaults or a
variant; no mount height), Patchwork++, Patchwork and linefit with their documented defaults
plus what their users set for a mount (``peer_settings``). Modes: ``cold`` = a fresh instance
per frame; ``streamed`` = one instance over a group's frames in order.

Every mask is scored under both protocols of ``gp_ground_segmentation.tools.evaluation``
(:data:`PROTOCOLS`): vegetation as non-ground (the default) and Patchwork++'s (vegetation not
scored); precision, recall, F1 and GroundGrid's IoU_g = TP / (TP + FP + FN), per scan and pooled
(TP/FP/FN summed, never a mean of F1). Held-out scores: the leave-one-group-out choice
(``tools.crossval``) among the defaults and the variants asked for, per protocol; with no
variant the defaults are the only candidate and the held-out score is theirs.

``--quick`` (1 seed, cold only, 2 timing rounds) and ``--real-only`` (the labelled real scans
only) are for iterating: they print and never write RESULTS.md, whose section is the full run's.
Nothing is cached: every run segments every frame again.

Library use (tests, choosing defaults)::

    from bench_quality import load_groups, evaluate
    groups = load_groups(seeds=3)
    counts = evaluate(SegmenterParams(), groups[0].frames, mode='cold')   # [{tp, fp, fn, tn}]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_peers  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation import SegmenterParams  # noqa: E402
from gp_ground_segmentation.tools.crossval import (  # noqa: E402
    best_candidate, group_folds, leave_one_group_out, pooled_f1)
from gp_ground_segmentation.tools.evaluation import (  # noqa: E402
    DEFAULT_PROTOCOL, PATCHWORKPP, VEGETATION_NONGROUND)

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
METHOD_KEYS = ('gp', 'patchworkpp', 'patchwork', 'linefit')
MODES = ('cold', 'streamed')
PROTOCOLS = (VEGETATION_NONGROUND, PATCHWORKPP)  # the two every table reports
MODE_TEXT = {'cold': 'a fresh instance per frame',
             'streamed': "one instance over a group's frames in order; a synthetic family's "
                         'seeds are different scenes played as one stream'}
CLASSIC_SCENES = common.FLAT_SCENES + common.SLOPED_SCENES + common.MIXED_SCENES
# Below this mount height (m) the peers get a short minimum range: their KITTI defaults (2.7 m)
# would drop the whole floor of a room seen from 0.5 m.
LOW_MOUNT_M = 1.0
LOW_MOUNT_MIN_RANGE_M = 0.3
# linefit's own KITTI config (Kin-Zhang/linefit assets/config/kitti.toml) sets 1.78 m for the
# 1.73 m KITTI mount; its documented default is kept for KITTI.
LINEFIT_KITTI_HEIGHT_M = 1.78
LABELS = {'gp': 'this project', 'patchworkpp': 'Patchwork++', 'patchwork': 'Patchwork',
          'linefit': 'linefit'}
DEFAULT_SEEDS = 3


# ------------------------------------------------------------------------------------ data

def load_groups(seeds: int = DEFAULT_SEEDS, families=None, real: bool = True,
                synthetic: bool = True) -> list:
    """Every evaluation group as a ``common.Dataset``: one real sequence (``kitti00`` ..
    ``kitti10``, ``rellis3d``), the eight classic synthetic scenes (``classic``) or one
    synthetic family with ``seeds`` seeds."""
    groups = common.labelled_groups() if real else []
    if not synthetic:
        return groups
    ds = common.load_synthetic(CLASSIC_SCENES, 'classic')
    if ds is not None:
        for frame in ds.frames:
            frame.mount_height_m = 1.73  # simulate_scan's default mount
            frame.has_intensity = False  # made-up reflectance, as in load_family
        ds.name = 'classic'
        groups.append(ds)
    try:
        from scenes.synthetic import FAMILY_NAMES
    except ImportError as exc:
        print(f'[data] skipped synthetic families: {exc}', file=sys.stderr)
        return groups
    for family in families or FAMILY_NAMES:
        ds = common.load_family(family, range(seeds))
        if ds is not None:
            groups.append(ds)
    return groups


def is_kitti(group) -> bool:
    return group.name.startswith('kitti')


def category(group) -> str:
    """'SemanticKITTI', 'RELLIS-3D', 'classic' or the synthetic family's group ('sloped', ..)."""
    if is_kitti(group):
        return 'SemanticKITTI'
    if group.group == 'real':
        return 'RELLIS-3D'
    return group.group.replace('synthetic-', '')


# ------------------------------------------------------------------------------------ methods

def peer_settings(frame) -> tuple:
    """(sensor height m, minimum range m or None = the peer's default) that a user would set."""
    height = frame.mount_height_m if frame.mount_height_m else common.KITTI_SENSOR_HEIGHT_M
    min_range = LOW_MOUNT_MIN_RANGE_M if height < LOW_MOUNT_M else None
    return height, min_range


class PatchworkPP(bench_peers.PatchworkPPMethod):
    """Patchwork++ defaults with the mount's height and, below 1 m mounts, a short min range."""

    def __init__(self, sensor_height, min_range=None):
        super().__init__(sensor_height)
        self.min_range = min_range

    def _params(self, has_intensity):
        params = super()._params(has_intensity)
        if self.min_range is not None:
            params.min_range = self.min_range
        return params


class Patchwork(bench_peers.PatchworkMethod):
    """Patchwork defaults with the mount's height and, below 1 m mounts, a short min range."""

    def __init__(self, sensor_height, min_range=None):
        super().__init__(sensor_height)
        if not hasattr(self.mod, 'patchwork'):
            raise ImportError('this pypatchworkpp has no `patchwork` (original Patchwork) binding')
        self.min_range = min_range

    def _params(self, has_intensity):
        params = super()._params(has_intensity)
        if self.min_range is not None:
            params.min_range = self.min_range
            params.min_ranges = [self.min_range] + list(params.min_ranges)[1:]
        return params


def make_method(key: str, frame, params: SegmenterParams | None = None):
    """A fresh, unstarted method for ``frame``'s mount (the GP ignores the mount)."""
    if key == 'gp':
        return bench_peers.GPMethod(params)
    height, min_range = peer_settings(frame)
    if key == 'patchworkpp':
        return PatchworkPP(height, min_range)
    if key == 'patchwork':
        return Patchwork(height, min_range)
    if key == 'linefit':
        kitti = frame.mount_height_m == common.KITTI_SENSOR_HEIGHT_M and frame.name.startswith(
            'kitti')
        return bench_peers.LinefitMethod(LINEFIT_KITTI_HEIGHT_M if kitti else height)
    raise ValueError(f'method: unknown {key!r}; choose from {", ".join(METHOD_KEYS)}')


def run_masks(key: str, frames, mode: str = 'cold', params: SegmenterParams | None = None,
              timings: list | None = None) -> list:
    """The ground mask of every frame by one method.

    cold: a fresh instance per frame; streamed: one instance over the frames in order, rebuilt
    only when a peer's mount settings change. ``timings`` (optional) collects seconds per call.
    """
    if mode not in MODES:
        raise ValueError(f'mode: unknown {mode!r}; choose cold or streamed')
    out, method, settings = [], None, None
    for i, frame in enumerate(frames):
        wanted = peer_settings(frame) if key != 'gp' else None
        if mode == 'cold' or method is None or wanted != settings:
            method, settings = make_method(key, frame, params), wanted
            same = [f for f in frames[i:] if (peer_settings(f) if key != 'gp' else None) == wanted]
            with common.quiet_stdout():
                method.start(common.Dataset('', [frame] if mode == 'cold' else same))
        mask, seconds = common.timed(method.run, frame)
        if timings is not None:
            timings.append(seconds)
        out.append(mask)
    return out


def scored(masks, frames) -> dict:
    """{protocol name: per-frame metrics} of ``masks`` under each of :data:`PROTOCOLS`."""
    return {p.name: [common.score(m, f, p) for m, f in zip(masks, frames)] for p in PROTOCOLS}


def run_frames(key: str, frames, mode: str = 'cold', params: SegmenterParams | None = None,
               protocol=DEFAULT_PROTOCOL) -> list:
    """Per-frame metrics (``common.score`` dicts) of one method under ``protocol``."""
    frames = list(frames)
    return [common.score(m, f, protocol)
            for m, f in zip(run_masks(key, frames, mode, params), frames)]


def evaluate(params: SegmenterParams, frames, mode: str = 'cold',
             protocol=DEFAULT_PROTOCOL) -> list:
    """Per-frame counts ``{'tp', 'fp', 'fn', 'tn'}`` of this project with ``params``.

    ``frames``: ``common.Frame`` objects with truth, in stream order for ``mode='streamed'``.
    """
    params = params.validate()
    return [{k: m[k] for k in ('tp', 'fp', 'fn', 'tn')}
            for m in run_frames('gp', frames, mode, params, protocol)]


def pooled(metrics) -> dict | None:
    """Pooled metrics of per-frame ones (TP/FP/FN summed); None if none."""
    return common.pool(list(metrics))


# ------------------------------------------------------------------------------------ variants

def parse_variant(text: str) -> tuple:
    """'NAME:key=value,key=value' -> (NAME, SegmenterParams); ValueError with the reason."""
    name, sep, body = text.partition(':')
    if not sep or not name.strip():
        raise ValueError(f'--variant {text!r}: expected NAME:key=value,key=value')
    values = common.parse_param_values([x for x in body.split(',') if x.strip()])
    return name.strip(), SegmenterParams(**values).validate()


def grid_variants(items) -> dict:
    """['a=1,2', 'b=x,y'] -> {'a=1, b=x': params, ...}: every combination (a joint grid) over
    the defaults (none without items); ValueError naming a bad item."""
    if not items:
        return {}
    axes = []
    for item in items:
        name, sep, values = item.partition('=')
        if not sep or not values.strip():
            raise ValueError(f'--grid {item!r}: expected name=v1,v2,...')
        axes.append([f'{name.strip()}={v.strip()}' for v in values.split(',') if v.strip()])
    out = {}
    for combo in itertools.product(*axes):
        params = SegmenterParams(**common.parse_param_values(list(combo))).validate()
        out[', '.join(combo)] = params
    return out


def ablation_variants() -> dict:
    """One-at-a-time switches of the paper's components and of every boolean field.

    * OLS instead of Deming: lambda = var(z err) / var(r err) -> infinity makes the Deming slope
      (d + sqrt(d^2 + 4 lambda s_rz^2)) / (2 s_rz), d = s_zz - lambda s_rr, tend to s_rz / s_rr,
      the ordinary least-squares fit of z on r; the range allows 1e4.
    * the length scale: the paper's non-stationary one or one length factor is the
      ``use_nonstationary_length_scale`` switch (below, with the other bools);
    * theta frozen: no marginal-likelihood evaluations at all, theta stays at its initial value;
    * every bool field of SegmenterParams (``use_*`` switches and others) flipped, discovered at
      run time so that new switches appear without code changes.
    """
    d = SegmenterParams()
    out = {
        'OLS lines (deming_variance_ratio=1e4)': {'deming_variance_ratio': 1e4},
        'theta frozen (0 optimizer evaluations)': {'optimizer_first_frame_evaluations': 0,
                                                   'optimizer_max_evaluations': 0},
    }
    for f in dataclasses.fields(SegmenterParams):
        if isinstance(f.default, bool):
            out[f'{f.name}={not f.default}'] = {f.name: not f.default}
    return {name: dataclasses.replace(d, **change).validate() for name, change in out.items()}


def theta_stream_variants() -> dict:
    """Whole-frame theta learning in a stream (the paper's second idea), streamed mode only.

    The defaults learn on the first frame and then on every ``optimizer_interval_frames``-th
    frame (a stream shorter than that learns on its first frame only).

    * every frame: ``optimizer_interval_frames`` = 1, the paper's per-frame learning;
    * first frame only: the cold start learns (``optimizer_first_frame_evaluations``), later
      frames keep that theta -- what the later evaluations add;
    * frozen: theta never learns, not even on the first frame.
    """
    d = SegmenterParams()
    return {'theta learned on every frame': d.replace(optimizer_interval_frames=1),
            'theta learned on the first frame only': d.replace(optimizer_max_evaluations=0),
            'theta frozen': d.replace(optimizer_max_evaluations=0,
                                      optimizer_first_frame_evaluations=0)}


# ------------------------------------------------------------------------------------ running

def run_all(groups, keys, modes, params=None) -> tuple:
    """(results[mode][key][group name][protocol name] = per-frame metrics,
    unavailable[key] = the reason a method could not run)."""
    results = {mode: {} for mode in modes}
    unavailable = {}
    for key in keys:
        for mode in modes:
            per = {}
            for g in groups:
                try:
                    per[g.name] = scored(run_masks(key, g.frames, mode, params), g.frames)
                except Exception as exc:  # noqa: BLE001 - report any peer failure verbatim
                    unavailable[key] = f'{type(exc).__name__}: {exc}'
                    break
            if key in unavailable:
                break
            results[mode][key] = per
            print(f'{key} {mode} done', file=sys.stderr, flush=True)
    return results, unavailable


def run_variants(groups, variants: dict, mode: str = 'cold') -> dict:
    """{variant name: {group name: {protocol name: per-frame metrics}}} of this project."""
    out = {}
    for name, params in variants.items():
        out[name] = {g.name: scored(run_masks('gp', g.frames, mode, params), g.frames)
                     for g in groups}
        print(f'variant {name} done', file=sys.stderr, flush=True)
    return out


def cross_validate(candidates: dict, groups, protocol) -> object:
    """Leave-one-group-out choice among ``candidates`` ({name: {group: {protocol: metrics}}},
    the defaults first): for each group the candidate with the best mean of the other groups'
    pooled F1 under ``protocol``, scored on the held-out group (``tools.crossval``)."""
    counts = {name: {g: per[g][protocol.name] for g in per} for name, per in candidates.items()}
    return leave_one_group_out(
        [g.name for g in groups], lambda name: name,
        lambda fold: best_candidate(counts, fold.train),
        lambda chosen, test: [c for g in test for c in counts[chosen][g]])


def time_kitti(groups, keys, rounds: int) -> dict:
    """Seconds per frame of each method streamed over the ~124k-point KITTI scans.

    One untimed warm-up round, then ``rounds`` timed rounds, methods taking turns frame by frame
    so load from other jobs on this shared machine hits all alike.
    """
    frames = [f for g in groups if is_kitti(g) for f in g.frames]
    if not frames or not rounds:
        return {}
    methods = {}
    for key in keys:
        try:
            methods[key] = make_method(key, frames[0])
            with common.quiet_stdout():
                methods[key].start(common.Dataset('', frames))
        except Exception:  # noqa: BLE001 - reported by run_all already
            continue
    times = {key: [] for key in methods}
    for rnd in range(rounds + 1):
        for frame in frames:
            for key, method in methods.items():
                seconds = common.timed(method.run, frame)[1]
                if rnd:
                    times[key].append(seconds)
    return {'times': times, 'frames': len(frames), 'rounds': rounds,
            'points': float(np.mean([len(f) for f in frames]))}


# ------------------------------------------------------------------------------------ tables

def prf(m, digits: int = 3) -> str:
    if m is None:
        return '-'
    return ' / '.join(common.fmt(m[k], digits) for k in ('precision', 'recall', 'f1'))


def row_sets(groups) -> list:
    """(label, member groups) of every table row: each group, then the pooled rows (the KITTI
    scans; each synthetic category with more than one family; all synthetic)."""
    rows = [(g.name, [g]) for g in groups]
    kitti = [g for g in groups if is_kitti(g)]
    if len(kitti) > 1:
        rows.insert(len(kitti), (f'**SemanticKITTI, {sum(len(g.frames) for g in kitti)} scans '
                                 'pooled**', kitti))
    synthetic = [g for g in groups if g.group != 'real']
    for cat in dict.fromkeys(category(g) for g in synthetic):
        members = [g for g in synthetic if category(g) == cat]
        if len(members) > 1:
            rows.append((f'**{cat} pooled** ({", ".join(g.name for g in members)})', members))
    if len(synthetic) > 1:
        rows.append((f'**all synthetic pooled** ({len(synthetic)} groups)', synthetic))
    return rows


def members_pooled(per_group: dict, members, protocol) -> dict | None:
    """Pooled metrics of ``members``' frames in ``per_group[group][protocol]``."""
    return pooled(m for g in members for m in per_group[g.name][protocol.name])


def held_out_kitti(cv_by_protocol: dict, groups) -> dict:
    """{protocol name: pooled held-out metrics of the KITTI folds}."""
    kitti = {g.name for g in groups if is_kitti(g)}
    return {name: pooled(c for fold in cv.folds if fold.held_out in kitti
                         for c in fold.test_counts)
            for name, cv in cv_by_protocol.items()}


def both_protocols_table(groups, cold: dict, cv_by_protocol: dict, candidates: int) -> str:
    """The compact table: ours vs Patchwork++ under both protocols, P/R/F1, F1 change, IoU_g;
    with the held-out KITTI pooled row of the leave-one-group-out choice."""
    ours, theirs = cold.get('gp'), cold.get('patchworkpp')
    headers = ['group', 'frames']
    for p in PROTOCOLS:
        headers += [f'{p.name}: ours P / R / F1', 'Patchwork++ P / R / F1', 'F1 ours - PW++',
                    'IoU_g ours / PW++']
    held = held_out_kitti(cv_by_protocol, groups)
    rows = []
    for label, members in row_sets(groups):
        row = [label, str(sum(len(g.frames) for g in members))]
        for p in PROTOCOLS:
            o = members_pooled(ours, members, p) if ours else None
            t = members_pooled(theirs, members, p) if theirs else None
            row += _comparison_cells(o, t)
        rows.append(row)
        if label.startswith('**SemanticKITTI') and held.get(PROTOCOLS[0].name):
            plural = 's' if candidates > 1 else ''
            row = [f'**SemanticKITTI held-out** (leave one sequence out, {candidates} '
                   f'candidate{plural})', row[1]]
            for p in PROTOCOLS:
                t = members_pooled(theirs, members, p) if theirs else None
                row += _comparison_cells(held[p.name], t)
            rows.append(row)
    return common.markdown_table(headers, rows)


def _comparison_cells(o, t) -> list:
    delta = f"{o['f1'] - t['f1']:+.4f}" if o and t else '-'
    iou = ' / '.join(common.fmt(m['iou'], 4) if m else '-' for m in (o, t))
    return [prf(o, 4), prf(t, 4), delta, iou]


def all_methods_table(groups, per_method: dict, keys, rows=None) -> str:
    """Every method per row: P / R / F1 under the default protocol, then F1 under Patchwork++'s
    protocol of each method (``rows``: the row sets, default :func:`row_sets`)."""
    other = PROTOCOLS[1]
    headers = (['group', 'frames'] + [f'{LABELS[k]} P / R / F1' for k in keys]
               + [f'{other.name}: F1 ' + ' / '.join(LABELS[k] for k in keys)])
    out = []
    for label, members in rows or row_sets(groups):
        out.append([label, str(sum(len(g.frames) for g in members))]
                   + [prf(members_pooled(per_method[k], members, DEFAULT_PROTOCOL))
                      for k in keys]
                   + [' / '.join(common.fmt((members_pooled(per_method[k], members, other)
                                             or {'f1': None})['f1'], 3) for k in keys)])
    return common.markdown_table(headers, out)


def pooled_row_sets(groups) -> list:
    """The rows of the streamed table: each real group and the pooled rows (no single
    synthetic family)."""
    return [(label, members) for label, members in row_sets(groups)
            if label.startswith('**') or members[0].group == 'real']


def losses_text(groups, cold: dict) -> str:
    """The groups and synthetic frames where this project's F1 is below Patchwork++'s."""
    if 'gp' not in cold or 'patchworkpp' not in cold:
        return ''
    lines = []
    for p in PROTOCOLS:
        lost_groups, lost_frames = [], []
        for g in groups:
            ours, ref = (pooled_f1(cold[k][g.name][p.name]) for k in ('gp', 'patchworkpp'))
            if ours < ref:
                lost_groups.append(f'{g.name} ({ours:.4f} vs {ref:.4f})')
            for frame, o, t in zip(g.frames, cold['gp'][g.name][p.name],
                                   cold['patchworkpp'][g.name][p.name]):
                if g.group != 'real' and o['f1'] < t['f1']:
                    lost_frames.append(f"{frame.name} ({o['f1']:.3f} vs {t['f1']:.3f})")
        lines.append(f'- {p.name}: groups below Patchwork++ (pooled F1, ours vs theirs): '
                     f'{", ".join(lost_groups) or "none"}; synthetic frames below it: '
                     f'{", ".join(lost_frames) or "none"}.')
    return '\n'.join(lines)


def timing_table(timing, keys) -> str:
    times = timing['times']
    ref = common.summary_ms(times.get('patchworkpp', []))['median']
    rows = []
    for key in keys:
        if key not in times:
            continue
        s = common.summary_ms(times[key])
        ratio = s['median'] / ref if ref and np.isfinite(ref) else float('nan')
        rows.append([LABELS[key], common.fmt(s['median']), common.fmt(s['p95']), str(s['n']),
                     common.fmt(ratio, 2) + 'x' if np.isfinite(ratio) else '-'])
    return common.markdown_table(['method', 'ms median', 'ms p95', 'calls', 'time / Patchwork++'],
                                 rows)


def variant_table(groups, variant_results: dict, protocol) -> str:
    """Pooled F1 per group for each variant of this project (same run), change vs the first."""
    names = list(variant_results)
    suffix = '' if protocol is DEFAULT_PROTOCOL else f' ({protocol.name})'
    headers = ['data set / family' + suffix] + names

    def f1(name, group):
        return pooled_f1(variant_results[name][group][protocol.name])

    rows = []
    for g in groups:
        rows.append([g.name] + [common.fmt(f1(n, g.name), 3) + (
            '' if n == names[0] else f' ({f1(n, g.name) - f1(names[0], g.name):+.3f})')
            for n in names])
    macro = {n: float(np.nanmean([f1(n, g.name) for g in groups])) for n in names}
    base = macro[names[0]]
    rows.append(['**mean of groups**'] + [
        common.fmt(macro[n], 3) + ('' if n == names[0] else f' ({macro[n] - base:+.3f})')
        for n in names])
    return common.markdown_table(headers, rows)


def cv_table(cv_by_protocol: dict, candidates: dict) -> str:
    """Per protocol: how often each candidate was chosen on the other groups, and the mean over
    the held-out groups of the chosen candidate's F1 and of the defaults'."""
    first = next(iter(candidates))
    rows = []
    for p in PROTOCOLS:
        folds = cv_by_protocol[p.name].folds
        held = np.mean([pooled_f1(f.test_counts) for f in folds])
        base = np.mean([pooled_f1(candidates[first][f.held_out][p.name]) for f in folds])
        rows.append([p.name, _choice_counts(f.choice for f in folds),
                     common.fmt(held, 4), common.fmt(base, 4)])
    rows.append(['both (the defaults\' rule): the mean of the two protocols\' F1',
                 *joint_cv_cells(candidates)])
    return common.markdown_table(['protocol', f'chosen on the other groups (folds of '
                                  f'{len(folds)})', 'held-out F1, mean of groups',
                                  f'{first} F1, mean of groups'], rows)


def _choice_counts(choices) -> str:
    """'name (folds), ...', the most chosen first (ties in the order first chosen)."""
    return ', '.join(f'{name} ({count})' for name, count in Counter(choices).most_common())


def joint_cv_cells(candidates: dict) -> list:
    """Leave-one-group-out over both protocols at once (how the defaults were chosen): a
    group's score is the mean of its pooled F1 under the two protocols (a synthetic group's is
    the same under both); each fold picks the candidate with the best mean score of the other
    groups. Returns (choices, held-out mean, the first candidate's mean)."""
    def score(name, group):
        return float(np.mean([pooled_f1(candidates[name][group][p.name]) for p in PROTOCOLS]))

    first = next(iter(candidates))
    choices, held, base = [], [], []
    for fold in group_folds(list(candidates[first]), lambda group: group):
        (g,) = fold.test
        best = max(candidates, key=lambda n: np.mean([score(n, h) for h in fold.train]))
        choices.append(best)
        held.append(score(best, g))
        base.append(score(first, g))
    return [_choice_counts(choices), common.fmt(float(np.mean(held)), 4),
            common.fmt(float(np.mean(base)), 4)]


def settings_text(groups) -> str:
    rellis = [f for g in groups if g.name == 'rellis3d' for f in g.frames]
    rellis_h = f'{rellis[0].mount_height_m:.2f} m' if rellis else 'n/a'
    protocols = '; '.join(f'`{p.name}`: {p.summary}' for p in PROTOCOLS)
    return (
        '- Peer settings: Patchwork++ (`pypatchworkpp.Parameters()`) and Patchwork '
        '(`PatchworkParams()`) defaults with `sensor_height` = the mount height: 1.73 m on '
        f'KITTI, {rellis_h} on RELLIS-3D (minus the median z of its labelled ground 3-10 m '
        'away), the true mount height on synthetic scans; below '
        f'{LOW_MOUNT_M:g} m mounts `min_range` = {LOW_MOUNT_MIN_RANGE_M:g} m (Patchwork: also '
        'the first zone\'s `min_ranges`). Patchwork++ RNR on for the KITTI scans (remission), '
        'off on RELLIS-3D (intensity normalised to ~0.012) and synthetic scans (made-up '
        f'intensity). linefit: its kitti.toml with `height` {LINEFIT_KITTI_HEIGHT_M} m on '
        'KITTI (the file\'s own value), the mount height elsewhere. Tilted mounts: the peers '
        'get the height only.\n'
        '- This project: `SegmenterParams()` defaults (or the variant named) for every group, '
        'no mount height.\n'
        f'- Scoring (`tools/evaluation.py`, everyone alike; positive = ground): {protocols}. '
        'SemanticKITTI ground 40/44/48/49/60/72, 0/1 not scored; RELLIS-3D ground '
        '1/3/10/23/31/33, 0 void not scored, 4 tree non-ground under both. Synthetic truth = '
        'terrain hit (curb faces ground), the same under both protocols. Pooled = TP/FP/FN '
        'summed over the frames; IoU_g = TP / (TP + FP + FN) (GroundGrid).\n'
        '- Held-out: leave one group out (a KITTI sequence, KITTI 00\'s three frames together; '
        'RELLIS-3D; each synthetic family; `classic`): the candidate with the best mean of '
        'the other groups\' pooled F1 under that protocol, scored on the held-out group; the '
        'candidates are the defaults and the `--variant` / `--grid` sets (the `--ablation` '
        'switches are reported, never chosen).\n')


def data_text(groups) -> str:
    """One paragraph: every group, its frame count and points per frame."""
    items = ', '.join(f'`{g.name}` ({len(g.frames)} x {g.points_per_frame / 1000:,.0f}k)'
                      for g in groups)
    return (f'- Groups (frames x points per frame): {items}. Synthetic families: 1024 firings '
            'per revolution, HDL-64E-like beams unless the family says otherwise, range noise '
            '0.02 m, exact per-point truth (`scenes.synthetic.family_scan(family, seed)`; '
            '`family_scene(family, seed).description` says what each member shows).')


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--quick', action='store_true',
                    help='1 seed per family, cold only, 2 timing rounds; never writes')
    ap.add_argument('--real-only', action='store_true',
                    help='the labelled real scans only (no synthetic group); never writes')
    ap.add_argument('--seeds', type=int, default=None,
                    help=f'seeds per family (default {DEFAULT_SEEDS}, --quick 1)')
    ap.add_argument('--families', default='', help='comma list of families (default all)')
    ap.add_argument('--methods', default=','.join(METHOD_KEYS))
    ap.add_argument('--modes', default=None,
                    help='comma list of cold, streamed (default both; --quick cold)')
    ap.add_argument('--variant', action='append', default=[],
                    help='NAME:key=value,key=value (repeatable): this project with changed '
                         'parameters, cold, side by side with the defaults and a CV candidate')
    ap.add_argument('--grid', nargs='*', default=[], metavar='NAME=V1,V2',
                    help='variants of every combination of these values (a joint grid)')
    ap.add_argument('--ablation', action='store_true',
                    help='the one-at-a-time switches of ablation_variants() and the streamed '
                         'theta-learning variants (reported, not held-out candidates)')
    ap.add_argument('--timing-rounds', type=int, default=None,
                    help='timed rounds over the KITTI scans (default 10, --quick 2)')
    ap.add_argument('--output', type=Path, default=RESULTS)
    ap.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args(argv)
    args.seeds = args.seeds if args.seeds is not None else (1 if args.quick else DEFAULT_SEEDS)
    args.timing_rounds = (args.timing_rounds if args.timing_rounds is not None
                          else (2 if args.quick else 10))
    args.keys = [k.strip() for k in args.methods.split(',') if k.strip()]
    args.modes = [m.strip() for m in (args.modes or ('cold' if args.quick else ','.join(MODES)))
                  .split(',') if m.strip()]
    bad = sorted(set(args.keys) - set(METHOD_KEYS)) + sorted(set(args.modes) - set(MODES))
    if bad or not args.keys or 'cold' not in args.modes or args.seeds < 1 \
            or args.timing_rounds < 0:
        ap.error(f'--methods from {", ".join(METHOD_KEYS)}, --modes from cold, streamed (cold '
                 f'always; bad: {", ".join(bad) or "none"}); --seeds >= 1; --timing-rounds >= 0')
    try:
        args.variants = dict(parse_variant(v) for v in args.variant)
        args.variants.update(grid_variants(args.grid))
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))
    args.ablations = ablation_variants() if args.ablation else {}
    args.families = [f.strip() for f in args.families.split(',') if f.strip()] or None
    # only the full record of the defaults goes into RESULTS.md
    args.partial = (args.quick or args.real_only or args.families is not None
                    or args.seeds != DEFAULT_SEEDS or len(args.modes) < len(MODES)
                    or set(args.keys) != set(METHOD_KEYS))
    return args


def report(args, groups, results, unavailable, timing, candidates, cv_by_protocol,
           ablations) -> str:
    """The markdown of the run (the RESULTS.md section). ``candidates``: the defaults and the
    variants asked for, the held-out choice is made among them; ``ablations``: the defaults
    and the one-at-a-time switches (``--ablation``), reported but never a candidate."""
    cold = results['cold']
    keys = [k for k in args.keys if k not in unavailable]
    parts = ['## Ground quality (bench_quality.py)', '',
             common.machine_markdown(common.command_line()), settings_text(groups),
             data_text(groups)]
    parts += [f'- **{LABELS[k]} not run**: {why}' for k, why in unavailable.items()]
    parts += ['', '### Both protocols, cold: this project vs Patchwork++', '',
              both_protocols_table(groups, cold, cv_by_protocol, len(candidates)), '',
              losses_text(groups, cold), '',
              f'### Every method, cold ({MODE_TEXT["cold"]})', '',
              all_methods_table(groups, cold, keys, pooled_row_sets(groups))]
    if 'streamed' in results:
        parts += ['', f'### Every method, streamed ({MODE_TEXT["streamed"]})', '',
                  all_methods_table(groups, results['streamed'], keys, pooled_row_sets(groups))]
    if timing:
        parts += ['', f'### Time on the {timing["frames"]} KITTI scans ({timing["points"]:,.0f} '
                  f'points on average), streamed, {timing["rounds"]} rounds', '',
                  timing_table(timing, keys)]
    real = [g for g in groups if g.group == 'real']
    if len(candidates) > 1:
        for p in PROTOCOLS:  # synthetic truth is the same under both: its rows once
            shown = groups if p is DEFAULT_PROTOCOL else real
            parts += ['', f'### Variants of this project (cold; {p.name}; pooled F1 per '
                      f'{"group" if shown is groups else "real group"}, change vs defaults)', '',
                      variant_table(shown, candidates, p)]
        parts += ['', '### Leave-one-group-out choice among the defaults and the variants', '',
                  cv_table(cv_by_protocol, candidates)]
    if ablations:
        parts += ['', f'### Ablation: one switch at a time (cold; {DEFAULT_PROTOCOL.name}; '
                  'pooled F1 per group, change vs defaults)', '',
                  variant_table(groups, ablations, DEFAULT_PROTOCOL)]
        streamed = {'defaults': (results['streamed']['gp'] if 'streamed' in results else
                                 run_variants(groups, {'d': SegmenterParams()}, 'streamed')['d']),
                    **run_variants(groups, theta_stream_variants(), 'streamed')}
        parts += ['', '### theta learning in a stream (streamed; pooled F1 per real group, '
                  'change vs defaults)', '', variant_table(real, streamed, DEFAULT_PROTOCOL)]
    return '\n'.join(parts) + '\n'


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    groups = load_groups(args.seeds, args.families, synthetic=not args.real_only)
    if not groups:
        print('bench_quality: no group to evaluate (no data found)', file=sys.stderr)
        return 1
    print(f'loaded {len(groups)} groups, {sum(len(g.frames) for g in groups)} frames in '
          f'{time.perf_counter() - t_start:.0f} s', file=sys.stderr, flush=True)
    results, unavailable = run_all(groups, args.keys, args.modes)
    if 'gp' not in results['cold']:
        print(f'bench_quality: this project did not run: {unavailable.get("gp")}',
              file=sys.stderr)
        return 1
    keys = [k for k in args.keys if k not in unavailable]
    timing = time_kitti(groups, keys, args.timing_rounds)
    defaults = {'defaults': results['cold']['gp']}
    candidates = {**defaults, **run_variants(groups, args.variants)}
    ablations = {**defaults, **run_variants(groups, args.ablations)} if args.ablations else {}
    cv_by_protocol = {p.name: cross_validate(candidates, groups, p) for p in PROTOCOLS}
    text = report(args, groups, results, unavailable, timing, candidates, cv_by_protocol,
                  ablations)
    text += f'\nTotal wall time of the run: {time.perf_counter() - t_start:.0f} s.\n'
    print(text)
    if args.partial:
        print('partial run (--quick, --real-only, a subset or other seeds): RESULTS.md not '
              'written', file=sys.stderr)
    elif not args.no_write:
        common.update_results_section(args.output, 'bench_quality', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
