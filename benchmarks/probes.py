# SPDX-License-Identifier: Apache-2.0
"""Probes: measurements whose findings RESULTS.md records; none of them chooses a default.

Usage::

    python benchmarks/probes.py errors [--set name=value ...] [--no-write]
    python benchmarks/probes.py perturbed [--set ...] [--no-write]
    python benchmarks/probes.py nonrepetitive [--set ...] [--no-write]
    python benchmarks/probes.py high-mount [--set ...] [--no-write]
    python benchmarks/probes.py length-scale [--set ...] [--no-write]
    python benchmarks/probes.py ceiling [--set ...] [--no-write]

Each subcommand writes its own RESULTS.md section unless ``--no-write`` or ``--set`` (this
project's parameters changed over the defaults: not the record of the defaults). Scoring:
``gp_ground_segmentation.tools.evaluation`` under the default protocol (vegetation non-ground);
Patchwork++ with bench_quality.py's settings (its defaults plus the mount height).

``errors`` (~35 s): where the defaults' errors lie on every labelled real scan (cold):

- missed ground (FN) turned obstacle by the structure test (``details.structure_feet``) or by
  the height test (z - z_hat above the point's threshold), with the classes they carry;
- false ground (FP) by class and by height above the predicted ground (``h``);
- how well features separate the main false-ground class (SemanticKITTI vegetation 70,
  RELLIS-3D tree 4 and bush 19) from the true ground kept, as Mann-Whitney AUCs (0.5 = no
  separation): remission (KITTI only: RELLIS-3D's intensity is normalised), the highest point
  within ``NEIGHBOUR_RADIUS_M`` and the share of the points within 0.3 / 0.5 m standing more
  than 0.15 m above z_hat;
- whether the ground continues beyond a structure foot along its ray (true under a car sill,
  not behind a wall), wrongly against rightly condemned feet;
- what rules on these features would trade as post-processes on the labels.

``perturbed`` (~10 s): the labelled scans made to look like other sensors and pipelines, so
that their labels still hold: as recorded; a 6 cm voxel grid (first point per voxel); every 2nd
/ 4th ring (a 32- / 16-beam sensor with the same field of view; the ring of a point is its row
in RELLIS-3D's organised 64 x 2048 cloud and, in a KITTI scan stored ring after ring, the
number of azimuth wraps before it); half the returns (seed 0); 3 cm range noise along the ray
(seed 0). Pooled P / R / F1 per data set, this project vs Patchwork++, cold.

``nonrepetitive`` (~6 s): scans without rings, a stand-in for a non-repetitive scanning LiDAR
(Livox-like): the classic scenes ``flat``, ``ramp15``, ``hill``, ``mixed`` and ``onslope15``
ray-cast from 1.73 m along 280 random elevations x 1,200 azimuths, a random ``POINTS_PER_SCAN``
of the returns kept, through a forward 70 deg window and over 360 deg; a random direction
pattern is not a model of a real rosette.

``high-mount`` (~5 s): the classic ``flat``, ``hill``, ``ramp15`` and ``mixed`` scenes from
0.4, 1.73, 3.0 and 4.5 m mounts (a truck, a mast): F1 vs Patchwork++ given the height, this
project's missed ground split by the stage that dropped it (structure or height test), and the
training candidates rejected as outliers.

``length-scale`` (~20 s): the paper's non-stationary length scale (eqs. 8, 12) measured on every
labelled real scan, cold: the learned theta and the share of training candidates at each clip
of d (``min_length_factor`` / ``max_length_factor``) with the paper's length scale, and the F1
under both protocols of the defaults (one length factor), the paper's d clipped as shipped, the
paper's d unclipped (d_max 100) and with the gain's bound raised to 50.

``ceiling`` (~15 s): what a perfect ground surface would give this labelling (not a method: the
surface comes from the labels): z_hat of every point the 10th percentile of the labelled
ground's z within 0.5 m, then the same threshold, structure test and free space as the
defaults, pooled over the SemanticKITTI scans under both protocols, beside the defaults and
Patchwork++.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import mannwhitneyu

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_quality  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402
from gp_ground_segmentation.tools.evaluation import (  # noqa: E402
    SEMANTIC_KITTI, ground_truth_from_labels, pooled_metrics, truth_metrics)
from scenes.synthetic import make_scene, simulate_scan  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'


def report_probe(args, section: str, title: str, note: str, headers, rows) -> str:
    """A probe's RESULTS.md section (title, machine and command, ``note``, the table), printed,
    and written unless ``--no-write`` or ``--set`` was given. Returns the text."""
    text = (f'## {title}\n\n' + common.machine_markdown(common.command_line()) + '\n' + note
            + '\n\n' + common.markdown_table(headers, rows) + '\n')
    print(text)
    if not args.no_write and not args.set:
        common.update_results_section(RESULTS, section, text)
    return text


def _prf(m) -> str:
    return f'{m["precision"]:.3f} / {m["recall"]:.3f} / {m["f1"]:.3f}'


# ------------------------------------------------------------------------------------ errors

NEIGHBOUR_RADIUS_M = 0.2  # "right beside": a few beam spacings on a 64-beam scan at 10 m
# thresholds on the neighbourhood's highest point above z_hat (m) whose trade is reported
NEIGHBOUR_THRESHOLDS_M = (0.1, 0.15, 0.2, 0.3)
# the share of raised neighbours: within these radii (m), above this height over z_hat (m)
RAISED_RADII_M = (0.3, 0.5)
RAISED_HEIGHT_M = 0.15
RAISED_SHARES = (0.3, 0.5, 0.7)
# ground beyond a structure foot along its ray: within this height of z_hat (m), this azimuth
# (deg) and 0.1 m to 0.1 m + this span (m) farther out
BEYOND_HEIGHT_M = 0.1
BEYOND_AZIMUTH_DEG = 0.15
BEYOND_SPAN_M = 2.0
# the rules RESULTS.md keeps (one of each kind; the script prints them all)
WRITTEN_RULES = ('highest within 0.2 m > 0.2 m', 'share within 0.5 m above 0.15 m > 0.5',
                 'spare every foot with ground beyond')

SEMANTIC_KITTI_NAMES = {
    10: 'car', 11: 'bicycle', 13: 'bus', 15: 'motorcycle', 18: 'truck', 20: 'other-vehicle',
    30: 'person', 31: 'bicyclist', 40: 'road', 44: 'parking', 48: 'sidewalk',
    49: 'other-ground', 50: 'building', 51: 'fence', 52: 'other-structure', 60: 'lane-marking',
    70: 'vegetation', 71: 'trunk', 72: 'terrain', 80: 'pole', 81: 'traffic-sign',
    99: 'other-object', 252: 'moving-car'}
RELLIS_3D_NAMES = {
    1: 'dirt', 3: 'grass', 4: 'tree', 5: 'pole', 6: 'water', 7: 'sky', 8: 'vehicle',
    9: 'object', 10: 'asphalt', 12: 'building', 15: 'log', 17: 'person', 18: 'fence',
    19: 'bush', 23: 'concrete', 27: 'barrier', 31: 'puddle', 33: 'mud', 34: 'rubble'}


def real_scans(data_dir: Path = common.DATA_DIR) -> list:
    """(name, points, classes, ontology, class names, remission?) of every labelled real scan
    found; missing files are skipped with a line on stderr."""
    scans = []
    for scan in common.labelled_scans(data_dir):
        if not scan.exists():
            print(f'[data] skipped {scan.name}: {scan.bin_path} or its labels not found',
                  file=sys.stderr)
            continue
        points, classes = scan.read()
        kitti = scan.ontology is SEMANTIC_KITTI
        scans.append((scan.name, points, classes, scan.ontology,
                      SEMANTIC_KITTI_NAMES if kitti else RELLIS_3D_NAMES, kitti))
    return scans


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """Mann-Whitney AUC: the chance that a ``positive`` value exceeds a ``negative`` one."""
    if positive.size == 0 or negative.size == 0:
        return float('nan')
    return float(mannwhitneyu(positive, negative).statistic / (positive.size * negative.size))


def top_classes(classes: np.ndarray, names: dict, k: int = 3) -> str:
    ids, counts = np.unique(classes, return_counts=True)
    order = np.argsort(-counts)[:k]
    return ', '.join(f'{names.get(int(ids[i]), int(ids[i]))} {counts[i]:,}' for i in order)


def spread(values: np.ndarray) -> str:
    """median [10th, 90th percentile] of ``values``."""
    if values.size == 0:
        return '-'
    p10, p50, p90 = np.percentile(values, (10, 50, 90))
    return f'{p50:.2f} [{p10:.2f}, {p90:.2f}]'


def ground_beyond_feet(points, h, feet_index):
    """How many points within ``BEYOND_HEIGHT_M`` of z_hat lie 0.1 m to 0.1 +
    ``BEYOND_SPAN_M`` m farther out than each foot, within ``BEYOND_AZIMUTH_DEG`` of its
    azimuth: the ground continuing under a car sill, not behind a wall."""
    r = np.hypot(points[:, 0], points[:, 1]).astype(np.float64)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0])).astype(np.float64)
    low = np.flatnonzero(np.isfinite(h) & (np.abs(h) < BEYOND_HEIGHT_M))
    if low.size == 0 or feet_index.size == 0:
        return np.zeros(feet_index.size, dtype=np.intp)
    # a box |d azimuth| <= BEYOND_AZIMUTH_DEG, 0.1 <= d r <= 0.1 + span: a Chebyshev ball of
    # radius 1 in scaled coordinates
    az_scale, r_scale = 1.0 / BEYOND_AZIMUTH_DEG, 2.0 / BEYOND_SPAN_M
    tree = cKDTree(np.c_[azimuth[low] * az_scale, r[low] * r_scale])
    centre = np.c_[azimuth[feet_index] * az_scale,
                   (r[feet_index] + 0.1 + BEYOND_SPAN_M / 2.0) * r_scale]
    return np.array([len(n) for n in tree.query_ball_point(centre, 1.0, p=np.inf)],
                    dtype=np.intp)


def analyse(name, points, classes, ontology, names, remission, params):
    """One row of the error table and the rows of the rule table of one scan."""
    truth, evaluated = ground_truth_from_labels(classes, ontology=ontology)
    result = GroundSegmenter(params).segment(points[:, :3], details=True)
    details = result.details
    ground = result.ground_mask
    h = result.height_above_ground
    feet = np.zeros(len(points), dtype=bool)
    if details.structure_feet is not None:
        feet[details.valid_index] = details.structure_feet
    tp = evaluated & truth & ground
    fp = evaluated & ~truth & ground
    fn = evaluated & truth & ~ground
    main_fp_classes = (70,) if ontology is SEMANTIC_KITTI else (4, 19)
    main_fp = fp & np.isin(classes, main_fp_classes)
    # the neighbours within NEIGHBOUR_RADIUS_M and RAISED_RADII_M of each point called ground
    called = np.flatnonzero(ground)
    xy = points[:, :2].astype(np.float64)
    tree = cKDTree(xy)
    finite_h = np.where(np.isfinite(h), h, -np.inf)
    highest = np.full(len(points), np.nan)
    highest[called] = [finite_h[n].max()
                       for n in tree.query_ball_point(xy[called], NEIGHBOUR_RADIUS_M)]
    raised = {}
    for radius in RAISED_RADII_M:
        share = np.zeros(len(points))
        share[called] = [np.mean(finite_h[n] > RAISED_HEIGHT_M)
                         for n in tree.query_ball_point(xy[called], radius)]
        raised[radius] = share
    # the structure feet, and which of them have ground beyond along their ray
    feet_index = np.flatnonzero(feet & evaluated)
    beyond = ground_beyond_feet(points, h, feet_index)
    wrong_feet = truth[feet_index]
    base = truth_metrics(ground, truth, evaluated)
    row = [name, f"{base['precision']:.3f} / {base['recall']:.3f} / {base['f1']:.4f}",
           f'{fn.sum():,}', f'{(fn & feet).sum():,}: {top_classes(classes[fn & feet], names)}',
           f'{(fn & ~feet).sum():,}: {top_classes(classes[fn & ~feet], names)}; '
           f'h {spread(h[fn & ~feet])}',
           f'{fp.sum():,}: {top_classes(classes[fp], names)}', spread(h[fp]), spread(h[main_fp]),
           f'{main_fp.sum() / max(1, fp.sum()):.0%}',
           (f'{auc(points[main_fp, 3], points[tp, 3]):.2f} / '
            f'{auc(points[main_fp, 3], points[tp & (classes == 72), 3]):.2f}')
           if remission else 'n/a',
           f'{auc(highest[main_fp], highest[tp]):.2f}',
           f'{spread(highest[main_fp])} vs {spread(highest[tp])}',
           ' / '.join(f'{auc(raised[radius][main_fp], raised[radius][tp]):.2f}'
                      for radius in RAISED_RADII_M),
           f'{auc(beyond[wrong_feet].astype(float), beyond[~wrong_feet].astype(float)):.2f}; '
           f'{np.mean(beyond[wrong_feet] > 0):.0%} vs {np.mean(beyond[~wrong_feet] > 0):.0%}']

    def rule_row(rule, labels):
        """The rule's trade on this scan, as counts (pooled over scans by rule_rows)."""
        m = truth_metrics(labels, truth, evaluated)
        return {'rule': rule, 'fp_removed': int((fp & ~labels).sum()),
                'main_removed': int((main_fp & ~labels).sum()),
                'tp_lost': int((tp & ~labels).sum()),
                'fp_added': int((evaluated & ~truth & labels & ~ground).sum()),
                'tp_back': int((evaluated & truth & labels & ~ground).sum()),
                'tp': int(tp.sum()), 'base': base, 'after': m}
    rules = [rule_row(f'highest within {NEIGHBOUR_RADIUS_M} m > {limit} m',
                      ground & ~(highest > limit)) for limit in NEIGHBOUR_THRESHOLDS_M]
    rules += [rule_row(f'share within {radius} m above {RAISED_HEIGHT_M} m > {share}',
                       ground & ~(raised[radius] > share))
              for radius in RAISED_RADII_M for share in RAISED_SHARES]
    spared = ground.copy()
    spared[feet_index[beyond > 0]] = True
    rules.append(rule_row('spare every foot with ground beyond', spared))
    return row, rules


