# SPDX-License-Identifier: Apache-2.0
"""Where ``batch`` and ``tune`` run their tasks: in this process, or on Dask distributed.

* :class:`InProcessEngine` runs each task when it is submitted (no Dask needed);
* :func:`open_engine` with ``jobs=N`` starts a ``dask.distributed.LocalCluster`` of N worker
  processes (one thread each) on this machine; with ``scheduler='tcp://host:8786'`` it connects
  to an existing cluster (``dask scheduler`` + ``dask worker``; workers need this package).

Dask is an optional extra (``pip install '.[scale]'``), imported only here and only when a
cluster is asked for. Both engines offer the same small interface (submit, wait for the first
done, gather, progress events from tasks, run a function on every worker), so the callers have one
code path. Progress from a task reaches the caller through ``engine.progress_sink(topic)``: a
picklable callable that the task calls with a small dict.
"""

from __future__ import annotations

import functools
import logging
import os
import resource
import time
import uuid
from pathlib import Path
from typing import Callable, Optional, Sequence

from .errors import CliError

DASK_MISSING = ("--jobs/--scheduler need Dask distributed, which is not installed: pip install "
                "'gp_ground_segmentation[scale]' (or: pip install 'dask[distributed]')")


# dask config key of the environment variable its nanny sets for worker processes (see below)
WORKER_MALLOC_KEY = 'distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_'


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB; Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _DoneFuture:
    """The result (or exception) of a task that already ran in this process."""

    def __init__(self, fn, args, kwargs):
        try:
            self._value, self._error = fn(*args, **kwargs), None
        except Exception as err:  # re-raised by result(), as a Dask future does
            self._value, self._error = None, err

    def result(self):
        if self._error is not None:
            raise self._error
        return self._value


class InProcessEngine:
    """Runs every task in this process, at submit time."""

    description = 'in-process'
    workers = 1
    startup_s = 0.0

    def __init__(self):
        self._handlers: dict = {}

    def submit(self, fn: Callable, *args, **kwargs) -> _DoneFuture:
        return _DoneFuture(fn, args, kwargs)

    def wait_first(self, pending: Sequence) -> tuple[list, list]:
        """(done, not done) of ``pending``; here everything is done."""
        return list(pending), []

    def progress_sink(self, topic: str) -> Callable:
        return functools.partial(self._dispatch, topic)

    def _dispatch(self, topic: str, msg) -> None:
        handler = self._handlers.get(topic)
        if handler is not None:
            handler(msg)

    def subscribe(self, topic: str, handler: Callable) -> None:
        self._handlers[topic] = handler

    def run_on_workers(self, fn: Callable, *args) -> dict:
        return {self.description: fn(*args)}

    def check_shared(self, paths: Sequence, out_dir: Optional[Path] = None) -> None:
        """Nothing to check: the tasks see what this process sees."""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _log_event(topic: str, msg) -> None:
    """Progress from inside a Dask task: an event the client subscribed to."""
    from distributed import get_worker
    get_worker().log_event(topic, msg)


def _visible(paths: Sequence[str], token: Optional[str]) -> dict:
    """Run on each worker: which of ``paths`` it cannot see, and whether it sees ``token``."""
    return {'missing': [p for p in paths if not os.path.exists(p)],
            'token': token is None or os.path.exists(token)}


