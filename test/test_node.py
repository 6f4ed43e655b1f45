# SPDX-License-Identifier: Apache-2.0
"""The ROS 2 node through real rclpy pub/sub (Fast DDS on loopback), in-process.

Real KITTI frames from ../shared/data are published to 'points'; 'ground', 'obstacles' and
'/diagnostics' are received by a peer node. Checks: exact byte-for-byte partition of the valid
input points, header and fields, diagnostics keys and levels, parameter service (valid, invalid,
effect), latest-wins dropping, parameter files at start-up, bad input that does not stop the node,
and main() as a process (clean Ctrl-C, failure naming a bad YAML key).
"""

import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import (NODE_MODULE, REPO, assert_output_like_input, start_module,
                      status_values, wait_for, wait_listening)

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.ros.cloud import make_cloud, point_rows
from gp_ground_segmentation.ros.config import ParameterConfigError, all_param_specs
from gp_ground_segmentation.ros.pipeline import STAGES, process_cloud

PARAMS_YAML = REPO / 'config' / 'params.yaml'


def _fast(**extra):
    """Node kwargs: diagnostics every 0.2 s (default 1 s) so tests do not wait long."""
    from rclpy.parameter import Parameter
    overrides = [Parameter('diagnostics_period_s', value=0.2)]
    overrides += [Parameter(k, value=v) for k, v in extra.items()]
    return {'parameter_overrides': overrides}


def _with_invalid_points(msg, stamp_sec):
    """A copy of ``msg`` with some rows set to NaN, +Inf and the (0,0,0) no-return value."""
    from sensor_msgs.msg import PointCloud2
    rows = point_rows(msg).copy()
    xyz = rows[:, :12].view('<f4')  # KITTI layout: x, y, z float32 at offsets 0, 4, 8
    xyz[::997, 0] = np.nan
    xyz[5::1999, 2] = np.inf
    xyz[7::1501, :] = 0.0
    out = PointCloud2()
    out.header.frame_id = msg.header.frame_id
    out.header.stamp.sec = stamp_sec
    out.header.stamp.nanosec = msg.header.stamp.nanosec
    out.height, out.width = 1, msg.width
    out.fields = msg.fields
    out.is_bigendian, out.point_step = msg.is_bigendian, msg.point_step
    out.row_step, out.is_dense = msg.row_step, False
    import array
    data = array.array('B')
    data.frombytes(rows.tobytes())
    out.data = data
    return out


def _sorted_rows(rows):
    rows = np.ascontiguousarray(rows)
    return np.sort(rows.view(np.dtype((np.void, rows.shape[1]))).reshape(-1))


def _valid(msg):
    from gp_ground_segmentation import valid_points_mask
    from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
    return valid_points_mask(cloud_xyz(read_cloud(msg)))