def rule_rows(data: str, per_scan: list) -> list:
    """One table row per rule: its trade summed over ``data``'s scans (``per_scan``: each scan's
    list of rule_row dicts, same rules in the same order)."""
    out = []
    for trades in zip(*per_scan):
        keys = ('fp_removed', 'main_removed', 'tp_lost', 'fp_added', 'tp_back', 'tp')
        total = {k: sum(t[k] for t in trades) for k in keys}
        change = (pooled_metrics([t['after'] for t in trades])['f1']
                  - pooled_metrics([t['base'] for t in trades])['f1'])
        out.append([data, trades[0]['rule'], f"{total['fp_removed']:,}",
                    f"{total['main_removed']:,}", f"{total['tp_lost']:,}",
                    f"{total['fp_added']:,}", f"{total['tp_back']:,}",
                    f"{total['tp_lost'] / max(1, total['tp']):.1%}", f'{change:+.4f}'])
    return out


def run_errors(args, params) -> int:
    """``probes.py errors``: where the defaults' remaining errors lie on the labelled scans."""
    scans = real_scans()
    if not scans:
        print('no labelled real scans found under ../shared/data', file=sys.stderr)
        return 1
    rows, trades = [], {}
    for scan in scans:
        row, scan_trades = analyse(*scan, params)
        rows.append(row)
        data = 'SemanticKITTI' if scan[3] is SEMANTIC_KITTI else 'RELLIS-3D'
        trades.setdefault(data, []).append(scan_trades)
    rules = [row for data, per_scan in trades.items() for row in rule_rows(data, per_scan)]
    for row in rules:  # every rule printed; RESULTS.md keeps one of each kind
        print(' | '.join(row))
    rules = [row for row in rules if row[1] in WRITTEN_RULES]
    note = (
        'Cold, this project\'s defaults; h = z - z_hat (m), "median [10th, 90th percentile]". '
        'FN feet = true ground the structure test turned obstacle; FN height test = true '
        'ground above its threshold. Main false-ground class (main FP): SemanticKITTI '
        'vegetation (70), RELLIS-3D tree (4) and bush (19). AUCs of main FP against the true '
        'ground kept (TP; 0.5 = no separation): by remission (against all TP / the terrain '
        f'TP), by the highest point within {NEIGHBOUR_RADIUS_M} m horizontally (m above z_hat) '
        f'and by the share of the points within {" / ".join(map(str, RAISED_RADII_M))} m '
        f'standing more than {RAISED_HEIGHT_M} m above z_hat. Ground beyond a foot: points '
        f'within {BEYOND_HEIGHT_M} m of z_hat 0.1 to {0.1 + BEYOND_SPAN_M} m farther out than '
        f'a structure foot, within {BEYOND_AZIMUTH_DEG} deg of its azimuth; AUC of the wrongly '
        'condemned feet (true ground) against the rightly condemned ones, and the share of '
        'each that has any.\n\n'
        + common.markdown_table(
            ['scan', 'P / R / F1', 'FN', 'FN feet: classes', 'FN height test: classes; h',
             'FP: classes', 'FP h', 'main FP h', 'main class share of FP',
             'remission AUC vs all / terrain TP', 'highest-neighbour AUC',
             'highest neighbour: main FP vs TP', 'raised-share AUC',
             'ground beyond feet: AUC; wrong vs right feet with any'], rows)
        + '\n\nWhat a rule of each kind would trade as a post-process on the labels (all '
        f'{len(NEIGHBOUR_THRESHOLDS_M) + len(RAISED_RADII_M) * len(RAISED_SHARES) + 1} rules '
        "are printed), summed over the data set's scans (false ground removed, of it main "
        'class, true ground lost, false ground added, true ground given back, share of the TP '
        'lost, change of the pooled F1):')
    report_probe(args, 'probe_errors',
                 'Where the remaining errors lie on the labelled real scans (`probes.py errors`)',
                 note, ['data', 'rule', 'FP removed', 'main-class FP removed', 'TP lost',
                        'FP added', 'TP given back', 'share of TP lost', 'F1 change'], rules)
    return 0


