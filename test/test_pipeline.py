# SPDX-License-Identifier: Apache-2.0
"""pipeline.process_cloud and diagnostics.ProcessingWindow/diagnostics_status, without rclpy.init.

Clouds are built in memory (as sensor_msgs_py's own tests do): extra fields of other types,
padding inside point_step, row padding, big-endian data and invalid rows, so the byte-exact
partition is checked on layouts the KITTI bag does not have.
"""

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.ros.cloud import (CloudFormatError, make_cloud, point_rows,
                                              split_cloud, subset_cloud)
from gp_ground_segmentation.ros.diagnostics import ProcessingWindow, diagnostics_status
from gp_ground_segmentation.ros.pipeline import (STAGES, FrameOutput, add_surface, frame_timings,
                                                 process_cloud)
from gp_ground_segmentation.core.segmenter import Hyperparameters, SegmentationResult


def _scene(n=6000, seed=0):
    """A sloped ground ring scan with two boxes: (N, 3) float64 (m)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(3.0, 40.0, n)
    a = rng.uniform(-np.pi, np.pi, n)
    x, y = r * np.cos(a), r * np.sin(a)
    z = -1.7 + 0.05 * x + rng.normal(0, 0.02, n)
    box = (np.abs(x - 10) < 1.5) & (np.abs(y) < 1.5) | (np.abs(x + 8) < 1) & (np.abs(y - 6) < 1)
    z[box] += rng.uniform(0.5, 2.0, box.sum())
    return np.stack([x, y, z], axis=1)


def _structured(xyz, big=False):
    o = '>' if big else '<'
    dt = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'ring', 't'],
                   'formats': [o + 'f4', o + 'f4', o + 'f4', 'u1', o + 'u2', o + 'f8'],
                   'offsets': [0, 4, 8, 12, 14, 16], 'itemsize': 32})  # padding 24..31
    pts = np.zeros(len(xyz), dtype=dt)
    pts['x'], pts['y'], pts['z'] = xyz.T
    pts['intensity'] = np.arange(len(xyz)) % 251
    pts['ring'] = np.arange(len(xyz)) % 32
    pts['t'] = np.arange(len(xyz)) * 1e-6
    return pts


def _msg(pts, frame_id='lidar', sec=12):
    header = Header(frame_id=frame_id)
    header.stamp.sec = sec
    return make_cloud(header, pts, PointCloud2)


def _sorted_rows(rows):
    rows = np.ascontiguousarray(rows)
    return np.sort(rows.view(np.dtype((np.void, rows.shape[1]))).reshape(-1))


def _check_partition(msg, out):
    rows = point_rows(msg)
    valid = out.result.valid_mask
    assert valid.shape == (rows.shape[0],)
    g, o = point_rows(out.ground), point_rows(out.obstacles)
    assert g.shape[0] + o.shape[0] + out.result.num_invalid == rows.shape[0]
    assert np.array_equal(_sorted_rows(np.concatenate([g, o])), _sorted_rows(rows[valid]))
    assert np.array_equal(g, rows[out.result.ground_mask])  # order kept too
    for cloud in (out.ground, out.obstacles):
        assert cloud.header.stamp == msg.header.stamp
        assert cloud.header.frame_id == msg.header.frame_id
        assert cloud.point_step == msg.point_step and cloud.is_bigendian == msg.is_bigendian
        assert [f.name for f in cloud.fields] == [f.name for f in msg.fields]


@pytest.mark.parametrize('big', [False, True])
def test_partition_with_extra_fields_padding_and_invalid_rows(big):
    xyz = _scene()
    xyz[::50] = np.nan
    xyz[1::70, 2] = -np.inf
    xyz[2::90] = 0.0
    msg = _msg(_structured(xyz, big))
    out = process_cloud(msg, GroundSegmenter(SegmenterParams()))
    _check_partition(msg, out)
    assert out.result.num_invalid == int((~np.isfinite(xyz).all(1) | (xyz == 0).all(1)).sum())
    assert out.ground.width > 0 and out.obstacles.width > 0
    assert out.decode_ms >= 0 and out.encode_ms >= 0 and out.total_ms >= out.decode_ms


def test_surface_added_after_the_split_is_the_eager_one():
    """The node publishes ground and obstacles, then builds the surface cloud (add_surface):
    the same bytes as process_cloud's own, and its time joins encode and total."""
    msg = _msg(_structured(_scene(seed=5)))
    eager = process_cloud(msg, GroundSegmenter(), publish_ground_surface=True)
    late = process_cloud(msg, GroundSegmenter(), publish_ground_surface=False)
    assert late.surface is None and np.isnan(late.surface_ms)
    encode, total = late.encode_ms, late.total_ms
    assert add_surface(late, msg) is late
    assert late.surface.width == eager.surface.width > 0
    assert bytes(late.surface.data) == bytes(eager.surface.data)
    assert late.surface.header.stamp == msg.header.stamp
    assert late.surface_ms >= 0
    assert late.encode_ms == encode + late.surface_ms and late.total_ms == total + late.surface_ms
    before = late.surface
    add_surface(late, msg)  # built already: nothing changes
    assert late.surface is before and late.total_ms == total + late.surface_ms
    assert frame_timings(late)['surface'] == late.surface_ms


