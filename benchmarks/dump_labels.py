# SPDX-License-Identifier: Apache-2.0
"""Dump the ground masks of the shared real frames and the synthetic scenes, or compare two dumps.

A refactor must leave the labels unchanged (and theta and the ground height: each frame's
learned hyperparameters and per-point ground height are dumped and compared too, exactly; NaN
heights of invalid points equal each other). Run this against the old tree and the new one with
the same parameters and compare (``PYTHONPATH`` picks the tree; the script itself only uses the
public API ``GroundSegmenter(params).segment(points)``)::

    PYTHONPATH=/tmp/old_tree python benchmarks/dump_labels.py dump /tmp/old.npz --fixed-theta
    python benchmarks/dump_labels.py dump /tmp/new.npz --fixed-theta
    python benchmarks/dump_labels.py compare /tmp/old.npz /tmp/new.npz

``--fixed-theta`` freezes theta at its initial value (optimizer evaluations 0 on every frame):
the cold-start optimum is sensitive to round-off, the labels at a fixed theta are not. Without it
every frame is segmented twice by one segmenter (cold start, then warm start), both dumped.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))  # scenes/ (appended: PYTHONPATH's package tree wins)
DATA = Path('/work/shared/data')


def frames():
    """(name, (N, 3) float32 points) of every shared frame and synthetic scene."""
    from gp_ground_segmentation.tools.io import read_points_file
    from scenes.synthetic import SCENE_NAMES, scan_scene
    paths = sorted(DATA.glob('*.bin')) + sorted((DATA / 'labeled').glob('*.bin')) + sorted(
        (DATA / 'sensors').glob('*.pcd'))
    for path in paths:
        arr = read_points_file(path)
        yield path.name, np.stack([arr[c].astype(np.float32) for c in 'xyz'], axis=1)
    for name in SCENE_NAMES:
        yield f'synthetic:{name}', scan_scene(name).points[:, :3]


def dump(out, fixed_theta):
    import gp_ground_segmentation as pkg
    from gp_ground_segmentation import GroundSegmenter, SegmenterParams
    print(f'package: {Path(pkg.__file__).parent}')
    params = SegmenterParams()
    if fixed_theta:
        params = params.replace(optimizer_first_frame_evaluations=0, optimizer_max_evaluations=0)
    masks = {}
    for name, points in frames():
        segmenter = GroundSegmenter(params)
        for rep in ('cold', 'warm'):
            result = segmenter.segment(points)
            masks[f'{name}|{rep}'] = result.ground_mask
            masks[f'{name}|{rep}|theta'] = np.asarray(result.hyperparameters, dtype=np.float64)
            masks[f'{name}|{rep}|height'] = result.ground_height
        print(f'{name}: {points.shape[0]} points, {int(masks[name + "|warm"].sum())} ground')
    np.savez_compressed(out, **masks)


def compare(old, new):
    a, b = np.load(old), np.load(new)
    if set(a.files) != set(b.files):
        sys.exit(f'different frames: {sorted(set(a.files) ^ set(b.files))}')
    total = thetas = 0
    for key in sorted(a.files):
        if key.endswith('|theta'):  # exact: a refactor must not move theta by one ulp
            thetas += int(not np.array_equal(a[key], b[key]))
            continue
        old_value, new_value = a[key], b[key]
        differ = old_value != new_value
        if old_value.dtype.kind == 'f':
            differ &= ~(np.isnan(old_value) & np.isnan(new_value))
        diff = int(np.count_nonzero(differ))
        total += diff
        what = 'heights' if key.endswith('|height') else 'labels'
        print(f'{key:62s} {old_value.size:8d} points {diff:6d} {what} differ')
    print(f'total differing labels and heights: {total}')
    if any(key.endswith('|theta') for key in a.files):
        print(f'frames with a different theta: {thetas}')
    return total + thetas


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True)
    d = sub.add_parser('dump')
    d.add_argument('out')
    d.add_argument('--fixed-theta', action='store_true')
    c = sub.add_parser('compare')
    c.add_argument('old')
    c.add_argument('new')
    args = parser.parse_args()
    if args.command == 'dump':
        dump(args.out, args.fixed_theta)
    else:
        sys.exit(1 if compare(args.old, args.new) else 0)


if __name__ == '__main__':
    main()
