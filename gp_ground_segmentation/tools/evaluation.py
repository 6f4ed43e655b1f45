# SPDX-License-Identifier: Apache-2.0
"""Ground-segmentation metrics against SemanticKITTI labels or synthetic per-point truth.

Protocol (follows the Patchwork / Patchwork++ evaluation of SemanticKITTI):

* ground classes: 40 road, 44 parking, 48 sidewalk, 49 other-ground, 60 lane-marking, 72 terrain;
* ignored: 0 unlabeled and 1 outlier are left out of every count;
* everything else is non-ground. **Vegetation (70) counts as non-ground by default**: bushes and
  hedges stand well above the terrain and a segmenter that calls them ground hides obstacles.
  Patchwork reports variants that count 70 as ground; ``vegetation_is_ground=True`` reproduces
  them.

"Positive" means *ground*: precision = TP / (TP + FP) is the share of points called ground that are
ground, recall = TP / (TP + FN) the share of true ground that was found.
"""

from __future__ import annotations

import numpy as np

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
IGNORED_CLASSES = (0, 1)
VEGETATION_CLASS = 70

# Label ontologies by data set: name -> (ground classes, ignored classes). RELLIS-3D ground is
# dirt 1, grass 3, asphalt 10, concrete 23, puddle 31, mud 33; void 0 (which also holds every
# no-return point) is left out.
DATASET_CLASSES = {
    'semantickitti': (GROUND_CLASSES, IGNORED_CLASSES),
    'rellis3d': ((1, 3, 10, 23, 31, 33), (0,)),
}


def semantic_classes(labels: np.ndarray) -> np.ndarray:
    """Semantic class of SemanticKITTI labels: the low 16 bits (the high 16 hold the instance)."""
    return np.asarray(labels).astype(np.uint32, copy=False) & 0xFFFF


def ground_truth_from_labels(semantic_labels: np.ndarray, vegetation_is_ground: bool = False
                             ) -> tuple[np.ndarray, np.ndarray]:
    """(truth_ground, evaluated) boolean masks from raw .label values or semantic classes."""
    ground_classes = GROUND_CLASSES + ((VEGETATION_CLASS,) if vegetation_is_ground else ())
    return labelled_ground_truth(semantic_labels, ground_classes, IGNORED_CLASSES)


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
    tp = int(np.count_nonzero(pred & truth))
    fp = int(np.count_nonzero(pred & ~truth))
    fn = int(np.count_nonzero(~pred & truth))
    tn = int(np.count_nonzero(~pred & ~truth))
    precision = tp / (tp + fp) if tp + fp else float('nan')
    recall = tp / (tp + fn) if tp + fn else float('nan')
    if np.isfinite(precision) and np.isfinite(recall) and precision + recall > 0:
        f1 = 2 * precision * recall / (precision + recall)
    elif tp + fp + fn and tp == 0:
        f1 = 0.0  # there was ground or a ground call and not one hit
    else:
        f1 = float('nan')
    return {'precision': precision, 'recall': recall, 'f1': f1, 'tp': tp, 'fp': fp, 'fn': fn,
            'tn': tn, 'evaluated_points': int(pred.size)}


def ground_metrics(pred_ground_mask: np.ndarray, semantic_labels: np.ndarray,
                   vegetation_is_ground: bool = False) -> dict:
    """Ground precision/recall/F1 of a prediction against SemanticKITTI labels (see module doc).

    ``semantic_labels`` may be the raw uint32 .label values (instance in the high 16 bits) or the
    semantic classes already. Unlabeled (0) and outlier (1) points are not evaluated.
    """
    labels = np.asarray(semantic_labels).ravel()
    pred = np.asarray(pred_ground_mask, dtype=bool).ravel()
    if labels.shape != pred.shape:
        raise ValueError(f'the cloud has {pred.size} points but the labels have {labels.size}')
    truth, evaluated = ground_truth_from_labels(labels, vegetation_is_ground)
    return truth_metrics(pred, truth, evaluated)
