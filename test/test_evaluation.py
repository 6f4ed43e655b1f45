# SPDX-License-Identifier: Apache-2.0
"""Ground metrics: hand-computed confusion counts, SemanticKITTI class handling, edge cases."""

import math

import numpy as np
import pytest

from gp_ground_segmentation.tools.evaluation import (
    DEFAULT_PROTOCOL, GROUND_CLASSES, IGNORED_CLASSES, ONTOLOGIES, PATCHWORKPP, PROTOCOLS,
    RELLIS_3D, SEMANTIC_KITTI, VEGETATION_GROUND, VEGETATION_NONGROUND, ground_metrics,
    ground_truth_from_labels, metrics_from_counts, pooled_metrics, truth_metrics)


def test_truth_metrics_hand_computed():
    # truth:  G G G G N N N N N N
    # pred:   G G G N G G N N N N  -> TP 3, FN 1, FP 2, TN 4
    truth = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], bool)
    pred = np.array([1, 1, 1, 0, 1, 1, 0, 0, 0, 0], bool)
    m = truth_metrics(pred, truth)
    assert (m['tp'], m['fp'], m['fn'], m['tn']) == (3, 2, 1, 4)
    assert m['evaluated_points'] == 10
    assert m['precision'] == pytest.approx(3 / 5)
    assert m['recall'] == pytest.approx(3 / 4)
    assert m['f1'] == pytest.approx(2 * 0.6 * 0.75 / 1.35)
    assert m['iou'] == pytest.approx(3 / (3 + 2 + 1))  # GroundGrid's IoU_g = TP/(TP+FP+FN)


def test_iou_is_nan_only_when_there_is_nothing_to_count():
    assert metrics_from_counts(0, 0, 4)['iou'] == 0.0
    assert math.isnan(metrics_from_counts(0, 0, 0, 7)['iou'])


def test_pooled_metrics_sum_the_counts():
    # frames: (TP 3, FP 2, FN 1, TN 4) and (TP 1, FP 0, FN 3, no TN) -> TP 4, FP 2, FN 4, TN 4
    frames = [{'tp': 3, 'fp': 2, 'fn': 1, 'tn': 4}, None, {'tp': 1, 'fp': 0, 'fn': 3}]
    m = pooled_metrics(frames)
    assert (m['tp'], m['fp'], m['fn'], m['tn']) == (4, 2, 4, 4)
    assert m['precision'] == pytest.approx(4 / 6) and m['recall'] == pytest.approx(4 / 8)
    assert m['f1'] == pytest.approx(2 * 4 / (2 * 4 + 2 + 4))
    assert m['iou'] == pytest.approx(4 / (4 + 2 + 4))
    assert pooled_metrics([]) is None and pooled_metrics([None]) is None
    assert pooled_metrics([{'tp': 0, 'fp': 2, 'fn': 0}])['f1'] == 0.0  # a call, not one hit
    assert math.isnan(pooled_metrics([{'tp': 0, 'fp': 0, 'fn': 0, 'tn': 5}])['f1'])


def test_truth_metrics_evaluated_mask_drops_points():
    truth = np.array([1, 1, 0, 0], bool)
    pred = np.array([1, 0, 1, 0], bool)
    m = truth_metrics(pred, truth, evaluated_mask=np.array([1, 1, 0, 1], bool))
    assert (m['tp'], m['fp'], m['fn'], m['tn'], m['evaluated_points']) == (1, 0, 1, 1, 3)
    assert m['precision'] == 1.0 and m['recall'] == 0.5


def test_semantic_kitti_classes_and_instance_bits():
    classes = np.array([40, 44, 48, 49, 60, 72, 70, 10, 50, 0, 1, 252], np.uint32)
    # instance ids in the high 16 bits must not matter
    raw = classes | (np.arange(classes.size, dtype=np.uint32) + 7) << 16
    # predict ground for: road, parking, vegetation, car, unlabeled
    pred = np.isin(classes, (40, 44, 70, 10, 0))
    m = ground_metrics(pred, raw)
    # 10 evaluated (0 and 1 ignored); ground truth = 6 ground classes
    assert m['evaluated_points'] == 10
    assert (m['tp'], m['fp'], m['fn'], m['tn']) == (2, 2, 4, 2)
    assert m['precision'] == pytest.approx(0.5)
    assert m['recall'] == pytest.approx(2 / 6)
    # vegetation counted as ground in the Patchwork variant: 70 turns from FP to TP
    mv = ground_metrics(pred, raw, protocol=VEGETATION_GROUND)
    assert (mv['tp'], mv['fp'], mv['fn'], mv['tn']) == (3, 1, 4, 2)
    # Patchwork++'s protocol: vegetation not scored at all, the FP on it is gone
    mp = ground_metrics(pred, raw, protocol=PATCHWORKPP)
    assert mp['evaluated_points'] == 9
    assert (mp['tp'], mp['fp'], mp['fn'], mp['tn']) == (2, 1, 4, 2)


def test_class_lists_match_protocol():
    assert set(GROUND_CLASSES) == {40, 44, 48, 49, 60, 72}
    assert set(IGNORED_CLASSES) == {0, 1}
    truth, evaluated = ground_truth_from_labels(np.array([70, 1, 72], np.uint32))
    assert truth.tolist() == [False, False, True]
    assert evaluated.tolist() == [True, False, True]


