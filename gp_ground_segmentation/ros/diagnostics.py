# SPDX-License-Identifier: Apache-2.0
"""Processing statistics over a window of frames, and the diagnostic_msgs status built from them.

``diagnostic_updater`` is not on PyPI, so this module does its job for the node (and for the
offline bag replay, which reuses ``ProcessingWindow`` + ``diagnostics_status``): per-stage timings
(mean/p95/max over the last ``window`` frames), input rate, frame counters (received, processed,
dropped, failed), the last frame's point counts, the GP hyperparameters theta and the segmenter's
counters (``result.stats``). Every KeyValue value is a string (diagnostic_msgs requires it; the
Jazzy updater does not convert). Levels use the ``DiagnosticStatus`` byte constants.

Level rules (first match wins):
  STALE  no cloud received yet;
  ERROR  the most recent frame failed: bad input (CloudFormatError, message given) or a processing
         error;
  WARN   a frame within the window was processed but its input looked wrong (``record_frame``
         warnings: empty, no valid point, trailing bytes, empty frame_id, stamp going backwards,
         field layout changed, cloud not sensor-centred; the node's IMU note when a frame
         used the static pose for want of an IMU sample near its stamp), mean total time >
         budget (the cold-start first frame, which learns theta from scratch, is left out of
         this mean once another frame exists), frames dropped within the window, earlier
         failures within the window, or no input for ``stale_after_s``;
  OK     otherwise.
``ProcessingWindow`` is thread-safe: the subscription callback, the worker thread and the timer
all update or read it.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from .pipeline import STAGES, FrameOutput, frame_timings

__all__ = ['ProcessingWindow', 'diagnostics_status', 'diagnostics_array', 'STATUS_NAME',
           'TIMING_STAGES']

STATUS_NAME = 'ground_segmentation: processing'
TIMING_STAGES = STAGES


def _fmt(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f'{float(value):.3f}' if np.isfinite(value) else str(float(value))
    return str(value)


class ProcessingWindow:
    """Counters and a sliding window of the last ``window`` frames (frames, not seconds).

    Timings cover the last ``window`` processed frames; drops and failures are counted over the
    last ``window`` frames whose fate is known (processed, failed or dropped).
    """

    def __init__(self, window: int = 50):
        self._lock = threading.Lock()
        self.frames_received = 0
        self.frames_processed = 0
        self.frames_dropped = 0
        self.frames_failed = 0
        self.last_frame_id = None
        self.last_receive_time = None
        self.last_error = None  # one-line text of the most recent failure
        self.last_outcome = None  # 'ok' | 'bad_input' | 'error'
        self.last_points = {}
        self.last_theta = None
        self.last_stats = {}
        self.last_warnings = []  # input warnings of the most recent processed frame
        self.frames_with_warnings = 0
        self.last_warning = None
        self._make_deques(window)

    def _make_deques(self, window: int, old=None):
        window = max(1, int(window))
        self.window = window
        old = old or {}
        self._timings = deque(old.get('timings', ()), maxlen=window)  # dict stage -> ms
        self._stats = deque(old.get('stats', ()), maxlen=window)  # result.stats per frame
        # Fate of the last ``window`` frames: 'ok' | 'warning' (processed, input warnings) |
        # 'bad_input' | 'error' | 'dropped'.
        self._outcomes = deque(old.get('outcomes', ()), maxlen=window)
        self._receive_times = deque(old.get('receive', ()), maxlen=window + 1)
        # Per entry of _timings: True for the cold-start first frame (kept out of the budget).
        self._cold = deque(old.get('cold', ()), maxlen=window)

    def resize(self, window: int) -> None:
        """Change the window length, keeping the most recent entries."""
        with self._lock:
            self._make_deques(window, {'timings': self._timings, 'stats': self._stats,
                                       'outcomes': self._outcomes,
                                       'receive': self._receive_times, 'cold': self._cold})

    # --- updates ---------------------------------------------------------------------------
    def record_received(self, frame_id: str | None = None, now: float | None = None) -> None:
        """A message arrived (monotonic time ``now`` in s)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self.frames_received += 1
            self.last_receive_time = now
            self._receive_times.append(now)
            if frame_id is not None:
                self.last_frame_id = frame_id

    def record_dropped(self, count: int = 1) -> None:
        """``count`` frames were discarded unprocessed (latest-wins slot overflow)."""
        with self._lock:
            self.frames_dropped += int(count)
            self._outcomes.extend(['dropped'] * int(count))

    def record_frame(self, out: FrameOutput, frame_id: str | None = None,
                     warnings: list | None = None, node_timings: dict | None = None) -> None:
        """A frame was processed successfully and its outputs published. ``warnings``: one-line
        notes on its input (default ``out.warnings``); they make the status WARN until the next
        frame. ``node_timings``: stage -> ms measured outside the pipeline (the node's
        ``handoff``, ``publish`` and ``ground_published``), kept with the frame's pipeline
        timings."""
        if warnings is None:
            warnings = list(getattr(out, 'warnings', None) or [])
        res = out.result
        n = int(res.valid_mask.size)
        n_ground = int(np.count_nonzero(res.ground_mask))
        with self._lock:
            self._cold.append(self.frames_processed == 0)
            self.frames_processed += 1
            self.last_outcome = 'ok'
            if frame_id is not None:
                self.last_frame_id = frame_id
            self._timings.append({**frame_timings(out), **(node_timings or {})})
            self._stats.append(dict(res.stats))
            self._outcomes.append('warning' if warnings else 'ok')
            self.last_points = {'points_in': n, 'points_ground': n_ground,
                                'points_obstacles': n - n_ground - res.num_invalid,
                                'points_invalid': res.num_invalid}
            self.last_theta = res.hyperparameters
            self.last_stats = dict(res.stats)
            self.last_warnings = list(warnings)
            if warnings:
                self.frames_with_warnings += 1
                self.last_warning = '; '.join(warnings)

    def record_failure(self, message: str, bad_input: bool, frame_id: str | None = None) -> None:
        """A frame could not be processed (nothing was published for it)."""
        with self._lock:
            self.frames_failed += 1
            self.last_outcome = 'bad_input' if bad_input else 'error'
            self.last_error = message
            if frame_id is not None:
                self.last_frame_id = frame_id
            self._outcomes.append(self.last_outcome)

    # --- reading ---------------------------------------------------------------------------
    def snapshot(self, now: float | None = None) -> dict:
        """A consistent copy of everything needed to build a status."""
        now = time.monotonic() if now is None else now
        with self._lock:
            outcomes = list(self._outcomes)
            timings = list(self._timings)
            warm = [t for t, cold in zip(timings, self._cold) if not cold]
            return {
                'timings': timings, 'stats': list(self._stats),
                'budget_timings': warm or timings,
                'warnings_in_window': sum(1 for o in outcomes if o == 'warning'),
                'failures_in_window': sum(1 for o in outcomes if o in ('bad_input', 'error')),
                'drops_in_window': sum(1 for o in outcomes if o == 'dropped'),
                'input_rate_hz': _input_rate(list(self._receive_times), now),
                'frames_received': self.frames_received,
                'frames_processed': self.frames_processed,
                'frames_dropped': self.frames_dropped, 'frames_failed': self.frames_failed,
                'last_frame_id': self.last_frame_id, 'last_error': self.last_error,
                'last_outcome': self.last_outcome, 'last_points': dict(self.last_points),
                'last_theta': self.last_theta, 'last_stats': dict(self.last_stats),
                'last_warnings': list(self.last_warnings),
                'frames_with_warnings': self.frames_with_warnings,
                'last_warning': self.last_warning,
                'seconds_since_input': (now - self.last_receive_time
                                        if self.last_receive_time is not None else None),
                'window': self.window,
            }


