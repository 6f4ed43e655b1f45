# SPDX-License-Identifier: Apache-2.0
"""The library side of benchmarks/bench_quality.py: evaluation, cross-validation, variants."""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
import bench_quality as bq  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation import SegmenterParams  # noqa: E402
from gp_ground_segmentation.core.lines import deming_fit  # noqa: E402


def _metrics(tp, fp, fn):
    return [{'tp': tp, 'fp': fp, 'fn': fn, 'tn': 0}]


class _Group:
    def __init__(self, name):
        self.name = name


def test_cross_validation_chooses_per_protocol_on_the_other_groups():
    groups = [_Group(n) for n in ('a', 'b', 'c')]
    strict, lenient = (p.name for p in bq.PROTOCOLS)

    def both(first, second):
        return {strict: _metrics(*first), lenient: _metrics(*second)}
    # under the first protocol 'wide' wins on a and b; under the second 'defaults' do
    candidates = {'defaults': {'a': both((90, 10, 10), (99, 1, 1)),
                               'b': both((90, 10, 10), (99, 1, 1)),
                               'c': both((50, 50, 50), (50, 50, 50))},
                  'wide': {'a': both((95, 5, 5), (90, 10, 10)),
                           'b': both((95, 5, 5), (90, 10, 10)),
                           'c': both((40, 60, 60), (40, 60, 60))}}
    cv = {p.name: bq.cross_validate(candidates, groups, p) for p in bq.PROTOCOLS}
    held = {name: {f.held_out: f for f in result.folds} for name, result in cv.items()}
    assert held[strict]['c'].choice == 'wide' and held[lenient]['c'].choice == 'defaults'
    assert held[strict]['c'].test_counts == _metrics(40, 60, 60)  # c's own score was not used
    # pooled held-out = the counts of the folds' choices summed, not a mean of their F1
    tp = sum(c['tp'] for f in cv[strict].folds for c in f.test_counts)
    assert cv[strict].pooled['tp'] == tp


def test_grid_variants_are_every_combination():
    grid = bq.grid_variants(['num_bins=16,20', 'ground_threshold_m=0.2,0.25'])
    assert list(grid) == ['num_bins=16, ground_threshold_m=0.2',
                          'num_bins=16, ground_threshold_m=0.25',
                          'num_bins=20, ground_threshold_m=0.2',
                          'num_bins=20, ground_threshold_m=0.25']
    assert grid['num_bins=20, ground_threshold_m=0.25'].num_bins == 20
    assert bq.grid_variants([]) == {}
    with pytest.raises(ValueError):
        bq.grid_variants(['num_bins'])


def test_quick_and_partial_runs_do_not_write_results():
    assert bq.parse_args(['--quick']).partial and bq.parse_args(['--real-only']).partial
    assert bq.parse_args(['--quick']).modes == ['cold']
    assert not bq.parse_args([]).partial and bq.parse_args([]).modes == list(bq.MODES)
    assert not bq.parse_args(['--variant', 'x:num_bins=20']).partial


def test_parse_variant_types_values_and_rejects_bad_input():
    name, params = bq.parse_variant('long:max_length_factor=4.5,num_bins=16')
    assert name == 'long' and params.max_length_factor == 4.5 and params.num_bins == 16
    assert isinstance(params.num_bins, int)
    for bad in ('no_colon', ':num_bins=3', 'x:not_a_field=1', 'x:num_bins'):
        with pytest.raises(ValueError):
            bq.parse_variant(bad)
    with pytest.raises(ValueError, match='num_bins'):
        bq.parse_variant('x:num_bins=1')  # out of range: validate() names the field


def test_ablation_switches_every_bool_field_and_each_paper_component():
    variants = bq.ablation_variants()
    defaults = SegmenterParams()
    for f in dataclasses.fields(SegmenterParams):
        if isinstance(f.default, bool):
            assert getattr(variants[f'{f.name}={not f.default}'], f.name) is (not f.default)
    frozen = [p for n, p in variants.items() if n.startswith('theta frozen')][0]
    assert frozen.optimizer_max_evaluations == 0 == frozen.optimizer_first_frame_evaluations
    # the length scale is a switch like the others: its variant is the other kind
    name = f'use_nonstationary_length_scale={not defaults.use_nonstationary_length_scale}'
    assert variants[name].use_nonstationary_length_scale is not (
        defaults.use_nonstationary_length_scale)
    ols = [p for n, p in variants.items() if n.startswith('OLS')][0]
    # A very large variance ratio makes the Deming slope the least-squares slope of z on r.
    rng = np.random.default_rng(0)
    r = rng.uniform(0, 30, 200)
    z = 0.1 * r + rng.normal(0, 0.3, 200)
    c = np.cov(r, z, bias=True)
    sums = (r.size, r.sum(), z.sum(), (r * r).sum(), (z * z).sum(), (r * z).sum())
    _, beta = deming_fit(*sums, ols.deming_variance_ratio)
    _, beta_orth = deming_fit(*sums, 1.0)
    assert beta == pytest.approx(c[0, 1] / c[0, 0], rel=1e-3)
    assert abs(beta_orth - c[0, 1] / c[0, 0]) > 10 * abs(beta - c[0, 1] / c[0, 0])


def test_peer_settings_follow_the_mount():
    low = common.Frame('low', np.zeros((1, 4), np.float32), True, mount_height_m=0.5)
    high = common.Frame('high', np.zeros((1, 4), np.float32), True, mount_height_m=2.0)
    assert bq.peer_settings(low) == (0.5, bq.LOW_MOUNT_MIN_RANGE_M)
    assert bq.peer_settings(high) == (2.0, None)


def test_evaluate_counts_match_the_scoring_in_both_modes():
    ds = common.load_family('beams16', [0, 1])
    for mode in bq.MODES:
        counts = bq.evaluate(SegmenterParams(), ds.frames, mode)
        assert len(counts) == 2
        for c, frame in zip(counts, ds.frames):
            assert c['tp'] + c['fp'] + c['fn'] + c['tn'] == int(frame.evaluated.sum())
            assert c['tp'] > 0.8 * frame.truth.sum()
    with pytest.raises(ValueError, match='mode'):
        bq.evaluate(SegmenterParams(), ds.frames, 'warm')


def test_a_labelled_scan_is_scored_under_each_protocol():
    group = common.labelled_group('kitti02')
    if group is None:
        pytest.skip('KITTI 02 frame 0 not in the shared data')
    (frame,) = group.frames
    (metrics,) = bq.run_frames('gp', group.frames)
    both = bq.scored(bq.run_masks('gp', group.frames), group.frames)
    assert both[bq.PROTOCOLS[0].name] == [metrics]  # the default protocol is the first
    vegetation = int(np.count_nonzero(frame.classes == 70))
    assert vegetation > 1000
    evaluated = [both[p.name][0]['evaluated_points'] for p in bq.PROTOCOLS]
    assert evaluated == [metrics['evaluated_points'], metrics['evaluated_points'] - vegetation]
