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


def _counts(tp, fp, fn):
    return [{'tp': tp, 'fp': fp, 'fn': fn, 'tn': 0}]


class _Group:
    def __init__(self, name):
        self.name = name


def test_loso_cv_chooses_on_the_other_groups_only():
    groups = [_Group(n) for n in ('a', 'b', 'c')]
    # 'wide' is best on a and b, 'special' only on c (by a lot).
    counts = {'defaults': {'a': _counts(90, 10, 10), 'b': _counts(90, 10, 10),
                           'c': _counts(50, 50, 50)},
              'wide': {'a': _counts(95, 5, 5), 'b': _counts(95, 5, 5), 'c': _counts(40, 60, 60)},
              'special': {'a': _counts(60, 40, 40), 'b': _counts(60, 40, 40),
                          'c': _counts(99, 1, 1)}}
    rows = {r['held_out']: r for r in bq.loso_cv_from_counts(counts, groups)}
    assert rows['c']['chosen'] == 'wide'  # c's own score cannot pick 'special'
    assert rows['c']['held_out_f1'] == pytest.approx(0.4)
    assert rows['c']['default_f1'] == pytest.approx(0.5)
    # Held out a: mean over b and c is 0.7 for defaults, 0.675 for wide, 0.795 for special.
    assert rows['a']['chosen'] == 'special'
    assert rows['a']['rest_score'] == pytest.approx((0.6 + 0.99) / 2)
    assert rows['a']['held_out_f1'] == pytest.approx(0.6)


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
    # the defaults hold L constant (chosen by cross-validation): the variant is the paper's
    # non-stationary L; with non-stationary defaults it would be constant L
    (name, length), = [(n, p) for n, p in variants.items()
                       if n.startswith(('constant L', 'non-stationary L'))]
    constant_default = defaults.min_length_factor >= 0.9 * defaults.max_length_factor
    assert name.startswith('non-stationary' if constant_default else 'constant')
    assert (length.min_length_factor < 0.1 * length.max_length_factor) is constant_default
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
