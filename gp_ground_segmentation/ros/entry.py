# SPDX-License-Identifier: Apache-2.0
"""The console scripts of both node variants: arguments, parameter files, rclpy, one-line errors.

``run_node(node_class, prog, args)`` is the whole ``main()`` of ``ground_segmentation_node``
(node.py) and ``ground_segmentation_lifecycle_node`` (lifecycle.py). Every way to start it
wrongly ends in one line and a non-zero exit, never a traceback:

* an argument before ``--ros-args`` that is not ``--help``: argparse's usage line and the error
  (exit 2);
* a ROS argument rcl cannot parse (``--ros-args --bogus``, ``-r foo``, ``--log-level nonsense``,
  ``-p x``): one FATAL line saying which argument and how it is written (exit 2); rcl's own
  "Failed to parse global arguments" line is kept out (its ``rcl`` logger is silenced while
  rclpy initialises, and set back after);
* a parameter file or value the node refuses: one FATAL line ``invalid parameters: ...``
  naming the file and key (exit 1).

``--help`` prints where this installation's parameter file and Fast DDS profile really are
(:func:`shipped_config_dir`): a colcon install's share directory, a pip install's
``<prefix>/share/gp_ground_segmentation/config``, or ``config/`` of the source tree (an
editable pip install, which installs no data files).
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from pathlib import Path

import rclpy
from ament_index_python.packages import get_package_share_directory
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import LoggingSeverity, get_logger_level, set_logger_level

from .config import (NODE_NAME, ParameterConfigError, params_file_values, params_from_values,
                     qos_override_topics, read_params_file)
from .shutdown import QuietShutdown, shutdown_context
from ..core.allocator import keep_freed_memory

__all__ = ['PACKAGE', 'check_params_file_sections', 'help_text', 'one_line',
           'ros_arguments_error', 'run_node', 'shipped_config_dir', 'split_command_line']

PACKAGE = 'gp_ground_segmentation'
RCLError = _rclpy.RCLError  # rcl failures, e.g. a parameter file it cannot parse
UnknownROSArgsError = _rclpy.UnknownROSArgsError  # a --ros-args token rcl does not know
EXIT_USAGE = 2  # argparse's exit code for a command line it refuses
EXIT_PARAMETERS = 1

_DESCRIPTION = """\
Ground/obstacle split of LiDAR point clouds with a Gaussian-process ground model (ROS 2 node{}).

Topics (relative names): points (sub, PointCloud2, sensor-data QoS), ground and obstacles (pub,
PointCloud2), labeled (pub, every valid point plus ground and height_above_ground, while
subscribed), ground_surface (pub, PointCloud2 x, y, z, z_std, while subscribed), the
imu_topic parameter's sensor_msgs/Imu (sub, when set), /diagnostics. The clouds must be in
the sensor's frame, or give its pose with the sensor_* parameters (docs/node.md, "Frames and
gravity")."""

_LIFECYCLE_NOTE = """

A managed node: it starts unconfigured; configure reads and validates the parameters and
creates the topics, activate starts the output, deactivate stops it (subscriptions, learned
GP state and IMU buffer kept), cleanup releases everything (lifecycle_msgs ChangeState on
<node>/change_state, or Nav2's lifecycle manager)."""

_FILES = """

Files of this installation ({where}):
  parameter file with every parameter and its default:
    {params}
  Fast DDS shared-memory profile: large clouds (~2 MB) from another process need it in the
  publisher's environment (and the node's):
    export FASTRTPS_DEFAULT_PROFILES_FILE={fastdds}"""

_NO_FILES = """

No config/ directory was found for this installation (none in the ament index, under
{prefix}/share/{package}, or beside the package): params.yaml and fastdds_large_shm.xml are
in config/ of the source tree."""

_EXAMPLES = """\
examples:
  {prog} --ros-args -r points:=/velodyne_points --params-file params.yaml
  {prog} --ros-args -r __ns:=/seg -r points:=/ouster/points
  ros2 launch gp_ground_segmentation ground_segmentation.launch.py points:=/velodyne_points{lc}
"""


