# SPDX-License-Identifier: Apache-2.0
"""ROS 2 node: PointCloud2 on ``points`` -> ground and obstacle PointCloud2 + /diagnostics.

Threading: the subscription callback only puts the newest message into a bounded latest-wins slot
(``collections.deque(maxlen=queue_size)`` under a ``threading.Condition``); when the slot is full
the oldest waiting frame is dropped and counted, never queued. A worker thread takes frames from
the slot, runs ``pipeline.process_cloud`` (decode -> segment -> two byte-exact subsets),
publishes ground and obstacles, then builds and publishes the ground surface cloud (so that
their subscribers do not wait for it). So the executor stays responsive (parameter services,
diagnostics timer) while a frame is being processed. No exception escapes a callback or the
worker: failures are logged on one line (at most once per 5 s per problem, with the count of
suppressed repeats), counted and reported in diagnostics (ERROR with the CloudFormatError text
for bad input), and the node goes on with the next frame. Usable but suspicious input (empty,
no valid point, trailing bytes, empty frame_id, stamp going backwards, field layout changed) is
processed, logged the same way and reported as a diagnostics WARN.

Topics (relative names; remap e.g. ``-r points:=/velodyne_points``):
  points     (sub) sensor_msgs/PointCloud2, qos_profile_sensor_data (best effort, keep last 5):
             a RELIABLE subscriber would receive nothing from best-effort LiDAR drivers.
  ground     (pub) sensor_msgs/PointCloud2, RELIABLE, VOLATILE, keep last 1.
  obstacles  (pub) same QoS as ground.
  ground_surface (pub) same QoS: the GP ground surface, PointCloud2 x, y, z, z_std (FLOAT32, m;
             z = GP mean + ground offset, z_std = std of the latent ground height (GP
             posterior and spread across the segment) without sensor noise; core/surface.py)
             at the bin edges
             of every segment with ground candidates, input header; only while
             ``publish_ground_surface`` is true, and built only while the topic has a
             subscriber (lazy: it costs ~1.4 ms a frame on 124k points in the node).
  /diagnostics (pub) diagnostic_msgs/DiagnosticArray, every diagnostics_period_s.
Output QoS: a RELIABLE publisher matches both RELIABLE subscribers (RViz's and ros2 bag record's
default) and BEST_EFFORT ones, whereas a BEST_EFFORT publisher is invisible to RELIABLE
subscribers; depth 1 keeps the latest-wins rule downstream (a slow subscriber never makes us
buffer old clouds); VOLATILE so no stale cloud is replayed to late joiners. The input and
the three output topics accept ``qos_overrides`` (history, depth, reliability) from the
parameter file; /diagnostics does not.

Parameters: every ``SegmenterParams`` field and the node-only ones of ``config.NODE_PARAMS`` are
declared with a ParameterDescriptor (description with units, numeric range). At start-up an
unknown parameter name, a wrong type or a bad value in the parameter file raises
``ParameterConfigError`` naming it (main() logs it and exits with status 1). At run time
``ros2 param set`` is validated in the on-set callback (a ``SegmenterParams.replace`` candidate,
so cross-field rules apply too) and applied in the post-set callback; the worker switches to the
new segmenter parameters at the start of the next frame, never mid-frame.
"""

from __future__ import annotations

import argparse
import copy
import re
import sys
import threading
import time
from collections import OrderedDict, deque

import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.qos_overriding_options import QoSOverridingOptions
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import PointCloud2

from .cloud import CloudFormatError
from .config import (NODE_NAME, NODE_PARAMS, ParameterConfigError, all_param_specs,
                     check_param_value, is_ros_builtin, params_file_values, params_from_values,
                     qos_override_topics, read_params_file, split_params)
from .diagnostics import ProcessingWindow, diagnostics_array, diagnostics_status
from ..core.allocator import keep_freed_memory
from ..core.params import SegmenterParams
from .pipeline import OUTPUT_SWITCHES, add_surface, process_cloud, warm_up as warm_up_outputs
from .shutdown import QuietShutdown, shutdown_context
from ..core.segmenter import GroundSegmenter
from ..core.sensor_frame import NOT_CENTRED

