# SPDX-License-Identifier: Apache-2.0
"""numba kernels of the core beside their numpy references: compile one, run one.

Every compiled stage is a :class:`Twin`, part of a row of the stage table (core/stages.py): a
numpy reference and a kernel with the same arguments and outputs. An ``exact`` twin's outputs
are the same bit for bit (the twin tests compare them on real frames), so a kernel need not be
ready to be asked for: :func:`run` calls it when it is compiled (or loaded from numba's disk
cache) for the arguments' types, and otherwise returns the reference's result and has one
background thread compile it. A new install's first frames take the numpy path while the
compilations (many seconds) run; later processes load them from the cache. The GP step's
twins are equal only to round-off: they are compiled before use instead (``warm_up``), so a
stream's numbers never depend on when a compilation finished. Kernels are cached on disk
(``cache=True``: ``__pycache__`` next to the module when writable, else numba's user cache
directory; ``NUMBA_CACHE_DIR`` overrides both) and release the GIL (``nogil``). :func:`wait`
blocks until the queued compilations are done (tests, benchmarks).
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

try:  # numba is a regular dependency, but the package must still work without it
    import numba
except ImportError:  # pragma: no cover - the numpy references are used instead
    numba = None

__all__ = ['AVAILABLE', 'Stage', 'Twin', 'call_later', 'compile_later', 'failed', 'kernel',
           'mark_failed', 'run', 'sort_in_place', 'wait']

AVAILABLE = numba is not None

_lock = threading.Lock()
_queued = set()  # (kernel, signature) or (function, 'call') given to the compiler thread
_failed = set()  # kernels that did not compile: the reference from then on
_ready = set()  # (kernel, _argument_key) that has a compiled signature: no typing needed
_INT64_MIN, _INT64_MAX = -2 ** 63, 2 ** 63 - 1
_jobs: queue.Queue = queue.Queue()
_compiler = None  # the background thread, started on first need


@dataclass(frozen=True, eq=False)
class Twin:
    """A compiled kernel and its numpy reference, registered once by its stage (the stage
    table, core/stages.py) and run through :meth:`run`.

    ``reference(*args)`` and ``kernel(*args)`` take the same arguments and return the same
    outputs: bit for bit when ``exact`` (then :meth:`run` takes the reference until the kernel
    is compiled for the arguments' types, :func:`run`), else to round-off (the GP step: the
    kernel is compiled before use, by ``GroundSegmenter.warm_up`` or its first call, and its
    errors reach the caller, which falls back). ``examples(dtype)`` gives the arguments of
    every signature a frame of points in ``dtype`` passes (warm_up); ``background``: warm_up
    leaves this round-off kernel to the background compiler unless asked for it now;
    ``outputs``, for a kernel that leaves scratch in its outputs, what of them carries the
    result. ``kernel`` is None without numba.
    """

    name: str
    reference: Callable
    kernel: Optional[Callable]
    examples: Callable
    exact: bool = True
    background: bool = False
    outputs: Optional[Callable] = None  # (args, outputs) -> what the twin tests compare

    def run(self, use_compiled: bool, *args):
        """The kernel's outputs when ``use_compiled`` (and, if ``exact``, compiled), else the
        reference's."""
        if self.exact:
            return _run(use_compiled, self.kernel, self.reference, *args)
        if use_compiled and self.kernel is not None:
            return self.kernel(*args)
        return self.reference(*args)

    def prepare(self, dtype, now: bool = False) -> None:
        """warm_up: compile the kernel for every example signature of ``dtype``, now (``now``:
        round-off twins only) or in the background thread."""
        if self.kernel is None:
            return
        for args in self.examples(dtype):
            if self.exact:
                compile_later(self.kernel, *args)
            elif now:
                self.kernel(*args)
            else:
                call_later(self.kernel, *args)


@dataclass(frozen=True)
class Stage:
    """A row of the stage table (core/stages.py): a step of a frame, whose it is (``origin``
    'paper' or 'ours'), the SegmenterParams bool that turns it off (``switch``; None: it always
    runs) and its compiled twins."""

    name: str
    origin: str
    switch: Optional[str] = None
    twins: tuple = ()

    def on(self, params) -> bool:
        """Whether ``params`` run this stage."""
        return self.switch is None or bool(getattr(params, self.switch))


def kernel(function, **options):
    """``function`` compiled with numba (cached, nogil, plus ``options``); None without numba.
    """
    if numba is None:
        return None
    return numba.njit(cache=True, nogil=True, **options)(function)


def run(use_compiled: bool, compiled_kernel, reference, *args):
    """``compiled_kernel(*args)`` when asked for and ready for these argument types, else
    ``reference(*args)`` (the same result), queueing the compilation when it is not."""
    if not use_compiled or compiled_kernel is None or compiled_kernel in _failed:
        return reference(*args)
    key = _argument_key(args)
    if key is not None and (compiled_kernel, key) in _ready:
        return compiled_kernel(*args)
    try:
        # numba's typeof_pyval costs ~10-30 us an argument, ~0.5 ms a frame over the kernels'
        # ~35 arguments: done once per argument key, then the key alone says "compiled"
        signature = tuple(compiled_kernel.typeof_pyval(a) for a in args)
        if signature in compiled_kernel.overloads:
            if key is not None:
                _ready.add((compiled_kernel, key))
            return compiled_kernel(*args)
    except Exception:  # noqa: BLE001 - numba typing/runtime failure: the reference
        _failed.add(compiled_kernel)
        return reference(*args)
    _queue(compiled_kernel, signature)
    return reference(*args)


