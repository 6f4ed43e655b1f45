# SPDX-License-Identifier: Apache-2.0
"""core/allocator.py: the glibc malloc settings of the node's and the CLI's processes.

Each check runs in a child process: the setting is process-wide and must not leak into the
test process.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

from conftest import module_env

GLIBC = platform.system() == 'Linux' and platform.libc_ver()[0] == 'glibc'

# Five rounds of allocating (and touching) 16 MB and 2.4 MB in a worker thread, then freeing
# them - a frame's arrays in the node's worker; minor page faults of the thread per round.
PROBE = """
import json, resource, sys, threading
import numpy as np
from gp_ground_segmentation.core.allocator import keep_freed_memory
note = keep_freed_memory() if sys.argv[1] == 'on' else 'not called'
faults = []
def rounds():
    for _ in range(5):
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        a, b = np.ones(2_000_000), np.ones(300_000)
        del a, b
        faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)
worker = threading.Thread(target=rounds)
worker.start()
worker.join()
print(json.dumps({'note': note, 'faults': faults}))
"""


def run_probe(mode: str, **env) -> dict:
    out = subprocess.run([sys.executable, '-c', PROBE, mode], capture_output=True, text=True,
                         env=module_env(env), timeout=120, check=True)
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.skipif(not GLIBC, reason='glibc malloc only')
def test_freed_memory_is_reused_by_the_next_round():
    """With the settings, only the first round touches fresh pages; the next four reuse them.
    Without them, the second round faults again (glibc raises its mmap threshold only after
    such a block was freed)."""
    on = run_probe('on')
    assert on['note'] is None
    first, rest = on['faults'][0], on['faults'][1:]
    assert first > 500  # 18 MB of fresh pages (fewer with transparent huge pages)
    assert sum(rest) < 0.05 * first, on['faults']
    off = run_probe('off')
    assert off['faults'][1] > 0.5 * off['faults'][0], off['faults']


@pytest.mark.skipif(not GLIBC, reason='glibc malloc only')
@pytest.mark.parametrize('env', [{'MALLOC_TRIM_THRESHOLD_': '1'},
                                 {'GLIBC_TUNABLES': 'glibc.malloc.trim_threshold=1'}])
def test_user_malloc_settings_win(env):
    """A user who set glibc's malloc tunables keeps them: the call says so and changes nothing
    (trim threshold 1 byte: every round faults again)."""
    probe = run_probe('on', **env)
    assert probe['note'].startswith('malloc settings left to the environment')
    assert min(probe['faults'][1:]) > 0.5 * probe['faults'][0], probe['faults']