# ------------------------------------------------------------------------------------ perturbed

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
    """The points ``keep`` of a labelled frame, with their truth and classes."""
    return dataclasses.replace(frame, points=np.ascontiguousarray(frame.points[keep]),
                               truth=frame.truth[keep], evaluated=frame.evaluated[keep],
                               classes=frame.classes[keep])


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


def run_perturbed(args, params) -> int:
    """``probes.py perturbed``: the labelled scans made to look like other sensors."""
    groups = common.labelled_groups()
    kitti = [f for g in groups if bench_quality.is_kitti(g) for f in g.frames]
    rellis = [f for g in groups if g.name == 'rellis3d' for f in g.frames]
    data = [(name, frames) for name, frames in ((f'SemanticKITTI ({len(kitti)} scans)', kitti),
                                                (f'RELLIS-3D ({len(rellis)} scan)', rellis))
            if frames]
    if not data:
        print('probes.py perturbed: no labelled scans found', file=sys.stderr)
        return 1
    rows = []
    for label, perturb in PERTURBATIONS:
        for data_name, frames in data:
            changed = [perturb(frame) for frame in frames]
            # cold: a fresh instance per scan, bench_quality's settings for each method
            ours = pooled_metrics(bench_quality.run_frames('gp', changed, params=params))
            theirs = pooled_metrics(bench_quality.run_frames('patchworkpp', changed))
            points = [len(frame.points) for frame in changed]
            rows.append([label, data_name, f'{int(np.mean(points)):,}', _prf(ours),
                         _prf(theirs), f'{ours["f1"] - theirs["f1"]:+.3f}'])
            print(' | '.join(rows[-1]), flush=True)
    report_probe(args, 'probe_perturbed',
                 'Labelled scans made to look like other sensors (`probes.py perturbed`)',
                 'Cold (a fresh instance per scan), pooled per data set; this project with '
                 '`SegmenterParams()` defaults, Patchwork++ with bench_quality.py\'s settings. '
                 'What each cloud is: the script\'s docstring. Not used to choose any default.',
                 ['cloud', 'data', 'points per scan', 'this project P / R / F1',
                  'Patchwork++ P / R / F1', 'F1 ours - Patchwork++'], rows)
    return 0


