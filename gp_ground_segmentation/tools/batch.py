# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg batch``: replay many inputs, one task each, in-process or on Dask.

Each input (a bag, a Velodyne .pcap, or a directory of bags' worth of .bin/.pcd files) is one
task that runs :func:`bag.replay` unchanged, so its output bag ``DIR/<input name>/`` is byte for
byte what ``gp-ground-seg replay INPUT DIR/<input name>`` writes (ground, obstacle and surface
clouds, the labelled one with ``--labeled``; diagnostics carry timings). ``replay`` writes into
a hidden sibling and renames it into place, so an output directory is either complete or absent:
re-running skips inputs whose output exists (``force`` redoes them), and an interrupted batch
leaves nothing half-written (hidden leftovers of killed workers are removed on the way out).

A failing input (corrupt bag, wrong type, missing topic) is a row with status ``failed`` and
replay's one-line message; the other tasks finish. ``DIR/summary.json`` and ``DIR/summary.csv``
list every input: frames, points, ground share, ms p50/p95 of the per-frame ``total`` (decode +
segment + encode, as the node reports), the theta range, status and error.
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from .bag import FrameSource, Progress, load_params, replay
from .engine import add_engine_arguments, open_engine, peak_rss_mb
from .errors import EXPECTED_ERRORS, CliError, one_line
from .options import add_input_options, add_labeled_option, add_storage_option

PROGRESS_TOPIC = 'gp-ground-seg-batch-progress'
BAG_SUFFIXES = ('.mcap', '.db3', '.bag', '.pcap')  # output DIR/<name without them>
THETA_NAMES = ('sigma_f', 'gain', 'sigma_n')
CSV_FIELDS = ('input', 'output', 'status', 'frames', 'skipped_frames', 'points', 'ground_share',
              'total_ms_p50', 'total_ms_p95') + tuple(
                  f'{n}_{end}' for n in THETA_NAMES for end in ('min', 'max')) + (
              'wall_s', 'error')


def output_name(input_path: str) -> str:
    """``DIR/<name>`` of an input: a directory's name, a bag file's name without its suffix."""
    path = Path(os.path.normpath(input_path))
    return path.stem if path.suffix.lower() in BAG_SUFFIXES else path.name


def _complete(out: Path) -> bool:
    """replay renames a bag into place only when it is finished: metadata.yaml marks it."""
    return (out / 'metadata.yaml').is_file()


def count_frames(input_path: str, topic: Optional[str]) -> int:
    """Frames of one input (for the progress total); 0 if it cannot be opened (its task will
    then report why)."""
    try:
        with FrameSource([input_path], topic) as source:
            return source.count
    except EXPECTED_ERRORS:
        return 0


class _TaskProgress:
    """The ``progress`` object replay updates, forwarded to the batch (via the sink)."""

    def __init__(self, key: str, sink: Callable):
        self.key, self.sink = key, sink

    def update(self, done: int) -> None:
        self.sink({'input': self.key, 'done': done})

    def close(self) -> None:
        pass


def replay_one(input_path: str, out_bag: str, *, label: str, topic: Optional[str],
               params_file: Optional[str], storage: str, force: bool, sink: Callable,
               labeled: bool = False) -> dict:
    """One task: replay ``input_path`` into ``out_bag``; a summary row for input ``label`` (the
    path as the user gave it). Never raises for bad input: the error is the row's, in replay's
    one-line wording."""
    row = {'input': label, 'output': out_bag, 'status': 'ok', 'error': ''}
    t0 = time.perf_counter()
    try:
        summary = replay([input_path], out_bag, topic=topic, params_file=params_file,
                         storage=storage, force=force, labeled=labeled,
                         progress=_TaskProgress(label, sink))
    except EXPECTED_ERRORS as err:
        row.update(status='failed', error=one_line(err), wall_s=time.perf_counter() - t0)
        return row
    total = np.asarray(summary.stage_ms.get('total', [np.nan]))
    theta = np.asarray(summary.thetas, dtype=float).reshape(-1, 3)
    row.update(frames=summary.frames, skipped_frames=summary.skipped, points=summary.points,
               ground_share=summary.ground / summary.valid if summary.valid else None,
               total_ms_p50=float(np.percentile(total, 50)),
               total_ms_p95=float(np.percentile(total, 95)),
               theta_range={n: [float(theta[:, k].min()), float(theta[:, k].max())]
                            for k, n in enumerate(THETA_NAMES)},
               wall_s=summary.wall_s, topic=summary.topic)
    return row


@dataclass
class BatchResult:
    """Rows of every input (in input order), the engine used and the totals."""

    rows: list
    engine: str
    wall_s: float
    frames: int
    worker_peak_rss_mb: dict = field(default_factory=dict)
    interrupted: bool = False

    @property
    def failed(self) -> int:
        return sum(r['status'] == 'failed' for r in self.rows)


def _csv_row(row: dict) -> dict:
    flat = {k: row.get(k, '') for k in CSV_FIELDS}
    for name, (low, high) in (row.get('theta_range') or {}).items():
        flat[f'{name}_min'], flat[f'{name}_max'] = low, high
    return {k: ('' if v is None else v) for k, v in flat.items()}


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f'.{path.name}.partial-{os.getpid()}')
    tmp.write_text(text)
    os.replace(tmp, path)


