# SPDX-License-Identifier: Apache-2.0
"""tools/crossval.py: leave-one-group-out folds, choices made without the held-out group."""

import numpy as np
import pytest

from gp_ground_segmentation.tools.crossval import (best_candidate, group_folds,
                                                   leave_one_group_out, pooled_f1)


def _counts(tp, fp, fn):
    return [{'tp': tp, 'fp': fp, 'fn': fn, 'tn': 0}]


def test_folds_hold_out_each_group_once_in_first_seen_order():
    items = ['a1', 'b1', 'a2', 'c1', 'b2']
    folds = group_folds(items, lambda item: item[0])
    assert [(f.index, f.held_out) for f in folds] == [(0, 'a'), (1, 'b'), (2, 'c')]
    assert folds[0].test == ('a1', 'a2') and folds[0].train == ('b1', 'c1', 'b2')
    assert folds[2].test == ('c1',) and folds[2].train == ('a1', 'b1', 'a2', 'b2')
    assert group_folds(['a1', 'a2'], lambda item: item[0]) == []  # one group: nothing to do


def test_the_choice_sees_only_the_other_groups_and_held_out_counts_are_pooled():
    seen = []

    def choose(fold):
        seen.append((fold.held_out, set(fold.train)))
        return len(fold.train)  # a 'choice' that depends on the training items

    def score(choice, test):
        return [{'tp': choice, 'fp': 1, 'fn': 0, 'tn': 0} for _ in test]

    cv = leave_one_group_out(['a1', 'a2', 'b1'], lambda item: item[0], choose, score)
    assert seen == [('a', {'b1'}), ('b', {'a1', 'a2'})]
    assert [(f.held_out, f.choice, len(f.test_counts)) for f in cv.folds] == [
        ('a', 1, 2), ('b', 2, 1)]
    # pooled over the folds: TP 1 + 1 + 2, FP 3
    assert (cv.pooled['tp'], cv.pooled['fp']) == (4, 3)
    assert cv.pooled['f1'] == pytest.approx(2 * 4 / (2 * 4 + 3))


def test_best_candidate_averages_the_groups_pooled_f1():
    # 'wide' is best on a and b, 'special' only on c (by a lot)
    counts = {'defaults': {'a': _counts(90, 10, 10), 'b': _counts(90, 10, 10),
                           'c': _counts(50, 50, 50)},
              'wide': {'a': _counts(95, 5, 5), 'b': _counts(95, 5, 5), 'c': _counts(40, 60, 60)},
              'special': {'a': _counts(60, 40, 40), 'b': _counts(60, 40, 40),
                          'c': _counts(99, 1, 1)}}
    assert best_candidate(counts, ['a', 'b']) == 'wide'  # c's own score cannot pick 'special'
    # without a: the mean over b and c is 0.7 for defaults, 0.675 for wide, 0.795 for special
    assert best_candidate(counts, ['b', 'c']) == 'special'
    tie = {'first': {'a': _counts(9, 1, 1)}, 'second': {'a': _counts(9, 1, 1)}}
    assert best_candidate(tie, ['a']) == 'first'


def test_pooled_f1_sums_counts():
    counts = [{'tp': 8, 'fp': 2, 'fn': 0, 'tn': 5}, {'tp': 0, 'fp': 0, 'fn': 2, 'tn': 1}]
    precision, recall = 8 / 10, 8 / 10
    assert pooled_f1(counts) == pytest.approx(2 * precision * recall / (precision + recall))
    assert np.isnan(pooled_f1([{'tp': 0, 'fp': 0, 'fn': 0, 'tn': 3}]))
    assert np.isnan(pooled_f1([]))