__all__ = ['GroundSegmentationNode', 'INPUT_TOPIC', 'OUTPUT_QOS', 'OUTPUT_TOPICS', 'main']

INPUT_TOPIC = 'points'  # relative names: remap them
OUTPUT_TOPICS = ('ground', 'obstacles', 'ground_surface')

RCLError = _rclpy.RCLError  # rcl failures, e.g. a parameter file it cannot parse

OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
_LOG_THROTTLE_S = 5.0
_TYPES = {'float': ParameterType.PARAMETER_DOUBLE, 'int': ParameterType.PARAMETER_INTEGER,
          'bool': ParameterType.PARAMETER_BOOL}


def _descriptor(spec: dict) -> ParameterDescriptor:
    """ParameterDescriptor with description (units), type and the range from the spec."""
    desc = ParameterDescriptor(name=spec['name'], type=_TYPES[spec['type']],
                               description=spec['description'],
                               read_only=bool(spec.get('read_only', False)))
    low, high = spec.get('min'), spec.get('max')
    if spec['type'] == 'float' and low is not None and high is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(low),
                                                        to_value=float(high), step=0.0)]
    elif spec['type'] == 'int' and low is not None and high is not None:
        desc.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    return desc


def _layout_of(msg) -> tuple:
    """What must stay the same between frames of one stream: fields, point_step, byte order."""
    return (tuple((f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields),
            int(msg.point_step), bool(msg.is_bigendian))


def _layout_text(layout: tuple) -> str:
    fields, step, big = layout
    return (' '.join(f'{n}@{o}:{d}x{c}' for n, o, d, c in fields)
            + f' step {step}' + (' big-endian' if big else ''))


def _stamp_s(msg) -> float:
    stamp = msg.header.stamp
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def _problem_key(text: str) -> str:
    """Throttling key of a log line: its text with the numbers blanked, so the same problem
    (e.g. 'data has 793 bytes but ... 800 required') is one key whatever the sizes."""
    return re.sub(r'[-+]?\d[\d.e+-]*', '#', text)


def _one_line(text: str, limit: int = 300) -> str:
    text = ' '.join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + '...'


class GroundSegmentationNode(Node):
    """Ground/obstacle split of LiDAR clouds with a Gaussian-process ground model."""

    def __init__(self, segmenter_factory=GroundSegmenter, announce: bool = True, **node_kwargs):
        """``segmenter_factory(params) -> segmenter`` (default GroundSegmenter); ``node_kwargs``
        go to rclpy Node (context, cli_args, parameter_overrides, namespace, ...). ``announce``:
        log the 'listening on' line now (main() does it itself once its checks passed)."""
        super().__init__(NODE_NAME, **node_kwargs)
        self._segmenter_factory = segmenter_factory
        self._worker = None
        # set once the worker thread has warmed the segmenter and the output pass up (or
        # failed to): frames that arrived before wait in the slot meanwhile
        self.warmed_up = threading.Event()
        self._stopping = False
        self._destroyed = False
        # Per-problem log throttling: key -> [last log time (monotonic s), suppressed count].
        self._log_lock = threading.Lock()
        self._log_times = OrderedDict()
        self._last_layout = None  # layout of the last processed frame
        self._last_stamp = None  # header stamp (s) of the last processed frame
        self._centring_logged = False  # 'not sensor-centred' is logged once per process
        try:
            self._setup()
        except BaseException:
            self._stop_worker()
            super().destroy_node()
            raise
        if announce:
            self.announce()

    # --- construction ----------------------------------------------------------------------
    def _check_overrides(self) -> None:
        """Fail fast on a parameter file/override naming an unknown key or giving a bad value.

        rclpy silently ignores overrides for parameters that are never declared; a typo in the
        YAML would then leave a default in force unnoticed, so it is an error here.
        """
        for name, param in sorted(self._parameter_overrides.items()):
            if is_ros_builtin(name):
                continue
            check_param_value(name, param.value, self._specs)

    def _setup(self) -> None:
        self._specs = all_param_specs()
        self._check_overrides()
        for name, spec in self._specs.items():
            self.declare_parameter(name, spec['default'], _descriptor(spec))
        values = {name: self.get_parameter(name).value for name in self._specs}
        seg_values, node_values = split_params(values)
        try:
            self._declared_params = SegmenterParams(**seg_values).validate()
        except ValueError as exc:
            raise ParameterConfigError(str(exc)) from None
        self._budget_ms = float(node_values['processing_budget_ms'])
        self._diag_period_s = float(node_values['diagnostics_period_s'])
        queue_size = int(node_values['queue_size'])
        self._outputs = {name: bool(node_values[name]) for name in OUTPUT_SWITCHES}

        self.window = ProcessingWindow(int(node_values['diagnostics_window']))
        self._segmenter = self._segmenter_factory(self._declared_params)
        self._pending_params = None
        self._cond = threading.Condition()
        self._slot = deque(maxlen=queue_size)

        # Each endpoint gets its own copy of its profile: with qos_overriding_options rclpy
        # writes the overrides into the profile object it is given, so a shared module-level
        # profile would carry a '/ground' override over to '/obstacles' (and to rclpy's
        # global qos_profile_sensor_data).
        self._pub_ground, self._pub_obstacles, self._pub_surface = (
            self.create_publisher(
                PointCloud2, topic, copy.copy(OUTPUT_QOS),
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            for topic in OUTPUT_TOPICS)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self._sub = self.create_subscription(
            PointCloud2, INPUT_TOPIC, self._on_cloud, copy.copy(qos_profile_sensor_data),
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self._diag_timer = self.create_timer(self._diag_period_s, self._on_diag_timer)

        self.add_on_set_parameters_callback(self._validate_params)
        self.add_post_set_parameters_callback(self._apply_params)

        self._worker = threading.Thread(target=self._worker_loop, name='ground_seg_worker',
                                        daemon=True)
        self._worker.start()

    def announce(self) -> None:
        """Log the one 'listening on' line: topics, slot size and budget."""
        self.get_logger().info(
            f"listening on '{self._sub.topic_name}', publishing '{self._pub_ground.topic_name}',"
            f" '{self._pub_obstacles.topic_name}' and '{self._pub_surface.topic_name}' (slot "
            f'{self._slot.maxlen}, budget {self._budget_ms:g} ms)')

    # --- public state (read-only views, for tests and tools) --------------------------------
    @property
    def segmenter_params(self) -> SegmenterParams:
        """Parameters of the segmenter the worker is using now."""
        return self._segmenter.params

    @property
    def segmenter(self):
        """The segmenter object the worker uses (read it, do not call it from other threads)."""
        return self._segmenter

    @property
    def topic_names(self) -> tuple:
        """Resolved names of the input and the three output topics (the ones that take
        ``qos_overrides``), after remapping and namespace."""
        return (self._sub.topic_name, self._pub_ground.topic_name,
                self._pub_obstacles.topic_name, self._pub_surface.topic_name)

    @property
    def declared_params(self) -> SegmenterParams:
        """Segmenter parameters as last set (applied by the worker from the next frame on)."""
        return self._declared_params

    # --- subscription: hand over only ------------------------------------------------------
    def _on_cloud(self, msg) -> None:
        try:
            self.window.record_received(getattr(getattr(msg, 'header', None), 'frame_id', None))
            with self._cond:
                if len(self._slot) == self._slot.maxlen:
                    self.window.record_dropped(1)  # deque(maxlen) evicts the oldest on append
                self._slot.append((msg, time.perf_counter()))
                self._cond.notify()
            # Hand the GIL to the woken worker now: otherwise it waits until this executor
            # thread blocks in its next wait (its Python bookkeeping after the callback)
            time.sleep(0)
        except Exception as exc:  # never let an exception out of an executor callback
            self.get_logger().error(f'cloud callback failed: {_one_line(exc)}',
                                    throttle_duration_sec=_LOG_THROTTLE_S)

    # --- worker thread ---------------------------------------------------------------------
    def _worker_loop(self) -> None:
        warm_up = getattr(self._segmenter, 'warm_up', None)
        try:
            if warm_up is not None:
                warm_up()  # load the compiled GP kernel before the first cloud arrives
        except Exception as exc:  # noqa: BLE001 - the segmenter now uses numpy; say so once
            self.get_logger().warning(f'compiled GP kernel unavailable, using numpy: {exc}')
        try:
            warm_up_outputs()  # queue the output clouds' compiled pass, after the segmenter's
        except Exception as exc:  # noqa: BLE001 - its numpy twin builds the same clouds
            self.get_logger().warning(f'output clouds pass unavailable, using numpy: {exc}')
        self.warmed_up.set()
        while True:
            with self._cond:
                while not self._slot and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                msg, received_at = self._slot.popleft()
                pending, self._pending_params = self._pending_params, None
            try:
                if pending is not None:
                    self._switch_segmenter(pending)
                self._process(msg, received_at)
            except Exception as exc:  # last line of defence: the worker must keep running
                self.window.record_failure(_one_line(f'{type(exc).__name__}: {exc}'), False)

    def _switch_segmenter(self, params: SegmenterParams) -> None:
        """Between frames: keep the segmenter (and its warm-started theta) when it can take new
        parameters (GroundSegmenter.set_params clips theta to the new bounds), else rebuild."""
        try:
            if hasattr(self._segmenter, 'set_params'):
                self._segmenter.set_params(params)
            else:
                self._segmenter = self._segmenter_factory(params)
        except Exception as exc:  # keep the old segmenter rather than stop processing
            self.window.record_failure(f'cannot apply new parameters: {_one_line(exc)}', False)
            self.get_logger().error(f'cannot apply new parameters: {_one_line(exc)}',
                                    throttle_duration_sec=_LOG_THROTTLE_S)

    def _log_throttled(self, level: str, text: str) -> None:
        """Log ``text`` (one line) at most once per _LOG_THROTTLE_S per problem (text with the
        numbers blanked), so a stream of bad clouds gives one line per problem, not a flood,
        while a different problem is still reported at once. Says how many were suppressed."""
        key = _problem_key(text)
        now = time.monotonic()
        with self._log_lock:
            entry = self._log_times.get(key)
            if entry is not None and now - entry[0] < _LOG_THROTTLE_S:
                entry[1] += 1
                return
            suppressed = entry[1] if entry is not None else 0
            self._log_times[key] = [now, 0]
            self._log_times.move_to_end(key)
            while len(self._log_times) > 256:  # bounded: distinct problems are few
                self._log_times.popitem(last=False)
        if suppressed:
            text += f' ({suppressed} more like this in the last {_LOG_THROTTLE_S:g} s)'
        # One call site per severity: rclpy's logger remembers the severity of each call site
        # and raises ValueError if one line logs at two severities.
        try:
            if level == 'error':
                self.get_logger().error(text)
            else:
                self.get_logger().warning(text)
        except Exception:  # logging must never take the worker down
            pass

    def _stream_warnings(self, msg) -> list:
        """Input problems only visible across frames or in the header (cloud itself usable)."""
        notes = []
        if not msg.header.frame_id:
            notes.append('empty header.frame_id (the cloud cannot be placed in TF)')
        stamp = _stamp_s(msg)
        if self._last_stamp is not None and stamp < self._last_stamp:
            notes.append(f'header stamp went backwards by {self._last_stamp - stamp:.3f} s '
                         f'(clock jump or bag loop?)')
        layout = _layout_of(msg)
        if self._last_layout is not None and layout != self._last_layout:
            notes.append(f'field layout changed from [{_layout_text(self._last_layout)}] to '
                         f'[{_layout_text(layout)}] (two publishers on the topic?)')
        return notes

    def _process(self, msg, received_at: float) -> None:
        """One frame: process, publish, record. ``received_at``: perf_counter() when the
        subscription callback put it into the slot (its wait there is the ``handoff`` time)."""
        frame_id = None
        try:
            frame_id = msg.header.frame_id
            handoff_ms = (time.perf_counter() - received_at) * 1e3
            outputs = dict(self._outputs)
            # Lazy, as image_transport's publishers: the surface cloud costs ~1.4 ms per frame
            # on 124k points (bench_node.py), spent only while someone subscribes to it, and
            # after ground and obstacles are published (add_surface below).
            surface_wanted = (outputs.pop('publish_ground_surface')
                              and self._pub_surface.get_subscription_count() > 0)
            out = process_cloud(msg, self._segmenter, publish_ground_surface=False, **outputs)
            notes = list(out.warnings)
            try:
                notes += self._stream_warnings(msg)
                self._last_stamp, self._last_layout = _stamp_s(msg), _layout_of(msg)
            except Exception as exc:  # a check must never cost the frame
                notes.append(f'input check failed: {_one_line(exc)}')
            t_publish = time.perf_counter()
            self._pub_ground.publish(out.ground)
            self._pub_obstacles.publish(out.obstacles)
            t_published = time.perf_counter()
            publish_ms = (t_published - t_publish) * 1e3
            # the latency their subscribers see: callback to ground and obstacles published
            ground_published_ms = (t_published - received_at) * 1e3
            if surface_wanted:
                add_surface(out, msg)  # its time counts in encode and total, as before
                if out.surface is not None:
                    t_publish = time.perf_counter()
                    self._pub_surface.publish(out.surface)
                    publish_ms += (time.perf_counter() - t_publish) * 1e3
            self.window.record_frame(out, frame_id, notes,
                                     {'handoff': handoff_ms, 'publish': publish_ms,
                                      'ground_published': ground_published_ms})
            for note in notes:
                if note.startswith(NOT_CENTRED):
                    if self._centring_logged:  # a property of the set-up: say it once
                        continue
                    self._centring_logged = True
                self._log_throttled('warning',
                                    f"suspicious input cloud (frame_id '{frame_id}'): {note}")
        except CloudFormatError as exc:
            text = _one_line(exc)
            self.window.record_failure(text, True, frame_id)
            self._log_throttled('warning', f"bad input cloud (frame_id '{frame_id}'), "
                                f'dropped: {text}')
        except Exception as exc:
            text = _one_line(f'{type(exc).__name__}: {exc}')
            self.window.record_failure(text, False, frame_id)
            if not self._stopping:
                self._log_throttled('error', f'frame processing failed: {text}')

    # --- diagnostics -----------------------------------------------------------------------
    def _on_diag_timer(self) -> None:
        try:
            stale = max(5.0, 3.0 * self._diag_period_s)
            status = diagnostics_status(self.window, budget_ms=self._budget_ms,
                                        stale_after_s=stale)
            self._pub_diag.publish(diagnostics_array([status],
                                                     self.get_clock().now().to_msg()))
        except Exception as exc:
            self.get_logger().error(f'diagnostics failed: {_one_line(exc)}',
                                    throttle_duration_sec=_LOG_THROTTLE_S)

    # --- parameters ------------------------------------------------------------------------
    def _split_changes(self, params):
        seg, node = {}, {}
        for p in params:
            if p.name in NODE_PARAMS:
                node[p.name] = p.value
            elif p.name in self._specs:
                seg[p.name] = p.value
        return seg, node

    def _validate_params(self, params) -> SetParametersResult:
        """On-set: validate only (names we do not own are accepted, as rclpy recommends)."""
        try:
            seg, node = self._split_changes(params)
            for name, value in list(seg.items()) + list(node.items()):
                check_param_value(name, value, self._specs)
            if seg:
                self._declared_params.replace(**seg)
            return SetParametersResult(successful=True)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=_one_line(exc))
        except Exception as exc:
            return SetParametersResult(successful=False,
                                       reason=_one_line(f'{type(exc).__name__}: {exc}'))

    def _apply_params(self, params) -> None:
        """Post-set: apply. The worker picks up segmenter changes at the next frame."""
        try:
            seg, node = self._split_changes(params)
            if seg:
                self._declared_params = self._declared_params.replace(**seg)
                with self._cond:
                    self._pending_params = self._declared_params
            # a new dict, not an update: the worker reads the old one whole or the new one
            self._outputs = dict(self._outputs, **{name: bool(node[name])
                                                   for name in OUTPUT_SWITCHES if name in node})
            if 'processing_budget_ms' in node:
                self._budget_ms = float(node['processing_budget_ms'])
            if 'diagnostics_window' in node:
                self.window.resize(int(node['diagnostics_window']))
            if 'diagnostics_period_s' in node:
                self._diag_period_s = float(node['diagnostics_period_s'])
                self.destroy_timer(self._diag_timer)
                self._diag_timer = self.create_timer(self._diag_period_s, self._on_diag_timer)
        except Exception as exc:
            self.get_logger().error(f'applying parameters failed: {_one_line(exc)}')

    # --- shutdown --------------------------------------------------------------------------
    def _stop_worker(self, timeout_s: float = 30.0) -> None:
        self._stopping = True
        cond = getattr(self, '_cond', None)
        if cond is not None:
            with cond:
                cond.notify_all()
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout_s)
            if self._worker.is_alive():
                self.get_logger().warning(f'worker thread did not stop within {timeout_s} s')

    def destroy_node(self):
        """Stop and join the worker (it finishes the frame in progress), then destroy."""
        if self._destroyed:
            return
        self._destroyed = True
        self._stop_worker()
        super().destroy_node()


USAGE = """ground_segmentation_node [--help] [--ros-args ...]

Ground/obstacle split of LiDAR point clouds with a Gaussian-process ground model (ROS 2 node).

Topics (relative names): points (sub, PointCloud2, sensor-data QoS), ground and obstacles (pub,
PointCloud2), ground_surface (pub, PointCloud2 x, y, z, z_std, while subscribed),
/diagnostics. The clouds must be in the sensor's frame, or give its pose with the
sensor_* parameters (README "Frames"). Large clouds (~2 MB) from another process need
Fast DDS's shared-memory profile in the publisher's environment (and the node's):
  export FASTRTPS_DEFAULT_PROFILES_FILE=<config>/fastdds_large_shm.xml
(<config>: config/ of the source tree, share/gp_ground_segmentation/config/ of an install).

Examples:
  ground_segmentation_node --ros-args -r points:=/velodyne_points --params-file params.yaml
  ground_segmentation_node --ros-args -r __ns:=/seg -r points:=/ouster/points
  ros2 launch gp_ground_segmentation ground_segmentation.launch.py points:=/velodyne_points
"""


def _split_command_line(args: list) -> tuple[list, list]:
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


def _check_params_file_sections(path: str, doc: dict, node) -> None:
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


def main(args=None):
    """Entry point of ``ros2 run gp_ground_segmentation ground_segmentation_node``."""
    argv = list(sys.argv if args is None else args)
    parser = argparse.ArgumentParser(prog='ground_segmentation_node', usage=USAGE,
                                     add_help=True)
    plain_args, params_files = _split_command_line(argv[1:])
    _, unknown = parser.parse_known_args(plain_args)  # --help prints the usage and exits here
    if unknown:  # e.g. '--params-file x' without --ros-args: rcl would ignore it silently
        parser.error(f"unrecognized arguments: {' '.join(unknown)} (ROS arguments such as "
                     '--params-file, -p and -r go after --ros-args)')
    logger = rclpy.logging.get_logger(NODE_NAME)
    # the process is the node's: keep each frame's freed memory for the next frame (about
    # half of segment()'s time went to page faults without it; core/allocator.py)
    allocator_note = keep_freed_memory()
    if allocator_note is not None:
        logger.info(allocator_note)
    quiet = QuietShutdown()
    quiet.install()
    node = None
    exit_code = 0
    try:
        # read before rcl, which reports an unreadable file in a traceback and one that is not
        # YAML in two lines naming its C sources; the documents serve the checks below
        documents = [(path, read_params_file(path)) for path in params_files]
        rclpy.init(args=argv)
        # The executor exists before the node announces itself, so a Ctrl-C right after the
        # 'listening' line never lands inside executor construction (an rclpy 7.1 __del__ race).
        executor = SingleThreadedExecutor()
        node = GroundSegmentationNode(announce=False)
        for path, doc in documents:
            _check_params_file_sections(path, doc, node)
        node.announce()  # after the checks: a refused file gives FATAL, not 'listening' first
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParameterConfigError, ParameterException, RCLError) as exc:
        logger.fatal(f'invalid parameters: {_one_line(exc, 1000)}')
        exit_code = 1
    finally:
        quiet.ignore_signals()  # from here on a signal must not interrupt the clean-up
        if node is not None:
            node.destroy_node()
        shutdown_context()
        quiet.ignore_signals()  # rclpy restores the handlers it replaced when it shuts down
    if exit_code:
        sys.exit(exit_code)


if __name__ == '__main__':
    main()
