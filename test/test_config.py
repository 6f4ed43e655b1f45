# SPDX-License-Identifier: Apache-2.0
"""config.py: the shipped params.yaml never drifts from the dataclass, and parameter files are
read with ROS's strict rules (unknown key, wrong type, out of range -> error naming the key)."""

import dataclasses

import pytest
import yaml
from conftest import REPO

from gp_ground_segmentation import SegmenterParams, describe_params
from gp_ground_segmentation.ros.config import (
    NODE_PARAMS, PARAMS_FILE_KEY, ParameterConfigError, all_param_specs, load_params_file,
    node_param_defaults, render_params_table, render_params_yaml)

PARAMS_YAML = REPO / 'config' / 'params.yaml'


def _write(tmp_path, text, name='p.yaml'):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_shipped_yaml_lists_exactly_all_params_with_defaults():
    doc = yaml.safe_load(PARAMS_YAML.read_text())
    assert list(doc) == [PARAMS_FILE_KEY]
    values = doc[PARAMS_FILE_KEY]['ros__parameters']
    expected = {f.name: f.default for f in dataclasses.fields(SegmenterParams)}
    expected.update(node_param_defaults())
    assert set(values) == set(expected)
    for name, default in expected.items():
        assert values[name] == default and type(values[name]) is type(default), name


def test_shipped_yaml_is_the_generated_text():
    # Regenerate with: python -c "from gp_ground_segmentation.ros.config import render_params_yaml
    # as r; print(r(), end='')" > config/params.yaml
    assert PARAMS_YAML.read_text() == render_params_yaml()


def test_every_param_has_a_comment_and_units_text():
    text = PARAMS_YAML.read_text().splitlines()
    for row in describe_params() + [dict(name=k, **v) for k, v in NODE_PARAMS.items()]:
        idx = next(i for i, ln in enumerate(text) if ln.strip().startswith(row['name'] + ':'))
        assert text[idx - 1].strip().startswith('#'), row['name']
        assert row['description'], row['name']


def test_load_shipped_file_gives_defaults():
    seg, node = load_params_file(PARAMS_YAML)
    assert seg == SegmenterParams()
    assert node == node_param_defaults()
    assert node == {'processing_budget_ms': 100.0, 'queue_size': 1, 'diagnostics_period_s': 1.0,
                    'diagnostics_window': 50, 'publish_ground_surface': True,
                    'imu_topic': '', 'imu_max_age_s': 0.1, 'imu_lidar_roll_rad': 0.0,
                    'imu_lidar_pitch_rad': 0.0, 'imu_lidar_yaw_rad': 0.0,
                    'imu_accel_time_constant_s': 0.5, 'add_height_above_ground_field': False}


@pytest.mark.parametrize('key', ['ground_segmentation', '/ground_segmentation', '/**',
                                 '/**/ground_segmentation', '"*"'])
def test_section_keys_that_match_the_node(tmp_path, key):
    path = _write(tmp_path, f'{key}:\n  ros__parameters:\n    num_bins: 32\n'
                            '    processing_budget_ms: 50.0\n')
    seg, node = load_params_file(path)
    assert seg.num_bins == 32 and seg.num_segments == SegmenterParams().num_segments
    assert node['processing_budget_ms'] == 50.0 and node['queue_size'] == 1


def test_sections_merge_in_order_and_other_nodes_are_ignored(tmp_path):
    path = _write(tmp_path, '/**:\n  ros__parameters:\n    num_bins: 32\n    use_sim_time: true\n'
                            'other_node:\n  ros__parameters:\n    whatever: 1\n'
                            'ground_segmentation:\n  ros__parameters:\n    num_bins: 64\n')
    seg, _ = load_params_file(path)
    assert seg.num_bins == 64


def test_namespaced_section(tmp_path):
    path = _write(tmp_path, 'robot:\n  ground_segmentation:\n    ros__parameters:\n'
                            '      num_bins: 16\n')
    assert load_params_file(path, namespace='/robot')[0].num_bins == 16
    with pytest.raises(ParameterConfigError, match='no section'):
        load_params_file(path)


@pytest.mark.parametrize('body, words', [
    ('num_bns: 40', ['num_bns', 'unknown', "did you mean 'num_bins'?"]),
    ('max_threshold_m: 1', ['max_threshold_m', 'double', 'decimal']),
    ('num_bins: 40.0', ['num_bins', 'integer']),
    ('density_in_flat_branch: 1', ['density_in_flat_branch', 'bool']),
    ('num_bins: "40"', ['num_bins', 'str']),
    ('num_bins: 2', ['num_bins', 'outside']),
    ('queue_size: 0', ['queue_size', 'outside']),
    ('processing_budget_ms: .nan', ['processing_budget_ms', 'finite']),
    ('slope_floor: 0.5\n    slope_ceiling: 0.4', ['slope_floor']),
    ('nested:\n      deep: 1.0', ['nested.deep']),
    # an earlier version's key and off values name what replaced them
    ('ground_threshold_std_factor: 0.0', ['ground_threshold_std_factor', 'use_std_threshold']),
    ('outlier_wide_terrain_m: 0.0', ['outlier_wide_terrain_m', 'use_wide_terrain_rule: false']),
    ('length_factor_smoothing_passes: 0', ['use_length_factor_smoothing: false']),
])
def test_bad_values_name_the_key(tmp_path, body, words):
    path = _write(tmp_path, f'ground_segmentation:\n  ros__parameters:\n    {body}\n')
    with pytest.raises(ParameterConfigError) as info:
        load_params_file(path)
    assert isinstance(info.value, ValueError)
    for word in words:
        assert word in str(info.value)
    assert str(path) in str(info.value)


