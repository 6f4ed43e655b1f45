# SPDX-License-Identifier: Apache-2.0
"""The node as people start it: console script under signals, --help, parameter files (also in a
namespace), QoS overrides per endpoint, and the launch file."""

import os
import signal
import time

import pytest
import yaml

from conftest import NODE_MODULE, REPO, start_module, wait_listening

LAUNCH_FILE = REPO / 'launch' / 'ground_segmentation.launch.py'
PARAMS_YAML = REPO / 'config' / 'params.yaml'


def _start(args, **kwargs):
    return start_module(NODE_MODULE, *args, **kwargs)


def _run(args, timeout=60):
    proc = _start(args)
    out, _ = proc.communicate(timeout=timeout)
    return proc.returncode, out


def _signal_once_up(args, send):
    """(exit code, output) of the node started with ``args`` in its own process group, after
    ``send(proc)`` once it logged 'listening on'."""
    proc = _start(args, start_new_session=True)
    try:
        first = ''.join(wait_listening(proc))
        send(proc)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, first + out


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_two_signals_to_the_process_group_exit_0_quietly(sig):
    # A terminal's Ctrl-C goes to the whole process group, and ros2 launch forwards another.
    def twice(proc):
        os.killpg(proc.pid, sig)
        os.killpg(proc.pid, sig)
    code, out = _signal_once_up(['--ros-args', '-r', 'points:=/gp_test_points'], twice)
    assert code == 0, out
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out


def test_signals_during_shutdown_are_ignored():
    # Signals keep coming while the node is being destroyed (worker joined): still exit 0.
    def five(proc):
        for _ in range(5):
            os.killpg(proc.pid, signal.SIGINT)
            time.sleep(0.02)
    code, out = _signal_once_up(['--ros-args', '-r', 'points:=/gp_test_points'], five)
    assert code == 0 and 'Traceback' not in out, out


def test_help_prints_usage_and_does_not_start():
    code, out = _run(['--help'])
    assert code == 0
    assert out.startswith('usage: ground_segmentation_node') and '--ros-args' in out
    assert 'listening on' not in out


def test_ros_arguments_without_ros_args_are_refused():
    # rcl ignores a '--params-file' that is not after --ros-args: the node would run with its
    # defaults without a word
    code, out = _run(['--params-file', 'config/params.yaml'])
    assert code == 2 and 'Traceback' not in out, out
    assert out.strip().splitlines()[-1].endswith('go after --ros-args)'), out
    assert 'listening on' not in out


def _fatal_line(params_file):
    """The node started with ``params_file`` exits 1 having printed one FATAL line naming it:
    that line, and the whole output."""
    code, out = _run(['--ros-args', '--params-file', str(params_file)])
    assert code == 1, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and 'FATAL' in lines[0] and str(params_file) in lines[0], out
    return lines[0], out


@pytest.mark.parametrize('make_path', [lambda tmp: tmp / 'missing.yaml', lambda tmp: tmp],
                         ids=['missing', 'directory'])
def test_unreadable_params_file_is_one_fatal_line(tmp_path, make_path):
    _, out = _fatal_line(make_path(tmp_path))
    assert 'Traceback' not in out and 'RCLError' not in out, out


@pytest.mark.parametrize('text, where', [
    (b'/**:\n  ros__parameters:\n    ground_threshold_m: [0.25\n',
     'line 3, column 25: while parsing a flow sequence'),
    (b'/**:\n  ros__parameters:\n    frame: "open\n', 'line 3, column 12: while scanning'),
    (b'/**:\n  ros__parameters:\n    ground_threshold_m: 0.25\n   bad: 1\n',
     "line 4, column 4: expected <block end>, but found '<block mapping start>'"),
    (b'/**:\n  ros__parameters:\n\tground_threshold_m: 0.25\n',
     "line 3, column 1: found character '\\t' that cannot start any token"),
    (b'/**:\n  ros__parameters:\n    a: &t 0.25\n    ground_threshold_m: *t\n',
     'line 4: YAML aliases (*t) are not supported'),
    (b'/**:\n  ros__parameters:\n    ground_threshold_m: 0.25 # caf\xe9\n',
     'line 3: not UTF-8 text (byte 58: 0xe9)'),
    (b'/**:\n  ros__parameters:\n    a: [0.5, 1]\n', 'line 3: a list mixes double and int'),
    (b'- just\n- a list\n', 'top level must be a mapping')],
    ids=['flow', 'quote', 'indent', 'tab', 'alias', 'latin1', 'mixed-list', 'list'])
def test_params_file_that_is_not_yaml_is_one_fatal_line(tmp_path, text, where):
    # rcl's own parser reports such errors in two log lines naming its C sources (a file that
    # is not UTF-8 made the node's own check raise a traceback)
    path = tmp_path / 'broken.yaml'
    path.write_bytes(text)
    line, out = _fatal_line(path)
    assert where in line and 'parse.c' not in out and 'listening on' not in out, out