def test_organized_cloud_with_row_padding():
    xyz = _scene(n=64 * 80)
    pts = _structured(xyz)
    flat = _msg(pts)
    step, width, height = flat.point_step, 80, 64
    raw = np.frombuffer(bytes(flat.data), np.uint8).reshape(height, width * step)
    padded = np.concatenate([raw, np.full((height, 8), 0xAB, np.uint8)], axis=1)
    msg = _msg(pts)
    msg.height, msg.width, msg.row_step = height, width, width * step + 8
    msg.data = padded.tobytes()
    out = process_cloud(msg, GroundSegmenter(SegmenterParams()))
    _check_partition(msg, out)
    assert out.ground.width + out.obstacles.width == height * width


def test_same_split_as_the_segmenter_on_xyz():
    xyz = _scene(seed=3)
    msg = _msg(xyz.astype(np.float32))
    seen = []

    class Spy(GroundSegmenter):
        def segment(self, points, details=False):
            seen.append(points.dtype)
            return super().segment(points, details)
    spy = Spy(SegmenterParams())
    out = process_cloud(msg, spy)
    assert seen == [np.float32]  # float32 fields reach the segmenter as float32
    direct = GroundSegmenter(SegmenterParams())
    direct_result = direct.segment(xyz.astype(np.float32).astype(np.float64))
    assert np.array_equal(out.result.ground_mask, direct_result.ground_mask)
    assert spy.hyperparameters == direct.hyperparameters  # the same cold start


def test_empty_cloud():
    msg = _msg(np.zeros((0, 3), np.float32))
    out = process_cloud(msg, GroundSegmenter(SegmenterParams()))
    assert out.ground.width == 0 and out.obstacles.width == 0 and out.result.num_invalid == 0


def test_bad_layout_raises_cloud_format_error():
    msg = _msg(np.zeros(5, dtype=[('x', '<f4'), ('y', '<f4')]))
    with pytest.raises(CloudFormatError, match='z'):
        process_cloud(msg, GroundSegmenter(SegmenterParams()))
    msg = _msg(np.ones((5, 3), np.float32))
    msg.data = bytes(msg.data)[:-1]
    with pytest.raises(CloudFormatError):
        process_cloud(msg, GroundSegmenter(SegmenterParams()))
    msg = _msg(np.ones((5, 3), np.float32))
    msg.fields = [PointField(name='x', offset=0, datatype=7, count=1),
                  PointField(name='y', offset=4, datatype=7, count=1),
                  PointField(name='z', offset=8, datatype=7, count=3)]
    msg.point_step = msg.row_step = 0
    with pytest.raises(CloudFormatError):
        process_cloud(msg, GroundSegmenter(SegmenterParams()))


