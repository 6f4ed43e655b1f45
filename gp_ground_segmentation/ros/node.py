# SPDX-License-Identifier: Apache-2.0
"""ROS 2 node: PointCloud2 on ``points`` -> ground, obstacle, labelled PointCloud2, /diagnostics.

Two variants share every line of the processing (``SegmentationNodeBase``): the plain
``GroundSegmentationNode`` below, which starts processing when it is constructed, and the
managed ``lifecycle.GroundSegmentationLifecycleNode`` (configure / activate / deactivate /
cleanup / shutdown, for Nav2-style bring-up).

Threading: the subscription callback only puts the newest message into a bounded latest-wins
slot (``collections.deque(maxlen=queue_size)`` under a ``threading.Condition``); when the slot is
full the oldest waiting frame is dropped and counted, never queued. A worker thread takes frames
from the slot, runs ``pipeline.process_cloud`` (decode -> segment -> two byte-exact subsets),
publishes ground and obstacles, then builds and publishes the labelled cloud and the ground
surface cloud (so that the subscribers of ground and obstacles do not wait for them). So the
executor stays responsive (parameter services, diagnostics timer) while a frame is being
processed. No exception escapes a callback or the worker: failures are logged on one line (at
most once per 5 s per problem, with the count of suppressed repeats), counted and reported in
diagnostics (ERROR with the CloudFormatError text for bad input), and the node goes on with the
next frame. Usable but suspicious input (empty, no valid point, trailing bytes, empty frame_id,
stamp going backwards, field layout changed, no IMU sample near the stamp) is processed, logged
the same way and reported as a diagnostics WARN.

Topics (relative names; remap e.g. ``-r points:=/velodyne_points``):
  points     (sub) sensor_msgs/PointCloud2, qos_profile_sensor_data (best effort, keep last 5):
             a RELIABLE subscriber would receive nothing from best-effort LiDAR drivers.
  ground     (pub) sensor_msgs/PointCloud2, RELIABLE, VOLATILE, keep last 1.
  obstacles  (pub) same QoS as ground.
  labeled    (pub) same QoS: one row per valid input point, in input order, every input byte
             plus ``ground`` (UINT8, 1 = ground) and ``height_above_ground`` (FLOAT32, m;
             labels.py), input header; built only while the topic has a subscriber (1.9 ms
             median a frame on 124k points in the node; bench_node.py --labeled).
  ground_surface (pub) same QoS: the GP ground surface, PointCloud2 x, y, z, z_std (FLOAT32, m;
             z = GP mean + ground offset, z_std = std of the latent ground height (GP
             posterior and spread across the segment) without sensor noise; core/surface.py)
             at the bin edges
             of every segment with ground candidates, input header; only while
             ``publish_ground_surface`` is true, and built only while the topic has a
             subscriber (lazy: it costs ~1.4 ms a frame on 124k points in the node).
  imu_topic  (sub, only when the parameter is set) sensor_msgs/Imu, sensor-data QoS: each
             cloud is levelled with the roll and pitch of the IMU sample nearest its header
             stamp (imu.py), or with the static sensor_roll_rad/sensor_pitch_rad and a
             diagnostics WARN giving the age when no sample lies within imu_max_age_s.
  /diagnostics (pub) diagnostic_msgs/DiagnosticArray, every diagnostics_period_s.
Output QoS: a RELIABLE publisher matches both RELIABLE subscribers (RViz's and ros2 bag record's
default) and BEST_EFFORT ones, whereas a BEST_EFFORT publisher is invisible to RELIABLE
subscribers; depth 1 keeps the latest-wins rule downstream (a slow subscriber never makes us
buffer old clouds); VOLATILE so no stale cloud is replayed to late joiners. The input and
the four output topics accept ``qos_overrides`` (history, depth, reliability) from the
parameter file; /diagnostics does not.

Parameters: every ``SegmenterParams`` field and the node-only ones of ``config.NODE_PARAMS`` are
declared with a ParameterDescriptor (description with units, numeric range). At start-up an
unknown parameter name, a wrong type or a bad value in the parameter file raises
``ParameterConfigError`` naming it (main() logs it and exits with status 1). At run time
``ros2 param set`` is validated in the on-set callback (a ``SegmenterParams`` candidate, so
cross-field rules apply too) and applied in the post-set callback; the worker switches to the
new segmenter parameters at the start of the next frame, never mid-frame.
"""