def _shipped_params_with(tmp_path, **changes):
    doc = yaml.safe_load(PARAMS_YAML.read_text())
    (section,) = doc
    doc[section]['ros__parameters'].update(changes)
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_namespaced_node_reads_the_shipped_params_file(tmp_path):
    # A bad value in the shipped file's layout must stop a node in a namespace too ...
    bad = _shipped_params_with(tmp_path, num_bins=2)
    code, out = _run(['--ros-args', '-r', '__ns:=/seg', '--params-file', str(bad)])
    assert code == 1 and 'num_bins' in out and 'Traceback' not in out, out
    # ... and a good one is applied there.
    import rclpy
    from gp_ground_segmentation.ros.node import GroundSegmentationNode
    good = _shipped_params_with(tmp_path, ground_threshold_m=0.27)
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(good)], context=context)
    try:
        node = GroundSegmentationNode(context=context, namespace='/seg')
        assert node.get_fully_qualified_name() == '/seg/ground_segmentation'
        assert node.declared_params.ground_threshold_m == 0.27
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_params_file_without_a_section_for_the_node_is_refused(tmp_path):
    # rcl ignores such a file silently; the node says so and stops.
    path = tmp_path / 'root_only.yaml'
    path.write_text('ground_segmentation:\n  ros__parameters:\n    ground_threshold_m: 0.25\n')
    code, out = _run(['--ros-args', '-r', '__ns:=/seg', '--params-file', str(path)])
    assert code == 1 and 'Traceback' not in out, out
    fatal = [ln for ln in out.splitlines() if 'FATAL' in ln]
    assert len(fatal) == 1 and "'/seg/ground_segmentation'" in fatal[0] \
        and str(path) in fatal[0], out
    assert 'listening on' not in out  # refused before it says it is up


def test_qos_override_of_a_topic_the_node_does_not_have_is_warned_about(tmp_path):
    # rclpy applies an override to the resolved name only: with the input remapped, an
    # override keyed '/points' does nothing, silently; the node says so and still runs.
    path = _shipped_params_with(tmp_path)
    doc = yaml.safe_load(path.read_text())
    (section,) = doc
    doc[section]['ros__parameters']['qos_overrides'] = {
        '/points': {'subscription': {'reliability': 'reliable'}},
        '/ground': {'publisher': {'depth': 3}}}
    path.write_text(yaml.safe_dump(doc))

    def interrupt(proc):  # the check ran before the 'listening' line
        os.killpg(proc.pid, signal.SIGINT)
    code, out = _signal_once_up(['--ros-args', '-r', 'points:=/gp_test_remapped',
                                 '--params-file', str(path)], interrupt)
    assert code == 0, out
    warnings = [ln for ln in out.splitlines() if 'qos_overrides' in ln]
    assert len(warnings) == 1 and 'WARN' in warnings[0], out
    assert 'for /points match none' in warnings[0] and '/gp_test_remapped' in warnings[0], out
    assert '/ground,' not in warnings[0].split('match none')[0]  # /ground's override applies


def test_qos_override_of_one_output_leaves_the_others_alone():
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from gp_ground_segmentation.ros.node import OUTPUT_QOS, GroundSegmentationNode
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '-p', 'qos_overrides./ground.publisher.depth:=7',
                     '-p', 'qos_overrides./points.subscription.depth:=3'], context=context)
    try:
        node = GroundSegmentationNode(context=context)

        pubs = {p.topic_name: p.qos_profile for p in node.publishers}
        subs = {s.topic_name: s.qos_profile for s in node.subscriptions}
        assert pubs['/ground'].depth == 7
        assert pubs['/obstacles'].depth == 1
        assert subs['/points'].depth == 3
        assert OUTPUT_QOS.depth == 1 and qos_profile_sensor_data.depth == 5
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_launch_file_is_installed_and_valid_python():
    compile(LAUNCH_FILE.read_text(), str(LAUNCH_FILE), 'exec')
    setup = (REPO / 'setup.py').read_text()
    assert "'share/' + package_name + '/launch'" in setup and '*.launch.py' in setup


