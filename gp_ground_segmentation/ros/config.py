# SPDX-License-Identifier: Apache-2.0
"""Parameters of the ROS 2 node: the segmenter's fields plus the node-only ones, and YAML loading.

One source of truth: the segmenter parameters come from ``describe_params()`` (the dataclass
metadata), the node-only ones from ``NODE_PARAMS`` below. The node declares exactly these, the
shipped ``config/params.yaml`` lists exactly these (a test checks it), and ``load_params_file``
reads a ROS 2 parameter file with the same strict typing rules as rclpy, so the offline tools
(bag replay) and the node accept and reject the same files.

ROS typing rules followed here (rclpy raises ``InvalidParameterTypeException`` otherwise): a double
parameter must be written with a decimal point (``80.0``, not ``80``), an integer without one, a
bool as ``true``/``false``. The errors say which key and which type was expected.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import textwrap
from pathlib import Path

from ..core.params import SegmenterParams, describe_params, retired_problem, value_problem

__all__ = ['NODE_NAME', 'NODE_PARAMS', 'PARAMS_FILE_KEY', 'ParameterConfigError',
           'all_param_specs', 'check_param_value', 'describe_node_params', 'is_ros_builtin',
           'load_params_file', 'node_param_defaults', 'params_file_values', 'params_from_values',
           'qos_override_topics', 'render_param_overrides', 'render_params_table',
           'render_params_yaml', 'split_params', 'validate_node_params']

NODE_NAME = 'ground_segmentation'
# Key of the shipped params file: '/**' matches the node in any namespace and under any name
# (-r __ns:=/seg, -r __node:=...); a plain 'ground_segmentation:' key only matches in the root
# namespace, and rcl silently ignores a file that has no section for the node.
PARAMS_FILE_KEY = '/**'

# Node-only parameters (not part of the segmenter): name -> spec, same keys as describe_params().
NODE_PARAMS = {
    'processing_budget_ms': {
        'default': 100.0, 'type': 'float', 'min': 0.001, 'max': 1e6, 'read_only': False,
        'description': 'processing time budget per frame (ms, decode + segment + encode); '
                       'diagnostics go WARN when the windowed mean exceeds it'},
    'queue_size': {
        'default': 1, 'type': 'int', 'min': 1, 'max': 100, 'read_only': True,
        'description': 'size of the latest-wins slot between the subscription and the worker '
                       '(frames); when full the oldest waiting frame is dropped and counted'},
    'diagnostics_period_s': {
        'default': 1.0, 'type': 'float', 'min': 0.01, 'max': 3600.0, 'read_only': False,
        'description': 'period of the DiagnosticArray on /diagnostics (s)'},
    'diagnostics_window': {
        'default': 50, 'type': 'int', 'min': 1, 'max': 100000, 'read_only': False,
        'description': 'number of most recent frames over which timings (mean/p95/max), '
                       'input rate and drops are reported (frames)'},
    'publish_ground_surface': {
        'default': True, 'type': 'bool', 'read_only': False,
        'description': 'publish the GP ground surface on ground_surface: PointCloud2 x, y, z, '
                       'z_std (FLOAT32, m) at the bin edges of every segment with ground '
                       'candidates; z_std is the std of the ground height itself (the GP '
                       'posterior std and the spread across the segment; without sensor '
                       'noise); the node builds it only while the topic has a subscriber'},
    'imu_topic': {
        'default': '', 'type': 'str', 'read_only': True,
        'description': 'sensor_msgs/Imu topic that levels every cloud (subscribed with '
                       'sensor-data QoS): the roll and pitch of the cloud frame come from the '
                       'IMU sample nearest the cloud header stamp (its orientation, or its '
                       'low-passed linear_acceleration when orientation_covariance[0] is -1) '
                       'and replace sensor_roll_rad and sensor_pitch_rad for that frame; '
                       'empty: no IMU'},
    'imu_max_age_s': {
        'default': 0.1, 'type': 'float', 'min': 0.0, 'max': 10.0, 'read_only': False,
        'description': 'largest |cloud stamp - IMU stamp| (s, header stamps, never the wall '
                       'clock) at which the nearest IMU sample is used; beyond it, or with no '
                       'sample, the frame uses the static sensor_roll_rad/sensor_pitch_rad and '
                       'diagnostics go WARN giving the age'},
    'imu_lidar_roll_rad': {
        'default': 0.0, 'type': 'float', 'min': -math.pi, 'max': math.pi, 'read_only': False,
        'description': 'roll of the LiDAR (cloud) frame in the IMU frame (rad, about x; with '
                       'imu_lidar_pitch_rad and imu_lidar_yaw_rad the rotation '
                       'R_z(yaw) R_y(pitch) R_x(roll) of a TF from the IMU frame to the LiDAR '
                       'frame, REP 103; all 0 when the IMU axes are the LiDAR axes)'},
    'imu_lidar_pitch_rad': {
        'default': 0.0, 'type': 'float', 'min': -math.pi / 2, 'max': math.pi / 2,
        'read_only': False,
        'description': 'pitch of the LiDAR frame in the IMU frame (rad, about y; see '
                       'imu_lidar_roll_rad)'},
    'imu_lidar_yaw_rad': {
        'default': 0.0, 'type': 'float', 'min': -math.pi, 'max': math.pi, 'read_only': False,
        'description': 'yaw of the LiDAR frame in the IMU frame (rad, about z; see '
                       'imu_lidar_roll_rad)'},
    'imu_accel_time_constant_s': {
        'default': 0.5, 'type': 'float', 'min': 0.0, 'max': 60.0, 'read_only': False,
        'description': 'time constant (s) of the first-order low-pass of the IMU '
                       'linear_acceleration, used for gravity when the driver gives no '
                       'orientation; longer keeps more of the vehicle motion out of the tilt '
                       'but follows a tilt later; 0: the raw sample'},
    'add_height_above_ground_field': {
        'default': False, 'type': 'bool', 'read_only': False,
        'description': 'append a FLOAT32 height_above_ground field (z - predicted ground '
                       'height, m) to the ground and obstacle clouds; off keeps them '
                       'byte-for-byte copies of the input points'},
}

# Parameters every rclpy node has or may get from rclpy itself; a params file may set them.
ROS_BUILTIN_PARAMS = ('use_sim_time', 'start_type_description_service')
ROS_BUILTIN_PREFIXES = ('qos_overrides.',)


class ParameterConfigError(ValueError):
    """A parameter file or override that names an unknown key or gives a bad value/type."""


def describe_node_params() -> list[dict]:
    """One dict per node-only parameter: name, default, type, description, min, max, read_only."""
    return [dict(name=name, **spec) for name, spec in NODE_PARAMS.items()]


def all_param_specs() -> dict:
    """name -> spec for every parameter the node declares (segmenter fields first)."""
    specs = {}
    for row in describe_params():
        specs[row['name']] = dict(row, read_only=False)
    for row in describe_node_params():
        specs[row['name']] = row
    return specs


def node_param_defaults() -> dict:
    """Node-only parameters with their defaults."""
    return {name: spec['default'] for name, spec in NODE_PARAMS.items()}


def is_ros_builtin(name: str) -> bool:
    """A parameter rclpy itself has or may get (a params file may set it; not ours to check)."""
    return name in ROS_BUILTIN_PARAMS or name.startswith(ROS_BUILTIN_PREFIXES)


def check_param_value(name: str, value, specs: dict | None = None) -> None:
    """Raise ParameterConfigError unless ``value`` has the declared type and lies in range."""
    specs = all_param_specs() if specs is None else specs
    retired = retired_problem(name, value)
    if retired:  # a key or value of an earlier version: name what replaced it
        raise ParameterConfigError(f"parameter '{name}': {retired}")
    if name not in specs:
        close = difflib.get_close_matches(name, list(specs), n=1)
        hint = f"did you mean '{close[0]}'? " if close else ''
        raise ParameterConfigError(
            f"unknown parameter '{name}' ({hint}known: {', '.join(sorted(specs))})")
    spec = specs[name]
    if spec['type'] == 'str':  # the core's parameters are numbers and bools only
        problem = None if isinstance(value, str) else \
            f'expected a string, got {type(value).__name__} {value!r}'
    else:
        problem = value_problem(value, spec['type'], spec.get('min'), spec.get('max'))
    if problem:
        raise ParameterConfigError(f"parameter '{name}': {problem}")


def split_params(values: dict) -> tuple[dict, dict]:
    """Split a flat name -> value dict into (segmenter fields, node-only params)."""
    seg_names = {f.name for f in dataclasses.fields(SegmenterParams)}
    seg = {k: v for k, v in values.items() if k in seg_names}
    node = {k: v for k, v in values.items() if k in NODE_PARAMS}
    return seg, node


def validate_node_params(node_params: dict) -> dict:
    """Check node-only params (types and ranges); return a full dict with defaults filled in."""
    out = node_param_defaults()
    for name, value in node_params.items():
        if name not in NODE_PARAMS:
            raise ParameterConfigError(f"unknown node parameter '{name}'")
        check_param_value(name, value, {n: dict(s) for n, s in NODE_PARAMS.items()})
        out[name] = value
    return out


def _flatten(prefix: str, tree: dict, out: dict, where: str) -> None:
    """ROS joins nested dicts under ros__parameters with '.'."""
    for key, value in tree.items():
        name = f'{prefix}.{key}' if prefix else str(key)
        if isinstance(value, dict):
            _flatten(name, value, out, where)
        else:
            out[name] = value


def _node_sections(doc: dict, path: tuple = ()):
    """Yield (node path, ros__parameters dict) for every section of a ROS 2 params file."""
    for key, value in doc.items():
        section = path + (str(key),)
        where = '/'.join(section)  # how the messages name the section
        if not isinstance(value, dict):
            raise ParameterConfigError(
                f"'{where}': expected a mapping (node name -> ros__parameters), got "
                f"{type(value).__name__}; parameters go under a 'ros__parameters:' key of the "
                "node's section")
        if 'ros__parameters' in value:
            params = value['ros__parameters']
            if params is None:  # rcl: "Cannot have a value before ros__parameters"
                raise ParameterConfigError(
                    f"'{where}/ros__parameters' is empty, which the node (rcl) refuses; write "
                    "'ros__parameters: {}' or put parameters under it")
            if not isinstance(params, dict):
                raise ParameterConfigError(
                    f"'{where}/ros__parameters' must be a mapping of parameter names to values")
            others = [k for k in value if k != 'ros__parameters']
            if others:
                raise ParameterConfigError(
                    f"'{where}': unexpected key(s) {others} beside ros__parameters")
            yield section, params
        else:
            yield from _node_sections(value, section)


def _matches(section_path: tuple, node_name: str, namespace: str) -> bool:
    """rcl's rule: the key is a fully qualified node name ('/' prepended if missing), where
    '**' matches any number of namespace levels (zero included) and '*' one token."""
    tokens = [t for p in section_path for t in str(p).split('/') if t]
    regex = ''
    for token in tokens:
        if token == '**':
            regex += '(?:/[^/]+)*'
        else:
            regex += '/' + '[^/]*'.join(re.escape(part) for part in token.split('*'))
    ns = namespace.strip('/')
    fqn = ('/' + ns if ns else '') + '/' + node_name
    return re.fullmatch(regex, fqn) is not None


def load_params_file(path, node_name: str = NODE_NAME, namespace: str = '/'):
    """Read a ROS 2 parameter YAML file; return ``(SegmenterParams, node_params dict)``.

    Sections whose key matches the node (``ground_segmentation``, ``/ground_segmentation``,
    ``/**``, ``/**/ground_segmentation``, ...) are merged in file order, later ones winning,
    as rcl does. Every key under ``ros__parameters`` must be a parameter of this node (or
    ``use_sim_time`` / ``qos_overrides.*``); an unknown key, a wrong type (``80`` for a double)
    or an out-of-range value raises ParameterConfigError (a ValueError) naming the key.
    Node params missing from the file get their defaults.
    """
    return params_from_values(path, params_file_values(path, node_name, namespace))


def params_from_values(path, values: dict):
    """``(SegmenterParams, node_params dict)`` of a parameter file's flattened values for this
    node (:func:`params_file_values`), checked as :func:`load_params_file` says; ``path`` names
    the file in the errors."""
    specs = all_param_specs()
    for name, value in values.items():
        if is_ros_builtin(name):
            continue
        try:
            check_param_value(name, value, specs)
        except ParameterConfigError as exc:
            raise ParameterConfigError(f'{path}: {exc}') from None
    seg_values, node_values = split_params(values)
    try:
        seg = SegmenterParams(**seg_values).validate()
    except ValueError as exc:
        raise ParameterConfigError(f'{path}: {exc}') from None
    return seg, validate_node_params(node_values)


def qos_override_topics(values: dict) -> set:
    """The topics named by the ``qos_overrides`` among a parameter file's flattened values for
    this node (:func:`params_file_values`; keys
    ``qos_overrides./TOPIC.publisher|subscription.POLICY``). rclpy applies an override only to
    the topic's resolved name (after remapping and namespace) and ignores the others without a
    word; the node warns about those."""
    topics = set()
    for name in values:
        if name.startswith('qos_overrides.'):
            # topic names have no dots: the last two parts are the entity and the policy
            topics.add(name[len('qos_overrides.'):].rsplit('.', 2)[0])
    return topics


# rcl reads a scalar that strtod takes whole as a double: '1e-1' and '1.5e3' too, which YAML 1.1
# (PyYAML) leaves strings (its floats need a '.' and a signed exponent)
_EXPONENT_FLOAT = re.compile(r'^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$')


def _ros_yaml_loader():
    """PyYAML's SafeLoader reading numbers with an exponent as floats, as rcl does, and
    keeping the first alias it composes (``first_alias``, an AliasEvent; rcl refuses them)."""
    import yaml

    class Loader(yaml.SafeLoader):
        first_alias = None

        def compose_node(self, parent, index):
            if self.first_alias is None and self.check_event(yaml.AliasEvent):
                self.first_alias = self.peek_event()
            return super().compose_node(parent, index)

    Loader.add_implicit_resolver('tag:yaml.org,2002:float', _EXPONENT_FLOAT,
                                 list('-+0123456789.'))
    return Loader


def read_params_file(path) -> dict:
    """The YAML document of a parameter file, as rcl reads it (a mapping of node names;
    empty file: {}); ParameterConfigError in one line when it is unreadable, not UTF-8, not
    YAML, not a mapping, or holds what rcl refuses: aliases and lists mixing kinds of values.
    The node calls it before rcl parses the file, whose parser reports such errors in two log
    lines naming its own source files."""
    import yaml  # local: the core does not need PyYAML

    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as exc:
        raise ParameterConfigError(
            f'cannot read parameter file {path}: {exc.strerror or exc}') from None
    except UnicodeDecodeError as exc:
        line = exc.object.count(b'\n', 0, exc.start) + 1
        raise ParameterConfigError(f'{path}: line {line}: not UTF-8 text (byte {exc.start}: '
                                   f'0x{exc.object[exc.start]:02x})') from None
    # one parse: the node tree (for the checks below), then the document built from it, as
    # yaml.load builds it
    loader = _ros_yaml_loader()(text)
    try:
        node = loader.get_single_node()
        doc = None if node is None else loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise ParameterConfigError(f'{path}: not valid YAML ({_yaml_error_text(exc)})') from None
    finally:
        loader.dispose()
    alias = loader.first_alias
    if alias is not None:
        raise ParameterConfigError(
            f'{path}: line {alias.start_mark.line + 1}: YAML aliases (*{alias.anchor}) are not '
            'supported by ROS 2 parameter files; write the value out')
    mixed = _mixed_sequence(node)
    if mixed is not None:
        line, kinds = mixed
        raise ParameterConfigError(
            f'{path}: line {line}: a list mixes {" and ".join(kinds)} values, which ROS 2 '
            'parameter files do not allow; write every element alike (1.0, not 1, in a list '
            'of doubles)')
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ParameterConfigError(f'{path}: top level must be a mapping of node names')
    return doc


def _mixed_sequence(node):
    """(line, sorted kinds) of the first YAML list whose scalar elements are of different
    kinds (int, double, string, bool), which rcl refuses; None when there is none."""
    import yaml

    if isinstance(node, yaml.SequenceNode):
        kinds = {child.tag.rsplit(':', 1)[-1] for child in node.value
                 if isinstance(child, yaml.ScalarNode)}
        kinds = {'double' if kind == 'float' else kind for kind in kinds}
        if len(kinds) > 1:
            return node.start_mark.line + 1, sorted(kinds)
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [value for _, value in node.value]
    else:
        return None
    for child in children:
        found = _mixed_sequence(child)
        if found is not None:
            return found
    return None


def _yaml_error_text(exc) -> str:
    """PyYAML's error in one line: what it was reading and where it began, then the problem
    and where it was found (a quote left open is found at the end of the file)."""
    parts = []
    for text, mark in ((getattr(exc, 'context', None), getattr(exc, 'context_mark', None)),
                       (getattr(exc, 'problem', None), getattr(exc, 'problem_mark', None))):
        if text:
            at = f'line {mark.line + 1}, column {mark.column + 1}: ' if mark else ''
            parts.append(at + text)
    return '; '.join(parts) or str(exc).splitlines()[0]


def params_file_values(path, node_name: str = NODE_NAME, namespace: str = '/',
                       doc: dict | None = None) -> dict:
    """The flattened ``ros__parameters`` of a parameter file's sections for this node, merged
    in file order (load_params_file); ParameterConfigError when unreadable, not YAML or without
    a section for the node. ``doc``: the file's document when the caller has read it already
    (:func:`read_params_file`), so that it is not parsed again."""
    path = Path(path)
    if doc is None:
        doc = read_params_file(path)
    values: dict = {}
    matched = False
    try:
        sections = list(_node_sections(doc))
    except ParameterConfigError as exc:
        raise ParameterConfigError(f'{path}: {exc}') from None
    for section, params in sections:
        if not _matches(section, node_name, namespace):
            continue
        matched = True
        _flatten('', params, values, str(path))
    if doc and not matched:
        ns = namespace.strip('/')
        fqn = ('/' + ns if ns else '') + '/' + node_name
        raise ParameterConfigError(
            f"{path}: no section for node '{fqn}' (its keys: {', '.join(map(str, doc))}); "
            f"use '/**:' (any node, any namespace) or '{fqn}:' with 'ros__parameters:' under it")
    return values


def _yaml_scalar(value) -> str:
    """A YAML literal that ROS reads back with the same type (doubles always with a '.')."""
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    text = repr(float(value))
    if 'e' in text or 'E' in text:  # PyYAML (YAML 1.1) reads '1e-06' as a string
        text = f'{value:.12f}'.rstrip('0')
        if text.endswith('.'):
            text += '0'
    return text


def _range_text(spec: dict) -> str:
    low, high = spec.get('min'), spec.get('max')
    if low is None and high is None:
        return ''
    return f' [{_yaml_scalar(low) if low is not None else "-inf"}, ' \
           f'{_yaml_scalar(high) if high is not None else "inf"}]'


def render_params_yaml(section_key: str = PARAMS_FILE_KEY) -> str:
    """The text of config/params.yaml: every parameter with its default and a comment.

    ``python -c "from gp_ground_segmentation.ros.config import render_params_yaml as r;
    print(r(), end='')" > config/params.yaml`` regenerates the shipped file.
    """
    lines = [
        '# Parameters of the gp_ground_segmentation node (defaults). Generated by',
        '# gp_ground_segmentation.ros.config.render_params_yaml(); test_config.py checks',
        '# this file lists exactly the declared parameters with their defaults.',
        '# Use:  ros2 run gp_ground_segmentation ground_segmentation_node --ros-args \\',
        '#         -r points:=/velodyne_points --params-file config/params.yaml',
        '# Types are strict (as in rclpy): doubles need a decimal point (80.0, not 80).',
        "# The key '/**' matches the node in any namespace and under any node name.",
        '# Optional QoS overrides of the outputs (keys are the resolved topic names, e.g.',
        '# /seg/ground in namespace /seg), e.g. a best-effort ground cloud:',
        '#   qos_overrides:',
        '#     /ground:',
        '#       publisher: {reliability: best_effort, depth: 1}',
        f"'{section_key}':",
        '  ros__parameters:',
    ]
    sections = [('segmenter (GroundSegmenter / SegmenterParams)', describe_params()),
                ('node only', describe_node_params())]
    for title, rows in sections:
        lines.append(f'    # --- {title} ---')
        for row in rows:
            ro = ', read-only at run time' if row.get('read_only') else ''
            comment = f"{row['description']}; {row['type']}{_range_text(row)}{ro}"
            lines.extend('    # ' + part for part in textwrap.wrap(comment, 94))
            lines.append(f"    {row['name']}: {_yaml_scalar(row['default'])}")
    return '\n'.join(lines) + '\n'


def render_param_overrides(values: dict, header_lines=(),
                           section_key: str = PARAMS_FILE_KEY) -> str:
    """A parameter file with only ``values`` (checked like load_params_file), in the layout of
    config/params.yaml ('/**': the node in any namespace), under a comment header (e.g. what
    a tuner tuned on)."""
    specs = all_param_specs()
    for name, value in values.items():
        check_param_value(name, value, specs)
    lines = ['# ' + part for text in header_lines for part in textwrap.wrap(text, 96)]
    lines += [f"'{section_key}':", '  ros__parameters:' + ('' if values else ' {}')]
    lines += [f'    {name}: {_yaml_scalar(value)}' for name, value in values.items()]
    return '\n'.join(lines) + '\n'


def render_params_table() -> str:
    """A Markdown table of every parameter (docs/parameters.md)."""
    out = ['| parameter | type | default | range | description |', '|---|---|---|---|---|']
    for row in describe_params() + describe_node_params():
        rng = _range_text(row).strip()
        desc = row['description'].replace('|', '\\|')
        if row.get('read_only'):
            desc += ' (read-only at run time)'
        out.append(f"| `{row['name']}` | {row['type']} | `{_yaml_scalar(row['default'])}` | "
                   f'{rng} | {desc} |')
    return '\n'.join(out) + '\n'
