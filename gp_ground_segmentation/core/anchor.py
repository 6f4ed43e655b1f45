# SPDX-License-Identifier: Apache-2.0
"""Stage ``anchor`` [ours, ``use_anchor``]: the ground under the vehicle as a shared GP point.

Every segment starts at the sensor, so all segment GPs meet at r = 0, where the ground is the
one the vehicle stands on (on a slope too). Each segment with a candidate gets one extra
training point there, at the frame's estimate of that height (:func:`ground_under_sensor`) with
noise std ``anchor_std_m``. It ties the segments together: a car parked beside the sensor, whose
roof is the first and only nearby candidate of its segments, is a step up from the vehicle's
ground and is rejected instead of becoming the ground. ``prior_mean_at_anchor`` also makes that
height the GP prior mean (:func:`prior_mean`), so long gaps fall back to the vehicle's ground.
The same height starts the ``plateau`` test (``plateau_from_sensor_ground``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .compiled import Stage, Twin, kernel, sort_in_place


@dataclass(frozen=True)
class GroundAnchor:
    """One extra training point at r = 0 in chosen segments: the ground under the vehicle."""

    height_m: float  # z of the point (m)
    noise_var: float  # its noise variance on top of sigma_n^2 (m^2)
    segments: np.ndarray  # (M,) bool: segments that get it
    length_factor: np.ndarray  # (M,) d of the point in each segment


def ground_under_sensor(cand_z: np.ndarray, training: np.ndarray, line_id: np.ndarray,
                        line_count: np.ndarray, intercept: np.ndarray,
                        compiled: bool = True) -> float:
    """Height of the ground under the vehicle (r = 0), shared by all segments (m).

    Every segment starts at the sensor, so all segment GPs meet at r = 0 where the ground is
    the one the vehicle stands on, on a slope too. The first training candidate of each
    segment belongs to a line; where that line has two or more candidates its intercept (the
    line extrapolated to r = 0) is one estimate, and the median over segments is robust to the
    few whose first line is a car or a wall. Fallbacks: without such a line, the median of the
    training candidates' heights; without training candidates, the median of all candidates;
    without candidates, 0. ``compiled``: the per-segment look-up in numba (as
    :func:`elevated_plateaus`).
    """
    any_training, estimates = INTERCEPTS.run(compiled, training, line_id, line_count,
                                             intercept)
    if not any_training:
        z = cand_z[np.isfinite(cand_z)]
        return _median(z, compiled) if z.size else 0.0
    if estimates.size:
        return _median(estimates, compiled)
    return _median(cand_z[training], compiled)


def _median(values: np.ndarray, compiled: bool) -> float:
    """``float(np.median(values))`` of finite values (one or more); ``compiled``: sorted in
    numba (np.median's Python overhead is many times the sort of a hundred values)."""
    median = MEDIAN.run(compiled, values)
    return float(np.median(values)) if math.isnan(median) else median


def _median_numpy(values):
    return float(np.median(values))


def _median_loop(values):
    """np.median's value of finite ``values`` (compiled with numba): the middle one of the sorted
    values, or the two middle ones' (a + b) / 2, as np.median's mean of them. NaN, for np.median
    itself to decide, when a middle value is zero: np.median's partition may order -0.0 and
    +0.0 otherwise than a sort, and its mean turns -0.0 into +0.0."""
    ordered = values.copy()
    sort_in_place(ordered)
    half = ordered.size // 2
    upper = ordered[half]
    lower = ordered[half - 1] if ordered.size % 2 == 0 else upper
    if lower == 0.0 or upper == 0.0:
        return np.nan
    if ordered.size % 2 == 1:
        return upper
    return (lower + upper) / 2.0


MEDIAN = Twin('median', _median_numpy, kernel(_median_loop), lambda _dtype: [(np.ones(2),)])


def _first_line_intercepts_numpy(training, line_id, line_count, intercept):
    """(any training candidate, intercepts of the segments' first training lines that have
    two or more candidates and a finite intercept, in segment order)."""
    rows = np.flatnonzero(training.any(axis=1))
    first = np.argmax(training[rows], axis=1)
    ids = line_id[rows, first]
    usable = (line_count[ids] >= 2) & np.isfinite(intercept[ids])
    return rows.size > 0, intercept[ids[usable]]


def _first_line_intercepts_loop(training, line_id, line_count, intercept):
    """:func:`_first_line_intercepts_numpy` as one loop (compiled with numba), the same values
    in the same order, without ~8 small numpy calls."""
    m_count, n_count = training.shape
    estimates = np.empty(m_count)
    found = 0
    any_training = False
    for m in range(m_count):
        for k in range(n_count):
            if training[m, k]:
                any_training = True
                i = line_id[m, k]
                if line_count[i] >= 2 and np.isfinite(intercept[i]):
                    estimates[found] = intercept[i]
                    found += 1
                break
    return any_training, estimates[:found]


INTERCEPTS = Twin('first lines\' intercepts', _first_line_intercepts_numpy,
                  kernel(_first_line_intercepts_loop),
                  lambda _dtype: [(np.ones((2, 2), bool), np.zeros((2, 2), np.intp),
                                   np.ones(1, np.intp), np.ones(1))])


def make_anchor(candidate_index, candidate_z, training, lines, d, std_m: float,
                compiled: bool = True) -> GroundAnchor:
    """The anchor of one frame: the ground under the sensor as the first training point of
    every segment with a candidate, its d the first training candidate's (the row's last d
    where none trains)."""
    height = ground_under_sensor(candidate_z, training, lines.line_id, lines.line_count,
                                 lines.intercept, compiled=compiled)
    segments, length_factor = ANCHOR_ROWS.run(compiled, candidate_index, d, training)
    return GroundAnchor(height, std_m ** 2, segments, length_factor)


def prior_mean(anchor: Optional[GroundAnchor], training_z: np.ndarray) -> Optional[float]:
    """The GP prior mean at the anchor height, kept within the training candidates' heights
    ``training_z`` (the anchor extrapolates lines to r = 0: a scene seen from far away must not
    put the prior kilometres off); None (FrameGP's median) without an anchor or candidates."""
    if anchor is None or not training_z.size:
        return None
    # np.clip of one number, without np.clip's array set-up (same value)
    return float(min(max(anchor.height_m, float(training_z.min())), float(training_z.max())))


def _anchor_rows_numpy(candidate_index, d, training):
    """(segments with a candidate (M,), each one's first training candidate's d, the last d
    of a row without one): the anchor's rows and length factors; the numpy reference of
    :func:`_anchor_rows_loop`."""
    return (candidate_index >= 0).any(axis=1), _first_known_along_rows(d, training)


def _anchor_rows_loop(candidate_index, d, training):
    """:func:`_anchor_rows` in one pass over the rows (compiled with numba): the same values
    without its ~8 numpy calls."""
    m_count, n_count = d.shape
    segments = np.zeros(m_count, dtype=np.bool_)
    length_factor = np.empty(m_count, dtype=d.dtype)
    for m in range(m_count):
        for k in range(n_count):
            if candidate_index[m, k] >= 0:
                segments[m] = True
                break
        pick = n_count - 1
        for k in range(n_count):
            if training[m, k]:
                pick = k
                break
        length_factor[m] = d[m, pick]
    return segments, length_factor


ANCHOR_ROWS = Twin('anchor rows', _anchor_rows_numpy, kernel(_anchor_rows_loop),
                   lambda _dtype: [(np.ones((2, 2), np.intp), np.ones((2, 2)),
                                    np.ones((2, 2), bool))])


def _first_known_along_rows(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Column 0 of ``_fill_along_rows(values, known)`` without filling the rows: each row's
    first known entry, the last entry in a row without one."""
    first = np.where(known.any(axis=1), known.argmax(axis=1), values.shape[1] - 1)
    return values[np.arange(values.shape[0]), first]


STAGE = Stage('anchor', 'ours', 'use_anchor', (INTERCEPTS, MEDIAN, ANCHOR_ROWS))
STAGES = (STAGE,)