def shipped_config_dir() -> tuple[Path, str] | None:
    """(directory, what it is) of this installation's config/ (params.yaml, the Fast DDS
    profile, the RViz view), the first of: the share directory of a colcon install (ament
    index; a sourced workspace), ``<prefix>/share/gp_ground_segmentation/config`` of the
    prefix the package is installed in (pip install, also with --prefix or --user) or of
    ``sys.prefix``, ``config/`` of the source tree beside the package (editable pip install,
    checkout). None when none of them holds params.yaml."""
    candidates = []
    try:
        candidates.append((Path(get_package_share_directory(PACKAGE)) / 'config',
                           'colcon install, ament index'))
    except (LookupError, OSError, ValueError):  # not installed by colcon / not sourced
        pass
    package = Path(__file__).resolve().parents[1]
    # <prefix>/lib/pythonX.Y/site-packages/gp_ground_segmentation: the data files went to
    # <prefix>/share (pip install, --prefix, --user; a colcon install without its setup sourced)
    installed = package.parent.name in ('site-packages', 'dist-packages')
    prefixes = [package.parents[3]] if installed else []
    for prefix in dict.fromkeys(prefixes + [Path(sys.prefix)]):
        candidates.append((prefix / 'share' / PACKAGE / 'config', f'installed in {prefix}'))
    candidates.append((package.parent / 'config', 'source tree'))
    for folder, what in candidates:
        if (folder / 'params.yaml').is_file():
            return folder, what
    return None


def help_text(prog: str, lifecycle: bool = False) -> tuple[str, str]:
    """(description, epilog) of ``prog --help``, with this installation's file paths."""
    text = _DESCRIPTION.format(', managed: lifecycle' if lifecycle else '')
    if lifecycle:
        text += _LIFECYCLE_NOTE
    found = shipped_config_dir()
    if found is None:
        text += _NO_FILES.format(prefix=sys.prefix, package=PACKAGE)
    else:
        folder, what = found
        text += _FILES.format(where=f'{what}: {folder}', params=folder / 'params.yaml',
                              fastdds=folder / 'fastdds_large_shm.xml')
    epilog = _EXAMPLES.format(prog=prog, lc=' lifecycle:=true' if lifecycle else '')
    return text, epilog


def one_line(text, limit: int = 300) -> str:
    """``text`` on one line (white space folded), cut to ``limit`` characters."""
    text = ' '.join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + '...'


# what an rcl "Couldn't parse ..." error is about -> (the one-line label, how it is written)
_RCL_ARGUMENT_KINDS = (
    ('remap rule', 'invalid remap rule', '-r FROM:=TO, e.g. -r points:=/velodyne_points'),
    ('log level', 'invalid log level',
     '--log-level LEVEL or --log-level LOGGER:=LEVEL, LEVEL one of debug, info, warn, error, '
     'fatal'),
    ('parameter override', 'invalid parameter override', '-p NAME:=VALUE, e.g. '
     '-p ground_threshold_m:=0.25'),
    ('enclave', 'invalid enclave', '-e /ENCLAVE'),
    ('external log', 'invalid logging option', 'see ros2 run --help'),
)


def ros_arguments_error(exc: BaseException) -> tuple[str, int]:
    """(one line, exit code) for an error rclpy.init raised on the command line ``--ros-args``:
    an unknown argument, or one rcl could not parse (remap, log level, parameter override:
    named for what it is, with how it is written; without rcl's C source locations). A
    parameter file rcl could not read is 'invalid parameters' (exit 1)."""
    if isinstance(exc, UnknownROSArgsError):
        try:
            unknown = [str(a) for a in ast.literal_eval(str(exc))]
        except (ValueError, SyntaxError):
            unknown = [str(exc)]
        return (f"unknown ROS argument{'s' if len(unknown) > 1 else ''} "
                f"{' '.join(unknown)} after --ros-args (known: -r FROM:=TO, -p NAME:=VALUE, "
                '--params-file FILE, --log-level LEVEL, -e ENCLAVE, ...; see '
                'https://docs.ros.org/en/jazzy/How-To-Guides/Node-arguments.html)', EXIT_USAGE)
    text = re.sub(r', at /\S+:\d+', '', one_line(exc, 1000))  # rcl's C source locations
    text = re.sub(r'^failed to initialize rcl: ', '', text)
    if 'params file' in text or 'parameter file' in text:
        return f'invalid parameters: {text}', EXIT_PARAMETERS
    for needle, label, written in _RCL_ARGUMENT_KINDS:
        if needle in text:
            return f'{label}: {text} (write {written})', EXIT_USAGE
    return f'invalid ROS arguments: {text}', EXIT_USAGE


def _init_rclpy(argv: list) -> None:
    """rclpy.init(args=argv) without rcl's own 'Failed to parse global arguments' ERROR line
    (the caller reports the exception in one line): rcl's logger is FATAL meanwhile, and set
    back unless the command line set its level itself (--log-level rcl:=...)."""
    before = get_logger_level('rcl')
    set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=argv)
    finally:
        names_rcl = any(str(token).startswith('rcl:=') for token in argv)
        if not names_rcl and get_logger_level('rcl') == LoggingSeverity.FATAL:
            set_logger_level('rcl', before)


