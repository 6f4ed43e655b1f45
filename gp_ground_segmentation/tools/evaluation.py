# SPDX-License-Identifier: Apache-2.0
"""Ground-segmentation metrics against SemanticKITTI or RELLIS-3D labels or synthetic truth.

Protocol for SemanticKITTI (follows the Patchwork / Patchwork++ evaluation):

* ground classes: 40 road, 44 parking, 48 sidewalk, 49 other-ground, 60 lane-marking, 72 terrain;
* ignored: 0 unlabeled and 1 outlier are left out of every count;
* everything else is non-ground. **Vegetation (70) counts as non-ground by default**: bushes and
  hedges stand well above the terrain and a segmenter that calls them ground hides obstacles.
  Patchwork reports variants that count 70 as ground; ``vegetation_is_ground=True`` reproduces
  them.

"Positive" means *ground*: precision = TP / (TP + FP) is the share of points called ground that are
ground, recall = TP / (TP + FN) the share of true ground that was found.

RELLIS-3D (``ontology=RELLIS_3D``) has its own class ids: ground = 1 dirt, 3 grass, 10 asphalt,
23 concrete, 31 puddle, 33 mud; 0 void is ignored (it also holds every (0, 0, 0) no-return of
the organised Ouster cloud); everything else (trees, bushes, fences, people, ...) is non-ground.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
IGNORED_CLASSES = (0, 1)
VEGETATION_CLASS = 70


class LabelOntology(NamedTuple):
    """Which semantic classes of a labelled data set are ground and which are left out."""

    name: str
    ground: tuple
    ignored: tuple
    vegetation: Optional[int] = None  # the class ``vegetation_is_ground`` adds, if any


SEMANTIC_KITTI = LabelOntology('SemanticKITTI', GROUND_CLASSES, IGNORED_CLASSES, VEGETATION_CLASS)
RELLIS_3D = LabelOntology('RELLIS-3D', (1, 3, 10, 23, 31, 33), (0,))
# name -> (ground classes, ignored classes), for tools that take the two lists (tools.tune)
DATASET_CLASSES = {'semantickitti': (SEMANTIC_KITTI.ground, SEMANTIC_KITTI.ignored),
                   'rellis3d': (RELLIS_3D.ground, RELLIS_3D.ignored)}


def semantic_classes(labels: np.ndarray) -> np.ndarray:
    """Semantic class of SemanticKITTI labels: the low 16 bits (the high 16 hold the instance)."""
    return np.asarray(labels).astype(np.uint32, copy=False) & 0xFFFF


def ground_truth_from_labels(semantic_labels: np.ndarray, vegetation_is_ground: bool = False,
                             ontology: LabelOntology = SEMANTIC_KITTI
                             ) -> tuple[np.ndarray, np.ndarray]:
    """(truth_ground, evaluated) boolean masks from raw .label values or semantic classes."""
    if vegetation_is_ground and ontology.vegetation is None:
        raise ValueError(f'vegetation_is_ground: {ontology.name} labels have no such variant')
    ground_classes = ontology.ground + ((ontology.vegetation,) if vegetation_is_ground else ())
    return labelled_ground_truth(semantic_labels, ground_classes, ontology.ignored)


def labelled_ground_truth(labels: np.ndarray, ground_classes, ignored_classes
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(truth_ground, evaluated) masks of .label values for any ontology's class lists."""
    classes = semantic_classes(labels)
    return np.isin(classes, ground_classes), ~np.isin(classes, ignored_classes)


def truth_metrics(pred_ground_mask: np.ndarray, truth_ground_mask: np.ndarray,
                  evaluated_mask: np.ndarray | None = None) -> dict:
    """Precision, recall, F1 of *ground* for a predicted vs a true boolean mask (same length).

    ``evaluated_mask`` (optional) selects the points that count; the rest are ignored. Ratios whose
    denominator is zero are NaN (e.g. precision when nothing was called ground), never a fake
    0 or 1.
    """
    pred = np.asarray(pred_ground_mask, dtype=bool).ravel()
    truth = np.asarray(truth_ground_mask, dtype=bool).ravel()
    if pred.shape != truth.shape:
        raise ValueError(f'prediction has {pred.size} points but the truth has {truth.size}')
    if evaluated_mask is not None:
        keep = np.asarray(evaluated_mask, dtype=bool).ravel()
        if keep.shape != pred.shape:
            raise ValueError(f'evaluated mask has {keep.size} points, expected {pred.size}')
        pred, truth = pred[keep], truth[keep]
    counts = metrics_from_counts(int(np.count_nonzero(pred & truth)),
                                 int(np.count_nonzero(pred & ~truth)),
                                 int(np.count_nonzero(~pred & truth)),
                                 int(np.count_nonzero(~pred & ~truth)))
    return dict(counts, evaluated_points=int(pred.size))


def metrics_from_counts(tp: int, fp: int, fn: int, tn: int = 0) -> dict:
    """Precision, recall and F1 of *ground* from the counts (module docstring), with the counts.

    A ratio whose denominator is zero is NaN; F1 is 0 when there was ground or a ground call
    and not one hit, NaN when there was neither.
    """
    precision = tp / (tp + fp) if tp + fp else float('nan')
    recall = tp / (tp + fn) if tp + fn else float('nan')
    if np.isfinite(precision) and np.isfinite(recall) and precision + recall > 0:
        f1 = 2 * precision * recall / (precision + recall)
    elif tp + fp + fn and tp == 0:
        f1 = 0.0  # there was ground or a ground call and not one hit
    else:
        f1 = float('nan')
    return {'precision': precision, 'recall': recall, 'f1': f1, 'tp': tp, 'fp': fp, 'fn': fn,
            'tn': tn}


def pooled_metrics(counts) -> dict | None:
    """:func:`metrics_from_counts` of the summed counts of several frames (dicts with ``tp``,
    ``fp``, ``fn`` and optionally ``tn``; None entries skipped); None when there is none."""
    counts = [c for c in counts if c is not None]
    if not counts:
        return None
    return metrics_from_counts(*(sum(c.get(k, 0) for c in counts)
                                 for k in ('tp', 'fp', 'fn', 'tn')))


def ground_metrics(pred_ground_mask: np.ndarray, semantic_labels: np.ndarray,
                   vegetation_is_ground: bool = False,
                   ontology: LabelOntology = SEMANTIC_KITTI) -> dict:
    """Ground precision/recall/F1 of a prediction against labels of ``ontology`` (module doc).

    ``semantic_labels`` may be the raw uint32 .label values (instance in the high 16 bits) or the
    semantic classes already. The ontology's ignored classes (SemanticKITTI: 0 unlabeled and
    1 outlier) are not evaluated.
    """
    labels = np.asarray(semantic_labels).ravel()
    pred = np.asarray(pred_ground_mask, dtype=bool).ravel()
    if labels.shape != pred.shape:
        raise ValueError(f'the cloud has {pred.size} points but the labels have {labels.size}')
    truth, evaluated = ground_truth_from_labels(labels, vegetation_is_ground, ontology)
    return truth_metrics(pred, truth, evaluated)
