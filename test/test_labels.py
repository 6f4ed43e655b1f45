# SPDX-License-Identifier: Apache-2.0
"""The labelled rows (labels.py) and the labelled cloud (pipeline.labeled_cloud), no rclpy.init.

Hand-built points with padding, mixed field types, invalid rows and both byte orders: the rows
are the valid points in input order, every input byte unchanged, ``ground`` and
``height_above_ground`` at the offsets the module promises; the PointCloud2 of a real KITTI
frame carries the same rows. labels.py imports no ROS package.
"""

import json
import subprocess
import sys
import textwrap
import types

import numpy as np
import pytest
from conftest import REPO

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.labels import (GROUND_FIELD, HEIGHT_FIELD, labeled_dtype,
                                           labeled_points, structured_points)
from gp_ground_segmentation.ros.cloud import make_cloud, point_rows, read_cloud
from gp_ground_segmentation.ros.pipeline import labeled_cloud, process_cloud


def _result(ground, valid, height):
    """A stand-in for a SegmentationResult: what labeled_points reads."""
    return types.SimpleNamespace(ground_mask=np.array(ground, bool),
                                 valid_mask=np.array(valid, bool),
                                 height_above_ground=np.array(height, float))


# x, y, z float32 at 0, 4, 8; a 2-byte gap; ring uint16 at 14; intensity uint8 at 16; 21 bytes
POINT = np.dtype({'names': ['x', 'y', 'z', 'ring', 'intensity'],
                  'formats': ['<f4', '<f4', '<f4', '<u2', 'u1'],
                  'offsets': [0, 4, 8, 14, 16], 'itemsize': 21})


def _points(dtype=POINT):
    pts = np.zeros(4, dtype=dtype)
    raw = pts.view(np.uint8).reshape(4, -1)
    raw[:] = np.arange(4 * dtype.itemsize, dtype=np.uint8).reshape(4, -1)  # padding too
    pts['x'], pts['y'], pts['z'] = [1, 2, np.nan, 4], [0, 0, 0, 1], [-1, 0.5, 0, -1.5]
    return pts


def test_layout_offsets_and_alignment():
    dt = labeled_dtype(POINT)
    # the first 4-byte boundary after the 21 input bytes, then a float32, row of 32 bytes
    assert dt.fields[GROUND_FIELD][1] == 24 and dt.fields[HEIGHT_FIELD][1] == 28
    assert dt.itemsize == 32
    assert dt.fields[GROUND_FIELD][0] == np.uint8
    assert dt.fields[HEIGHT_FIELD][0] == np.dtype('<f4')
    for name in POINT.names:
        assert dt.fields[name] == POINT.fields[name]
    # a point already a multiple of 4 bytes: the labels follow it directly
    assert labeled_dtype(np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                   ('i', '<f4')])).fields[GROUND_FIELD][1] == 16


def test_rows_are_the_valid_points_in_order_with_their_bytes():
    pts = _points()
    result = _result([True, False, False, False], [True, True, False, True],
                     [0.05, 1.25, np.nan, -0.5])
    rows = labeled_points(pts, result)
    assert rows.shape == (3,)
    raw_in = pts.view(np.uint8).reshape(4, 21)
    raw_out = rows.view(np.uint8).reshape(3, 32)
    assert np.array_equal(raw_out[:, :21], raw_in[[0, 1, 3]])  # every byte, padding too
    assert np.array_equal(raw_out[:, 21:24], np.zeros((3, 3), np.uint8))  # zeroed padding
    assert rows[GROUND_FIELD].tolist() == [1, 0, 0]
    assert rows[HEIGHT_FIELD].tolist() == [np.float32(0.05), 1.25, -0.5]
    assert rows['ring'].tolist() == pts['ring'][[0, 1, 3]].tolist()


def test_big_endian_points_get_a_big_endian_height():
    big = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['>f4'] * 3, 'offsets': [0, 4, 8],
                    'itemsize': 12})
    pts = np.zeros(2, dtype=big)
    pts['x'] = [1.0, 2.0]
    rows = labeled_points(pts, _result([False, True], [True, True], [0.75, -2.0]))
    assert rows.dtype.fields[HEIGHT_FIELD][0] == np.dtype('>f4')
    assert rows.view(np.uint8).reshape(2, 20)[:, 16:].tobytes() == \
        np.array([0.75, -2.0], '>f4').tobytes()
    # asked for explicitly (a cloud's is_bigendian), whatever the fields say
    assert labeled_points(pts, _result([0, 1], [1, 1], [0, 0]),
                          '<').dtype.fields[HEIGHT_FIELD][0] == np.dtype('<f4')