class _Liar:
    """A segmenter that labels an invalid point as ground: the counts no longer add up, and the
    pipeline must refuse to publish such a split."""

    params = SegmenterParams()

    def segment(self, xyz):
        n = len(xyz)
        valid = np.ones(n, bool)
        valid[0] = False
        ground = np.zeros(n, bool)
        ground[: n // 2] = True  # includes the invalid point 0
        return SegmentationResult(ground, valid, np.zeros(n), Hyperparameters(1.0, 1.0, 0.1))


def test_inconsistent_split_is_refused(split_path):
    msg = _msg(_scene(100).astype(np.float32))
    # 50 ground (point 0 among them) + 50 valid non-ground + 1 invalid (point 0)
    with pytest.raises(RuntimeError,
                       match=r'^inconsistent split: 50 ground \+ 50 obstacles \+ 1 invalid '
                             r'!= 100 points$'):
        process_cloud(msg, _Liar())


def test_bag_frames_output_clouds_are_the_subsets_of_the_masks(kitti_msgs, split_path):
    """process_cloud's clouds (one split_cloud pass) are subset_cloud's of the result's ground
    and obstacle masks, message and bytes; split_cloud on the bag's layout with other masks
    too; and a bad mask on a bag frame is refused with the counts."""
    seg = GroundSegmenter()
    rng = np.random.default_rng(2)
    for msg in kitti_msgs:
        out = process_cloud(msg, seg)
        res = out.result
        for got, mask in ((out.ground, res.ground_mask), (out.obstacles, res.obstacle_mask)):
            expected = subset_cloud(msg, mask)
            assert got == expected and bytes(got.data) == bytes(expected.data)
        n = res.valid_mask.size
        ground, valid = rng.random(n) < 0.5, rng.random(n) < 0.95
        got = split_cloud(msg, ground, valid)
        for message, mask in zip(got, (ground, valid & ~ground)):
            expected = subset_cloud(msg, mask)
            assert message == expected and bytes(message.data) == bytes(expected.data)
    n = kitti_msgs[0].width * kitti_msgs[0].height
    with pytest.raises(RuntimeError, match=rf'^inconsistent split: {n // 2} ground \+ '
                                           rf'{n - n // 2} obstacles \+ 1 invalid != '
                                           rf'{n} points$'):
        process_cloud(kitti_msgs[0], _Liar())


def test_pipeline_warm_up_queues_the_output_pass(tmp_path):
    """After the node's warm-up (GroundSegmenter.warm_up(), then pipeline.warm_up()), bag
    frames (and the same points as x, y, z-only, 22-byte and FLOAT64 clouds) ask numba for no
    signature it has not queued, the output clouds' pass included (a missed one compiles only
    once a frame needs it: numpy-twin frames meanwhile), and every queued kernel compiles. In
    a fresh interpreter with an empty numba cache (as
    test_warm_up_queues_every_compiled_stage_a_frame_needs)."""
    from gp_ground_segmentation.core import compiled
    from conftest import BAG, check_warm_up_in_fresh_cache
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    if not BAG.is_dir():
        pytest.skip(f'real data not found: {BAG}')
    script = f"""if True:
        from rclpy.serialization import deserialize_message
        from rosbags.highlevel import AnyReader
        from sensor_msgs.msg import PointCloud2
        from gp_ground_segmentation import GroundSegmenter
        from gp_ground_segmentation.core import compiled
        from gp_ground_segmentation.ros import cloud, pipeline
        with AnyReader([__import__('pathlib').Path({str(BAG)!r})]) as reader:
            conns = [c for c in reader.connections if c.topic == '/velodyne_points']
            msgs = [deserialize_message(raw, PointCloud2)
                    for _, _, raw in reader.messages(connections=conns)][:2]
        # the other layouts drivers publish: x, y, z only (a read-only C view in the node),
        # 22-byte points (rows not 4-byte aligned: copied to columns), FLOAT64 x, y, z
        import numpy as np
        xyz = cloud.cloud_xyz(cloud.read_cloud(msgs[0]), None)
        for dtype in (np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4')]),
                      np.dtype({{'names': ['x', 'y', 'z', 'intensity', 'ring'],
                                'formats': ['<f4'] * 4 + ['<u2'],
                                'offsets': [0, 4, 8, 12, 16], 'itemsize': 22}}),
                      np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8')])):
            points = np.zeros(len(xyz), dtype)
            points['x'], points['y'], points['z'] = xyz.T
            msgs.append(cloud.make_cloud(msgs[0].header, points, PointCloud2))
        seg = GroundSegmenter()
        seg.warm_up()
        pipeline.warm_up()
        queued = set(compiled._queued)
        for msg in msgs:
            pipeline.process_cloud(msg, seg, publish_ground_surface=True,
                                   add_height_above_ground_field=True)
            pipeline.process_cloud(msg, seg)
        compiled.wait(240.0)  # (queued is kept: the report's check is not affected)
        print('SPLIT', len(cloud._split_rows_compiled.signatures))
        """
    assert 'SPLIT 1' in check_warm_up_in_fresh_cache(script, tmp_path)


# --- diagnostics ------------------------------------------------------------------------------

def _fake_output(total_ms=10.0, n=100, n_ground=60, n_invalid=5, stats=None):
    valid = np.ones(n, bool)
    valid[:n_invalid] = False
    ground = np.zeros(n, bool)
    ground[n_invalid:n_invalid + n_ground] = True
    timings = {'grid': 1.0, 'lines': 1.0, 'gp_fit': 4.5, 'predict': 1.0, 'label': 1.0,
               'structure': 0.5,
               'total': total_ms - 2.0}
    res = SegmentationResult(ground, valid, np.zeros(n), Hyperparameters(0.5, 2.0, 0.05),
                             timings, dict(stats or {'cholesky_fallbacks': 1}))
    return FrameOutput(ground=None, obstacles=None, result=res, decode_ms=1.0, encode_ms=1.0,
                       total_ms=total_ms)


def _values(status):
    return {kv.key: kv.value for kv in status.values}


def test_frame_timings_has_every_stage():
    t = frame_timings(_fake_output())
    assert set(STAGES) <= set(t) and t['total'] == 10.0 and t['segment'] == 8.0


def test_status_levels():
    w = ProcessingWindow(window=4)
    s = diagnostics_status(w, budget_ms=100.0, now=0.0)
    assert s.level == DiagnosticStatus.STALE and s.hardware_id == 'none'

    w.record_received('velo', now=0.0)
    w.record_frame(_fake_output(), 'velo')
    w.record_received('velo', now=0.1)
    w.record_frame(_fake_output(total_ms=20.0), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.2)
    v = _values(s)
    assert s.level == DiagnosticStatus.OK and s.message == 'ok' and s.hardware_id == 'velo'
    assert all(isinstance(x, str) for x in v.values())
    assert v['total_ms_mean'] == '15.000' and v['total_ms_max'] == '20.000'
    assert float(v['total_ms_p95']) == pytest.approx(19.5)
    assert v['input_rate_hz'] == '10.000'
    assert (v['points_in'], v['points_ground'], v['points_obstacles'], v['points_invalid']) == \
        ('100', '60', '35', '5')
    assert v['cholesky_fallbacks'] == '1' and v['cholesky_fallbacks_window'] == '2'
    assert v['sigma_f'] == '0.500' and v['gain'] == '2.000' and v['sigma_n'] == '0.050'

    s = diagnostics_status(w, budget_ms=12.0, now=0.2)
    assert s.level == DiagnosticStatus.WARN and 'budget' in s.message
    s = diagnostics_status(w, budget_ms=100.0, now=60.0, stale_after_s=5.0)
    assert s.level == DiagnosticStatus.WARN and 'no input' in s.message

    w.record_received('velo', now=0.3)
    w.record_dropped()
    s = diagnostics_status(w, budget_ms=100.0, now=0.3)
    assert s.level == DiagnosticStatus.WARN and 'dropped' in s.message

    w.record_received('velo', now=0.4)
    w.record_failure("cloud has no field z (fields: ['x', 'y'])", True, 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.4)
    assert s.level == DiagnosticStatus.ERROR and s.message.startswith('bad input: cloud has no')
    w.record_received('velo', now=0.5)
    w.record_frame(_fake_output(), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.5)
    assert s.level == DiagnosticStatus.WARN and 'failed' in s.message
    # The window slides: after 4 good frames the drop and the failure are forgotten.
    for i in range(4):
        w.record_received('velo', now=0.6 + i / 10)
        w.record_frame(_fake_output(), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=1.0)
    assert s.level == DiagnosticStatus.OK, s.message
    assert _values(s)['frames_dropped'] == '1' and _values(s)['frames_failed'] == '1'


def test_window_resize_keeps_recent_frames():
    w = ProcessingWindow(window=10)
    for i in range(10):
        w.record_frame(_fake_output(total_ms=float(i + 3)))
    w.resize(2)
    v = _values(diagnostics_status(w, budget_ms=100.0))
    assert v['total_ms_mean'] == '11.500' and v['window_frames'] == '2'


def test_input_warning_stays_warn_over_the_window():
    # 14 frames whose stamps go backwards, then clean ones: WARN until the window has slid past.
    w = ProcessingWindow(window=20)
    for i in range(14):
        w.record_received('velo', now=i / 10)
        w.record_frame(_fake_output(), 'velo', ['header stamp went backwards by 0.100 s'])
    w.record_received('velo', now=1.4)
    w.record_frame(_fake_output(), 'velo', [])
    s = diagnostics_status(w, budget_ms=100.0, now=1.4)
    assert s.level == DiagnosticStatus.WARN, s.message
    assert 'backwards' in s.message and '14 frame(s)' in s.message
    assert _values(s)['input_warnings_in_window'] == '14'
    for i in range(19):
        w.record_received('velo', now=1.5 + i / 10)
        w.record_frame(_fake_output(), 'velo', [])
    s = diagnostics_status(w, budget_ms=100.0, now=3.4)
    assert s.level == DiagnosticStatus.OK, s.message


def test_input_rate_decays_when_input_stops():
    w = ProcessingWindow(window=50)
    for i in range(50):
        w.record_received('velo', now=i / 10)
    assert float(_values(diagnostics_status(w, budget_ms=100.0, now=4.95))['input_rate_hz']) \
        == pytest.approx(10.0)
    rates = [float(_values(diagnostics_status(w, budget_ms=100.0, now=4.9 + silence))
                   ['input_rate_hz']) for silence in (1.0, 6.0, 60.0)]
    assert rates[0] < 9.0 and rates[1] < 5.0 and rates[2] < 1.0
    assert rates == sorted(rates, reverse=True)


def test_cold_first_frame_does_not_turn_the_budget_warn():
    # The first frame learns theta from scratch (40 evaluations, compiled kernel loading):
    # one slow frame then fast ones is OK; slow frames after it still WARN.
    w = ProcessingWindow(window=50)
    w.record_received('velo', now=0.0)
    w.record_frame(_fake_output(total_ms=850.0), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.0)
    assert s.level == DiagnosticStatus.WARN and 'budget' in s.message  # nothing else to judge
    for i in range(2):
        w.record_received('velo', now=0.1 * (i + 1))
        w.record_frame(_fake_output(total_ms=60.0), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.2)
    assert s.level == DiagnosticStatus.OK, s.message
    assert _values(s)['total_ms_max'] == '850.000'  # still shown in the timings
    w.record_received('velo', now=0.3)
    w.record_frame(_fake_output(total_ms=300.0), 'velo')
    s = diagnostics_status(w, budget_ms=100.0, now=0.3)
    assert s.level == DiagnosticStatus.WARN and 'budget' in s.message