def test_partition_header_fields_and_diagnostics(kitti_msgs, ros_harness):
    """Three real frames (one with NaN/Inf/zero rows): exact split, same bytes, same header."""
    h = ros_harness(node_kwargs=_fast())
    frames = [kitti_msgs[0], _with_invalid_points(kitti_msgs[1], kitti_msgs[1].header.stamp.sec),
              kitti_msgs[2]]
    reference = GroundSegmenter(SegmenterParams())  # same frames, same order -> same theta
    for msg in frames:
        ground, obstacles = h.publish_and_wait(msg)
        rows = point_rows(msg)
        valid = _valid(msg)
        for out in (ground, obstacles):
            assert_output_like_input(msg, out)
            assert out.header.frame_id == 'velodyne'
        g_rows, o_rows = point_rows(ground), point_rows(obstacles)
        assert ground.width + obstacles.width == int(valid.sum())
        both = np.concatenate([g_rows, o_rows])
        assert np.array_equal(_sorted_rows(both), _sorted_rows(rows[valid]))
        # Same split as the pipeline run directly on the same sequence of frames.
        expected = process_cloud(msg, reference)
        assert bytes(ground.data) == bytes(expected.ground.data)
        assert bytes(obstacles.data) == bytes(expected.obstacles.data)
    n_invalid = int((~_valid(frames[1])).sum())
    assert n_invalid > 100
    status = h.wait_status(lambda s: status_values(s).get('frames_processed') == '3')
    assert status is not None, 'no diagnostics after 3 frames'
    values = status_values(status)
    assert all(isinstance(v, str) for v in values.values())
    assert status.hardware_id == 'velodyne'
    for stage in STAGES:
        mean, p95, mx = (float(values[f'{stage}_ms_{k}']) for k in ('mean', 'p95', 'max'))
        assert 0.0 <= mean <= mx and p95 <= mx, stage
    assert float(values['total_ms_max']) >= float(values['gp_fit_ms_max'])
    assert values['frames_received'] == '3' and values['frames_dropped'] == '0'
    last = frames[2]
    assert int(values['points_in']) == last.width
    assert int(values['points_ground']) + int(values['points_obstacles']) == last.width
    for key in ('sigma_f', 'gain', 'sigma_n', 'input_rate_hz', 'cholesky_fallbacks'):
        assert key in values
    assert float(values['sigma_f']) > 0


def test_worker_warms_up_the_segmenter_then_the_output_pass(kitti_msgs, ros_harness,
                                                            monkeypatch):
    """Before the first frame the worker loads the segmenter's compiled stages, then queues
    the output clouds' pass (pipeline.warm_up), a frame's order."""
    import gp_ground_segmentation.ros.node as node_module
    calls = []
    real = (GroundSegmenter.warm_up, node_module.warm_up_outputs, node_module.process_cloud)
    monkeypatch.setattr(GroundSegmenter, 'warm_up',
                        lambda self: (calls.append('segmenter'), real[0](self))[1])
    monkeypatch.setattr(node_module, 'warm_up_outputs',
                        lambda: (calls.append('outputs'), real[1]())[1])
    monkeypatch.setattr(node_module, 'process_cloud',
                        lambda *a, **kw: (calls.append('frame'), real[2](*a, **kw))[1])
    h = ros_harness(node_kwargs=_fast())
    h.publish_and_wait(kitti_msgs[0])
    assert calls[:3] == ['segmenter', 'outputs', 'frame']


def test_stale_before_input_then_error_on_bad_input_then_recovers(kitti_msgs, ros_harness):
    """No input -> STALE; malformed clouds -> ERROR naming the problem, no output; the next good
    frame is processed normally."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from std_msgs.msg import Header
    h = ros_harness(node_kwargs=_fast())
    stale = h.wait_status(lambda s: True)
    assert stale is not None and stale.level == DiagnosticStatus.STALE
    assert 'no input' in stale.message and stale.hardware_id == 'none'

    header = Header(frame_id='lidar_bad')
    header.stamp.sec = 7
    no_z = make_cloud(header, np.zeros(10, dtype=[('x', '<f4'), ('y', '<f4')]))
    h.pub.publish(no_z)
    err = h.wait_status(lambda s: s.level == DiagnosticStatus.ERROR)
    assert err is not None and 'bad input' in err.message and 'z' in err.message
    assert err.hardware_id == 'lidar_bad'

    truncated = make_cloud(header, np.ones((50, 3), dtype=np.float32))
    truncated.header.stamp.sec = 8
    truncated.data = truncated.data[:-7]
    h.pub.publish(truncated)
    err = h.wait_status(lambda s: 'missing' in s.message)
    assert err is not None and err.level == DiagnosticStatus.ERROR
    assert h.outputs_for(no_z.header.stamp) is None and h.outputs_for(truncated.header.stamp) \
        is None

    h.publish_and_wait(kitti_msgs[0])
    ok = h.wait_status(lambda s: status_values(s)['frames_processed'] == '1')
    assert ok is not None and ok.level != DiagnosticStatus.ERROR
    assert int(status_values(ok)['frames_failed']) == 2


def _call_set(h, params, timeout=10.0):
    """SetParameters through the node's service, like `ros2 param set`."""
    from rcl_interfaces.srv import SetParameters
    client = h.peer.create_client(SetParameters, '/ground_segmentation/set_parameters')
    try:
        assert client.wait_for_service(timeout_sec=timeout)
        future = client.call_async(SetParameters.Request(
            parameters=[p.to_parameter_msg() for p in params]))
        assert wait_for(future.done, timeout)
        return future.result().results
    finally:
        h.peer.destroy_client(client)


