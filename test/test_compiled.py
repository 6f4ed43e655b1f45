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
    assert compiled.wait(300.0)
    assert compiled.run(True, kernel, _minus_one, 1.0) == 2.0
    assert compiled.run(True, kernel, _minus_one, 1) == 0  # other types: compiled separately
    assert compiled.run(False, kernel, _minus_one, 1.0) == 0.0  # not asked for
    assert compiled.run(True, None, _minus_one, 1.0) == 0.0  # no numba


def test_a_kernel_that_does_not_compile_leaves_the_reference():
    import numba
    kernel = numba.njit(_broken)
    assert compiled.run(True, kernel, _minus_one, 1.0) == 0.0
    assert compiled.wait(300.0)
    for _ in range(2):  # never retried, never raised
        assert compiled.run(True, kernel, _minus_one, 1.0) == 0.0


def _sum_plus_one(x):
    return x.sum() + 1.0


def _sum_minus_one(x):
    return x.sum() - 1.0


def test_argument_types_seen_once_are_not_typed_again_and_others_still_wait():
    """The cheap argument key (what skips numba's typing once a signature is known compiled)
    must tell apart every array numba types differently: each new kind takes the reference
    until its own compilation is done."""
    import numba
    import numpy as np
    kernel = numba.njit(_sum_plus_one)
    base = np.arange(6.0)
    readonly = base.copy()
    readonly.flags.writeable = False
    kinds = [base, base.astype(np.float32), readonly, base[::2], base.reshape(2, 3),
             np.asfortranarray(base.reshape(2, 3))]
    for x in kinds:
        assert compiled.run(True, kernel, _sum_minus_one, x) == x.sum() - 1.0  # not yet
        assert compiled.wait(300.0)
        assert compiled.run(True, kernel, _sum_minus_one, x) == x.sum() + 1.0
        assert compiled.run(True, kernel, _sum_minus_one, x) == x.sum() + 1.0  # key known
    assert len(set(compiled._argument_key((x,)) for x in kinds)) == len(kinds)


def test_argument_key_covers_scalars_and_refuses_what_it_cannot_describe():
    import numpy as np
    key = compiled._argument_key((1.0, 2, True, np.float32(1)))
    assert key == (float, int, bool, np.float32)
    assert compiled._argument_key((2 ** 63,)) is None  # numba: uint64, not int64
    assert compiled._argument_key(((1.0, 2.0),)) is None  # tuples: numba's typing decides


@pytest.mark.parametrize('size', [0, 1, 2, 3, 10, 64, 65, 1001])
def test_sort_in_place_sorts_like_np_sort(size):
    import numpy as np
    rng = np.random.default_rng(size)
    for values in (rng.normal(size=size), np.round(rng.normal(size=size), 1),  # duplicates
                   np.arange(size, dtype=np.float64), np.arange(size, 0, -1.0)):
        ours = values.copy()
        compiled.sort_in_place(ours)
        np.testing.assert_array_equal(ours, np.sort(values))
        python = values.copy()  # the Python function (what runs without numba)
        compiled._sort_in_place(python)
        np.testing.assert_array_equal(python, np.sort(values))


def test_compile_later_queues_a_compilation_and_runs_nothing():
    import numba
    kernel = numba.njit(_plus_one)  # no disk cache: a fresh compilation
    compiled.compile_later(kernel, 1.0)  # returns at once: the compiler thread compiles it
    assert compiled.wait(300.0)
    assert len(kernel.signatures) == 1 and kernel(1.0) == 2.0
    compiled.compile_later(kernel, 1.0)  # compiled already: nothing queued again
    assert compiled.wait(300.0) and len(kernel.signatures) == 1
    compiled.compile_later(None, 1.0)  # no numba: nothing


def test_call_later_calls_once_in_the_background_and_remembers_a_failure():
    calls = []

    def compiles(x):
        calls.append(x)

    def fails():
        raise RuntimeError('no LLVM here')
    compiled.call_later(compiles, 1.0)
    compiled.call_later(compiles, 2.0)  # queued already: not again
    compiled.call_later(fails)
    assert compiled.wait(300.0)
    assert calls == [1.0] and compiled.failed(fails) and not compiled.failed(compiles)


def test_gp_warm_up_leaves_the_std_kernel_to_the_background_when_asked():
    """stages.compile_round_off(background_too=False) (the segmenter's warm_up, when the labels
    do not use the GP std) compiles the solve and prediction kernels and queues the std's, the
    background compiler's first job; with background_too=True it is compiled before returning.
    In fresh interpreters: this one has every kernel loaded already."""
    import subprocess
    import sys
    from pathlib import Path
    script = """if True:
        from gp_ground_segmentation.core import compiled, predict, stages
        stages.compile_round_off(background_too={now})
        queued = [getattr(k, 'py_func', k).__name__ for k, _ in compiled._queued]
        print('QUEUED', queued, 'READY', len(predict._std_into.overloads))
        """
    root = Path(__file__).resolve().parents[1]
    for now, expected in ((False, "QUEUED ['std_batched']"), (True, 'QUEUED [] READY 1')):
        out = subprocess.run([sys.executable, '-c', script.format(now=now)], cwd=root,
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert expected in out.stdout, out.stdout
