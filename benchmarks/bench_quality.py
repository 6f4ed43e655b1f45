# SPDX-License-Identifier: Apache-2.0
"""Ground quality on every labelled scan and synthetic family: the evaluation deciding defaults.

Usage::

    python benchmarks/bench_quality.py [--quick] [--seeds N] [--no-write]
                                       [--methods gp,patchworkpp,patchwork,linefit]
                                       [--variant NAME:key=value,key=value ...] [--ablation]
                                       [--cv] [--timing-rounds N]

Data (each absent file is skipped with a printed reason):

* real: the spvnas SemanticKITTI scan, KITTI 00 frames 0-2 with SemanticKITTI labels (one scene,
  streamed in order), the RELLIS-3D Ouster OS1-64 scan (its own ontology, organised with (0,0,0)
  no-returns); see ../shared/data/README.md sections 1 and 6;
* synthetic: the eight classic scenes of ``scenes.synthetic`` (seed 0, group ``classic``) and every
  randomised family of ``scenes.synthetic.FAMILY_NAMES`` with seeds 0..N-1 (3, ``--quick`` 1).

Methods, fed the same (N, 4) float32 frames and scored alike (``common.score``): this project
(``SegmenterParams()`` defaults or a variant; no mount height), Patchwork++, Patchwork and
linefit with their documented defaults plus what their users set for a mount (see
``peer_settings``).

Modes: ``cold`` = a fresh instance per frame; ``streamed`` = one instance over a data set's
frames in order (a peer is rebuilt only when the mount it was configured for changes).

Library use (cross-validation of defaults)::

    from bench_quality import load_groups, evaluate, loso_cv
    groups = load_groups(seeds=3)
    counts = evaluate(SegmenterParams(), groups[0].frames, mode='cold')   # [{tp, fp, fn, tn}]
    table = loso_cv({'default': SegmenterParams(), 'L1.5': SegmenterParams(
        max_length_factor=1.5)}, groups)
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_peers  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation import SegmenterParams  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
METHOD_KEYS = ('gp', 'patchworkpp', 'patchwork', 'linefit')
MODES = ('cold', 'streamed')
MODE_TEXT = {'cold': 'a fresh instance per frame',
             'streamed': "one instance over a data set's frames in order; a synthetic family's "
                         'seeds are different scenes played as one stream'}
CLASSIC_SCENES = common.FLAT_SCENES + common.SLOPED_SCENES + common.MIXED_SCENES
# Below this mount height (m) the peers get a short minimum range: their KITTI defaults (2.7 m)
# would drop the whole floor of a room seen from 0.5 m.
LOW_MOUNT_M = 1.0
LOW_MOUNT_MIN_RANGE_M = 0.3
# linefit's own KITTI config (Kin-Zhang/linefit assets/config/kitti.toml) sets 1.78 m for the
# 1.73 m KITTI mount; its documented default is kept for KITTI.
LINEFIT_KITTI_HEIGHT_M = 1.78


# ------------------------------------------------------------------------------------ data

def load_groups(seeds: int = 3, families=None, real: bool = True, classic: bool = True) -> list:
    """Every evaluation group as a ``common.Dataset``: one real scene or one synthetic family.

    Real groups: ``kitti_spvnas``, ``kitti00_labeled`` (frames 0-2, one scene), ``rellis3d``;
    synthetic: ``classic`` (the eight fixed scenes) and each family with ``seeds`` seeds.
    """
    groups = []
    if real:
        ds = common.load_labeled_kitti()
        if ds is not None:
            for frame in ds.frames:
                frame.mount_height_m = common.KITTI_SENSOR_HEIGHT_M
            ds.name = 'kitti_spvnas'
            groups.append(ds)
        for loader in (common.load_kitti00_labeled, common.load_rellis):
            ds = loader()
            if ds is not None:
                groups.append(ds)
    if classic:
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
            ('kitti', 'semantickitti'))
        return bench_peers.LinefitMethod(LINEFIT_KITTI_HEIGHT_M if kitti else height)
    raise ValueError(f'method: unknown {key!r}; choose from {", ".join(METHOD_KEYS)}')


def run_frames(key: str, frames, mode: str = 'cold', params: SegmenterParams | None = None,
               timings: list | None = None) -> list:
    """Per-frame metrics (``common.score`` dicts) of one method over ``frames``.

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
        out.append(common.score(mask, frame))
    return out


def evaluate(params: SegmenterParams, frames, mode: str = 'cold') -> list:
    """Per-frame counts ``{'tp', 'fp', 'fn', 'tn'}`` of this project with ``params``.

    ``frames``: ``common.Frame`` objects with truth, in stream order for ``mode='streamed'``.
    """
    params = params.validate()
    return [{k: m[k] for k in ('tp', 'fp', 'fn', 'tn')}
            for m in run_frames('gp', list(frames), mode, params)]


