# SPDX-License-Identifier: Apache-2.0
"""config/ground_segmentation.rviz: parses, shows the node's topics, is installed and documented.

RViz itself cannot be installed here; the file is checked as the YAML RViz 2 reads.
"""

import ast

import yaml
from conftest import REPO

from gp_ground_segmentation.labels import HEIGHT_FIELD
from gp_ground_segmentation.ros.node import INPUT_TOPIC, OUTPUT_TOPICS

RVIZ = REPO / 'config' / 'ground_segmentation.rviz'


def _displays():
    doc = yaml.safe_load(RVIZ.read_text())
    manager = doc['Visualization Manager']
    return manager, {d['Name']: d for d in manager['Displays']}


def test_displays_subscribe_to_the_package_topics():
    manager, displays = _displays()
    clouds = [d for d in displays.values() if d['Class'] == 'rviz_default_plugins/PointCloud2']
    topics = {d['Topic']['Value'] for d in clouds}
    assert topics == {'/' + t for t in (INPUT_TOPIC,) + OUTPUT_TOPICS}
    for d in clouds:
        # the input is best effort (LiDAR drivers): a reliable RViz subscriber would get nothing
        expected = 'Best Effort' if d['Topic']['Value'] == '/' + INPUT_TOPIC else 'Reliable'
        assert d['Topic']['Reliability Policy'] == expected, d['Name']
    surface = next(d for d in clouds if d['Topic']['Value'] == '/ground_surface')
    assert surface['Color Transformer'] == 'Intensity' and surface['Channel Name'] == 'z_std'
    # the labelled cloud coloured by its height above the GP ground, over fixed bounds (a
    # frame's own extremes, autocomputed, would give each frame another scale)
    labeled = next(d for d in clouds if d['Topic']['Value'] == '/labeled')
    assert labeled['Color Transformer'] == 'Intensity'
    assert labeled['Channel Name'] == HEIGHT_FIELD
    assert labeled['Autocompute Intensity Bounds'] is False
    assert labeled['Min Intensity'] == 0 and labeled['Max Intensity'] == 2
    assert manager['Global Options']['Fixed Frame'] == 'velodyne'


def test_rviz_file_installed_and_readme_says_how_to_open_it():
    tree = ast.parse((REPO / 'setup.py').read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, 'id', '') == 'setup')
    data_files = ast.unparse(next(k.value for k in call.keywords if k.arg == 'data_files'))
    assert "'*.rviz'" in data_files
    readme = (REPO / 'README.md').read_text()
    assert 'rviz2 -d' in readme and 'config/ground_segmentation.rviz' in readme
    assert 'Fixed Frame' in readme and '`velodyne`' in readme