def _input_rate(times: list, now: float) -> float:
    """Frames per second over the last receptions ``times`` (s, ascending), NaN below two.

    Measured up to ``now`` once the input has been silent for more than two mean periods, so
    the rate falls towards 0 when the input stops instead of keeping its last value.
    """
    if len(times) < 2 or times[-1] <= times[0]:
        return float('nan')
    span = times[-1] - times[0]
    if now - times[-1] > 2.0 * span / (len(times) - 1):
        span = now - times[0]
    return (len(times) - 1) / span


def _timing_summary(timings: list) -> dict:
    """stage -> (mean, p95, max) ms over the frames that reported that stage."""
    out = {}
    stages = list(STAGES) + sorted({k for t in timings for k in t} - set(STAGES))
    for stage in stages:
        values = np.array([t[stage] for t in timings if stage in t], dtype=float)
        values = values[np.isfinite(values)]
        if values.size:
            out[stage] = (float(values.mean()), float(np.percentile(values, 95)),
                          float(values.max()))
    return out


def diagnostics_status(window: ProcessingWindow, *, budget_ms: float, name: str = STATUS_NAME,
                       stale_after_s: float | None = 5.0, now: float | None = None,
                       extra: dict | None = None):
    """Build a ``diagnostic_msgs/DiagnosticStatus`` from ``window``.

    ``budget_ms``: processing budget per frame (ms); ``stale_after_s``: WARN when no input for
    this long (s; None disables, e.g. for offline replay); ``extra``: more key -> value pairs.
    Keys: ``<stage>_ms_mean|p95|max`` for stage in decode, grid, lines, gp_fit, predict, label,
    structure, encode, total (+ segment), ``input_rate_hz``, ``frames_*``, ``points_*`` (last
    frame), ``sigma_f``/``gain``/``sigma_n``, each ``result.stats`` key (last frame) and, for
    integer counters, ``<key>_window`` (sum over the window), ``budget_ms``, ``window_frames``,
    ``last_error``.
    """
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    snap = window.snapshot(now)
    summary = _timing_summary(snap['timings'])
    values = []

    def add(key, value):
        values.append(KeyValue(key=key, value=_fmt(value)))

    for stage, (mean, p95, mx) in summary.items():
        add(f'{stage}_ms_mean', mean)
        add(f'{stage}_ms_p95', p95)
        add(f'{stage}_ms_max', mx)
    add('input_rate_hz', snap['input_rate_hz'])
    for key in ('frames_received', 'frames_processed', 'frames_dropped', 'frames_failed',
                'drops_in_window', 'failures_in_window'):
        add(key, snap[key])
    for key in ('points_in', 'points_ground', 'points_obstacles', 'points_invalid'):
        add(key, snap['last_points'].get(key, 'n/a'))
    theta = snap['last_theta']
    for i, key in enumerate(('sigma_f', 'gain', 'sigma_n')):
        add(key, float(theta[i]) if theta is not None else 'n/a')
    for key, value in sorted(snap['last_stats'].items()):
        add(key, value)
        # Window sums only for counters (ints); a sum of e.g. likelihoods would mean nothing.
        numeric = [s[key] for s in snap['stats']
                   if isinstance(s.get(key), (int, np.integer))
                   and not isinstance(s.get(key), bool)]
        if numeric and isinstance(value, (int, np.integer)):
            add(f'{key}_window', sum(numeric))
    add('budget_ms', float(budget_ms))
    add('window_frames', snap['window'])
    add('last_error', snap['last_error'] or 'none')
    add('frames_with_input_warnings', snap['frames_with_warnings'])
    add('input_warnings_in_window', snap['warnings_in_window'])
    add('last_input_warning', snap['last_warning'] or 'none')
    for key, value in (extra or {}).items():
        add(key, value)

    warnings = []
    if snap['frames_received'] == 0:
        level, message = DiagnosticStatus.STALE, 'no input received yet'
    elif snap['last_outcome'] in ('bad_input', 'error'):
        level = DiagnosticStatus.ERROR
        prefix = 'bad input' if snap['last_outcome'] == 'bad_input' else 'processing error'
        message = f"{prefix}: {snap['last_error']}"
    else:
        if snap['warnings_in_window'] > 0:
            warnings.append(f"input: {snap['last_warning']} ({snap['warnings_in_window']} "
                            f"frame(s) with input warnings in the window)")
        total = _timing_summary(snap['budget_timings']).get('total')
        if total is not None and total[0] > budget_ms:
            warnings.append(f'mean processing {total[0]:.1f} ms > budget {budget_ms:g} ms')
        if snap['drops_in_window'] > 0:
            warnings.append(f"{snap['drops_in_window']} frame(s) dropped in the window")
        if snap['failures_in_window'] > 0:
            warnings.append(f"{snap['failures_in_window']} frame(s) failed in the window "
                            f"(last: {snap['last_error']})")
        since = snap['seconds_since_input']
        if stale_after_s is not None and since is not None and since > stale_after_s:
            warnings.append(f'no input for {since:.1f} s')
        if snap['frames_processed'] == 0 and not warnings:
            warnings.append('waiting for the first frame to be processed')
        level = DiagnosticStatus.WARN if warnings else DiagnosticStatus.OK
        message = '; '.join(warnings) if warnings else 'ok'
    return DiagnosticStatus(level=level, name=name, message=message,
                            hardware_id=snap['last_frame_id'] or 'none', values=values)


def diagnostics_array(statuses, stamp=None):
    """Wrap statuses in a ``diagnostic_msgs/DiagnosticArray`` (stamp: builtin_interfaces/Time)."""
    from diagnostic_msgs.msg import DiagnosticArray

    arr = DiagnosticArray(status=list(statuses))
    if stamp is not None:
        arr.header.stamp = stamp
    return arr