_run = run  # what Twin.run calls (its own name is taken there)


def compile_later(compiled_kernel, *args) -> None:
    """Queue the compilation of ``compiled_kernel`` for these arguments' types on the background
    thread, without running anything (for a kernel that is compiled before use, whose numpy twin
    is not bit for bit the same); nothing when it already has that signature or is None."""
    if compiled_kernel is None:
        return
    signature = tuple(compiled_kernel.typeof_pyval(a) for a in args)
    if signature not in compiled_kernel.overloads:
        _queue(compiled_kernel, signature)


def call_later(function, *args) -> None:
    """Have the background thread call ``function(*args)`` once (a Python function that
    compiles a round-off kernel on its first call, see :class:`Twin`); its failure marks
    ``function`` failed."""
    with _lock:
        if (function, 'call') in _queued:
            return
        _queued.add((function, 'call'))
    _jobs.put(('call', function, args))
    _start_compiler()


def failed(compiled_kernel) -> bool:
    """True once ``compiled_kernel`` failed to compile (here or in the background thread)."""
    return compiled_kernel in _failed


def mark_failed(compiled_kernel) -> None:
    """Remember that ``compiled_kernel`` failed (for kernels called directly, not by run)."""
    _failed.add(compiled_kernel)


# The array flags numba's type depends on (C, F contiguous, aligned, writeable: layout,
# alignment, readonly); numpy's flag bits, read as one integer (ndarray.flags.num)
_LAYOUT_FLAGS = 0x0001 | 0x0002 | 0x0100 | 0x0400
_SCALAR_TYPES = (float, bool, np.floating, np.integer, np.bool_)


def _argument_key(args):
    """What decides numba's type of each argument (arrays: dtype, ndim, layout, writeable,
    aligned; scalars: their Python or numpy type), cheap to make; None for other arguments.

    A key may be finer than numba's types (a 1-D array is both C and F contiguous), never
    coarser, so one key stands for one compiled signature."""
    key = []
    for a in args:
        kind = type(a)
        if kind is np.ndarray:  # the common case first: ~0.15 us, not ~0.3 us, an array
            key.append((a.dtype, a.ndim, a.flags.num & _LAYOUT_FLAGS))
        elif kind is float or kind is bool:
            key.append(kind)
        elif kind is int:
            if not _INT64_MIN <= a <= _INT64_MAX:  # numba: uint64 or object
                return None
            key.append(int)
        elif isinstance(a, np.ndarray):  # a subclass: its type is part of the key
            key.append((kind, a.dtype, a.ndim, a.flags.num & _LAYOUT_FLAGS))
        elif isinstance(a, _SCALAR_TYPES):
            key.append(kind)
        else:
            return None
    return tuple(key)


def wait(timeout_s: float | None = None) -> bool:
    """Block until every queued compilation is done (at most ``timeout_s``); True if done."""
    done = threading.Event()
    _jobs.put(done)
    _start_compiler()
    return done.wait(timeout_s)


def _queue(compiled_kernel, signature) -> None:
    with _lock:
        if (compiled_kernel, signature) in _queued:
            return
        _queued.add((compiled_kernel, signature))
    _jobs.put(('compile', compiled_kernel, signature))
    _start_compiler()


def _start_compiler() -> None:
    global _compiler
    with _lock:
        if _compiler is None:
            _compiler = threading.Thread(target=_compile_forever, name='numba_compiler',
                                         daemon=True)
            _compiler.start()


def _compile_forever() -> None:
    while True:
        job = _jobs.get()
        if isinstance(job, threading.Event):
            job.set()
            continue
        what, compiled_kernel, arguments = job
        try:
            if what == 'compile':
                compiled_kernel.compile(arguments)  # compiles, or loads numba's disk cache
            else:
                compiled_kernel(*arguments)  # call_later: it compiles what it calls
        except Exception:  # noqa: BLE001 - the reference stays in use for this kernel
            _failed.add(compiled_kernel)


def _sort_in_place(values):
    """Sort a 1-D array in place, ascending, for kernels (heapsort, O(n log n)): numba's
    ``np.sort`` compiles a quicksort for seconds on a new install, these loops in a fraction.
    Equal values (-0.0 and +0.0 too) may end up in any order among themselves."""
    n = values.size
    for start in range(n // 2 - 1, -1, -1):
        _sift_down(values, start, n)
    for end in range(n - 1, 0, -1):
        top = values[0]
        values[0] = values[end]
        values[end] = top
        _sift_down(values, 0, end)


def _sift_down(values, root, end):
    """Move values[root] down the max-heap values[:end] to its place."""
    while True:
        child = 2 * root + 1
        if child >= end:
            return
        if child + 1 < end and values[child + 1] > values[child]:
            child += 1
        if not values[child] > values[root]:
            return
        swap = values[root]
        values[root] = values[child]
        values[child] = swap
        root = child


_sift_down = kernel(_sift_down) or _sift_down  # before the kernel that calls it
sort_in_place = kernel(_sort_in_place) or _sort_in_place
