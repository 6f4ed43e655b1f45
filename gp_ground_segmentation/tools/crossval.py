# SPDX-License-Identifier: Apache-2.0
"""Leave-one-group-out cross-validation: a choice of parameters scored on data it was not made on.

A *group* is a set of frames that are not independent of each other: the consecutive frames of
one drive (KITTI 00 frames 0-2 are one), one sequence, one synthetic family. Holding out single
frames would let a choice made on one frame of a street be scored on the next frame of the same
street. Each fold holds one group out, makes the choice on the other groups (``choose``) and
scores it on the held-out one (``score``, per-frame confusion counts); the held-out counts of
every fold are pooled (TP/FP/FN summed) into the cross-validated score.

``gp-ground-seg tune`` makes its choice with an Optuna study per fold; benchmarks/bench_quality.py
picks the best of fixed candidates (:func:`best_candidate`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Hashable, Sequence

import numpy as np

from .evaluation import pooled_metrics


@dataclass(frozen=True)
class Fold:
    """One fold: the held-out group, the items of the other groups and its own items."""

    index: int  # 0, 1, ... in the order the groups first appear
    held_out: Hashable
    train: tuple
    test: tuple


@dataclass(frozen=True)
class FoldResult:
    """What was chosen without the held-out group and its counts on that group."""

    held_out: Hashable
    choice: object
    test_counts: list  # per-frame {tp, fp, fn, tn} of the choice on the held-out group


@dataclass(frozen=True)
class CrossValidation:
    """Every fold's result; :attr:`pooled` is the cross-validated score."""

    folds: list

    @property
    def pooled(self):
        """:func:`evaluation.pooled_metrics` of the held-out counts of every fold (None when
        there was no fold)."""
        return pooled_metrics([c for fold in self.folds for c in fold.test_counts])


def group_folds(items: Sequence, group_of: Callable) -> list:
    """One :class:`Fold` per group of ``items`` (``group_of(item)`` names its group), groups in
    the order they first appear, items in their given order; none when there are fewer than two
    groups (nothing would be left to choose on)."""
    items = list(items)
    groups = list(dict.fromkeys(group_of(item) for item in items))
    if len(groups) < 2:
        return []
    return [Fold(k, group, tuple(i for i in items if group_of(i) != group),
                 tuple(i for i in items if group_of(i) == group))
            for k, group in enumerate(groups)]


def leave_one_group_out(items: Sequence, group_of: Callable, choose: Callable,
                        score: Callable) -> CrossValidation:
    """For each :func:`group_folds` fold: ``choice = choose(fold)`` (which must look at
    ``fold.train`` only), then ``score(choice, fold.test)`` -> per-frame counts."""
    results = []
    for fold in group_folds(items, group_of):
        choice = choose(fold)
        results.append(FoldResult(fold.held_out, choice, list(score(choice, fold.test))))
    return CrossValidation(results)


def pooled_f1(counts: Sequence) -> float:
    """F1 of the summed counts of several frames; NaN when there is none."""
    pooled = pooled_metrics(list(counts))
    return pooled['f1'] if pooled else float('nan')


def best_candidate(counts: dict, groups: Sequence) -> Hashable:
    """The candidate whose pooled F1 per group, averaged over ``groups``, is highest (each group
    weighs the same whatever its point count; the first candidate wins a tie).
    ``counts[candidate][group]`` = per-frame counts."""
    def mean_f1(name):
        return float(np.nanmean([pooled_f1(counts[name][g]) for g in groups]))
    return max(counts, key=mean_f1)