class DaskEngine:
    """Tasks on a Dask distributed cluster (a LocalCluster started here or a remote one)."""

    def __init__(self, client, cluster=None, description: str = '', startup_s: float = 0.0):
        self.client, self.cluster = client, cluster
        self.description, self.startup_s = description, startup_s

    @property
    def workers(self) -> int:
        return max(1, len(self.client.scheduler_info(n_workers=-1)['workers']))

    def submit(self, fn: Callable, *args, **kwargs):
        # kwargs go to fn; Client.submit keeps some names for itself (key, workers, pure, ...)
        return self.client.submit(fn, *args, pure=False, **kwargs)

    def wait_first(self, pending: Sequence) -> tuple[list, list]:
        from distributed import wait
        done, not_done = wait(list(pending), return_when='FIRST_COMPLETED')
        return list(done), list(not_done)

    def progress_sink(self, topic: str) -> Callable:
        return functools.partial(_log_event, topic)

    def subscribe(self, topic: str, handler: Callable) -> None:
        self.client.subscribe_topic(topic, lambda event: handler(event[1]))

    def run_on_workers(self, fn: Callable, *args) -> dict:
        return self.client.run(fn, *args)

    def check_shared(self, paths: Sequence, out_dir: Optional[Path] = None) -> None:
        """Fail up front unless every worker sees every input that this process sees, and the
        output directory is the same storage (a token file written here must be visible there).

        Inputs that nobody sees are left to the task, which reports them like replay does.
        """
        local = [os.path.abspath(p) for p in paths if os.path.exists(p)]
        token = None
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            token_path = out_dir / f'.gp-ground-seg-probe-{uuid.uuid4().hex}'
            token_path.write_text('probe\n')
            token = str(token_path.resolve())
        try:
            answers = self.client.run(_visible, local, token)
        finally:
            if token is not None:
                os.unlink(token)
        for worker, answer in sorted(answers.items()):
            if answer['missing']:
                raise CliError(f'{answer["missing"][0]} is not visible on worker {worker}: '
                               f'inputs and the output directory must be on storage every '
                               f'worker sees (same path), e.g. NFS')
            if not answer['token']:
                raise CliError(f'output directory {out_dir} is not the same storage on worker '
                               f'{worker} (a probe file written here is not there): use a '
                               f'directory every worker sees under the same path')

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise CliError(DASK_MISSING) from None
    return distributed


def open_engine(jobs: Optional[int] = None, scheduler: Optional[str] = None):
    """The engine for ``--jobs N`` / ``--scheduler ADDRESS`` (neither: in-process)."""
    if jobs is not None and scheduler is not None:
        raise CliError('give either --jobs or --scheduler, not both')
    if jobs is None and scheduler is None:
        return InProcessEngine()
    distributed = _import_distributed()
    t0 = time.perf_counter()
    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout='20s')
        except (OSError, TimeoutError) as err:
            raise CliError(f'cannot reach the Dask scheduler at {scheduler}: {err}') from None
        return DaskEngine(client, None, f'Dask cluster at {scheduler}',
                          time.perf_counter() - t0)
    if jobs < 1:
        raise CliError('--jobs must be at least 1')
    import dask
    # One thread per worker process: a task is one sequential replay/trial, and the segmenter
    # caps its BLAS threads itself; N processes then use N cores. Dask's default
    # MALLOC_TRIM_THRESHOLD_=65536 for workers also pins glibc's mmap threshold, so every
    # frame-sized array is mmapped and page-faulted afresh: measured 2x the CPU per frame of
    # replay (0.8 -> 1.7 s for 30 KITTI frames). Leave glibc's adaptive default.
    # The scheduler's HTTP server (dashboard, metrics) on a free port: two clusters on one
    # machine (two users, parallel CI jobs) must not fight over the fixed default 8787.
    with dask.config.set({WORKER_MALLOC_KEY: None}):
        cluster = distributed.LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                                           dashboard_address=':0', silence_logs=logging.ERROR)
    client = distributed.Client(cluster)
    return DaskEngine(client, cluster, f'Dask LocalCluster, {jobs} worker process(es)',
                      time.perf_counter() - t0)


def add_engine_arguments(parser) -> None:
    """``--jobs N`` / ``--scheduler ADDRESS`` (shared by batch and tune)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--jobs', type=int, metavar='N',
                       help='start a Dask LocalCluster of N worker processes on this machine '
                       '(needs the [scale] extra); default: run in this process')
    group.add_argument('--scheduler', metavar='ADDRESS',
                       help='submit to a running Dask cluster, e.g. tcp://host:8786 (inputs and '
                       'outputs must be on storage every worker sees, under the same path)')
