# SPDX-License-Identifier: Apache-2.0
"""Keep freed memory in the process for the next frame (glibc malloc settings).

A process that segments a stream allocates and frees the same few dozen arrays of 0.1-3 MB every
frame (the decoded points, the grid's per-point arrays, the masks, the output clouds). glibc
serves a block above its mmap threshold with a fresh ``mmap`` and gives the top of its heap back
to the system above its trim threshold; both start at 128 kB and the mmap threshold only adapts
after such a block is freed, per allocation pattern. In the node (messages allocated by the
executor's and DDS's threads, freed by the worker's) and in bag replay (a new message per frame)
the result is fresh pages - minor page faults - on almost every array of every frame: the node's
worker thread spent ~9 ms of system time per 124k-point KITTI frame, and ``segment()`` took
~17 ms in the node against ~9 ms in a benchmark loop (``benchmarks/bench_node.py --node-process``;
RESULTS.md). Fixing the mmap threshold at 32 MiB (glibc's maximum on 64-bit) and the trim threshold
at 256 MiB keeps those pages in the process, to be reused by the next frame.

This is a process-wide setting, so the library never applies it by itself: the entry points that
own their process do (the node's ``main()`` and the ``gp-ground-seg`` command line); a program
that calls ``GroundSegmenter`` in a loop can call :func:`keep_freed_memory` once at start.
The cost is memory held, not returned: at most about one frame's peak working set (tens of MB on
124k-point clouds). Not applied where the C library has no ``mallopt`` (macOS, Windows) or
ignores it (musl), or when the user set glibc's malloc tunables already (``GLIBC_TUNABLES``
with ``glibc.malloc.*``, or ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``): theirs win.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ['keep_freed_memory', 'MMAP_THRESHOLD_BYTES', 'TRIM_THRESHOLD_BYTES']

MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # blocks below this come from the heap (glibc's max)
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024  # free heap top kept up to this much
# mallopt() parameter numbers (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_USER_ENV = ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_')


def keep_freed_memory(mmap_threshold: int = MMAP_THRESHOLD_BYTES,
                      trim_threshold: int = TRIM_THRESHOLD_BYTES) -> str | None:
    """Set glibc's mmap and trim thresholds (bytes) for this process.

    Returns None when both were applied, else one line saying why the allocator was left as
    it is (user settings in the environment, no glibc ``mallopt``, a value it refused).
    """
    if 'glibc.malloc.' in os.environ.get('GLIBC_TUNABLES', '') or any(
            name in os.environ for name in _USER_ENV):
        return 'malloc settings left to the environment (GLIBC_TUNABLES / MALLOC_*_ set)'
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return 'malloc settings left as they are: the C library has no mallopt'
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success, 0 when it refuses a value (musl: always 0)
    if not (mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))
            and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold))):
        return (f'malloc settings not applied: mallopt refused mmap threshold {mmap_threshold} '
                f'or trim threshold {trim_threshold} bytes')
    return None