def f1_of(counts) -> float:
    """Pooled F1 of a list of count dicts (sum TP/FP/FN)."""
    pooled = common.pool(list(counts))
    return pooled['f1'] if pooled else float('nan')


def loso_cv(candidates: dict, groups=None, mode: str = 'cold') -> list:
    """Leave-one-group-out choice of parameters: one row per held-out group.

    For each group (a real scene -- KITTI 00 frames 0-2 are one -- or a synthetic family) the
    candidate with the best score on the *other* groups is chosen; the row gives its F1 on the
    held-out group. The score on the rest is the mean of the groups' pooled F1, so that every
    scene or family weighs the same whatever its point count.
    """
    groups = groups if groups is not None else load_groups()
    counts = {name: {g.name: evaluate(p, g.frames, mode) for g in groups}
              for name, p in candidates.items()}
    return loso_cv_from_counts(counts, groups)


def loso_cv_from_counts(counts: dict, groups) -> list:
    """``loso_cv`` on counts already computed: counts[candidate][group name] = per-frame list."""
    f1 = {name: {g.name: f1_of(per[g.name]) for g in groups} for name, per in counts.items()}
    rows = []
    for held in groups:
        rest = {name: float(np.nanmean([v for g, v in per.items() if g != held.name]))
                for name, per in f1.items()}
        chosen = max(rest, key=rest.get)
        rows.append({'held_out': held.name, 'chosen': chosen, 'rest_score': rest[chosen],
                     'held_out_f1': f1[chosen][held.name],
                     'default_f1': f1.get('defaults', {}).get(held.name, float('nan'))})
    return rows


# ------------------------------------------------------------------------------------ variants

def parse_variant(text: str) -> tuple:
    """'NAME:key=value,key=value' -> (NAME, SegmenterParams); ValueError with the reason."""
    name, sep, body = text.partition(':')
    if not sep or not name.strip():
        raise ValueError(f'--variant {text!r}: expected NAME:key=value,key=value')
    values = common.parse_param_values([x for x in body.split(',') if x.strip()])
    return name.strip(), SegmenterParams(**values).validate()