def test_parameter_service_valid_invalid_and_effect(kitti_msgs, ros_harness):
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.parameter import Parameter
    h = ros_harness(node_kwargs=_fast())
    node = h.node
    g_default, _ = h.publish_and_wait(kitti_msgs[0])
    segmenter = node.segmenter

    bad = [
        ([Parameter('num_segments', value=2)], 'num_segments'),             # below its range
        ([Parameter('sigma_f_init_m', value=30.0)], 'sigma_f_init_m'),      # > sigma_f_max_m
        ([Parameter('num_bins', value=4.5)], 'num_bins'),                   # double for an int
        ([Parameter('queue_size', value=3)], 'queue_size'),                 # read-only
    ]
    for params, name in bad:
        (result,) = _call_set(h, params)
        assert not result.successful, name
        assert name in result.reason or 'read-only' in result.reason or 'type' in result.reason
    assert node.get_parameter('num_segments').value == 120
    assert node.get_parameter('sigma_f_init_m').value == 0.5
    assert node.get_parameter('queue_size').value == 1
    assert node.declared_params == SegmenterParams()

    results = _call_set(h, [Parameter('ground_threshold_m', value=0.0),
                            Parameter('use_std_threshold', value=False),
                            Parameter('max_threshold_m', value=0.0)])
    assert all(r.successful for r in results), [r.reason for r in results]
    assert node.get_parameter('ground_threshold_m').value == 0.0
    # Applied at the next frame, not before.
    assert node.segmenter_params.ground_threshold_m == SegmenterParams().ground_threshold_m > 0
    again = _with_invalid_points(kitti_msgs[0], 4242)
    g_tight, _ = h.publish_and_wait(again)
    assert node.segmenter_params.ground_threshold_m == 0.0
    assert node.segmenter_params.max_threshold_m == 0.0
    assert node.segmenter is segmenter  # same object: the learned theta stays warm
    assert g_tight.width < g_default.width

    (result,) = _call_set(h, [Parameter('processing_budget_ms', value=0.001)])
    assert result.successful
    warn = h.wait_status(lambda s: 'budget' in s.message)
    assert warn is not None and warn.level == DiagnosticStatus.WARN
    assert status_values(warn)['budget_ms'] == '0.001'


class _GatedSegmenter:
    """Blocks each segment() call until released: makes processing slower than publishing."""

    def __init__(self, params, gate):
        self._inner = GroundSegmenter(params)
        self._gate = gate
        self.entered = threading.Event()

    @property
    def params(self):
        return self._inner.params

    def segment(self, points, details=False):
        self.entered.set()
        assert self._gate.wait(60.0)
        return self._inner.segment(points, details=details)


