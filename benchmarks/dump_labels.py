# SPDX-License-Identifier: Apache-2.0
"""Dump the ground masks of the shared real frames and the synthetic scenes, or compare two dumps.

A refactor must leave the labels unchanged (and theta, the ground height and the ground surface:
each frame's learned hyperparameters, per-point ground height and the surface's z and z_std are
dumped and compared too, exactly; NaN heights of invalid points equal each other). Run this
against the old tree and the new one with the same parameters and compare (``PYTHONPATH`` picks
the tree; the script itself only uses the public API ``GroundSegmenter(params).segment(points)``
and the result's fields)::

    PYTHONPATH=/tmp/old_tree python benchmarks/dump_labels.py dump /tmp/old.npz --fixed-theta
    python benchmarks/dump_labels.py dump /tmp/new.npz --fixed-theta
    python benchmarks/dump_labels.py compare /tmp/old.npz /tmp/new.npz

Frames: every shared real scan (the labelled ones included), the classic synthetic scenes and
every synthetic family (``scenes.synthetic.FAMILY_NAMES``, seeds 0 .. ``--seeds`` - 1, made as
``benchmarks/common.load_family`` makes them: organised scans keep their (0, 0, 0) no-returns).

``--fixed-theta`` freezes theta at its initial value (optimizer evaluations 0 on every frame):
the cold-start optimum is sensitive to round-off, the labels at a fixed theta are not. Without it
every frame is segmented twice by one segmenter (cold start, then warm start), both dumped.

``--variant`` (repeatable, or ``all``) also dumps the frames under parameter sets other than the
defaults (switches off, options flipped, a sensor pose), each spelt in the parameter names of the
tree that runs (an old tree's ``outlier_wide_terrain_m: 0`` is the new ``use_wide_terrain_rule:
false``), so that both trees run the same rules. ``--backend numpy`` runs the numpy references.
"""

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.append(str(ROOT))  # scenes/ (appended: PYTHONPATH's package tree wins)
try:  # the one data-path finder; a tree from before it (on PYTHONPATH) has none
    from scenes.real_data import DATA_DIR as DATA
except ImportError:
    DATA = ROOT.parent / 'shared' / 'data'

# name -> spellings of one parameter set, newest first: the first whose keys are all fields of
# the SegmenterParams that runs is used
VARIANTS = {
    'wide_terrain_off': ({'use_wide_terrain_rule': False}, {'outlier_wide_terrain_m': 0.0}),
    'smoothing_off': ({'use_length_factor_smoothing': False},
                      {'length_factor_smoothing_passes': 0}),
    'outlier_std_off': ({'use_outlier_std_limit': False}, {'outlier_std_factor': 0.0}),
    'std_threshold_on': ({'use_std_threshold': True, 'std_threshold_factor': 1.0},
                         {'ground_threshold_std_factor': 1.0}),
    'switches_off': ({'use_chord_slope_for_single_points': False,
                      'use_elevated_plateaus': False, 'use_outlier_rejection': False,
                      'use_anchor': False, 'prior_mean_at_anchor': False,
                      'use_cross_slope_threshold': False, 'use_vertical_structure_test': False,
                      'use_length_factor_smoothing': False},
                     {'use_chord_slope_for_single_points': False,
                      'use_elevated_plateaus': False, 'use_outlier_rejection': False,
                      'use_anchor': False, 'prior_mean_at_anchor': False,
                      'use_cross_slope_threshold': False, 'use_vertical_structure_test': False,
                      'length_factor_smoothing_passes': 0}),
    'options_flipped': ({'plateau_ends_on_drop': True, 'plateau_from_sensor_ground': False,
                         'outlier_worst_per_segment': True, 'density_in_flat_branch': True,
                         'prior_mean_at_anchor': False},),
    'learn_every_frame': ({'optimizer_interval_frames': 1},),  # warm frames learn (cap 2)
    'pose': ({'sensor_x_m': 0.4, 'sensor_z_m': 0.3, 'sensor_roll_rad': 0.02,
              'sensor_pitch_rad': -0.03},),
}


def variant_params(name):
    """SegmenterParams of variant ``name`` ('defaults' or a VARIANTS key) in this tree's names."""
    from gp_ground_segmentation import SegmenterParams
    if name == 'defaults':
        return SegmenterParams()
    fields = {f.name for f in dataclasses.fields(SegmenterParams)}
    for spelling in VARIANTS[name]:
        if set(spelling) <= fields:
            return SegmenterParams(**spelling).validate()
    sys.exit(f'variant {name}: no spelling fits this tree\'s SegmenterParams')