def ablation_variants() -> dict:
    """One-at-a-time switches of the paper's components and of every boolean field.

    * OLS instead of Deming: lambda = var(z err) / var(r err) -> infinity makes the Deming slope
      (d + sqrt(d^2 + 4 lambda s_rz^2)) / (2 s_rz), d = s_zz - lambda s_rr, tend to s_rz / s_rr,
      the ordinary least-squares fit of z on r; the range allows 1e4.
    * constant L: min_length_factor just below max_length_factor (equal is rejected), so every
      d_i is clipped to one value and L = a d is the same everywhere; when the defaults are
      already that, the paper's non-stationary L instead (d_i in [0.05, 2]);
    * theta frozen: no marginal-likelihood evaluations at all, theta stays at its initial value;
    * outlier limit fixed: ``outlier_std_factor`` 0 (the leave-one-out std does not widen it);
    * raw length factors: ``length_factor_smoothing_passes`` 0 (the paper's d_i, not smoothed
      along the segment);
    * the wide-terrain rule off: ``outlier_wide_terrain_m`` 0 (obstacle tops that both
      neighbouring segments continue are rejected like any other);
    * every bool field of SegmenterParams (``use_*`` switches and others) flipped, discovered at
      run time so that new switches appear without code changes.
    """
    d = SegmenterParams()
    out = {
        'OLS lines (deming_variance_ratio=1e4)': {'deming_variance_ratio': 1e4},
        **({'constant L (min_length_factor=0.999*max)': {
            'min_length_factor': 0.999 * d.max_length_factor}}
           if d.min_length_factor < 0.9 * d.max_length_factor else
           {'non-stationary L (min_length_factor=0.05, max_length_factor=2)': {
               'min_length_factor': 0.05, 'max_length_factor': 2.0}}),
        'theta frozen (0 optimizer evaluations)': {'optimizer_first_frame_evaluations': 0,
                                                   'optimizer_max_evaluations': 0},
        'outlier_std_factor=0': {'outlier_std_factor': 0.0},
        'length_factor_smoothing_passes=0': {'length_factor_smoothing_passes': 0},
        'outlier_wide_terrain_m=0': {'outlier_wide_terrain_m': 0.0},
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

def run_all(groups, keys, modes, params=None) -> dict:
    """results[mode][key][group name] = per-frame metrics; unavailable[key] = reason."""
    results = {mode: {} for mode in modes}
    unavailable = {}
    for key in keys:
        for mode in modes:
            per = {}
            for g in groups:
                try:
                    per[g.name] = run_frames(key, g.frames, mode, params)
                except Exception as exc:  # noqa: BLE001 - report any peer failure verbatim
                    unavailable[key] = f'{type(exc).__name__}: {exc}'
                    break
            if key in unavailable:
                break
            results[mode][key] = per
            print(f'{key} {mode} done', file=sys.stderr, flush=True)
    return results, unavailable


def time_kitti(groups, keys, rounds: int) -> dict:
    """Seconds per frame of each method streamed over the ~124k-point KITTI scans.

    One untimed warm-up round, then ``rounds`` timed rounds, methods taking turns frame by frame
    so load from other jobs on this shared machine hits all alike.
    """
    frames = [f for g in groups if is_kitti(g) for f in g.frames]
    if not frames:
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
    return {'times': times, 'frames': len(frames),
            'points': float(np.mean([len(f) for f in frames]))}


# ------------------------------------------------------------------------------------ tables

LABELS = {'gp': 'this project', 'patchworkpp': 'Patchwork++', 'patchwork': 'Patchwork',
          'linefit': 'linefit'}


def prf(m) -> str:
    if m is None:
        return '-'
    return ' / '.join(common.fmt(m[k], 3) for k in ('precision', 'recall', 'f1'))


def obstacle_to_ground(metrics) -> float:
    """Share of scored non-ground points called ground (false-positive rate), pooled."""
    fp = sum(m['fp'] for m in metrics if m)
    tn = sum(m['tn'] for m in metrics if m)
    return fp / (fp + tn) if fp + tn else float('nan')


def pooled_rows(groups, per_method, keys):
    """Rows per group, then pooled rows of the SemanticKITTI scans and of group categories."""
    aggregates = [('**SemanticKITTI, 4 scans pooled**', [g for g in groups if is_kitti(g)])]
    for category in sorted({g.group for g in groups if g.group.startswith('synthetic')}):
        members = [g for g in groups if g.group == category]
        aggregates.append((f'**{category} pooled** ({", ".join(g.name for g in members)})',
                           members))
    rows = []
    for name, members in [(g.name, [g]) for g in groups] + aggregates:
        if not members:
            continue
        metrics = {k: [m for g in members for m in per_method[k][g.name]] for k in keys}
        pooled = {k: common.pool(metrics[k]) for k in keys}
        row = [name, str(sum(len(g.frames) for g in members))]
        row += [prf(pooled[k]) for k in keys]
        if 'gp' in keys and 'patchworkpp' in keys and pooled['gp'] and pooled['patchworkpp']:
            row.append(f"{pooled['gp']['f1'] - pooled['patchworkpp']['f1']:+.3f}")
        elif 'gp' in keys and 'patchworkpp' in keys:
            row.append('-')
        row += [common.fmt(100 * obstacle_to_ground(metrics[k]), 1) for k in keys
                if k in ('gp', 'patchworkpp')]
        rows.append(row)
    return rows


def losses_text(groups, per_method) -> str:
    """One line: the groups where this project's pooled F1 is below Patchwork++'s."""
    if 'gp' not in per_method or 'patchworkpp' not in per_method:
        return ''
    lost = []
    for g in groups:
        ours, ref = f1_of(per_method['gp'][g.name]), f1_of(per_method['patchworkpp'][g.name])
        if ours < ref:
            lost.append(f'{g.name} ({ours:.3f} vs {ref:.3f}, {ours - ref:+.4f})')
    return ('Below Patchwork++ (pooled F1, ours vs theirs): ' + (', '.join(lost) or 'none')
            + '.')


def pooled_table(groups, per_method, keys) -> str:
    headers = ['data set / family', 'frames'] + [f'{LABELS[k]} P / R / F1' for k in keys]
    if 'gp' in keys and 'patchworkpp' in keys:
        headers.append('F1 ours - Patchwork++')
    headers += [f'{LABELS[k]} non-ground called ground %' for k in keys
                if k in ('gp', 'patchworkpp')]
    return common.markdown_table(headers, pooled_rows(groups, per_method, keys))


def per_frame_table(groups, per_method, keys) -> str:
    headers = ['frame', 'points'] + [f'{LABELS[k]} P / R / F1' for k in keys]
    rows = []
    for g in groups:
        for i, frame in enumerate(g.frames):
            rows.append([frame.name, common.fmt(len(frame))]
                        + [prf(per_method[k][g.name][i]) for k in keys])
    return common.markdown_table(headers, rows)


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


def variant_table(groups, variant_results) -> str:
    """Pooled F1 per group for each variant of this project (same run, cold)."""
    names = list(variant_results)
    headers = ['data set / family'] + names
    rows = []
    base = variant_results[names[0]]
    for g in groups:
        row = [g.name]
        for name in names:
            f1 = f1_of(variant_results[name][g.name])
            delta = f1 - f1_of(base[g.name])
            row.append(common.fmt(f1, 3) + ('' if name == names[0] else f' ({delta:+.3f})'))
        rows.append(row)
    macro = {n: float(np.nanmean([f1_of(r[g.name]) for g in groups]))
             for n, r in variant_results.items()}
    base_macro = macro[names[0]]
    rows.append(['**mean of groups**'] + [
        common.fmt(macro[n], 3) + ('' if n == names[0] else f' ({macro[n] - base_macro:+.3f})')
        for n in names])
    return common.markdown_table(headers, rows)


def cv_table(rows) -> str:
    return common.markdown_table(
        ['held-out group', 'chosen on the rest', 'its mean F1 on the rest', 'held-out F1',
         'defaults held-out F1'],
        [[r['held_out'], r['chosen'], common.fmt(r['rest_score'], 3),
          common.fmt(r['held_out_f1'], 3), common.fmt(r['default_f1'], 3)] for r in rows])


def settings_text(groups) -> str:
    rellis = [f for g in groups if g.name == 'rellis3d' for f in g.frames]
    rellis_h = f'{rellis[0].mount_height_m:.2f} m' if rellis else 'n/a'
    return (
        '- Peer settings: Patchwork++ (`pypatchworkpp.Parameters()`) and Patchwork '
        '(`PatchworkParams()`) defaults with `sensor_height` = the mount height: 1.73 m on '
        f'KITTI, {rellis_h} on RELLIS-3D (measured once: minus the median z of the labelled '
        'ground 3-10 m from the sensor), the true mount height on synthetic scans '
        f'(0.3-2.5 m); below {LOW_MOUNT_M:g} m mounts `min_range` = {LOW_MOUNT_MIN_RANGE_M:g} m '
        '(Patchwork: also the first zone\'s `min_ranges`), otherwise their default 2.7 m. '
        'Patchwork++ RNR (reflected-noise removal) on for the KITTI scans (remission intensity), '
        'off on RELLIS-3D (its intensity is normalised to ~0.012, not remission) and on '
        'synthetic scans (their intensity is not physically modelled). linefit: its '
        f'repository\'s kitti.toml (r_min 0.1 m) with `height` {LINEFIT_KITTI_HEIGHT_M} m on '
        'KITTI (the file\'s own value) and the mount height elsewhere. Tilted mounts: the peers '
        'get the height only (none of them takes a tilt).\n'
        '- This project: one parameter set (`SegmenterParams()` defaults unless a variant is '
        'named) for every data set, no mount height.\n'
        '- Scoring (everyone alike, positive = ground, TP/FP/FN summed over frames for pooled '
        'rows): SemanticKITTI ground 40/44/48/49/60/72, 0/1 ignored, 70 vegetation non-ground; '
        'RELLIS-3D ground 1/3/10/23/31/33, 0 void ignored; synthetic truth = terrain hit (curb '
        'faces ground), (0, 0, 0) no-return rows of organised scans ignored.\n')


def data_text(groups) -> str:
    """A details block: every group, its frames' sizes and what each synthetic member shows."""
    lines = ['<details><summary>Data: groups and frames</summary>', '']
    for g in groups:
        lines.append(f'- `{g.name}` ({g.group}, {len(g.frames)} frame(s), '
                     f'{g.points_per_frame:,.0f} points per frame): {g.description}')
        if g.name not in ('classic',) and g.group.startswith('synthetic'):
            try:
                from scenes.synthetic import family_scene
                for frame in g.frames:
                    seed = int(frame.name.rsplit('_', 1)[1])
                    lines.append(f'  - `{frame.name}`: {family_scene(g.name, seed).description}')
            except (ImportError, ValueError):
                pass
    lines += ['', 'Synthetic family scans: 1024 firings per revolution, HDL-64E-like beams unless '
              'the family says otherwise, range noise 0.02 m, exact per-point truth '
              '(`scenes.synthetic.family_scan(family, seed)`).', '', '</details>']
    return '\n'.join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--quick', action='store_true', help='1 seed per family, 2 timing rounds')
    ap.add_argument('--seeds', type=int, default=None, help='seeds per family (default 3)')
    ap.add_argument('--families', default='', help='comma list of families (default all)')
    ap.add_argument('--methods', default=','.join(METHOD_KEYS))
    ap.add_argument('--variant', action='append', default=[],
                    help='NAME:key=value,key=value (repeatable): this project with changed '
                         'parameters, evaluated side by side with the defaults (cold)')
    ap.add_argument('--ablation', action='store_true',
                    help='evaluate the one-at-a-time switches of ablation_variants() (cold)')
    ap.add_argument('--cv', action='store_true',
                    help='leave-one-group-out choice among defaults + variants (+ ablation)')
    ap.add_argument('--timing-rounds', type=int, default=None,
                    help='timed rounds over the KITTI scans (default 10, --quick 2)')
    ap.add_argument('--output', type=Path, default=RESULTS)
    ap.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args(argv)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 3)
    rounds = args.timing_rounds if args.timing_rounds is not None else (2 if args.quick else 10)
    keys = [k.strip() for k in args.methods.split(',') if k.strip()]
    bad = sorted(set(keys) - set(METHOD_KEYS))
    if bad or not keys or seeds < 1 or rounds < 0:
        ap.error(f'--methods from {", ".join(METHOD_KEYS)} (bad: {", ".join(bad)}); '
                 '--seeds >= 1; --timing-rounds >= 0')
    try:
        variants = dict(parse_variant(v) for v in args.variant)
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))
    if args.ablation:
        variants.update(ablation_variants())
    families = [f.strip() for f in args.families.split(',') if f.strip()] or None

    t_start = time.perf_counter()
    command = common.command_line()
    groups = load_groups(seeds, families)
    print(f'loaded {len(groups)} groups, {sum(len(g.frames) for g in groups)} frames in '
          f'{time.perf_counter() - t_start:.0f} s', file=sys.stderr, flush=True)
    results, unavailable = run_all(groups, keys, MODES)
    keys = [k for k in keys if k not in unavailable]
    timing = time_kitti(groups, keys, rounds) if rounds else {}

    parts = ['## Ground quality (bench_quality.py)', '', common.machine_markdown(command),
             settings_text(groups)]
    for key, why in unavailable.items():
        parts.append(f'- **{LABELS[key]} not run**: {why}')
    parts += ['', data_text(groups)]
    for mode in MODES:
        parts += ['', f'### Pooled per data set / family, {mode} ({MODE_TEXT[mode]})', '',
                  pooled_table(groups, results[mode], keys), '',
                  losses_text(groups, results[mode])]
    if timing:
        parts += ['', f'### Time on the {timing["frames"]} KITTI scans '
                  f'({timing["points"]:,.0f} points on average), streamed, {rounds} rounds', '',
                  timing_table(timing, keys)]
    if variants:
        t0 = time.perf_counter()
        variant_results = {'defaults': results['cold']['gp'] if 'gp' in results['cold'] else {
            g.name: run_frames('gp', g.frames, 'cold') for g in groups}}
        for name, params in variants.items():
            variant_results[name] = {g.name: run_frames('gp', g.frames, 'cold', params)
                                     for g in groups}
            print(f'variant {name} done', file=sys.stderr, flush=True)
        parts += ['', '### Variants of this project (cold; pooled F1 per group, change vs '
                  'defaults)', '', variant_table(groups, variant_results),
                  '', f'Variants took {time.perf_counter() - t0:.0f} s.']
        if args.ablation:
            streamed = {'defaults': results['streamed']['gp'] if 'gp' in results['streamed']
                        else {g.name: run_frames('gp', g.frames, 'streamed') for g in groups}}
            for name, params in theta_stream_variants().items():
                streamed[name] = {g.name: run_frames('gp', g.frames, 'streamed', params)
                                  for g in groups}
            parts += ['', '### theta learning in a stream (streamed; pooled F1 per group, '
                      'change vs defaults)', '', variant_table(groups, streamed)]
        if args.cv:
            counts = {n: {g: [{k: m[k] for k in ('tp', 'fp', 'fn', 'tn')} for m in ms]
                          for g, ms in r.items()} for n, r in variant_results.items()}
            rows = loso_cv_from_counts(counts, groups)
            parts += ['', '### Leave-one-group-out choice among defaults and variants', '',
                      cv_table(rows)]
    for mode in MODES:
        parts += ['', f'<details><summary>Per frame, {mode}</summary>', '',
                  per_frame_table(groups, results[mode], keys), '', '</details>']
    parts += ['', f'Total wall time of the run: {time.perf_counter() - t_start:.0f} s.']
    text = '\n'.join(parts) + '\n'
    print(text)
    if not args.no_write:
        common.update_results_section(args.output, 'bench_quality', text)
        print(f'updated {args.output}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
