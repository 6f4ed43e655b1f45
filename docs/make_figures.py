#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Regenerate the README figure(s) from the shipped sample with the default parameters.

    .venv/bin/python docs/make_figures.py

The numbers shown in a figure are also stored in the PNG (text chunk 'gp_ground_segmentation');
test/test_readme.py checks them against a fresh segmentation, so a stale figure fails the tests.
"""

import argparse
import os
import sys
from pathlib import Path

from gp_ground_segmentation.tools.cli import main

ROOT = Path(__file__).resolve().parents[1]
# (frame, output) pairs; the README shows docs/kitti00_frame0.png.
FIGURES = [('data/kitti00_sample:0', 'docs/kitti00_frame0.png')]

if __name__ == '__main__':
    # no options: --help says what is written, and anything else is refused before it is
    argparse.ArgumentParser(
        description=__doc__.split('\n\n')[0] + ' Overwrites: '
        + ', '.join(out for _, out in FIGURES) + '.').parse_args()
    os.chdir(ROOT)  # relative paths, so the figure's title does not show this machine's path
    for frame, out in FIGURES:
        status = main(['plot', frame, '--out', out, '--force'])
        if status:
            sys.exit(status)
