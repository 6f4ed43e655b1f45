# SPDX-License-Identifier: Apache-2.0
"""core/compiled.py: a kernel runs once compiled; until then (or if it cannot compile) the
numpy reference runs, and the compilation happens in a background thread."""

import pytest

from gp_ground_segmentation.core import compiled

pytestmark = pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')


def _plus_one(x):
    return x + 1.0


def _minus_one(x):  # a "reference" that differs, to see which one ran
    return x - 1.0


def _broken(x):
    return x + undefined_name  # noqa: F821 - fails to compile on purpose


def test_reference_until_compiled_then_the_kernel():
    import numba
    kernel = numba.njit(_plus_one)  # no disk cache: a fresh compilation
    assert compiled.run(True, kernel, _minus_one, 1.0) == 0.0  # queued, reference meanwhile
    assert compiled.wait(60.0)
    assert compiled.run(True, kernel, _minus_one, 1.0) == 2.0
    assert compiled.run(True, kernel, _minus_one, 1) == 0  # other types: compiled separately
    assert compiled.run(False, kernel, _minus_one, 1.0) == 0.0  # not asked for
    assert compiled.run(True, None, _minus_one, 1.0) == 0.0  # no numba


def test_a_kernel_that_does_not_compile_leaves_the_reference():
    import numba
    kernel = numba.njit(_broken)
    assert compiled.run(True, kernel, _minus_one, 1.0) == 0.0
    assert compiled.wait(60.0)
    for _ in range(2):  # never retried, never raised
        assert compiled.run(True, kernel, _minus_one, 1.0) == 0.0
