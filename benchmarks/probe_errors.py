# SPDX-License-Identifier: Apache-2.0
"""Probe (issue 10): where the defaults' remaining errors lie on the labelled real scans.

Usage::

    python benchmarks/probe_errors.py [--no-write] [--set name=value ...]

For every labelled real scan in ../shared/data (the SemanticKITTI spvnas scan, KITTI 00 frames
0-2, the RELLIS-3D scan; cold, a fresh ``GroundSegmenter`` per frame, this project's defaults
unless ``--set``), it splits the errors the way the segmenter makes them:

- missed ground (FN) turned obstacle by the structure test (``details.structure_feet``) or by
  the height test (z - z_hat above the point's threshold), with the classes they carry;
- false ground (FP) by class and by height above the predicted ground (``h``);
- two features that a rule against the main false-ground class (SemanticKITTI vegetation 70,
  RELLIS-3D tree 4 and bush 19) could use, each measured as the Mann-Whitney AUC of that class's
  false ground against the true ground the segmenter keeps (0.5 = no separation, 1 = perfect):
  the point's remission against all true ground kept and against its terrain (72) alone
  (KITTI scans only: RELLIS-3D's intensity is normalised, not remission),
  and the highest point within ``NEIGHBOUR_RADIUS_M`` horizontally (its height above z_hat);
- the share of the points within 0.3 / 0.5 m standing more than 0.15 m above z_hat (a bush is
  mostly raised, the road beside a car or a curb mostly not), measured the same way;
- whether the ground continues beyond a structure foot along its ray (true under a car sill,
  not behind a wall): the wrongly condemned feet against the rightly condemned ones;
- what rules on these features would trade as post-processes on the labels: the false ground
  removed (or added) against the true ground lost (or given back), and the F1 change.

Nothing here is in the core. Writes the section ``probe_errors`` of RESULTS.md unless
``--no-write`` or ``--set``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import mannwhitneyu

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter  # noqa: E402
from gp_ground_segmentation.tools.evaluation import (  # noqa: E402
    SEMANTIC_KITTI, ground_truth_from_labels, truth_metrics)

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
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
    for name, bin_path, label_path, ontology in common.labeled_real_files(data_dir):
        if not (bin_path.is_file() and label_path.is_file()):
            print(f'[data] skipped {name}: {bin_path} or its labels not found', file=sys.stderr)
            continue
        points, classes = common._read_labeled_pair(bin_path, label_path)
        kitti = ontology is SEMANTIC_KITTI
        scans.append((name, points, classes, ontology,
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
        m = truth_metrics(labels, truth, evaluated)
        return [name, rule, f'{(fp & ~labels).sum():,}', f'{(main_fp & ~labels).sum():,}',
                f'{(tp & ~labels).sum():,}', f'{(evaluated & ~truth & labels & ~ground).sum():,}',
                f'{(evaluated & truth & labels & ~ground).sum():,}',
                f'{(tp & ~labels).sum() / max(1, tp.sum()):.1%}',
                f"{m['f1'] - base['f1']:+.4f}"]
    rules = [rule_row(f'highest within {NEIGHBOUR_RADIUS_M} m > {limit} m',
                      ground & ~(highest > limit)) for limit in NEIGHBOUR_THRESHOLDS_M]
    rules += [rule_row(f'share within {radius} m above {RAISED_HEIGHT_M} m > {share}',
                       ground & ~(raised[radius] > share))
              for radius in RAISED_RADII_M for share in RAISED_SHARES]
    spared = ground.copy()
    spared[feet_index[beyond > 0]] = True
    rules.append(rule_row('spare every foot with ground beyond', spared))
    return row, rules


def main(argv=None) -> int:
    args, params = common.probe_arguments(__doc__.split('\n\n')[0], argv)
    scans = real_scans()
    if not scans:
        print('no labelled real scans found under ../shared/data', file=sys.stderr)
        return 1
    rows, rules = [], []
    for scan in scans:
        row, rule_rows = analyse(*scan, params)
        rows.append(row)
        rules.extend(rule_rows)
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
        + '\n\nWhat each rule would trade as a post-process on the labels (false ground '
        'removed, of it main class, true ground lost, false ground added, true ground given '
        'back, share of the TP lost, F1 change):')
    common.report_probe(args, RESULTS, 'probe_errors',
                        'Where the remaining errors lie on the labelled real scans '
                        '(`probe_errors.py`)', note,
                        ['scan', 'rule', 'FP removed', 'main-class FP removed', 'TP lost',
                         'FP added', 'TP given back', 'share of TP lost', 'F1 change'], rules)
    return 0


if __name__ == '__main__':
    sys.exit(main())
