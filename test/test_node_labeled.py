# SPDX-License-Identifier: Apache-2.0
"""The node's ``labeled`` topic over real rclpy pub/sub: advertised with no parameter, built only
while subscribed, one row per valid input point in input order with every input byte plus
``ground`` and ``height_above_ground``."""

import numpy as np
from conftest import wait_for

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.labels import GROUND_FIELD, HEIGHT_FIELD
from gp_ground_segmentation.ros.cloud import make_cloud, point_rows, read_cloud
from gp_ground_segmentation.ros.node import OUTPUT_QOS
from gp_ground_segmentation.ros.pipeline import process_cloud


def _with_holes(msg, sec):
    """``msg``'s points (x, y, z, intensity) with NaN, Inf and (0, 0, 0) rows, stamped ``sec``."""
    points = read_cloud(msg).copy()
    points['x'][::613] = np.nan
    points['z'][3::1409] = np.inf
    for c in 'xyz':
        points[c][11::1201] = 0.0
    out = make_cloud(msg.header, points)
    out.header.stamp.sec = sec
    return out


def test_labeled_rows_fields_bytes_order_and_counts(kitti_msgs, ros_harness):
    h = ros_harness(labeled=True)
    reference = GroundSegmenter(SegmenterParams())  # same frames, same order -> same theta
    frames = [kitti_msgs[0], _with_holes(kitti_msgs[1], 2000)]
    for msg in frames:
        ground, obstacles = h.publish_and_wait(msg)
        labeled = wait_for(lambda: h.labeled_for(msg.header.stamp), 10.0)
        assert labeled is not None, 'no labeled message for the frame'
        assert labeled.header.frame_id == msg.header.frame_id == 'velodyne'
        step = msg.point_step
        assert [(f.name, f.offset, f.datatype, f.count) for f in labeled.fields] == [
            (f.name, f.offset, f.datatype, f.count) for f in msg.fields] + [
            (GROUND_FIELD, step, 2, 1), (HEIGHT_FIELD, step + 4, 7, 1)]
        expected = process_cloud(msg, reference)
        valid = expected.result.valid_mask
        # one row per valid input point, in input order, its bytes unchanged
        assert labeled.width == int(valid.sum()) == ground.width + obstacles.width
        rows = point_rows(labeled)
        assert np.array_equal(rows[:, :step], point_rows(msg)[valid])
        values = read_cloud(labeled)
        assert set(np.unique(values[GROUND_FIELD]).tolist()) == {0, 1}
        assert np.array_equal(values[GROUND_FIELD] == 1, expected.result.ground_mask[valid])
        assert int(values[GROUND_FIELD].sum()) == ground.width
        height = values[HEIGHT_FIELD]
        assert np.isfinite(height).all()
        np.testing.assert_allclose(height, expected.result.height_above_ground[valid],
                                   atol=1e-4)
        # ground lies at the GP surface, obstacles well above it
        assert abs(float(np.median(height[values[GROUND_FIELD] == 1]))) < 0.1
        assert float(np.median(height[values[GROUND_FIELD] == 0])) > 0.3
    assert int((~_valid_mask(frames[1])).sum()) > 100  # the holes were really left out
    timing = h.node.window.snapshot()['timings'][-1]
    assert timing['labeled'] > 0 and timing['encode'] >= timing['labeled']


def _valid_mask(msg):
    from gp_ground_segmentation import valid_points_mask
    from gp_ground_segmentation.ros.cloud import cloud_xyz
    return valid_points_mask(cloud_xyz(read_cloud(msg)))


def test_labeled_is_advertised_and_built_only_while_subscribed(kitti_msgs, ros_harness,
                                                               monkeypatch):
    from gp_ground_segmentation.ros import pipeline
    h = ros_harness()  # the peer does not subscribe to labeled
    node = h.node
    builds = []
    real = pipeline.labeled_cloud
    monkeypatch.setattr(pipeline, 'labeled_cloud',
                        lambda *a, **kw: (builds.append(1), real(*a, **kw))[1])
    # advertised by default, no parameter, the QoS of ground
    [pub] = [p for p in node.publishers if p.topic_name == '/labeled']
    qos = pub.qos_profile
    assert (qos.reliability, qos.durability, qos.depth) == (
        OUTPUT_QOS.reliability, OUTPUT_QOS.durability, OUTPUT_QOS.depth)
    assert wait_for(lambda: h.peer.count_publishers('/labeled') == 1, 10.0)
    h.publish_and_wait(kitti_msgs[0])
    assert builds == [] and 'labeled' not in node.window.snapshot()['timings'][-1]
    received = []
    h.peer.create_subscription(type(kitti_msgs[0]), 'labeled', received.append, OUTPUT_QOS)
    assert wait_for(lambda: node.count_subscribers('/labeled') == 1, 10.0)
    msg = kitti_msgs[1]
    h.publish_and_wait(msg)
    assert wait_for(lambda: any(m.header.stamp == msg.header.stamp for m in received), 10.0)
    assert builds == [1] and 'labeled' in node.window.snapshot()['timings'][-1]