# ------------------------------------------------------------------------------------ rings

NONREPETITIVE_SCENES = ('flat', 'ramp15', 'hill', 'mixed', 'onslope15')
NONREPETITIVE_MOUNT_M = 1.73
POINTS_PER_SCAN = 60_000
# field of view: (name, half azimuth width deg or None for 360, lowest and highest elevation deg)
PATTERNS = (('forward 70 deg', 35.0, -35.0, 35.0), ('360 deg', None, -25.0, 15.0))


def ringless_scan(scene: str, half_azimuth_deg, low_deg: float, high_deg: float,
                  seed: int = 0):
    """(points (K, 4), is_ground (K,), returned (K,)) of ``scene`` seen from
    NONREPETITIVE_MOUNT_M along 280 random elevations in [low_deg, high_deg] x 1,200 azimuths,
    of which at most POINTS_PER_SCAN returns inside the field of view are kept at random (in
    their ray order)."""
    rng = np.random.default_rng(seed)
    elevations = np.sort(rng.uniform(low_deg, high_deg, 280))[::-1]  # top first
    scan = simulate_scan(make_scene(scene), elevations_deg=elevations, azimuth_steps=1200,
                         sensor_height_m=NONREPETITIVE_MOUNT_M, seed=1)
    inside = np.ones(len(scan.points), dtype=bool)
    if half_azimuth_deg is not None:
        azimuth = np.degrees(np.arctan2(scan.points[:, 1], scan.points[:, 0]))
        inside = np.abs(azimuth) <= half_azimuth_deg
    rows = np.flatnonzero(inside)
    rows = np.sort(rng.choice(rows, min(rows.size, POINTS_PER_SCAN), replace=False))
    return np.ascontiguousarray(scan.points[rows]), scan.is_ground[rows], scan.returned[rows]