from __future__ import annotations

import copy
import re
import threading
import time
from collections import OrderedDict, deque

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.qos_overriding_options import QoSOverridingOptions
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Imu, PointCloud2

from .cloud import CloudFormatError
from .config import (NODE_NAME, NODE_PARAMS, ParameterConfigError, all_param_specs,
                     check_param_value, is_ros_builtin, split_params)
from .diagnostics import ProcessingWindow, diagnostics_array, diagnostics_status
from .entry import one_line as _one_line, run_node
from .imu import GravityTracker, frame_pose, stamp_seconds, tracker_settings
from ..core.params import SegmenterParams
from .pipeline import (OUTPUT_SWITCHES, add_labeled, add_surface, process_cloud,
                       warm_up as warm_up_outputs)
from ..core.segmenter import GroundSegmenter
from ..core.sensor_frame import NOT_CENTRED

__all__ = ['GroundSegmentationNode', 'SegmentationNodeBase', 'INPUT_TOPIC', 'OUTPUT_QOS',
           'OUTPUT_TOPICS', 'IMU_PARAMS', 'main']

INPUT_TOPIC = 'points'  # relative names: remap them
OUTPUT_TOPICS = ('ground', 'obstacles', 'ground_surface', 'labeled')
# node parameters that set the gravity tracker (imu.GravityTracker), imu_topic aside
IMU_PARAMS = ('imu_max_age_s', 'imu_lidar_roll_rad', 'imu_lidar_pitch_rad', 'imu_lidar_yaw_rad',
              'imu_accel_time_constant_s')

OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
_LOG_THROTTLE_S = 5.0
_TYPES = {'float': ParameterType.PARAMETER_DOUBLE, 'int': ParameterType.PARAMETER_INTEGER,
          'bool': ParameterType.PARAMETER_BOOL, 'str': ParameterType.PARAMETER_STRING}


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


def _problem_key(text: str) -> str:
    """Throttling key of a log line: its text with the numbers blanked, so the same problem
    (e.g. 'data has 793 bytes but ... 800 required') is one key whatever the sizes."""
    return re.sub(r'[-+]?\d[\d.e+-]*', '#', text)


