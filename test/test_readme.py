# SPDX-License-Identifier: Apache-2.0
"""The README stays true: its parameter table is the code's, its commands name real things."""

import re
from pathlib import Path

from gp_ground_segmentation.ros.config import render_params_table
from gp_ground_segmentation.core.params import describe_params

README = Path(__file__).resolve().parents[1] / 'README.md'


def test_parameter_table_matches_the_code():
    text = README.read_text()
    assert render_params_table().strip() in text, (
        'README parameter table is stale: paste render_params_table() output')
    for row in describe_params():
        assert f"`{row['name']}`" in text


def test_two_setup_commands_use_existing_paths():
    text = README.read_text()
    blocks = re.findall(r'```bash\n(python3 -m venv .*?)\n```', text)
    assert len(blocks) == 2, blocks
    main_job, tests = blocks
    root = README.parent
    assert (root / 'data' / 'kitti00_sample' / 'metadata.yaml').exists()
    assert 'data/kitti00_sample' in main_job and 'pytest' in tests
    assert (root / 'docs' / 'kitti00_frame0.png').exists()