def patchworkpp_metrics(points, is_ground, returned, mount_m: float):
    """Patchwork++'s metrics on one synthetic scan with bench_quality.py's settings for its
    mount (cold; made-up intensity flagged as absent, as common.load_family does), or None
    when pypatchworkpp is not installed."""
    frame = common.Frame('probe', np.ascontiguousarray(points), False, is_ground, returned,
                         mount_m)
    try:
        return bench_quality.run_frames('patchworkpp', [frame])[0]
    except ImportError:
        return None


def run_nonrepetitive(args, params) -> int:
    """``probes.py nonrepetitive``: scans without rings (a non-repetitive pattern)."""
    rows = []
    for pattern, half_azimuth, low, high in PATTERNS:
        for scene in NONREPETITIVE_SCENES:
            points, is_ground, returned = ringless_scan(scene, half_azimuth, low, high)
            result = GroundSegmenter(params).segment(points[:, :3])
            m = truth_metrics(result.ground_mask, is_ground, returned)
            peer = patchworkpp_metrics(points, is_ground, returned, NONREPETITIVE_MOUNT_M)
            rows.append([pattern, scene, f'{len(points):,}', _prf(m),
                         _prf(peer) if peer else 'n/a'])
            print(' | '.join(rows[-1]), flush=True)
    report_probe(
        args, 'probe_nonrepetitive',
        'Scans without rings, non-repetitive pattern (`probes.py nonrepetitive`)',
        'Cold, one scan per row (1.73 m mount, 280 random elevations x 1,200 azimuths, a random '
        'fifth of the returns kept: no regular rings); what is set: the script\'s docstring. '
        'Not used to choose any default.',
        ['field of view', 'scene', 'points', 'this project P / R / F1',
         'Patchwork++ P / R / F1'], rows)
    return 0


