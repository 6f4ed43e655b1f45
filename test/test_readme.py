# SPDX-License-Identifier: Apache-2.0
"""The README stays true: its parameter table is the code's, its commands name real things."""

import json
import re
from pathlib import Path

import pytest

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


def test_readme_figure_is_current():
    # docs/make_figures.py stores the figure's numbers in the PNG; they must be what the code
    # gives now for the same frame with the default parameters.
    pytest.importorskip('matplotlib')
    from PIL import Image

    from gp_ground_segmentation.core.segmenter import GroundSegmenter
    from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
    from gp_ground_segmentation.tools.bag import read_frame
    from gp_ground_segmentation.tools.plot import FIGURE_METADATA_KEY

    root = README.parent
    assert 'docs/make_figures.py' in README.read_text()
    shown = json.loads(Image.open(root / 'docs' / 'kitti00_frame0.png').text[FIGURE_METADATA_KEY])
    msg, _ = read_frame(str(root / 'data' / 'kitti00_sample:0'))
    result = GroundSegmenter().segment(cloud_xyz(read_cloud(msg)))
    assert shown['points'] == result.valid_mask.size
    assert shown['ground_points'] == int(result.ground_mask.sum()), \
        'docs/kitti00_frame0.png is stale: run docs/make_figures.py'
    assert shown['sigma_f'] == pytest.approx(result.hyperparameters.sigma_f, rel=1e-6)


def test_readme_names_the_launch_file():
    launch = README.parent / 'launch' / 'ground_segmentation.launch.py'
    assert launch.is_file()
    assert f'ros2 launch gp_ground_segmentation {launch.name}' in README.read_text()