def test_plain_arrays_get_named_columns():
    xyzi = np.array([[1.0, 2.0, 3.0, 0.5], [4.0, 5.0, 6.0, 0.25]], np.float32)
    assert structured_points(xyzi).dtype.names == ('x', 'y', 'z', 'column_3')
    rows = labeled_points(xyzi, _result([True, False], [True, True], [0.1, 0.9]))
    assert rows['column_3'].tolist() == [0.5, 0.25] and rows['z'].tolist() == [3.0, 6.0]
    with pytest.raises(ValueError, match='numeric array'):
        structured_points(np.zeros((3, 2)))


def test_refusals_name_the_problem():
    pts = _points()
    with pytest.raises(ValueError, match='4 points but the result labels 3'):
        labeled_points(pts, _result([0, 0, 0], [1, 1, 1], [0, 0, 0]))
    taken = np.zeros(2, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('ground', 'u1')])
    with pytest.raises(ValueError, match='already have a field named ground'):
        labeled_points(taken, _result([0, 0], [1, 1], [0, 0]))
    empty = labeled_points(pts, _result([0] * 4, [0] * 4, [np.nan] * 4))
    assert empty.shape == (0,) and empty.dtype == labeled_dtype(POINT)


def test_labeled_cloud_of_a_real_frame(kitti_msgs):
    msg = kitti_msgs[0]
    out = process_cloud(msg, GroundSegmenter(SegmenterParams()), labeled=True)
    cloud, result = out.labeled, out.result
    assert cloud is not None and np.isfinite(out.labeled_ms) and out.labeled_ms > 0
    assert cloud.header.stamp == msg.header.stamp and cloud.header.frame_id == 'velodyne'
    step = msg.point_step  # 16: x, y, z, intensity
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in msg.fields] + [
        (GROUND_FIELD, step, 2, 1), (HEIGHT_FIELD, step + 4, 7, 1)]
    assert cloud.point_step == step + 8 and cloud.height == 1 and cloud.is_dense
    valid = result.valid_mask
    assert cloud.width == int(valid.sum())
    rows = point_rows(cloud)
    assert np.array_equal(rows[:, :step], point_rows(msg)[valid])  # input order, same bytes
    values = read_cloud(cloud)
    assert np.array_equal(values[GROUND_FIELD].astype(bool), result.ground_mask[valid])
    np.testing.assert_allclose(values[HEIGHT_FIELD], result.height_above_ground[valid],
                               atol=1e-5)
    assert int(values[GROUND_FIELD].sum()) == out.ground.width
    # the same rows as the Python API's, as a message
    assert bytes(cloud.data) == labeled_points(read_cloud(msg), result).tobytes()


def test_labeled_cloud_leaves_invalid_points_out_and_keeps_big_endian():
    pts = np.zeros(5, dtype=[('x', '>f4'), ('y', '>f4'), ('z', '>f4')])
    pts['x'] = [1.0, np.nan, 0.0, 3.0, 4.0]
    pts['y'] = [0.0, 1.0, 0.0, 1.0, 2.0]
    pts['z'] = [-1.0, -1.0, 0.0, -0.9, 0.6]
    from std_msgs.msg import Header
    msg = make_cloud(Header(frame_id='lidar'), pts)
    result = _result([1, 0, 0, 1, 0], [1, 0, 0, 1, 1], [0.0, np.nan, np.nan, 0.1, 1.6])
    cloud = labeled_cloud(msg, result)
    assert msg.is_bigendian and cloud.is_bigendian and cloud.width == 3
    assert cloud.header.frame_id == 'lidar'
    values = read_cloud(cloud)
    assert values['x'].tolist() == [1.0, 3.0, 4.0]
    assert values[GROUND_FIELD].tolist() == [1, 1, 0]
    np.testing.assert_allclose(values[HEIGHT_FIELD], [0.0, 0.1, 1.6], atol=1e-6)


def test_labels_module_needs_no_ros():
    script = textwrap.dedent('''
        import json, sys
        BLOCKED = {'rclpy', 'sensor_msgs', 'std_msgs', 'rosbags', 'builtin_interfaces'}

        class NoRos:
            def find_spec(self, name, path=None, target=None):
                if name.split('.')[0] in BLOCKED:
                    raise ImportError(name + ' is blocked')
                return None
        sys.meta_path.insert(0, NoRos())
        import numpy as np
        from gp_ground_segmentation import GroundSegmenter
        from gp_ground_segmentation.labels import labeled_points
        rng = np.random.default_rng(1)
        xyz = np.c_[rng.uniform(-20, 20, (5000, 2)), rng.normal(-1.7, 0.02, 5000)]
        rows = labeled_points(xyz, GroundSegmenter().segment(xyz))
        print(json.dumps({'rows': int(rows.size), 'ground': float(rows['ground'].mean()),
                          'ros': sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)}))
    ''')
    out = subprocess.run([sys.executable, '-c', script], cwd=REPO, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report['ros'] == [] and report['rows'] == 5000
    assert report['ground'] > 0.95  # a flat floor