class SegmentationNodeBase:
    """The processing both node variants share; mixed into an rclpy ``Node`` (or
    ``LifecycleNode``), which the subclass constructs first.

    Life cycle of the processing: ``_declare_parameters`` (once, in the constructor), then
    ``_configure`` (reads and validates the parameters, creates the publishers, subscriptions,
    timer and worker thread), ``accepting`` frames on and off, and ``_release`` (stops the worker,
    destroys what ``_configure`` created). A variant chooses its publisher class with
    ``_make_publisher`` / ``_drop_publisher`` (lifecycle publishers publish only while active).
    """

    def _init_state(self, segmenter_factory) -> None:
        """The attributes every method may read, before anything is created."""
        self._segmenter_factory = segmenter_factory
        self._worker = None
        # set once the worker thread has warmed the segmenter and the output pass up (or
        # failed to): frames that arrived before wait in the slot meanwhile
        self.warmed_up = threading.Event()
        self._stopping = False
        self._destroyed = False
        self._configured = False
        self.accepting = False  # frames are processed only while True (lifecycle: active)
        self._declared_params = None
        self._created = []  # (kind, entity) made by _configure, destroyed by _release
        # Per-problem log throttling: key -> [last log time (monotonic s), suppressed count].
        self._log_lock = threading.Lock()
        self._log_times = OrderedDict()
        self._gravity = None  # imu.GravityTracker while imu_topic is set
        self._imu_sub = None
        self._last_imu_pose = None  # imu.ImuPose of the last frame
        self.frames_while_inactive = 0  # clouds received while not accepting (not processed)
        self._last_layout = None  # layout of the last processed frame
        self._last_stamp = None  # header stamp (s) of the last processed frame
        self._centring_logged = False  # 'not sensor-centred' is logged once per process

    # --- construction ----------------------------------------------------------------------
    def _declare_parameters(self) -> None:
        """Declare every parameter (with its descriptor) and the on-set / post-set callbacks.

        A parameter file or override naming an unknown key or giving a bad value fails here:
        rclpy silently ignores overrides for parameters that are never declared, and a typo in
        the YAML would then leave a default in force unnoticed.
        """
        self._specs = all_param_specs()
        for name, param in sorted(self._parameter_overrides.items()):
            if not is_ros_builtin(name):
                check_param_value(name, param.value, self._specs)
        for name, spec in self._specs.items():
            self.declare_parameter(name, spec['default'], _descriptor(spec))
        self.add_on_set_parameters_callback(self._validate_params)
        self.add_post_set_parameters_callback(self._apply_params)

    def _read_parameters(self) -> dict:
        """The node-only values of the declared parameters; sets ``_declared_params`` (the
        validated SegmenterParams). ParameterConfigError naming a cross-field problem."""
        values = {name: self.get_parameter(name).value for name in self._specs}
        seg_values, node_values = split_params(values)
        try:
            self._declared_params = SegmenterParams(**seg_values).validate()
        except ValueError as exc:
            raise ParameterConfigError(str(exc)) from None
        return node_values

    def _configure(self) -> None:
        """Read and validate the parameters, create every endpoint and start the worker. On
        failure what was created is released again and the error raised."""
        try:
            node_values = self._read_parameters()
            self._budget_ms = float(node_values['processing_budget_ms'])
            self._diag_period_s = float(node_values['diagnostics_period_s'])
            self._outputs = {name: bool(node_values[name]) for name in OUTPUT_SWITCHES}
            self.window = ProcessingWindow(int(node_values['diagnostics_window']))
            self._segmenter = self._segmenter_factory(self._declared_params)
            self._static_params = self._declared_params  # the worker's, without the IMU pose
            self._pending_params = None
            self._last_stamp = self._last_layout = None  # a new stream for the input checks
            self._cond = threading.Condition()
            self._slot = deque(maxlen=int(node_values['queue_size']))
            self._create_endpoints(node_values)
            self._stopping = False
            self.warmed_up.clear()
            self._worker = threading.Thread(target=self._worker_loop, name='ground_seg_worker',
                                            daemon=True)
            self._worker.start()
            self._configured = True
        except BaseException:
            self._release()
            raise

    def _create_endpoints(self, node_values: dict) -> None:
        """Publishers, subscriptions (points; imu_topic when set) and the diagnostics timer."""
        # Each endpoint gets its own copy of its profile: with qos_overriding_options rclpy
        # writes the overrides into the profile object it is given, so a shared module-level
        # profile would carry a '/ground' override over to '/obstacles' (and to rclpy's
        # global qos_profile_sensor_data).
        self._pub_ground, self._pub_obstacles, self._pub_surface, self._pub_labeled = (
            self._make_publisher(
                PointCloud2, topic, copy.copy(OUTPUT_QOS),
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            for topic in OUTPUT_TOPICS)
        self._pub_diag = self._make_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self._sub = self._keep('subscription', self.create_subscription(
            PointCloud2, INPUT_TOPIC, self._on_cloud, copy.copy(qos_profile_sensor_data),
            qos_overriding_options=QoSOverridingOptions.with_default_policies()))
        self._imu_sub = None
        topic = node_values['imu_topic']
        if topic:
            self._gravity = GravityTracker()
            self._configure_gravity(node_values)
            try:
                self._imu_sub = self._keep('subscription', self.create_subscription(
                    Imu, topic, self._on_imu, copy.copy(qos_profile_sensor_data)))
            except Exception as exc:  # e.g. InvalidTopicNameException
                raise ParameterConfigError(f"parameter 'imu_topic': {_one_line(exc)}") from None
        self._diag_timer = self._keep('timer', self.create_timer(self._diag_period_s,
                                                                 self._on_diag_timer))

    def _configure_gravity(self, node_values: dict) -> None:
        self._gravity.configure(**tracker_settings(node_values))

    def _make_publisher(self, msg_type, topic, qos, **kwargs):
        """A publisher that ``_release`` destroys (the lifecycle variant makes lifecycle ones)."""
        return self._keep('publisher', self.create_publisher(msg_type, topic, qos, **kwargs))

    def _drop_publisher(self, publisher) -> None:
        self.destroy_publisher(publisher)

    def _keep(self, kind: str, entity):
        self._created.append((kind, entity))
        return entity

    def _release(self) -> None:
        """Stop and join the worker (it finishes the frame in progress), then destroy every
        endpoint ``_configure`` created. The parameters stay declared."""
        self.accepting = False
        self._stop_worker()
        self._configured = False
        created, self._created = self._created, []
        for kind, entity in reversed(created):
            try:
                if kind == 'publisher':
                    self._drop_publisher(entity)
                elif kind == 'subscription':
                    self.destroy_subscription(entity)
                else:
                    self.destroy_timer(entity)
            except Exception as exc:  # release the rest all the same
                self.get_logger().warning(f'could not destroy a {kind}: {_one_line(exc)}')
        self._gravity = self._imu_sub = None
        self._last_imu_pose = None

    def log_started(self) -> None:
        """The line main() logs once the node is up and its parameter files are checked."""
        self.announce()

    def announce(self) -> None:
        """Log the one 'listening on' line: topics, slot size and budget."""
        imu = f", IMU '{self._imu_sub.topic_name}'" if self._imu_sub is not None else ''
        self.get_logger().info(
            f"listening on '{self._sub.topic_name}'{imu}, publishing "
            f"'{self._pub_ground.topic_name}', '{self._pub_obstacles.topic_name}', "
            f"'{self._pub_labeled.topic_name}' and '{self._pub_surface.topic_name}' (slot "
            f'{self._slot.maxlen}, budget {self._budget_ms:g} ms)')

    # --- public state (read-only views, for tests and tools) --------------------------------
    @property
    def segmenter_params(self) -> SegmenterParams:
        """Parameters of the segmenter the worker is using now (with the last frame's IMU
        roll and pitch when imu_topic is set)."""
        return self._segmenter.params

    @property
    def segmenter(self):
        """The segmenter object the worker uses (read it, do not call it from other threads)."""
        return self._segmenter

    @property
    def topic_names(self) -> tuple:
        """Resolved names of the input and the four output topics (the ones that take
        ``qos_overrides``), after remapping and namespace."""
        return tuple(self.resolve_topic_name(topic) for topic in (INPUT_TOPIC,) + OUTPUT_TOPICS)

    @property
    def declared_params(self) -> SegmenterParams:
        """Segmenter parameters as last set (applied by the worker from the next frame on);
        None before the parameters were first read (a lifecycle node before configure)."""
        return self._declared_params

    @property
    def gravity(self):
        """The imu.GravityTracker fed by imu_topic (None without it): read, do not add."""
        return self._gravity

    @property
    def last_imu_pose(self):
        """imu.ImuPose of the last processed frame (None without imu_topic or before a frame)."""
        return self._last_imu_pose

    # --- subscriptions: hand over only -----------------------------------------------------
    def _on_cloud(self, msg) -> None:
        try:
            if not self.accepting:
                self.frames_while_inactive += 1
                return
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

    def _on_imu(self, msg) -> None:
        try:
            gravity = self._gravity
            if gravity is not None:
                gravity.add_message(msg)
        except Exception as exc:  # a malformed sample must not stop the executor
            self._log_throttled('warning', f'IMU sample ignored: {_one_line(exc)}')

    def discard_waiting_frames(self) -> int:
        """Drop (and count as dropped) the frames waiting in the slot; their number."""
        with self._cond:
            count = len(self._slot)
            self._slot.clear()
        if count:
            self.window.record_dropped(count)
        return count

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
        """Between frames: use new parameters (see :meth:`_use_params`); they are the static
        ones from now on (the IMU replaces only roll and pitch, per frame)."""
        try:
            self._use_params(params)
            self._static_params = params
        except Exception as exc:  # keep the old segmenter rather than stop processing
            self.window.record_failure(f'cannot apply new parameters: {_one_line(exc)}', False)
            self.get_logger().error(f'cannot apply new parameters: {_one_line(exc)}',
                                    throttle_duration_sec=_LOG_THROTTLE_S)

    def _use_params(self, params: SegmenterParams) -> None:
        """Keep the segmenter (and its warm-started theta) when it can take new parameters
        (GroundSegmenter.set_params clips theta to the new bounds), else rebuild it."""
        if hasattr(self._segmenter, 'set_params'):
            self._segmenter.set_params(params)
        else:
            self._segmenter = self._segmenter_factory(params)

    def _level_with_imu(self, msg):
        """With imu_topic set: give the segmenter this frame's roll and pitch from the IMU
        sample nearest the cloud's stamp (or the static ones); the one-line note when the
        static pose is used, else None. Without imu_topic: nothing, None."""
        gravity = self._gravity
        if gravity is None:
            return None
        static = self._static_params
        try:
            pose, params = frame_pose(gravity, static, msg.header.stamp)
            if params != self._segmenter.params:
                self._use_params(params)
        except Exception as exc:  # the IMU must never cost the frame: the static pose
            if self._segmenter.params != static:
                self._use_params(static)
            self._last_imu_pose = None
            return f'IMU pose failed ({_one_line(exc)}): the static pose is used'
        self._last_imu_pose = pose
        return pose.note

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
        """Input problems only visible across frames or in the header (cloud itself usable);
        a check that fails is a note too (it must never cost the frame)."""
        notes = []
        try:
            if not msg.header.frame_id:
                notes.append('empty header.frame_id (the cloud cannot be placed in TF)')
            stamp = stamp_seconds(msg.header.stamp)
            if self._last_stamp is not None and stamp < self._last_stamp:
                notes.append(f'header stamp went backwards by {self._last_stamp - stamp:.3f} s '
                             f'(clock jump or bag loop?)')
            layout = _layout_of(msg)
            if self._last_layout is not None and layout != self._last_layout:
                notes.append(f'field layout changed from [{_layout_text(self._last_layout)}] '
                             f'to [{_layout_text(layout)}] (two publishers on the topic?)')
            self._last_stamp, self._last_layout = stamp, layout
        except Exception as exc:
            notes.append(f'input check failed: {_one_line(exc)}')
        return notes

    def _lazy_outputs(self, surface_on: bool) -> list:
        """(publisher, builder, FrameOutput attribute) of the outputs built after ground and
        obstacles, only while someone subscribes, as image_transport's publishers: the
        labelled cloud (~1.9 ms per frame on 124k points) and the surface cloud (~1.4 ms;
        bench_node.py) while publish_ground_surface is on."""
        wanted = []
        if self._pub_labeled.get_subscription_count() > 0:
            wanted.append((self._pub_labeled, add_labeled, 'labeled'))
        if surface_on and self._pub_surface.get_subscription_count() > 0:
            wanted.append((self._pub_surface, add_surface, 'surface'))
        return wanted

    def _publish_lazy(self, out, msg, wanted: list) -> float:
        """Build and publish the ``wanted`` outputs (their build time counts in encode and
        total, as when process_cloud builds them); the publish time (ms)."""
        publish_ms = 0.0
        for publisher, build, name in wanted:
            build(out, msg)
            cloud = getattr(out, name)
            if cloud is not None:
                t_publish = time.perf_counter()
                publisher.publish(cloud)
                publish_ms += (time.perf_counter() - t_publish) * 1e3
        return publish_ms

    def _process(self, msg, received_at: float) -> None:
        """One frame: process, publish, record. ``received_at``: perf_counter() when the
        subscription callback put it into the slot (its wait there is the ``handoff`` time)."""
        frame_id = None
        try:
            frame_id = msg.header.frame_id
            handoff_ms = (time.perf_counter() - received_at) * 1e3
            outputs = dict(self._outputs)
            lazy = self._lazy_outputs(outputs.pop('publish_ground_surface'))
            imu_note = self._level_with_imu(msg)
            out = process_cloud(msg, self._segmenter, publish_ground_surface=False, **outputs)
            notes = list(out.warnings) + self._stream_warnings(msg)
            t_publish = time.perf_counter()
            self._pub_ground.publish(out.ground)
            self._pub_obstacles.publish(out.obstacles)
            t_published = time.perf_counter()
            # the latency their subscribers see: callback to ground and obstacles published
            ground_published_ms = (t_published - received_at) * 1e3
            publish_ms = (t_published - t_publish) * 1e3 + self._publish_lazy(out, msg, lazy)
            self.window.record_frame(out, frame_id, notes + ([imu_note] if imu_note else []),
                                     {'handoff': handoff_ms, 'publish': publish_ms,
                                      'ground_published': ground_published_ms})
            self._log_notes(frame_id, notes, imu_note)
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

    def _log_notes(self, frame_id, notes: list, imu_note) -> None:
        for note in notes:
            if note.startswith(NOT_CENTRED):
                if self._centring_logged:  # a property of the set-up: say it once
                    continue
                self._centring_logged = True
            self._log_throttled('warning', f"suspicious input cloud (frame_id '{frame_id}'): "
                                f'{note}')
        if imu_note:
            self._log_throttled('warning', f'IMU: {imu_note}')

    # --- diagnostics -----------------------------------------------------------------------
    def _on_diag_timer(self) -> None:
        try:
            stale = max(5.0, 3.0 * self._diag_period_s)
            status = diagnostics_status(self.window, budget_ms=self._budget_ms,
                                        stale_after_s=stale, extra=self._diagnostics_extra())
            self._pub_diag.publish(diagnostics_array([status],
                                                     self.get_clock().now().to_msg()))
        except Exception as exc:
            self.get_logger().error(f'diagnostics failed: {_one_line(exc)}',
                                    throttle_duration_sec=_LOG_THROTTLE_S)

    def _diagnostics_extra(self) -> dict:
        """Keys of the status beyond the window's: the IMU's (none without imu_topic)."""
        gravity, pose = self._gravity, self._last_imu_pose
        if gravity is None:
            return {}
        return {'imu_topic': self._imu_sub.topic_name if self._imu_sub is not None else 'none',
                'imu_samples': gravity.samples_added,
                'imu_samples_unusable': gravity.samples_unusable,
                'imu_pose_source': pose.source if pose is not None else 'n/a',
                'imu_age_s': pose.age_s if pose is not None and pose.age_s is not None
                else 'n/a',
                'sensor_roll_rad_used': pose.roll if pose is not None else 'n/a',
                'sensor_pitch_rad_used': pose.pitch if pose is not None else 'n/a'}

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
            if seg:  # the cross-field rules, on the current values with these changes
                current = split_params({name: self.get_parameter(name).value
                                        for name in self._specs})[0]
                SegmenterParams(**dict(current, **seg)).validate()
            return SetParametersResult(successful=True)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=_one_line(exc))
        except Exception as exc:
            return SetParametersResult(successful=False,
                                       reason=_one_line(f'{type(exc).__name__}: {exc}'))

    def _apply_params(self, params) -> None:
        """Post-set: apply. The worker picks up segmenter changes at the next frame. Before
        configure (lifecycle) there is nothing to apply: configure reads every value."""
        if not self._configured:
            return
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
                self._replace_diag_timer()
            if self._gravity is not None and any(name in node for name in IMU_PARAMS):
                self._configure_gravity({name: self.get_parameter(name).value
                                         for name in IMU_PARAMS})
        except Exception as exc:
            self.get_logger().error(f'applying parameters failed: {_one_line(exc)}')

    def _replace_diag_timer(self) -> None:
        old = self._diag_timer
        self._created = [(kind, e) for kind, e in self._created if e is not old]
        self.destroy_timer(old)
        self._diag_timer = self._keep('timer', self.create_timer(self._diag_period_s,
                                                                 self._on_diag_timer))

    # --- shutdown --------------------------------------------------------------------------
    def _stop_worker(self, timeout_s: float = 30.0) -> None:
        self._stopping = True
        cond = getattr(self, '_cond', None)
        if cond is not None:
            with cond:
                cond.notify_all()
        worker, self._worker = self._worker, None
        if worker is not None and worker is not threading.current_thread():
            worker.join(timeout_s)
            if worker.is_alive():
                self.get_logger().warning(f'worker thread did not stop within {timeout_s} s')

    def destroy_node(self):
        """Stop and join the worker (it finishes the frame in progress), release every
        endpoint, then destroy the node."""
        if self._destroyed:
            return
        self._destroyed = True
        self._release()
        super().destroy_node()


class GroundSegmentationNode(SegmentationNodeBase, Node):
    """Ground/obstacle split of LiDAR clouds with a Gaussian-process ground model."""

    LIFECYCLE = False  # run_node: the help of the plain node

    def __init__(self, segmenter_factory=GroundSegmenter, announce: bool = True, **node_kwargs):
        """``segmenter_factory(params) -> segmenter`` (default GroundSegmenter); ``node_kwargs``
        go to rclpy Node (context, cli_args, parameter_overrides, namespace, ...). ``announce``:
        log the 'listening on' line now (main() does it itself once its checks passed)."""
        Node.__init__(self, NODE_NAME, **node_kwargs)
        self._init_state(segmenter_factory)
        self.accepting = True  # from its first cloud on
        try:
            self._declare_parameters()
            self._configure()
        except BaseException:
            Node.destroy_node(self)
            raise
        if announce:
            self.announce()


def main(args=None):
    """Entry point of ``ros2 run gp_ground_segmentation ground_segmentation_node``."""
    run_node(GroundSegmentationNode, 'ground_segmentation_node', args)


if __name__ == '__main__':
    main()
