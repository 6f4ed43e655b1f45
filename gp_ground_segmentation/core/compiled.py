# SPDX-License-Identifier: Apache-2.0
"""numba kernels of the core beside their numpy references: compile one, run one.

Each compiled stage (line growing, plateau state machine, structure look-ups, surface offsets)
keeps a numpy reference that gives the same output (tests compare them bit for bit) and is
used without numba, or when the kernel fails to compile or run. Kernels are cached on disk
(``cache=True``, see gp_compiled.py for where) and release the GIL (``nogil``) so a ROS
executor thread keeps running meanwhile.
"""

from __future__ import annotations

try:  # numba is a regular dependency, but the package must still work without it
    import numba
except ImportError:  # pragma: no cover - the numpy references are used instead
    numba = None

__all__ = ['AVAILABLE', 'kernel', 'run']

AVAILABLE = numba is not None


def kernel(function, **options):
    """``function`` compiled with numba (cached, nogil, plus ``options``); None without numba.
    """
    if numba is None:
        return None
    return numba.njit(cache=True, nogil=True, **options)(function)


def run(use_compiled: bool, compiled_kernel, reference, *args):
    """``compiled_kernel(*args)`` when asked for and available, else (or if it raises)
    ``reference(*args)``."""
    if use_compiled and compiled_kernel is not None:
        try:
            return compiled_kernel(*args)
        except Exception:  # noqa: BLE001 - numba compile/runtime failure: the reference
            pass
    return reference(*args)