def split_command_line(args: list) -> tuple[list, list]:
    """(non-ROS arguments, ``--params-file`` values) of ``args`` (without the program name).

    ROS arguments are those between ``--ros-args`` and ``--`` (or the end). Done here rather
    than with rclpy.utilities.remove_ros_args, which already fails on a missing params file.
    """
    plain, files, in_ros, i = [], [], False, 0
    while i < len(args):
        token = args[i]
        if token == '--ros-args':
            in_ros = True
        elif token == '--' and in_ros:
            in_ros = False
        elif in_ros and token == '--params-file' and i + 1 < len(args):
            files.append(args[i + 1])
            i += 1
        elif not in_ros:
            plain.append(token)
        i += 1
    return plain, files


def check_params_file_sections(path: str, doc: dict, node) -> None:
    """A params file with no section for this node would be ignored silently by rcl (e.g. a
    'ground_segmentation:' key when the node runs in a namespace): refuse to start instead.
    QoS overrides of topics this node does not have (rclpy ignores them silently; usually the
    name before remapping, '/points' for a node remapped to '/velodyne_points') get a warning:
    not an error, as a '/**' section may hold other nodes' overrides."""
    values = params_file_values(path, node.get_name(), node.get_namespace(), doc)
    params_from_values(path, values)
    unused = qos_override_topics(values) - set(node.topic_names)
    if unused:
        node.get_logger().warning(
            f"{path}: qos_overrides for {', '.join(sorted(unused))} match none of this node's "
            f"topics ({', '.join(node.topic_names)}) and are ignored; the key is the resolved "
            'topic name, after remapping and namespace')


def _parse_plain_arguments(prog: str, argv: list, lifecycle: bool) -> list:
    """Check the arguments before ``--ros-args`` (``--help`` prints the help and exits here);
    the ``--params-file`` paths."""
    description, epilog = help_text(prog, lifecycle)
    parser = argparse.ArgumentParser(prog=prog, usage='%(prog)s [--help] [--ros-args ...]',
                                     description=description, epilog=epilog,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    plain_args, params_files = split_command_line(argv[1:])
    _, unknown = parser.parse_known_args(plain_args)
    if unknown:  # e.g. '--params-file x' without --ros-args: rcl would ignore it silently
        parser.error(f"unrecognized arguments: {' '.join(unknown)} (ROS arguments such as "
                     '--params-file, -p and -r go after --ros-args)')
    return params_files


def run_node(node_class, prog: str, args=None) -> None:
    """The console script: check the command line, read the parameter files, start rclpy and
    ``node_class(announce=False)``, check the files' sections, ``node.log_started()``, spin
    until Ctrl-C / SIGTERM; errors as the module docstring says (``sys.exit`` with the code)."""
    argv = list(sys.argv if args is None else args)
    params_files = _parse_plain_arguments(prog, argv, getattr(node_class, 'LIFECYCLE', False))
    logger = rclpy.logging.get_logger(NODE_NAME)
    # the process is the node's: keep each frame's freed memory for the next frame (about
    # half of segment()'s time went to page faults without it; core/allocator.py)
    allocator_note = keep_freed_memory()
    if allocator_note is not None:
        logger.info(allocator_note)
    exit_code = _serve(node_class, argv, params_files, logger)
    if exit_code:
        sys.exit(exit_code)


def _serve(node_class, argv: list, params_files: list, logger) -> int:
    """rclpy, the node and its executor from start to clean shutdown; the exit code."""
    quiet = QuietShutdown()
    quiet.install()
    node = None
    exit_code = 0
    try:
        # read before rcl, which reports an unreadable file in a traceback and one that is not
        # YAML in two lines naming its C sources; the documents serve the checks below
        documents = [(path, read_params_file(path)) for path in params_files]
        try:
            _init_rclpy(argv)
        except (UnknownROSArgsError, RCLError) as exc:
            text, exit_code = ros_arguments_error(exc)
            logger.fatal(text)
            return exit_code
        # The executor exists before the node announces itself, so a Ctrl-C right after the
        # 'listening' line never lands inside executor construction (an rclpy 7.1 __del__ race).
        executor = SingleThreadedExecutor()
        node = node_class(announce=False)
        for path, doc in documents:
            check_params_file_sections(path, doc, node)
        node.log_started()  # after the checks: a refused file gives FATAL, not 'listening'
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParameterConfigError, ParameterException, RCLError) as exc:
        logger.fatal(f'invalid parameters: {one_line(exc, 1000)}')
        exit_code = EXIT_PARAMETERS
    finally:
        quiet.ignore_signals()  # from here on a signal must not interrupt the clean-up
        if node is not None:
            node.destroy_node()
        shutdown_context()
        quiet.ignore_signals()  # rclpy restores the handlers it replaced when it shuts down
    return exit_code
