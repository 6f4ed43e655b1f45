# SPDX-License-Identifier: Apache-2.0
"""The README and docs/ stay true: the parameter table is the code's, the commands name real
things, the quoted results are RESULTS.md's."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from gp_ground_segmentation.ros.config import render_params_table
from gp_ground_segmentation.core.params import describe_params

README = Path(__file__).resolve().parents[1] / 'README.md'
DOCS = README.parent / 'docs'


def test_parameter_table_matches_the_code():
    text = (DOCS / 'parameters.md').read_text()
    assert render_params_table().strip() in text, (
        'docs/parameters.md parameter table is stale: paste render_params_table() output')
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
    z_std = result.ground_surface.points()[:, 3]
    assert shown.get('surface_z_std_mean') == pytest.approx(float(np.mean(z_std)), rel=1e-4), \
        'docs/kitti00_frame0.png is stale (its surface panel): run docs/make_figures.py'


def test_readme_names_the_launch_file():
    launch = README.parent / 'launch' / 'ground_segmentation.launch.py'
    assert launch.is_file()
    assert f'ros2 launch gp_ground_segmentation {launch.name}' in README.read_text()


RESULTS = README.parent / 'benchmarks' / 'RESULTS.md'
TRIPLE = r'\d\.\d{3,4} / \d\.\d{3,4} / \d\.\d{3,4}'  # P / R / F1


def _section(text, start, end):
    assert start in text, f'{start!r} missing'
    begin = text.index(start)
    return text[begin:text.index(end, begin)]


def _table_rows(text):
    """Cells of every markdown table row in text (header and separator rows included)."""
    return [[c.strip() for c in line.strip().strip('|').split('|')]
            for line in text.splitlines() if line.startswith('|')]


def _quality_deltas():
    """{(column header, group): 'F1 change'} from every variant table of bench_quality."""
    text = RESULTS.read_text()
    quality = _section(text, '<!-- BEGIN bench_quality -->', '<!-- END bench_quality -->')
    deltas, header = {}, None
    for cells in _table_rows(quality):
        if cells[0] == 'data set / family':
            header = cells
        elif header is not None and len(cells) == len(header):
            for name, cell in zip(header, cells):
                found = re.fullmatch(r'\d\.\d{3} \(([+-]\d\.\d{3})\)', cell)
                if found:
                    deltas[name, cells[0].strip('*')] = found.group(1)
    return deltas


def test_method_page_ablation_numbers_are_the_ones_in_results():
    # Every row of docs/method.md's ablation table names a bench_quality variant column; its
    # mean and per-group F1 changes must be what RESULTS.md's bench_quality section says.
    deltas = _quality_deltas()
    table = _section((DOCS / 'method.md').read_text(), '| part | from | variant (bench_quality)',
                     '\n\n')
    rows = [r for r in _table_rows(table)[2:]]
    assert len(rows) >= 14
    for part, _origin, variant, mean, largest in rows:
        column = variant.strip('`')
        assert deltas[column, 'mean of groups'] == mean, (part, mean)
        if largest.startswith('none'):
            assert all(d in ('+0.000', '-0.000') for (c, _g), d in deltas.items() if c == column)
            continue
        pairs = re.findall(r'([a-z_0-9]+) ([+-]\d\.\d{3})', largest)
        assert pairs, largest
        for group, delta in pairs:
            assert deltas[column, group] == delta, (part, group, delta)


def _assert_quotes_bench_quality(table, least):
    # Each (this project, Patchwork++) pair of P / R / F1 triples of a row must stand side by
    # side in one row of RESULTS.md's cold bench_quality tables.
    quality = _section(RESULTS.read_text(), '<!-- BEGIN bench_quality -->',
                       '### Every method, streamed').replace('**', '')
    assert len(re.findall(TRIPLE, table)) >= least
    for cells in _table_rows(table)[2:]:
        found = re.findall(TRIPLE, ' | '.join(c.strip('*') for c in cells[1:]))
        assert len(found) % 2 == 0, cells[0]
        for ours, theirs in zip(found[::2], found[1::2]):
            assert f'{ours} | {theirs}' in quality, cells[0]


def test_readme_results_table_is_bench_quality():
    # The headline quality table quotes bench_quality's pooled cold rows verbatim, both
    # protocols, this project beside Patchwork++.
    _assert_quotes_bench_quality(_section(README.read_text(), '| data (frames) |', '\n\n'), 30)


def test_results_page_per_scan_table_is_bench_quality():
    table = _section((DOCS / 'results.md').read_text(), '| scan | vegetation-nonground', '\n\n')
    _assert_quotes_bench_quality(table, 32)


def test_readme_links_resolve():
    # Every relative link of the README and docs/ names a file of the repository.
    checked = 0
    for page in [README, *sorted(DOCS.glob('*.md'))]:
        for target in re.findall(r'\]\(([^)#:]+)(?:#[^)]*)?\)', page.read_text()):
            assert (page.parent / target).exists(), (page.name, target)
            checked += 1
    assert checked >= 20  # the README links every docs page, the pages link each other


def test_python_api_block_runs_as_written():
    # The README's Python API example, executed on the shipped sample's first frame: a renamed
    # attribute or a changed signature fails here instead of in a user's first script.
    from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
    from gp_ground_segmentation.tools.bag import read_frame

    text = README.read_text()
    section = text[text.index('## Python API'):]
    block = re.search(r'```python\n(.*?)\n```', section, re.S).group(1)
    msg, _ = read_frame(str(README.parent / 'data' / 'kitti00_sample:0'))
    points = cloud_xyz(read_cloud(msg))
    x, y = points[:100, 0], points[:100, 1]
    scope = {'points': points, 'x': x, 'y': y}
    exec(compile(block, 'README.md (Python API)', 'exec'), scope)
    result, surface = scope['result'], scope['surface']
    assert scope['ground'].shape == (int(result.ground_mask.sum()), points.shape[1])
    assert result.ground_mask.any() and result.obstacle_mask.any()
    assert np.all(np.isfinite(scope['z_hat'])) and np.all(scope['z_std'] >= 0)
    assert surface.z.shape == surface.z_std.shape
    rows = scope['rows']  # the labelled rows: the valid points, in order, with their labels
    assert rows.shape == (int(result.valid_mask.sum()),)
    assert np.array_equal(rows['ground'] == 1, result.ground_mask[result.valid_mask])
    # the sample is a sensor-centred cloud in metres: nothing to note
    assert scope['cloud_notes'](points, scope['seg'].params.sensor_pose) == []
