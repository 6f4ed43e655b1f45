# SPDX-License-Identifier: Apache-2.0
"""Ground-segmentation metrics against SemanticKITTI or RELLIS-3D labels or synthetic truth.

Two things decide what is scored: the *ontology* of the labels (which class ids are ground,
which are left out) and the *protocol* (what happens to vegetation, the one choice that moves
F1 by several points between published tables; ../shared/data/README.md section 7).

Ontologies (:data:`ONTOLOGIES`, by the name ``--dataset`` takes):

* ``semantickitti``: ground 40 road, 44 parking, 48 sidewalk, 49 other-ground, 60 lane-marking,
  72 terrain; 0 unlabeled and 1 outlier left out; vegetation 70;
* ``rellis3d``: ground 1 dirt, 3 grass, 10 asphalt, 23 concrete, 31 puddle, 33 mud; 0 void left
  out (it also holds every (0, 0, 0) no-return of the organised Ouster cloud); vegetation 19
  bush (4 tree is not vegetation here: a trunk is an obstacle under every protocol).

Everything else is non-ground. Protocols (:data:`PROTOCOLS`, by the name ``--protocol`` takes):

* ``vegetation-nonground`` (the default, :data:`DEFAULT_PROTOCOL`): vegetation is non-ground,
  the strictest reading; a segmenter that calls a hedge ground hides an obstacle;
* ``patchworkpp``: vegetation is not scored at all (neither ground nor non-ground), as in
  Patchwork++'s paper and GroundGrid's evaluation;
* ``vegetation-ground``: vegetation counts as ground (a variant some Patchwork tables use).

"Positive" means *ground*: precision = TP / (TP + FP) is the share of points called ground that
are ground, recall = TP / (TP + FN) the share of true ground found, and GroundGrid's ground IoU
(``iou``) = TP / (TP + FP + FN). Several frames are pooled by summing their counts
(:func:`pooled_metrics`), never by averaging their F1.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
IGNORED_CLASSES = (0, 1)
VEGETATION_CLASS = 70


class LabelOntology(NamedTuple):
    """Which semantic classes of a labelled data set are ground, left out and vegetation."""

    name: str  # as people write it, e.g. 'SemanticKITTI'
    key: str  # the --dataset value, e.g. 'semantickitti'
    ground: tuple
    ignored: tuple
    vegetation: tuple  # the classes a protocol treats apart


SEMANTIC_KITTI = LabelOntology('SemanticKITTI', 'semantickitti', GROUND_CLASSES,
                               IGNORED_CLASSES, (VEGETATION_CLASS,))
RELLIS_3D = LabelOntology('RELLIS-3D', 'rellis3d', (1, 3, 10, 23, 31, 33), (0,), (19,))
ONTOLOGIES = {o.key: o for o in (SEMANTIC_KITTI, RELLIS_3D)}


class ScoringProtocol(NamedTuple):
    """What a scoring protocol does with an ontology's vegetation classes (module docstring)."""

    name: str  # the --protocol value
    vegetation: str  # 'non-ground', 'unscored' or 'ground'
    summary: str  # one line for --help and the benchmark tables

    def classes(self, ontology: LabelOntology) -> tuple[tuple, tuple]:
        """(ground classes, left-out classes) of ``ontology`` under this protocol."""
        ground, ignored = tuple(ontology.ground), tuple(ontology.ignored)
        if self.vegetation == 'ground':
            ground = tuple(sorted(set(ground) | set(ontology.vegetation)))
        elif self.vegetation == 'unscored':
            ignored = tuple(sorted(set(ignored) | set(ontology.vegetation)))
        return ground, ignored


VEGETATION_NONGROUND = ScoringProtocol('vegetation-nonground', 'non-ground',
                                       'vegetation counts as non-ground')
PATCHWORKPP = ScoringProtocol('patchworkpp', 'unscored',
                              "vegetation is not scored (Patchwork++'s paper, GroundGrid)")
VEGETATION_GROUND = ScoringProtocol('vegetation-ground', 'ground',
                                    'vegetation counts as ground (a Patchwork variant)')
PROTOCOLS = {p.name: p for p in (VEGETATION_NONGROUND, PATCHWORKPP, VEGETATION_GROUND)}
DEFAULT_PROTOCOL = VEGETATION_NONGROUND


def semantic_classes(labels: np.ndarray) -> np.ndarray:
    """Semantic class of SemanticKITTI labels: the low 16 bits (the high 16 hold the instance)."""
    return np.asarray(labels).astype(np.uint32, copy=False) & 0xFFFF


def ground_truth_from_labels(semantic_labels: np.ndarray,
                             ontology: LabelOntology = SEMANTIC_KITTI,
                             protocol: ScoringProtocol = DEFAULT_PROTOCOL
                             ) -> tuple[np.ndarray, np.ndarray]:
    """(truth_ground, evaluated) boolean masks from raw .label values or semantic classes."""
    return labelled_ground_truth(semantic_labels, *protocol.classes(ontology))


def labelled_ground_truth(labels: np.ndarray, ground_classes, ignored_classes
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(truth_ground, evaluated) masks of .label values for any ontology's class lists."""
    classes = semantic_classes(labels)
    return np.isin(classes, ground_classes), ~np.isin(classes, ignored_classes)


def truth_metrics(pred_ground_mask: np.ndarray, truth_ground_mask: np.ndarray,
                  evaluated_mask: np.ndarray | None = None) -> dict:
    """Precision, recall, F1, IoU of *ground* for a predicted vs a true mask (same length).

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
    """Precision, recall, F1 and IoU of *ground* from the counts (module docstring), with the
    counts.

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
    iou = tp / (tp + fp + fn) if tp + fp + fn else float('nan')
    return {'precision': precision, 'recall': recall, 'f1': f1, 'iou': iou, 'tp': tp, 'fp': fp,
            'fn': fn, 'tn': tn}


def pooled_metrics(counts) -> dict | None:
    """:func:`metrics_from_counts` of the summed counts of several frames (dicts with ``tp``,
    ``fp``, ``fn`` and optionally ``tn``; None entries skipped); None when there is none."""
    counts = [c for c in counts if c is not None]
    if not counts:
        return None
    return metrics_from_counts(*(sum(c.get(k, 0) for c in counts)
                                 for k in ('tp', 'fp', 'fn', 'tn')))


def ground_metrics(pred_ground_mask: np.ndarray, semantic_labels: np.ndarray, *,
                   ontology: LabelOntology = SEMANTIC_KITTI,
                   protocol: ScoringProtocol = DEFAULT_PROTOCOL) -> dict:
    """Ground precision/recall/F1/IoU of a prediction against labels of ``ontology`` scored
    under ``protocol`` (module docstring).

    ``semantic_labels`` may be the raw uint32 .label values (instance in the high 16 bits) or the
    semantic classes already.
    """
    labels = np.asarray(semantic_labels).ravel()
    pred = np.asarray(pred_ground_mask, dtype=bool).ravel()
    if labels.shape != pred.shape:
        raise ValueError(f'the cloud has {pred.size} points but the labels have {labels.size}')
    truth, evaluated = ground_truth_from_labels(labels, ontology, protocol)
    return truth_metrics(pred, truth, evaluated)