def test_launch_description():
    pytest.importorskip('launch_ros', reason='launch_ros is not installable from PyPI here; '
                        'this runs in a ROS 2 installation')
    import importlib.util
    from launch.actions import DeclareLaunchArgument
    from launch_ros.actions import Node
    spec = importlib.util.spec_from_file_location('gs_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    from launch_ros.actions import LifecycleNode
    names = {e.name for e in description.entities if isinstance(e, DeclareLaunchArgument)}
    assert {'points', 'params_file', 'namespace', 'use_sim_time', 'lifecycle', 'autostart',
            'rviz'} <= names
    nodes = [e for e in description.entities if isinstance(e, Node)]
    # the plain node, the managed one (each under a condition on 'lifecycle') and RViz
    assert len(nodes) == 3
    assert len([n for n in nodes if isinstance(n, LifecycleNode)]) == 1


# --- the first ten minutes: command-line mistakes, one line each, and where the files are ---

@pytest.mark.parametrize('args, words', [
    (['--ros-args', '--bogus'], ['unknown ROS argument --bogus after --ros-args', '-r FROM:=TO']),
    (['--ros-args', '-r', 'foo'], ["invalid remap rule: Couldn't parse remap rule: '-r foo'",
                                   'write -r FROM:=TO']),
    (['--ros-args', '--log-level', 'nonsense'],
     ["invalid log level: Couldn't parse log level: '--log-level nonsense'", 'debug, info']),
    (['--ros-args', '-p', 'x'], ['invalid parameter override', "'-p x'", 'write -p NAME:=VALUE'])],
    ids=['unknown', 'remap', 'log-level', 'override'])
def test_bad_ros_arguments_are_one_line_saying_what_they_are(args, words):
    code, out = _run(args)
    assert code == 2, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and 'FATAL' in lines[0], out  # no traceback, no rcl ERROR line
    for word in words:
        assert word in lines[0], out
    assert 'invalid parameters' not in out and '.c:' not in out  # no rcl C source locations


def test_unknown_plain_argument_prints_usage_and_error_only():
    code, out = _run(['--bogus'])
    assert code == 2
    assert out.strip().splitlines() == [
        'usage: ground_segmentation_node [--help] [--ros-args ...]',
        'ground_segmentation_node: error: unrecognized arguments: --bogus (ROS arguments such '
        'as --params-file, -p and -r go after --ros-args)']


def _help_files(out):
    """The parameter file and Fast DDS profile paths --help names."""
    lines = [ln.strip() for ln in out.splitlines()]
    params = lines[lines.index('parameter file with every parameter and its default:') + 1]
    fastdds = next(ln for ln in lines if ln.startswith('export FASTRTPS_DEFAULT_PROFILES_FILE='))
    return params, fastdds.split('=', 1)[1]


def test_help_names_the_source_trees_files_for_an_editable_install():
    code, out = _run(['--help'])
    assert code == 0
    params, fastdds = _help_files(out)
    assert params == str(REPO / 'config' / 'params.yaml') and os.path.isfile(params)
    assert fastdds == str(REPO / 'config' / 'fastdds_large_shm.xml') and os.path.isfile(fastdds)
    assert 'share/gp_ground_segmentation/config/' not in out  # not a path that may not exist


def _installed_layout(prefix):
    """The files a pip (or colcon) install writes under ``prefix``: the package in
    lib/pythonX.Y/site-packages, setup.py's data files under share/ (config/*.yaml, *.xml)."""
    import shutil
    import sys
    site = prefix / 'lib' / f'python{sys.version_info[0]}.{sys.version_info[1]}' / \
        'site-packages'
    shutil.copytree(REPO / 'gp_ground_segmentation', site / 'gp_ground_segmentation',
                    ignore=shutil.ignore_patterns('__pycache__'))
    config = prefix / 'share' / 'gp_ground_segmentation' / 'config'
    config.mkdir(parents=True)
    for pattern in ('*.yaml', '*.xml'):
        for path in (REPO / 'config').glob(pattern):
            shutil.copy(path, config)
    return site, config


def test_help_names_the_installed_files_of_a_pip_install(tmp_path):
    import subprocess
    import sys
    site, config = _installed_layout(tmp_path / 'prefix')
    env = dict(os.environ, PYTHONPATH=str(site))
    out = subprocess.run([sys.executable, '-c', 'import sys; sys.argv[0] = "x"; '
                          'import gp_ground_segmentation.ros.node as n; print(n.__file__); '
                          'n.main(["ground_segmentation_node", "--help"])'],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0].startswith(str(site))  # the installed copy ran
    assert _help_files(out.stdout) == (str(config / 'params.yaml'),
                                       str(config / 'fastdds_large_shm.xml'))


def test_help_names_the_colcon_installs_share_directory(tmp_path):
    # a sourced colcon workspace: the package is in the ament index (AMENT_PREFIX_PATH)
    install = tmp_path / 'install'
    marker = install / 'share' / 'ament_index' / 'resource_index' / 'packages'
    marker.mkdir(parents=True)
    (marker / 'gp_ground_segmentation').write_text('')
    config = install / 'share' / 'gp_ground_segmentation' / 'config'
    config.mkdir(parents=True)
    for name in ('params.yaml', 'fastdds_large_shm.xml'):
        (config / name).write_text((REPO / 'config' / name).read_text())
    proc = _start(['--help'], env_extra={'AMENT_PREFIX_PATH': str(install)})
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert _help_files(out) == (str(config / 'params.yaml'),
                                str(config / 'fastdds_large_shm.xml'))
    assert 'colcon install' in out