# ------------------------------------------------------------------------------------ mounts

HIGH_MOUNT_SCENES = ('flat', 'hill', 'ramp15', 'mixed')
MOUNTS_M = (0.4, 1.73, 3.0, 4.5)


def run_high_mount(args, params) -> int:
    """``probes.py high-mount``: the classic scenes from lower and higher mounts."""
    rows = []
    for scene in HIGH_MOUNT_SCENES:
        for mount in MOUNTS_M:
            scan = simulate_scan(make_scene(scene), sensor_height_m=mount, seed=1)
            result = GroundSegmenter(params).segment(scan.points[:, :3], details=True)
            m = truth_metrics(result.ground_mask, scan.is_ground, scan.returned)
            feet = np.zeros(len(scan.points), dtype=bool)
            feet[result.details.valid_index] = result.details.structure_feet
            missed = scan.is_ground & ~result.ground_mask
            peer = patchworkpp_metrics(scan.points, scan.is_ground, scan.returned, mount)
            rows.append([scene, f'{mount:.2f}', _prf(m),
                         f'{peer["f1"]:.3f}' if peer else 'n/a',
                         f'{np.count_nonzero(missed & feet):,}',
                         f'{np.count_nonzero(missed & ~feet):,}',
                         f'{result.stats["outlier_candidates"]:,} of '
                         f'{result.stats["candidates"]:,}'])
            print(' | '.join(rows[-1]), flush=True)
    report_probe(
        args, 'probe_high_mount',
        'Classic scenes from lower and higher mounts (`probes.py high-mount`)',
        'Cold, one scan per row (HDL-64E-like beams, seed 1); what is set: the script\'s '
        'docstring. Not used to choose any default.',
        ['scene', 'mount m', 'this project P / R / F1', 'Patchwork++ F1',
         'missed ground: structure test', 'missed ground: height test',
         'candidates rejected as outliers'], rows)
    return 0