def write_summary(out_dir: Path, result: BatchResult, meta: dict) -> None:
    doc = dict(meta, engine=result.engine, wall_s=result.wall_s, frames=result.frames,
               failed=result.failed, interrupted=result.interrupted,
               worker_peak_rss_mb=result.worker_peak_rss_mb, inputs=result.rows)
    _write_atomic(out_dir / 'summary.json', json.dumps(doc, indent=2) + '\n')
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator='\n')
    writer.writeheader()
    writer.writerows(_csv_row(r) for r in result.rows)
    _write_atomic(out_dir / 'summary.csv', buf.getvalue())


def _previous_rows(out_dir: Path) -> dict:
    """Rows of an earlier run's summary.json by output path (to report skipped inputs)."""
    try:
        doc = json.loads((out_dir / 'summary.json').read_text())
        return {r['output']: r for r in doc.get('inputs', []) if r.get('status') == 'ok'}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _remove_leftovers(out_dir: Path, names: Sequence[str]) -> None:
    """Hidden partial/old directories replay leaves only when its process is killed."""
    for name in names:
        for pattern in (f'.{name}.partial-*', f'.{name}.old-*'):
            for leftover in out_dir.glob(pattern):
                shutil.rmtree(leftover, ignore_errors=True)


def task_line(row: dict) -> str:
    """The one-line per-task summary printed as tasks finish."""
    if row['status'] == 'failed':
        return f"{row['input']}: FAILED: {row['error']}"
    share = row.get('ground_share')
    share_text = 'n/a' if share is None else f'{share:.3f}'
    return (f"{row['input']}: {row['status']}, {row.get('frames')} frames, ground share "
            f"{share_text}, total ms p50 {row.get('total_ms_p50', float('nan')):.1f} "
            f"p95 {row.get('total_ms_p95', float('nan')):.1f} -> {row['output']}")


