# SPDX-License-Identifier: Apache-2.0
"""Style gate, as ROS packages ship it (ament_flake8 is not on PyPI; plain flake8 is)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_flake8_clean():
    pytest.importorskip('flake8')
    result = subprocess.run(
        [sys.executable, '-m', 'flake8', '--max-line-length', '99',
         'gp_ground_segmentation', 'scenes', 'test', 'benchmarks', 'setup.py'],
        cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