# ------------------------------------------------------------------------------ length scale

LENGTH_SCALE_VARIANTS = (
    ('defaults (one length factor)', {}),
    ("paper's d, clipped to [0.05, 2]", dict(use_nonstationary_length_scale=True)),
    ("paper's d unclipped (d_max 100)",
     dict(use_nonstationary_length_scale=True, max_length_factor=100.0)),
    ("paper's d, gain bound 50", dict(use_nonstationary_length_scale=True,
                                      length_scale_gain_max=50.0)),
)


def _protocol_metrics(mask, classes, ontology):
    """{protocol name: metrics} of a mask against a scan's labels under both protocols."""
    return {protocol.name: truth_metrics(mask, *ground_truth_from_labels(classes, ontology,
                                                                         protocol))
            for protocol in bench_quality.PROTOCOLS}


def run_length_scale(args, params) -> int:
    """``probes.py length-scale``: the paper's non-stationary length scale, measured."""
    rows, pooled = [], {}
    for name, points, classes, ontology, _, _ in real_scans():
        paper = GroundSegmenter(params.replace(use_nonstationary_length_scale=True))
        result = paper.segment(points, details=True)
        d = result.details.length_scale[result.details.training] / result.hyperparameters.gain
        p = params
        at_high = np.mean(d >= p.max_length_factor * (1 - 1e-12))
        at_low = np.mean(d <= p.min_length_factor * (1 + 1e-12))
        theta = ' / '.join(f'{v:.3f}' for v in result.hyperparameters)
        scores = []
        for label, change in LENGTH_SCALE_VARIANTS:
            mask = GroundSegmenter(params.replace(**change)).segment(points).ground_mask
            by_protocol = _protocol_metrics(mask, classes, ontology)
            if ontology is SEMANTIC_KITTI:
                for proto, m in by_protocol.items():
                    pooled.setdefault((label, proto), []).append(m)
            scores.append(' / '.join(f'{m["f1"]:.4f}' for m in by_protocol.values()))
        rows.append([name, theta, f'{at_low:.2f} / {at_high:.2f}', f'{np.median(d):.2f}',
                     *scores])
        print(' | '.join(rows[-1]), flush=True)
    totals = ['SemanticKITTI pooled', '', '', '']
    for label, _ in LENGTH_SCALE_VARIANTS:
        totals.append(' / '.join(f'{pooled_metrics(pooled[label, p.name])["f1"]:.4f}'
                                 for p in bench_quality.PROTOCOLS))
    rows.append(totals)
    report_probe(
        args, 'probe_length_scale',
        "The paper's non-stationary length scale (`probes.py length-scale`)",
        'Cold, one scan per row. theta (sigma_f m / gain a / sigma_n m) and the clip shares '
        "are the paper's length scale's (`use_nonstationary_length_scale` true, d clipped to "
        '[min_length_factor, max_length_factor] = [0.05, 2]), over the candidates that trained '
        'the GP. F1 under vegetation-nonground / patchworkpp.',
        ['scan', 'theta (paper d)', 'share of d at lower / upper clip', 'median d',
         *[f'F1: {label}' for label, _ in LENGTH_SCALE_VARIANTS]], rows)
    return 0