def run_batch(inputs: Sequence[str], out_dir, engine, *, topic: Optional[str] = None,
              params_file: Optional[str] = None, storage: str = 'mcap', force: bool = False,
              report: Optional[Callable] = None, progress_stream=None,
              labeled: bool = False) -> BatchResult:
    """Replay every input into ``out_dir/<name>/`` on ``engine``; write the summaries.

    ``report(row)`` is called as each task finishes (and for each skipped input).
    KeyboardInterrupt cancels the outstanding tasks, removes their hidden leftovers, writes the
    summary of what finished and is re-raised.
    """
    # tasks get absolute paths: a remote worker's working directory is not ours
    out_dir = Path(out_dir).absolute()
    params_file = None if params_file is None else os.path.abspath(params_file)
    names = _output_names(inputs, out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise CliError(f'{out_dir} exists and is not a directory')
    if params_file is not None:
        load_params(params_file)  # a bad file fails once, up front, not once per task
    out_dir.mkdir(parents=True, exist_ok=True)
    engine.check_shared(inputs, out_dir)
    report = report or (lambda row: None)
    t0 = time.perf_counter()
    rows, todo = _skip_complete(inputs, names, out_dir, force, report)
    progress = _BatchProgress(engine, todo, topic, progress_stream)
    task = {'topic': topic, 'params_file': params_file, 'storage': storage, 'force': force,
            'labeled': labeled, 'sink': engine.progress_sink(PROGRESS_TOPIC)}
    interrupted = False
    try:
        _run_tasks(engine, todo, task, rows, progress, report)
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        progress.close()
        if interrupted:
            engine.close()  # stops a LocalCluster's workers before their leftovers are removed
            _remove_leftovers(out_dir, names)
        ordered = [rows.get(p, {'input': p, 'output': str(out_dir / n), 'status': 'interrupted',
                                'error': 'interrupted before it finished'})
                   for p, n in zip(inputs, names)]
        rss = {} if interrupted else engine.run_on_workers(peak_rss_mb)
        result = BatchResult(ordered, engine.description, time.perf_counter() - t0,
                             sum(r.get('frames', 0) or 0 for r in ordered if r['status'] == 'ok'),
                             rss, interrupted)
        write_summary(out_dir, result, {'params_file': params_file, 'topic': topic,
                                        'storage': storage, 'labeled': labeled})
    return result


def _output_names(inputs: Sequence[str], out_dir: Path) -> list:
    """The output name of every input; CliError when there is none or two would collide."""
    if not inputs:
        raise CliError('give at least one input')
    names = [output_name(p) for p in inputs]
    seen = {}
    for path, name in zip(inputs, names):
        if name in seen:
            raise CliError(f'{seen[name]} and {path} would both be written to {out_dir / name}; '
                           f'rename one')
        seen[name] = path
    return names


def _skip_complete(inputs, names, out_dir: Path, force: bool, report: Callable) -> tuple:
    """({input: row} of the inputs whose complete output exists (reported as skipped, with the
    earlier run's numbers), [(input, output path)] of those still to do)."""
    previous = _previous_rows(out_dir)
    rows, todo = {}, []
    for path, name in zip(inputs, names):
        out = out_dir / name
        if _complete(out) and not force:
            row = dict(previous.get(str(out), {'input': path, 'output': str(out)}),
                       status='skipped', error='')
            rows[path] = row
            report(row)
        else:
            todo.append((path, str(out)))
    return rows, todo


class _BatchProgress:
    """The batch's progress bar over the frames of every input to do, fed by the tasks'
    progress events (through the engine) and by their completion."""

    def __init__(self, engine, todo, topic, stream):
        counts = [engine.submit(count_frames, os.path.abspath(path), topic) for path, _ in todo]
        self.totals = {path: f.result() for (path, _), f in zip(todo, counts)}
        self.bar = Progress(sum(self.totals.values()), stream=stream)
        self.done = {path: 0 for path, _ in todo}
        self.lock = threading.Lock()
        engine.subscribe(PROGRESS_TOPIC, self.update)

    def update(self, msg) -> None:
        with self.lock:
            key = msg['input']
            if key not in self.done:  # a late event of an earlier batch on this engine
                return
            self.done[key] = max(self.done[key], int(msg['done']))
            self.bar.update(sum(self.done.values()))

    def finished(self, path) -> None:
        self.update({'input': path, 'done': self.totals.get(path, 0)})

    def close(self) -> None:
        self.bar.close()


def _run_tasks(engine, todo, task: dict, rows: dict, progress: _BatchProgress,
               report: Callable) -> None:
    """Submit one replay task per input to do, collect their rows as they finish; on
    KeyboardInterrupt cancel those still pending and re-raise."""
    futures: dict = {}
    pending: list = []
    try:
        for path, out in todo:  # in-process, each task runs right here
            fut = engine.submit(replay_one, os.path.abspath(path), out, label=path, **task)
            futures[fut] = path
            pending.append(fut)
        while pending:
            done, pending = engine.wait_first(pending)
            for fut in done:
                rows[futures[fut]] = fut.result()
                progress.finished(futures[fut])
                report(rows[futures[fut]])
    except KeyboardInterrupt:
        for fut in pending:
            cancel = getattr(fut, 'cancel', None)
            if cancel is not None:
                cancel()
        raise


def print_result(result: BatchResult, out_dir: Path, stream=None) -> None:
    stream = stream or sys.stdout
    ok = sum(r['status'] == 'ok' for r in result.rows)
    skipped = sum(r['status'] == 'skipped' for r in result.rows)
    fps = result.frames / result.wall_s if result.wall_s > 0 else float('nan')
    print(f'batch summary ({result.engine}): {ok} done, {skipped} skipped (output existed), '
          f'{result.failed} failed; {result.frames} frames in {result.wall_s:.1f} s '
          f'({fps:.1f} frames/s); {out_dir / "summary.json"}, {out_dir / "summary.csv"}',
          file=stream)


def add_parser(sub) -> None:
    """Register ``gp-ground-seg batch``."""
    p = sub.add_parser('batch', help='replay many bags / point-file directories, one task each',
                       description='Replay each INPUT (a bag, or a directory of .bin/.pcd '
                       'files) exactly as `gp-ground-seg replay INPUT DIR/<name>` does, in this '
                       'process or on Dask; writes DIR/summary.json and DIR/summary.csv. Inputs '
                       'whose complete output exists are skipped (--force redoes them). Exit '
                       'status 1 if any input failed.')
    p.add_argument('inputs', nargs='+', metavar='INPUT', help='bag (directory or file), '
                   'Velodyne .pcap, or a directory of .bin/.pcd files; one output bag each')
    p.add_argument('--out', required=True, metavar='DIR', help='output directory')
    add_engine_arguments(p)
    add_input_options(p)
    add_storage_option(p)
    p.add_argument('--force', action='store_true', help='redo inputs whose output exists')
    add_labeled_option(p)
    p.set_defaults(func=cmd_batch)


def cmd_batch(args) -> int:
    out_dir = Path(args.out)
    with open_engine(args.jobs, args.scheduler) as engine:
        if engine.startup_s:
            print(f'gp-ground-seg batch: note: {engine.description} ready in '
                  f'{engine.startup_s:.1f} s', file=sys.stderr)
        result = run_batch(args.inputs, out_dir, engine, topic=args.topic,
                           params_file=args.params, storage=args.storage, force=args.force,
                           labeled=args.labeled,
                           report=lambda row: print(task_line(row), flush=True))
    print_result(result, out_dir)
    return 1 if result.failed else 0
