# SPDX-License-Identifier: Apache-2.0
"""The node's ground surface output and height_above_ground field, over real rclpy pub/sub."""

import numpy as np
from conftest import assert_output_like_input, wait_for

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.ros.cloud import point_rows, read_cloud
from gp_ground_segmentation.ros.pipeline import HEIGHT_FIELD, SURFACE_FIELDS, process_cloud


def _overrides(**values):
    from rclpy.parameter import Parameter
    return {'parameter_overrides': [Parameter(k, value=v) for k, v in values.items()]}


def test_surface_arrives_with_four_fields_input_header_finite_values(kitti_msgs, ros_harness):
    h = ros_harness()
    msg = kitti_msgs[0]
    h.publish_and_wait(msg)
    surface = wait_for(lambda: h.surface_for(msg.header.stamp), 10.0)
    assert surface is not None, 'no ground_surface message for the frame'
    assert surface.header.frame_id == msg.header.frame_id == 'velodyne'
    assert [(f.name, f.offset, f.datatype, f.count) for f in surface.fields] == [
        (name, 4 * i, 7, 1) for i, name in enumerate(SURFACE_FIELDS)]
    values = read_cloud(surface)
    params = SegmenterParams()
    # every segment of a full KITTI sweep has ground candidates: M x (N + 1) points
    assert surface.width == params.num_segments * (params.num_bins + 1)
    columns = np.stack([values[name] for name in SURFACE_FIELDS], axis=1)
    assert np.isfinite(columns).all()
    assert (values['z_std'] >= 0).all()
    # the surface lies under the ground points: KITTI's road is ~1.73 m below the sensor
    near = np.hypot(values['x'], values['y']) < 15.0
    assert abs(float(np.median(values['z'][near])) + 1.73) < 0.1


def test_height_above_ground_field_and_original_bytes(kitti_msgs, ros_harness):
    h = ros_harness(node_kwargs=_overrides(add_height_above_ground_field=True))
    reference = GroundSegmenter(SegmenterParams())  # same frames, same order -> same theta
    for msg in kitti_msgs[:2]:
        ground, obstacles = h.publish_and_wait(msg)
        expected = process_cloud(msg, reference)
        height = expected.result.height_above_ground
        masks = (expected.result.ground_mask, expected.result.obstacle_mask)
        for out, plain, mask in zip((ground, obstacles), (expected.ground, expected.obstacles),
                                    masks):
            step = msg.point_step
            assert out.header.stamp == msg.header.stamp
            assert out.header.frame_id == msg.header.frame_id
            assert [(f.name, f.offset, f.datatype) for f in out.fields] == [
                (f.name, f.offset, f.datatype) for f in msg.fields] + [(HEIGHT_FIELD, step, 7)]
            assert out.point_step == step + 4 and out.width == plain.width
            rows = point_rows(out)
            assert rows[:, :step].tobytes() == bytes(plain.data)  # original fields untouched
            field = rows[:, step:].copy().view('<f4').ravel()
            z = read_cloud(plain)['z'].astype(np.float64)
            assert np.isfinite(field).all()
            np.testing.assert_allclose(field, z - expected.result.ground_height[mask], atol=1e-4)
            np.testing.assert_allclose(field, height[mask], atol=1e-4)
    ground_field = point_rows(ground)[:, msg.point_step:].copy().view('<f4')
    assert float(np.median(ground_field)) < 0.2 < float(np.median(
        point_rows(obstacles)[:, msg.point_step:].copy().view('<f4')))


def test_switches_are_live_settable_and_validated(kitti_msgs, ros_harness):
    from rclpy.parameter import Parameter
    h = ros_harness()
    node = h.node
    bad = node.set_parameters([Parameter('publish_ground_surface', value=1)])[0]
    assert not bad.successful and 'BOOL' in bad.reason
    assert node.set_parameters([Parameter('publish_ground_surface', value=False)])[0].successful
    msg = kitti_msgs[0]
    ground, obstacles = h.publish_and_wait(msg)
    assert_output_like_input(msg, ground)  # default: no extra field
    assert h.surface_for(msg.header.stamp) is None
    assert node.set_parameters([Parameter('publish_ground_surface', value=True)])[0].successful
    msg = kitti_msgs[1]
    h.publish_and_wait(msg)
    assert wait_for(lambda: h.surface_for(msg.header.stamp), 10.0) is not None


def test_surface_is_built_only_while_subscribed(kitti_msgs, ros_harness, monkeypatch):
    """Lazy surface: with publish_ground_surface on but no subscriber on ground_surface, the
    node spends nothing on it (no 'surface' stage time); a subscriber turns it back on, and the
    surface cloud is built only after ground and obstacles are published."""
    from gp_ground_segmentation.ros import pipeline
    h = ros_harness()
    node = h.node
    events = []  # the worker's calls, in order: which publisher, or the surface build

    def recording(name, call):
        def record(*args, **kwargs):
            events.append(name)
            return call(*args, **kwargs)
        return record
    # the build itself, wherever it is called from (process_cloud or add_surface)
    monkeypatch.setattr(pipeline, 'surface_cloud',
                        recording('build surface', pipeline.surface_cloud))
    for name in ('ground', 'obstacles', 'surface'):
        publisher = getattr(node, f'_pub_{name}')
        monkeypatch.setattr(publisher, 'publish', recording(name, publisher.publish))
    subscriptions = list(h.peer.subscriptions)
    [surface_sub] = [s for s in subscriptions if s.topic_name.endswith('/ground_surface')]
    topic, qos = surface_sub.topic_name, surface_sub.qos_profile
    h.peer.destroy_subscription(surface_sub)
    assert wait_for(lambda: node.count_subscribers(topic) == 0, 10.0)
    h.publish_and_wait(kitti_msgs[0])
    assert node.window.frames_processed == 1
    assert events == ['ground', 'obstacles']
    assert not any('surface' in t for t in node.window.snapshot()['timings']), \
        'surface built with nobody subscribed'
    received = []
    h.peer.create_subscription(type(kitti_msgs[0]), topic, received.append,
                               qos)
    assert wait_for(lambda: node.count_subscribers(topic) == 1, 10.0)
    msg = kitti_msgs[1]
    events.clear()
    h.publish_and_wait(msg)
    assert wait_for(lambda: any(m.header.stamp == msg.header.stamp for m in received), 10.0)
    timing = node.window.snapshot()['timings'][-1]
    assert 'surface' in timing
    # ground and obstacles go out before the surface cloud is built (their subscribers do not
    # wait for it); checked by the order of the calls, not by times, which load can skew
    assert events == ['ground', 'obstacles', 'build surface', 'surface']
    assert timing['ground_published'] > 0, timing