# ------------------------------------------------------------------------------------ ceiling

CEILING_RADIUS_M = 0.5
CEILING_QUANTILE = 10


def label_surface(points, truth, z_hat):
    """Per point: the CEILING_QUANTILE-th percentile of the labelled ground's z within
    CEILING_RADIUS_M horizontally (``z_hat`` where no labelled ground is that near)."""
    ground = np.flatnonzero(truth)
    tree = cKDTree(points[ground, :2])
    distance, index = tree.query(points[:, :2], k=16, distance_upper_bound=CEILING_RADIUS_M)
    near = np.isfinite(distance)
    heights = np.where(near, points[ground[np.minimum(index, ground.size - 1)], 2], np.nan)
    has = near.any(axis=1)
    out = np.asarray(z_hat, dtype=np.float64).copy()
    out[has] = np.nanpercentile(heights[has], CEILING_QUANTILE, axis=1)
    return out


def ceiling_mask(points, truth, params):
    """The defaults' labelling (threshold, structure test, free space) on the labels' surface."""
    from gp_ground_segmentation.core.structure import structure_feet
    result = GroundSegmenter(params).segment(points)
    valid = result.valid_mask
    xyz = np.asarray(points[valid, :3], dtype=np.float32)
    surface = label_surface(xyz, truth[valid], result.ground_height[valid]).astype(np.float32)
    ground = xyz[:, 2] - surface <= params.ground_threshold_m
    feet = structure_feet(params, xyz[:, 0], xyz[:, 1], xyz[:, 2], surface, ground)
    mask = np.zeros(len(points), dtype=bool)
    mask[np.flatnonzero(valid)] = ground & ~feet
    return mask, result.ground_mask


def run_ceiling(args, params) -> int:
    """``probes.py ceiling``: this labelling on a perfect (label-derived) ground surface."""
    sums = {}
    for name, points, classes, ontology, _, _ in real_scans():
        if ontology is not SEMANTIC_KITTI:
            continue
        ceiling, ours = ceiling_mask(points, ground_truth_from_labels(classes)[0], params)
        for label, mask in (("this labelling on the labels' surface", ceiling),
                            ('defaults', ours)):
            for proto, m in _protocol_metrics(mask, classes, ontology).items():
                sums.setdefault((label, proto), []).append(m)
    rows = [[label, *(' / '.join(f'{v:.4f}' for v in (m['precision'], m['recall'], m['f1']))
                      for m in (pooled_metrics(sums[label, p.name])
                                for p in bench_quality.PROTOCOLS))]
            for label in dict.fromkeys(k[0] for k in sums)]
    report_probe(
        args, 'probe_ceiling', 'A perfect ground surface under this labelling (`probes.py '
        'ceiling`)',
        f'Cold, the SemanticKITTI scans pooled. The surface of the first row comes from the '
        f"labels (the {CEILING_QUANTILE}th percentile of the labelled ground's z within "
        f'{CEILING_RADIUS_M} m of each point): a bound on what a better surface model could give '
        'with the same threshold, structure test and free space, not a method. P / R / F1.',
        ['ground surface', *(p.name for p in bench_quality.PROTOCOLS)], rows)
    return 0


# ------------------------------------------------------------------------------------ main

PROBES = {'errors': run_errors, 'perturbed': run_perturbed, 'nonrepetitive': run_nonrepetitive,
          'high-mount': run_high_mount, 'length-scale': run_length_scale, 'ceiling': run_ceiling}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    sub = ap.add_subparsers(dest='probe', required=True)
    for name, run in PROBES.items():
        p = sub.add_parser(name, help=run.__doc__.split(': ', 1)[1].rstrip('.'))
        p.add_argument('--set', nargs='*', default=[],
                       help='name=value over the defaults (ours); nothing is written then')
        p.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args(argv)
    try:
        params = SegmenterParams(**common.parse_param_values(args.set)).validate()
    except (ValueError, TypeError) as exc:
        ap.error(str(exc))
    return PROBES[args.probe](args, params)


if __name__ == '__main__':
    sys.exit(main())