def frames(seeds):
    """(name, points) of every shared frame (float32 x, y, z), synthetic scene and family member
    (their (N, 4) float32 rows, as the benchmarks feed them)."""
    from gp_ground_segmentation.tools.io import read_points_file
    from scenes import synthetic
    paths = sorted(DATA.glob('*.bin')) + sorted((DATA / 'labeled').glob('*.bin')) + sorted(
        (DATA / 'sensors').glob('*.pcd'))
    for path in paths:
        arr = read_points_file(path)
        yield path.name, np.stack([arr[c].astype(np.float32) for c in 'xyz'], axis=1)
    for name in synthetic.SCENE_NAMES:
        yield f'synthetic:{name}', synthetic.scan_scene(name).points[:, :3]
    for family in synthetic.FAMILY_NAMES:
        for seed in range(seeds):
            member = synthetic.family_scene(family, seed)
            scan = synthetic.simulate_scan(member.scene, seed=seed, **member.scan_kwargs)
            yield f'family:{family}_{seed}', np.ascontiguousarray(scan.points)


def _record(out, key, result):
    out[f'{key}'] = result.ground_mask
    out[f'{key}|theta'] = np.asarray(result.hyperparameters, dtype=np.float64)
    out[f'{key}|height'] = result.ground_height
    surface = result.ground_surface
    out[f'{key}|surface_z'] = np.asarray(surface.z, dtype=np.float64)
    out[f'{key}|surface_std'] = np.asarray(surface.z_std, dtype=np.float64)


def dump(out, fixed_theta, variants, seeds, backend):
    import gp_ground_segmentation as pkg
    from gp_ground_segmentation import GroundSegmenter
    from gp_ground_segmentation.core import compiled
    print(f'package: {Path(pkg.__file__).parent}')
    if backend != 'numpy':  # every kernel compiled before the first frame: no numpy twin runs
        GroundSegmenter(backend=backend).warm_up()
        compiled.wait(900.0)
    sets = {}
    for name in ['defaults'] + list(variants):
        params = variant_params(name)
        if fixed_theta:
            params = params.replace(optimizer_first_frame_evaluations=0,
                                    optimizer_max_evaluations=0)
        sets[name] = params
    masks = {}
    for frame, points in frames(seeds):
        for name, params in sets.items():
            segmenter = GroundSegmenter(params, backend=backend)
            for rep in ('cold', 'warm'):
                with np.errstate(all='ignore'):
                    _record(masks, f'{frame}|{name}|{rep}', segmenter.segment(points))
        print(f'{frame}: {points.shape[0]} points, '
              f'{int(masks[frame + "|defaults|warm"].sum())} ground', flush=True)
    np.savez_compressed(out, **masks)
    failed = [getattr(k, 'py_func', k).__name__ for k in getattr(compiled, '_failed', ())]
    print(f'{len(masks)} arrays; kernels that failed to compile: {failed or "none"}')


def _theta_ratio(a, b) -> float:
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-300)))


def compare(old, new, verbose):
    a, b = np.load(old), np.load(new)
    if set(a.files) != set(b.files):
        sys.exit(f'different frames: {sorted(set(a.files) ^ set(b.files))}')
    totals = {'labels': 0, 'heights': 0, 'surface': 0}
    thetas, worst_theta, frames_with_diff = 0, 0.0, []
    for key in sorted(a.files):
        if key.endswith('|theta'):  # exact: a mechanical refactor does not move theta one ulp
            if not np.array_equal(a[key], b[key]):
                thetas += 1
                worst_theta = max(worst_theta, _theta_ratio(a[key], b[key]))
            continue
        old_value, new_value = a[key], b[key]
        differ = old_value != new_value
        if old_value.dtype.kind == 'f':
            differ &= ~(np.isnan(old_value) & np.isnan(new_value))
        diff = int(np.count_nonzero(differ))
        what = ('heights' if key.endswith('|height') else 'surface' if '|surface' in key
                else 'labels')
        totals[what] += diff
        if diff:
            frames_with_diff.append(key)
        if verbose or diff:
            print(f'{key:70s} {old_value.size:8d} values {diff:6d} {what} differ')
    print(f'compared {len(a.files)} arrays; differing labels {totals["labels"]}, heights '
          f'{totals["heights"]}, surface values {totals["surface"]}')
    print(f'frames with a different theta: {thetas} (largest relative difference '
          f'{worst_theta:.3g})')
    return sum(totals.values()) + thetas


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True)
    d = sub.add_parser('dump')
    d.add_argument('out')
    d.add_argument('--fixed-theta', action='store_true')
    d.add_argument('--variant', action='append', default=[],
                   help=f'also dump: {", ".join(VARIANTS)} or all')
    d.add_argument('--seeds', type=int, default=3, help='members of every family (default 3)')
    d.add_argument('--backend', default='auto', choices=('auto', 'numba', 'numpy'))
    c = sub.add_parser('compare')
    c.add_argument('old')
    c.add_argument('new')
    c.add_argument('--verbose', action='store_true', help='a line for every array')
    args = parser.parse_args()
    if args.command == 'dump':
        variants = list(VARIANTS) if 'all' in args.variant else args.variant
        dump(args.out, args.fixed_theta, variants, args.seeds, args.backend)
    else:
        sys.exit(1 if compare(args.old, args.new, args.verbose) else 0)


if __name__ == '__main__':
    main()
