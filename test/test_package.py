# SPDX-License-Identifier: Apache-2.0
"""Static checks of the ament_python packaging (the full colcon build runs in .ci/run)."""

import ast
import configparser
import xml.etree.ElementTree as ET

from conftest import REPO

PKG = 'gp_ground_segmentation'


def test_package_xml_format3_ament_python_with_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == PKG
    assert root.find('export/build_type').text == 'ament_python'
    exec_deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'rcl_interfaces', 'sensor_msgs', 'std_msgs', 'diagnostic_msgs',
            'python3-numpy', 'python3-scipy', 'lifecycle_msgs', 'ament_index_python'} <= exec_deps
    assert 'python3-pytest' in {e.text for e in root.findall('test_depend')}
    assert root.findall('buildtool_depend') == []  # not used by Jazzy ament_python packages


def test_resource_marker_and_config_present():
    marker = REPO / 'resource' / PKG
    assert marker.is_file() and marker.stat().st_size == 0
    assert (REPO / 'config' / 'params.yaml').is_file()


def test_setup_cfg_puts_scripts_where_ros2_run_looks():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / 'setup.cfg')
    assert cfg['develop']['script_dir'] == f'$base/lib/{PKG}'
    assert cfg['install']['install_scripts'] == f'$base/lib/{PKG}'
    assert cfg['tool:pytest']['testpaths'].strip() == 'test'


def _setup_kwargs():
    tree = ast.parse((REPO / 'setup.py').read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, 'id', '') == 'setup')
    return {kw.arg: kw.value for kw in call.keywords}


def test_setup_py_entry_points_and_data_files():
    kw = _setup_kwargs()
    scripts = ast.literal_eval(kw['entry_points'])['console_scripts']
    assert f'ground_segmentation_node = {PKG}.ros.node:main' in scripts
    assert f'ground_segmentation_lifecycle_node = {PKG}.ros.lifecycle:main' in scripts
    assert f'gp-ground-seg = {PKG}.tools.cli:main' in scripts
    src = ast.unparse(kw['data_files'])
    for needle in ("'share/ament_index/resource_index/packages'", "'resource/' + package_name",
                   "'package.xml'", "'/config'", "'*.yaml'"):
        assert needle in src, needle
    extras = ast.literal_eval(kw['extras_require'])
    assert set(extras['test']) >= {'pytest', 'hypothesis'}
    requires = ast.literal_eval(kw['install_requires'])
    assert 'ros-jazzy-rclpy[fastrtps]' in requires and 'numpy' in requires


def test_package_versions_agree():
    import gp_ground_segmentation
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.findtext('version') == gp_ground_segmentation.__version__
    assert ast.literal_eval(_setup_kwargs()['version']) == gp_ground_segmentation.__version__