def test_frames_dropped_and_counted_not_queued(kitti_msgs, ros_harness):
    from diagnostic_msgs.msg import DiagnosticStatus
    gate = threading.Event()
    made = []

    def factory(params):
        made.append(_GatedSegmenter(params, gate))
        return made[-1]
    h = ros_harness(node_kwargs=dict(_fast(),
                                     segmenter_factory=factory))
    node = h.node
    sent = []
    for i, base in enumerate(kitti_msgs):
        msg = _with_invalid_points(base, 1000 + i) if i else base
        h.pub.publish(msg)
        sent.append(msg)
        if i == 0:
            assert wait_for(made[0].entered.is_set, 20.0)  # worker busy with frame 0
        time.sleep(0.05)
    wait_for(lambda: node.window.frames_received >= len(sent), 10.0)
    received = node.window.frames_received
    assert received >= 3, 'too few frames arrived to test dropping'
    with node._cond:
        assert len(node._slot) <= node._slot.maxlen == 1
    gate.set()
    assert wait_for(lambda: node.window.frames_processed + node.window.frames_dropped
                    == received, 30.0)
    w = node.window
    assert w.frames_dropped == received - w.frames_processed >= 1
    assert w.frames_processed == 2  # the one in progress and the newest one
    assert wait_for(lambda: len(h.ground) == w.frames_processed, 10.0)
    if w.frames_received == len(sent):  # every frame arrived: the newest one must win
        assert wait_for(lambda: h.outputs_for(sent[-1].header.stamp), 10.0)
    status = h.wait_status(lambda s: status_values(s)['frames_processed'] == '2')
    assert status.level == DiagnosticStatus.WARN and 'dropped' in status.message
    assert status_values(status)['frames_dropped'] == str(w.frames_dropped)


def test_shipped_params_yaml_loads_at_construction(ros_harness):
    h = ros_harness(context_args=['--ros-args', '--params-file', str(PARAMS_YAML)])
    for name, spec in all_param_specs().items():
        value = h.node.get_parameter(name).value
        assert value == spec['default'] and type(value) is type(spec['default']), name
    assert h.node.declared_params == SegmenterParams()


def test_params_file_values_override_defaults(tmp_path, ros_harness):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    num_bins: 40\n    ground_threshold_m: 0.3\n'
                    '    diagnostics_window: 7\n')
    h = ros_harness(node_kwargs={'cli_args': ['--ros-args', '--params-file', str(path)]})
    assert h.node.get_parameter('num_bins').value == 40
    assert h.node.segmenter_params.num_bins == 40
    assert h.node.segmenter_params.ground_threshold_m == 0.3
    assert h.node.window.window == 7


@pytest.mark.parametrize('body, words', [
    ('    num_bns: 40\n', ['num_bns']),
    ('    max_threshold_m: 1\n', ['max_threshold_m', 'double']),
    ('    num_bins: 1\n', ['num_bins', '1']),
    ('    slope_floor: 0.5\n    slope_ceiling: 0.4\n', ['slope_floor']),
])
def test_bad_params_file_fails_at_startup_naming_the_key(tmp_path, body, words):
    import rclpy
    from gp_ground_segmentation.ros.node import GroundSegmentationNode
    path = tmp_path / 'bad.yaml'
    path.write_text('ground_segmentation:\n  ros__parameters:\n' + body)
    ctx = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=ctx)
    # a node of its own keeps the context's DDS participant alive while the failing node is
    # made and destroyed (test_node_params.py's context fixture says why)
    keeper = rclpy.create_node('test_node_keeper', context=ctx, use_global_arguments=False)
    try:
        with pytest.raises(ParameterConfigError) as info:
            GroundSegmentationNode(context=ctx)
        for word in words:
            assert word in str(info.value)
    finally:
        keeper.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _run_node(args, env_extra=None):
    return start_module(NODE_MODULE, *args, env_extra=env_extra)


def test_main_bad_yaml_exits_with_message(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('ground_segmentation:\n  ros__parameters:\n    sensor_hieght: 1.73\n')
    proc = _run_node(['--ros-args', '--params-file', str(path)])
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert 'sensor_hieght' in out and 'Traceback' not in out


def test_main_clean_shutdown_on_sigint():
    proc = _run_node(['--ros-args', '-r', 'points:=/velodyne_points'])
    try:
        lines = wait_listening(proc)
        assert any("'/velodyne_points'" in ln for ln in lines), lines
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert 'Traceback' not in out


def test_executable_path_is_importable():
    # The console script target exists (setup.py entry point gp_ground_segmentation.ros.node:main).
    from gp_ground_segmentation.ros import node
    assert callable(node.main)
    assert Path(node.__file__).name == 'node.py'