@pytest.mark.parametrize('text, value', [('1e-1', 0.1), ('2.5E-1', 0.25), ('.25e0', 0.25),
                                         ('+1.5e-1', 0.15)])
def test_numbers_with_an_exponent_are_doubles_as_for_rcl(tmp_path, text, value):
    # rcl takes whatever strtod reads as a double; PyYAML alone would give the string '1e-1'
    path = _write(tmp_path, f'/**:\n  ros__parameters:\n    ground_threshold_m: {text}\n')
    assert load_params_file(path)[0].ground_threshold_m == value
    bad = _write(tmp_path, '/**:\n  ros__parameters:\n    num_bins: 1e1\n')
    with pytest.raises(ParameterConfigError, match='num_bins'):  # a double for an integer
        load_params_file(bad)


def test_sections_rcl_refuses_are_refused_with_the_file_named(tmp_path):
    # an empty 'ros__parameters:' stops the node (rcl) but the tools took it as no change
    empty = _write(tmp_path, '/**:\n  ros__parameters:\n')
    with pytest.raises(ParameterConfigError, match=r"is empty.*'ros__parameters: \{\}'") as info:
        load_params_file(empty)
    assert str(empty) in str(info.value)
    assert load_params_file(_write(tmp_path, '/**:\n  ros__parameters: {}\n'))[0] == \
        SegmenterParams()
    bare = _write(tmp_path, 'ground_segmentation:\n  num_bins: 32\n')
    with pytest.raises(ParameterConfigError, match="go under a 'ros__parameters:' key") as info:
        load_params_file(bare)
    assert str(bare) in str(info.value)


def test_structure_errors(tmp_path):
    with pytest.raises(ParameterConfigError, match='cannot read'):
        load_params_file(tmp_path / 'missing.yaml')
    with pytest.raises(ParameterConfigError, match='not valid YAML'):
        load_params_file(_write(tmp_path, 'a: [1,\n'))
    with pytest.raises(ParameterConfigError, match='mapping'):
        load_params_file(_write(tmp_path, '- 1\n- 2\n'))
    with pytest.raises(ParameterConfigError, match='beside ros__parameters'):
        load_params_file(_write(tmp_path, 'ground_segmentation:\n  ros__parameters: {}\n'
                                          '  extra: 1\n'))


@pytest.mark.parametrize('value, kinds', [('[0.1, 1]', 'double and int'),
                                          ('[true, 1]', 'bool and int'),
                                          ('["1", 2]', 'int and str')])
def test_lists_mixing_kinds_are_refused_with_their_line(tmp_path, value, kinds):
    # rcl refuses them ('Sequence should be of same type') in two log lines of its own
    from gp_ground_segmentation.ros.config import read_params_file
    text = ('/**:\n  ros__parameters:\n    a: [1.0, 2.0]\n    nested:\n      ok: ["x", "y"]\n'
            f'      bad: {value}\n')
    with pytest.raises(ParameterConfigError, match=f'line 6: a list mixes {kinds} values'):
        read_params_file(_write(tmp_path, text))
    same = text.replace(value, '[1.0, 2.5]')
    assert read_params_file(_write(tmp_path, same))['/**']['ros__parameters']['nested'] == {
        'ok': ['x', 'y'], 'bad': [1.0, 2.5]}


def test_qos_overrides_and_builtins_are_accepted(tmp_path):
    path = _write(tmp_path, 'ground_segmentation:\n  ros__parameters:\n    use_sim_time: false\n'
                            '    qos_overrides:\n      /ground:\n        publisher:\n'
                            '          reliability: best_effort\n')
    seg, node = load_params_file(path)
    assert seg == SegmenterParams() and node == node_param_defaults()


def test_specs_cover_both_sets_once():
    specs = all_param_specs()
    names = [r['name'] for r in describe_params()] + list(NODE_PARAMS)
    assert list(specs) == names and len(set(names)) == len(names)
    for spec in specs.values():
        assert spec['type'] in ('int', 'float', 'bool', 'str') and spec['description']
        if spec['type'] in ('int', 'float'):
            assert spec['min'] <= spec['default'] <= spec['max'], spec['name']
    # the only string, the IMU topic: off by default, fixed at start-up (it is subscribed to)
    assert [n for n, s in specs.items() if s['type'] == 'str'] == ['imu_topic']
    assert specs['imu_topic']['default'] == '' and specs['imu_topic']['read_only']


def test_string_parameter_is_checked_and_written_as_a_string(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text("/**:\n  ros__parameters:\n    imu_topic: /imu/data\n")
    assert load_params_file(path)[1]['imu_topic'] == '/imu/data'
    path.write_text('/**:\n  ros__parameters:\n    imu_topic: 3\n')
    with pytest.raises(ParameterConfigError, match="'imu_topic': expected a string, got int 3"):
        load_params_file(path)
    assert "    imu_topic: ''" in render_params_yaml().splitlines()


def test_params_table_has_a_row_per_param():
    table = render_params_table().splitlines()
    assert len(table) == 2 + len(all_param_specs())
    assert all(line.count('|') >= 6 for line in table)