def test_degenerate_cases_are_nan_or_zero_not_fake_perfect():
    truth = np.array([0, 0, 0], bool)
    m = truth_metrics(np.zeros(3, bool), truth)
    assert math.isnan(m['precision']) and math.isnan(m['recall']) and math.isnan(m['f1'])
    m = truth_metrics(np.zeros(3, bool), np.array([1, 0, 0], bool))  # missed all ground
    assert m['recall'] == 0.0 and math.isnan(m['precision']) and m['f1'] == 0.0
    m = truth_metrics(np.ones(3, bool), truth)  # called ground where there is none
    assert m['precision'] == 0.0 and m['f1'] == 0.0


def test_length_mismatch_is_a_value_error():
    with pytest.raises(ValueError, match='labels have 3'):
        ground_metrics(np.zeros(4, bool), np.zeros(3, np.uint32))
    with pytest.raises(ValueError):
        truth_metrics(np.zeros(4, bool), np.zeros(5, bool))


def test_rellis3d_ontology_has_its_own_ground_and_void():
    # RELLIS-3D ids: 1 dirt, 3 grass, 10 asphalt, 23 concrete, 31 puddle, 33 mud are ground;
    # 0 void is ignored; 4 tree, 18 fence, 19 bush are not ground. 40 (road in SemanticKITTI)
    # means nothing in RELLIS and must not count as ground there.
    classes = np.array([0, 1, 3, 10, 23, 31, 33, 4, 18, 19, 40], np.uint32)
    truth, evaluated = ground_truth_from_labels(classes, ontology=RELLIS_3D)
    assert truth.tolist() == [False] + [True] * 6 + [False] * 4
    assert evaluated.tolist() == [False] + [True] * 10
    pred = np.isin(classes, (0, 3, 19))  # one void (ignored), one grass (TP), one bush (FP)
    m = ground_metrics(pred, classes, ontology=RELLIS_3D)
    assert (m['tp'], m['fp'], m['fn'], m['tn']) == (1, 1, 5, 3)
    # the same ids read as SemanticKITTI: only 40 is ground, 0 and 1 are ignored
    assert ground_truth_from_labels(classes)[0].tolist() == [False] * 10 + [True]
    # Patchwork++'s protocol leaves 19 bush out of the score; 4 tree stays non-ground
    truth, evaluated = ground_truth_from_labels(classes, RELLIS_3D, PATCHWORKPP)
    assert truth.tolist() == [False] + [True] * 6 + [False] * 4
    assert evaluated.tolist() == [False] + [True] * 8 + [False, True]
    m = ground_metrics(pred, classes, ontology=RELLIS_3D, protocol=PATCHWORKPP)
    assert (m['tp'], m['fp'], m['fn'], m['tn']) == (1, 0, 5, 3)


def test_protocols_by_name_and_their_class_lists():
    assert list(PROTOCOLS) == ['vegetation-nonground', 'patchworkpp', 'vegetation-ground']
    assert DEFAULT_PROTOCOL is VEGETATION_NONGROUND
    assert set(ONTOLOGIES) == {'semantickitti', 'rellis3d'}
    assert VEGETATION_NONGROUND.classes(SEMANTIC_KITTI) == (GROUND_CLASSES, IGNORED_CLASSES)
    assert PATCHWORKPP.classes(SEMANTIC_KITTI) == (GROUND_CLASSES, (0, 1, 70))
    assert VEGETATION_GROUND.classes(SEMANTIC_KITTI) == ((40, 44, 48, 49, 60, 70, 72), (0, 1))
    assert PATCHWORKPP.classes(RELLIS_3D) == ((1, 3, 10, 23, 31, 33), (0, 19))
    with pytest.raises(TypeError):  # the protocol is a keyword, never a stray positional bool
        ground_metrics(np.zeros(1, bool), np.zeros(1, np.uint32), False)


def test_command_line_classes_follow_dataset_protocol_and_overrides():
    import argparse

    from gp_ground_segmentation.tools.errors import CliError
    from gp_ground_segmentation.tools.options import add_label_class_arguments, label_classes
    parser = argparse.ArgumentParser()
    add_label_class_arguments(parser)

    def classes(*argv):
        return label_classes(parser.parse_args(list(argv)))
    assert classes() == (GROUND_CLASSES, IGNORED_CLASSES)
    assert classes('--protocol', 'patchworkpp') == (GROUND_CLASSES, (0, 1, 70))
    assert classes('--vegetation-ground') == ((40, 44, 48, 49, 60, 70, 72), (0, 1))
    assert classes('--dataset', 'rellis3d', '--protocol', 'patchworkpp') == (
        (1, 3, 10, 23, 31, 33), (0, 19))
    # explicit lists win over what the protocol gives
    assert classes('--protocol', 'patchworkpp', '--ignore-classes', '0') == (GROUND_CLASSES, (0,))
    assert classes('--ground-classes', '72, 40') == ((40, 72), IGNORED_CLASSES)
    with pytest.raises(CliError, match='comma-separated integers'):
        classes('--ground-classes', '40,road')
    with pytest.raises(SystemExit):  # one protocol only
        parser.parse_args(['--protocol', 'patchworkpp', '--vegetation-ground'])
