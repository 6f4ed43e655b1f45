# SPDX-License-Identifier: Apache-2.0
"""Tests for gp_ground_segmentation.ros.cloud: PointCloud2 <-> numpy, hand-built and random.

Messages are built in memory with the rclpy message classes; no rclpy.init() is needed.
The reference decoder below uses the struct module point by point, independent of numpy dtypes.
"""

import array
import os
import struct
import subprocess
import sys
import types

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st, HealthCheck
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from builtin_interfaces.msg import Time

from gp_ground_segmentation.core import compiled
from gp_ground_segmentation.ros import cloud as cloud_module
from gp_ground_segmentation.ros.cloud import (
    POINTFIELD_DTYPES, CloudFormatError, cloud_xyz, fields_dtype, float32_cloud, make_cloud,
    point_rows, read_cloud, split_cloud, subset_cloud, xyz_dtype)
from scenes.real_data import DATA_DIR as DATA

STRUCT_CHARS = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}
SIZES = {k: struct.calcsize(v) for k, v in STRUCT_CHARS.items()}


def pf(name, offset, datatype, count=1):
    return PointField(name=name, offset=offset, datatype=datatype, count=count)


def cloud(fields, point_step, data, width, height=1, row_step=None, bigendian=False,
          dense=False, frame='lidar'):
    return PointCloud2(header=Header(stamp=Time(sec=12, nanosec=345), frame_id=frame),
                       height=height, width=width, fields=fields, is_bigendian=bigendian,
                       point_step=point_step,
                       row_step=width * point_step if row_step is None else row_step,
                       data=array.array('B', bytes(data)), is_dense=dense)


def reference_decode(msg):
    """Slow decoder: dict name -> list over points of tuples (count values each)."""
    endian = '>' if msg.is_bigendian else '<'
    data = bytes(msg.data)
    out = {f.name: [] for f in msg.fields}
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            for f in msg.fields:
                fmt = endian + STRUCT_CHARS[f.datatype] * f.count
                out[f.name].append(struct.unpack_from(fmt, data, base + f.offset))
    return out


def reference_rows(msg):
    data = bytes(msg.data)
    return [data[r * msg.row_step + c * msg.point_step:
                 r * msg.row_step + (c + 1) * msg.point_step]
            for r in range(msg.height) for c in range(msg.width)]


def assert_matches_reference(msg, pts):
    ref = reference_decode(msg)
    assert pts.shape == (msg.height * msg.width,)
    for f in msg.fields:
        got = pts[f.name].reshape(pts.shape[0], f.count)
        exp = np.array(ref[f.name], dtype=np.float64 if f.datatype >= 7 else np.int64)
        exp = exp.reshape(pts.shape[0], f.count)
        with np.errstate(invalid='ignore'):  # signalling-NaN bit patterns from random bytes
            got = got.astype(exp.dtype)
        np.testing.assert_array_equal(got, exp)


# --------------------------------------------------------------------------- hand-built layouts

def test_padded_layout_with_intensity_and_ring():
    # x y z float32, 4 pad bytes, intensity float32, ring uint16, 6 trailing pad bytes.
    fields = [pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7), pf('intensity', 16, 7),
              pf('ring', 20, 4)]
    step = 28
    rng = np.random.default_rng(1)
    n = 7
    raw = bytearray(rng.integers(0, 256, n * step, dtype=np.uint8).tobytes())
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    for i in range(n):
        struct.pack_into('<fff', raw, i * step, *xyz[i])
        struct.pack_into('<fH', raw, i * step + 16, float(i), 100 + i)
    msg = cloud(fields, step, raw, n)
    pts = read_cloud(msg)
    assert pts.dtype.itemsize == step
    np.testing.assert_array_equal(cloud_xyz(pts), xyz.astype(np.float64))
    np.testing.assert_array_equal(pts['ring'], np.arange(100, 100 + n))
    np.testing.assert_array_equal(pts['intensity'], np.arange(n, dtype=np.float32))
    rows = point_rows(msg)
    assert rows.shape == (n, step) and rows.tobytes() == bytes(raw)


def test_every_datatype_and_count_greater_than_one():
    fields, off = [], 0
    for dt in range(1, 9):
        fields.append(pf(f'f{dt}', off, dt, count=1 + dt % 3))
        off += SIZES[dt] * (1 + dt % 3) + 1  # one pad byte after each: unaligned offsets
    rng = np.random.default_rng(2)
    n = 11
    raw = rng.integers(0, 256, n * off, dtype=np.uint8).tobytes()
    msg = cloud(fields, off, raw, n)
    pts = read_cloud(msg)
    for dt in range(1, 9):
        ft = pts.dtype.fields[f'f{dt}'][0]
        assert ft.base.kind == POINTFIELD_DTYPES[dt].kind
        assert ft.base.itemsize == POINTFIELD_DTYPES[dt].itemsize
        assert ft.shape == (() if 1 + dt % 3 == 1 else (1 + dt % 3,))
    assert_matches_reference(msg, pts)


def test_bigendian_and_littleendian_give_identical_xyz():
    rng = np.random.default_rng(3)
    n = 50
    xyz = rng.normal(scale=20, size=(n, 3))
    fields = [pf('x', 0, 8), pf('y', 8, 8), pf('z', 16, 8), pf('ring', 24, 4)]
    ring = np.arange(n, dtype=np.uint16)
    out = {}
    for big in (False, True):
        o = '>' if big else '<'
        arr = np.zeros(n, dtype=np.dtype({'names': ['x', 'y', 'z', 'ring'],
                                          'formats': [o + 'f8'] * 3 + [o + 'u2'],
                                          'offsets': [0, 8, 16, 24], 'itemsize': 32}))
        arr['x'], arr['y'], arr['z'], arr['ring'] = xyz[:, 0], xyz[:, 1], xyz[:, 2], ring
        msg = cloud(fields, 32, arr.tobytes(), n, bigendian=big)
        pts = read_cloud(msg)
        out[big] = cloud_xyz(pts)
        assert out[big].dtype == np.float64 and out[big].dtype.isnative
        np.testing.assert_array_equal(pts['ring'], ring)
        assert_matches_reference(msg, pts)
        # Raw bytes are kept in the message byte order.
        assert point_rows(msg).tobytes() == arr.tobytes()
        sub = subset_cloud(msg, ring % 2 == 0)
        assert sub.is_bigendian == big
        assert bytes(sub.data) == arr[ring % 2 == 0].tobytes()
    np.testing.assert_array_equal(out[False], xyz)
    np.testing.assert_array_equal(out[True], out[False])


def test_organized_cloud_with_row_padding():
    height, width, step, row_step = 4, 5, 12, 5 * 12 + 7
    rng = np.random.default_rng(4)
    grid = rng.normal(size=(height, width, 3)).astype(np.float32)
    raw = bytearray(rng.integers(0, 256, height * row_step, dtype=np.uint8).tobytes())
    for r in range(height):
        raw[r * row_step:r * row_step + width * step] = grid[r].tobytes()
    msg = cloud([pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)], step, raw, width,
                height=height, row_step=row_step)
    pts = read_cloud(msg)
    np.testing.assert_array_equal(cloud_xyz(pts), grid.reshape(-1, 3).astype(np.float64))
    rows = point_rows(msg)
    assert [bytes(r) for r in rows] == reference_rows(msg)
    sel = np.array([19, 0, 7, 7])
    sub = subset_cloud(msg, sel)
    assert bytes(sub.data) == b''.join(reference_rows(msg)[i] for i in sel)
    assert (sub.height, sub.width, sub.row_step) == (1, 4, 4 * step)


def test_float64_and_int16_xyz():
    n = 9
    x64 = np.zeros(n, dtype=[('x', '<f8'), ('y', '<f8'), ('z', '<f8')])
    x64['x'] = np.linspace(-1, 1, n)
    x64['y'] = 1e-12
    x64['z'] = np.pi
    pts = read_cloud(cloud([pf('x', 0, 8), pf('y', 8, 8), pf('z', 16, 8)], 24, x64.tobytes(), n))
    xyz = cloud_xyz(pts)
    np.testing.assert_array_equal(xyz[:, 0], x64['x'])
    assert xyz[0, 1] == 1e-12 and xyz[0, 2] == np.pi  # no float32 round trip
    i16 = np.zeros(n, dtype=[('z', '<i2'), ('x', '<i2'), ('y', '<i2')])
    i16['x'] = np.arange(n) - 4
    i16['y'] = -32768
    i16['z'] = 32767
    pts = read_cloud(cloud([pf('z', 0, 3), pf('x', 2, 3), pf('y', 4, 3)], 6, i16.tobytes(), n))
    xyz = cloud_xyz(pts)
    assert xyz.dtype == np.float64
    np.testing.assert_array_equal(xyz, np.stack([np.arange(n) - 4, np.full(n, -32768),
                                                 np.full(n, 32767)], axis=1))


def test_cloud_xyz_view_only_where_the_layout_allows_it():
    """copy=False: a read-only strided view on the message data for native, consecutive,
    aligned x, y, z of the asked precision; for every other layout the same values as a copy
    (big-endian, another order, a gap between fields, float64 asked of float32 fields,
    unaligned offsets, padded rows)."""
    rng = np.random.default_rng(9)
    n = 40
    xyz = rng.normal(scale=30, size=(n, 3)).astype(np.float32)

    def msg_of(order, offsets, step, fmt='<f4', big=False, datatype=7):
        arr = np.zeros(n, dtype=np.dtype({'names': list(order), 'formats': [fmt] * 3,
                                          'offsets': offsets, 'itemsize': step}))
        for c in order:
            arr[c] = xyz[:, 'xyz'.index(c)]
        fields = [pf(c, o, datatype) for c, o in zip(order, offsets)]
        return cloud(fields, step, arr.tobytes(), n, bigendian=big)

    viewed = msg_of('xyz', [0, 4, 8], 16)
    view = cloud_xyz(read_cloud(viewed), dtype=None, copy=False)
    assert view.dtype == np.float32 and view.strides == (16, 4) and not view.flags.writeable
    assert np.shares_memory(view, np.frombuffer(viewed.data, np.uint8))
    np.testing.assert_array_equal(view, xyz)
    shifted = cloud_xyz(read_cloud(msg_of('xyz', [4, 8, 12], 20)), None, copy=False)
    assert not shifted.flags.writeable and shifted.strides == (20, 4)  # x not at 0: a view
    np.testing.assert_array_equal(shifted, xyz)
    copied = [msg_of('xyz', [0, 4, 8], 16, '>f4', big=True), msg_of('zxy', [0, 4, 8], 16),
              msg_of('xyz', [0, 4, 12], 16), msg_of('xyz', [1, 5, 9], 13)]
    for msg in copied:
        out = cloud_xyz(read_cloud(msg), dtype=None, copy=False)
        assert out.flags.writeable and out.flags.f_contiguous, msg.fields
        np.testing.assert_array_equal(out, xyz)
    out = cloud_xyz(read_cloud(viewed), dtype=np.float64, copy=False)
    assert out.dtype == np.float64 and out.flags.writeable
    np.testing.assert_array_equal(out, xyz)
    # no points: (0, 3) whatever the offsets (an empty buffer holds no view at an offset)
    for offsets, step in (([0, 4, 8], 16), ([4, 8, 12], 20), ([16, 20, 24], 32)):
        empty = cloud([pf(c, o, 7) for c, o in zip('xyz', offsets)], step, b'', 0)
        assert cloud_xyz(read_cloud(empty), dtype=None, copy=False).shape == (0, 3)


def test_data_as_bytes_and_list_and_longer_than_needed():
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    msg = cloud([pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)], 12, xyz.tobytes() + b'\x01\x02', 4)
    np.testing.assert_array_equal(cloud_xyz(read_cloud(msg)), xyz)  # trailing bytes ignored
    assert point_rows(msg).shape == (4, 12)
    duck = types.SimpleNamespace(**{k: getattr(msg, k) for k in
                                    ('header', 'height', 'width', 'fields', 'is_bigendian',
                                     'point_step', 'row_step', 'is_dense')})
    duck.data = xyz.tobytes()  # read-only bytes (as some deserialisers return)
    np.testing.assert_array_equal(cloud_xyz(read_cloud(duck)), xyz)
    duck.data = list(xyz.tobytes())
    np.testing.assert_array_equal(cloud_xyz(read_cloud(duck)), xyz)
    sub = subset_cloud(duck, [3, 1])
    assert isinstance(sub, types.SimpleNamespace)
    assert bytes(sub.data) == xyz[[3, 1]].tobytes()
    assert sub.header is not duck.header and sub.header.frame_id == 'lidar'


def test_read_cloud_is_view_without_row_padding():
    xyz = np.arange(6, dtype=np.float32).reshape(2, 3)
    msg = cloud([pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)], 12, xyz.tobytes(), 2)
    pts = read_cloud(msg)
    assert np.shares_memory(pts, np.frombuffer(msg.data, np.uint8))


def test_empty_clouds():
    f = [pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)]
    for width, height in ((0, 1), (5, 0), (0, 0)):
        msg = cloud(f, 12, b'', width, height=height)
        pts = read_cloud(msg)
        assert pts.shape == (0,)
        assert cloud_xyz(pts).shape == (0, 3)
        assert point_rows(msg).shape == (0, 12)
        sub = subset_cloud(msg, np.zeros(0, bool))
        assert sub.width == 0 and len(sub.data) == 0


# --------------------------------------------------------------------------- make_cloud / subset

@pytest.mark.parametrize('rows', [0, 1, 3000])
@pytest.mark.parametrize('names', [('x', 'y', 'z', 'z_std'), ('x', 'y', 'z'), ('a', 'z')])
def test_float32_cloud_is_make_cloud_of_the_structured_rows(rows, names):
    """The surface cloud's builder gives make_cloud's message: header copied, fields, sizes,
    bytes, is_dense (False with a NaN in x, y or z, or without all three)."""
    rng = np.random.default_rng(rows)
    values = rng.normal(size=(rows, len(names))).astype(np.float32)
    header = Header(stamp=Time(sec=5, nanosec=6), frame_id='base')
    cases = [values]
    if rows:
        nan = values.copy()
        nan[rows // 2, len(names) - 1] = np.nan
        cases.append(nan)
    for case in cases:
        packed = case.view([(n, np.float32) for n in names]).reshape(-1)
        expected = make_cloud(header, packed)
        msg = float32_cloud(header, case, names)
        assert msg == expected and msg.header is not header
        assert float32_cloud(header, case, names, PointCloud2) == expected
    with pytest.raises(ValueError):
        float32_cloud(header, values[:, :1], names)
    # repeated names: make_cloud cannot build their structured dtype, and neither does this
    with pytest.raises(ValueError, match='repeated'):
        float32_cloud(header, np.zeros((rows, 2), np.float32), ('z', 'z'))


def test_make_cloud_round_trip_structured_with_padding():
    dt = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'ring', 'rgb'],
                   'formats': ['<f4', '<f4', '<f4', '<u1', '<u2', ('<u1', (3,))],
                   'offsets': [0, 4, 8, 13, 16, 20], 'itemsize': 24})
    rng = np.random.default_rng(5)
    pts = np.zeros(40, dtype=dt)
    for name in ('x', 'y', 'z'):
        pts[name] = rng.normal(size=40)
    pts['intensity'] = rng.integers(0, 256, 40)
    pts['ring'] = rng.integers(0, 32, 40)
    pts['rgb'] = rng.integers(0, 256, (40, 3))
    header = Header(stamp=Time(sec=5, nanosec=6), frame_id='base')
    msg = make_cloud(header, pts)
    assert isinstance(msg, PointCloud2)
    assert msg.header == header and msg.header is not header
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 40, 24, 960)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('intensity', 13, 2, 1),
        ('ring', 16, 4, 1), ('rgb', 20, 2, 3)]
    assert msg.is_dense
    back = read_cloud(msg)
    assert back.dtype == dt
    for name in dt.names:
        np.testing.assert_array_equal(back[name], pts[name])
    assert_matches_reference(msg, back)


def test_make_cloud_from_xyz_array_and_bigendian_array():
    xyz = np.array([[1, 2, 3], [np.nan, 0, 0]], dtype=np.float64)
    msg = make_cloud(None, xyz)
    assert [f.datatype for f in msg.fields] == [7, 7, 7] and msg.point_step == 12
    assert not msg.is_dense
    np.testing.assert_array_equal(cloud_xyz(read_cloud(msg)), xyz)
    big = np.zeros(3, dtype=[('x', '>f8'), ('y', '>f8'), ('z', '>f8'), ('t', '>u4')])
    big['x'] = [1.5, -2, 3]
    big['t'] = [7, 8, 9]
    msg = make_cloud(Header(frame_id='f'), big)
    assert msg.is_bigendian and bytes(msg.data) == big.tobytes()
    np.testing.assert_array_equal(read_cloud(msg)['t'], [7, 8, 9])


def brute_force_subset(msg, idx):
    rows = reference_rows(msg)
    return b''.join(rows[i] for i in idx)


@pytest.mark.parametrize('seed', range(5))
def test_subset_cloud_byte_identity(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 30))
    step = int(rng.integers(12, 25))
    fields = [pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)]
    raw = rng.integers(0, 256, n * step, dtype=np.uint8).tobytes()
    msg = cloud(fields, step, raw, n, dense=bool(seed % 2), bigendian=bool(seed % 3 == 0))
    mask = rng.random(n) < 0.5
    sub = subset_cloud(msg, mask)
    assert type(sub) is PointCloud2
    assert bytes(sub.data) == brute_force_subset(msg, [i for i in range(n) if mask[i]])
    assert (sub.height, sub.width, sub.point_step, sub.row_step) == (
        1, int(mask.sum()), step, int(mask.sum()) * step)
    assert sub.is_dense == msg.is_dense and sub.is_bigendian == msg.is_bigendian
    assert sub.fields == msg.fields and sub.fields[0] is not msg.fields[0]
    assert sub.header == msg.header and sub.header is not msg.header
    assert isinstance(sub.data, array.array)
    idx = rng.integers(0, n, 7)
    assert bytes(subset_cloud(msg, idx).data) == brute_force_subset(msg, idx)
    # complementary masks partition the bytes
    rest = subset_cloud(msg, ~mask)
    assert sub.width + rest.width == n


def test_subset_cloud_bad_selection():
    msg = cloud([pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)], 12, bytes(36), 3)
    with pytest.raises(ValueError):
        subset_cloud(msg, np.ones(4, bool))
    with pytest.raises(IndexError):
        subset_cloud(msg, [3])
    with pytest.raises(IndexError):
        subset_cloud(msg, [-1])


# --------------------------------------------------------------------------- split_cloud

def assert_split_is_subsets(msg, ground, valid):
    """split_cloud's messages are subset_cloud's of the two masks, byte for byte."""
    ground_msg, obstacle_msg, counts = split_cloud(msg, ground, valid)
    obstacles = valid & ~ground
    for got, mask in ((ground_msg, ground), (obstacle_msg, obstacles)):
        expected = subset_cloud(msg, mask)
        assert got == expected
        assert bytes(got.data) == bytes(expected.data)
        assert type(got) is type(expected) and type(got.data) is array.array
        assert got.header is not msg.header and got.fields[0] is not msg.fields[0]
    assert counts == (int(ground.sum()), int(obstacles.sum()), int((~valid).sum()))
    assert all(type(c) is int for c in counts)
    return counts


def _run_masks(rng, n, mean_run):
    """ground, valid (n,) bool with runs of about mean_run points of each class."""
    classes = np.repeat(rng.integers(0, 3, n), rng.geometric(1 / mean_run, n))[:n]
    return classes == 1, classes >= 1


def test_split_cloud_organized_with_row_padding(split_path):
    height, width, step, row_step = 4, 5, 12, 5 * 12 + 7
    rng = np.random.default_rng(4)
    msg = cloud(XYZ, step, rng.integers(0, 256, height * row_step + 3, dtype=np.uint8), width,
                height=height, row_step=row_step)
    for seed in range(5):
        ground, valid = _run_masks(np.random.default_rng(seed), height * width, 3)
        assert_split_is_subsets(msg, ground, valid)


@pytest.mark.parametrize('step', [13, 12, 16, 17, 32])
@pytest.mark.parametrize('bigendian', [False, True])
def test_split_cloud_random_masks_and_layouts(split_path, step, bigendian):
    """Short and long runs (word steps across a run's end), unaligned point_step (13, 17), and
    masks at every byte offset from an 8-byte boundary (views into a longer mask)."""
    rng = np.random.default_rng(step + 100 * bigendian)
    for n, mean_run in ((1, 1), (7, 2), (9, 20), (64, 8), (1000, 1.5), (3000, 60), (3000, 400)):
        fields = [pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)]
        msg = cloud(fields, step, rng.integers(0, 256, n * step, dtype=np.uint8), n,
                    bigendian=bigendian, dense=bool(n % 2))
        ground, valid = _run_masks(rng, n, mean_run)
        assert_split_is_subsets(msg, ground, valid)
        assert_split_is_subsets(msg, rng.random(n) < 0.5, rng.random(n) < 0.9)
        for shift in range(1, 8):
            longer = np.zeros((2, n + 8), dtype=bool)
            longer[0, shift:shift + n], longer[1, 8 - shift:8 - shift + n] = ground, valid
            assert_split_is_subsets(msg, longer[0, shift:shift + n],
                                    longer[1, 8 - shift:8 - shift + n])


def test_split_cloud_all_ground_all_invalid_and_empty(split_path):
    n, step = 50, 16
    msg = cloud(XYZ, step, (np.arange(n * step) % 251).astype(np.uint8), n)
    ones, zeros = np.ones(n, bool), np.zeros(n, bool)
    assert assert_split_is_subsets(msg, ones, ones) == (n, 0, 0)  # all ground
    assert assert_split_is_subsets(msg, zeros, ones) == (0, n, 0)  # all obstacles
    assert assert_split_is_subsets(msg, zeros, zeros) == (0, 0, n)  # all invalid
    for empty in (cloud(XYZ, step, b'', 0), cloud(XYZ, step, b'', 5, height=0),
                  cloud(XYZ, 12, b'', 0, height=3)):
        none = np.zeros(0, bool)
        assert assert_split_is_subsets(empty, none, none) == (0, 0, 0)


def test_split_cloud_counts_a_ground_point_that_is_not_valid(split_path):
    """Masks that do not add up (an invalid point labelled ground): the messages are still
    subset_cloud's, and the counts show it (ground + obstacles + invalid > points)."""
    n = 40
    msg = cloud(XYZ, 12, (np.arange(n * 12) % 256).astype(np.uint8), n)
    ground = np.zeros(n, bool)
    ground[:20] = True
    valid = np.ones(n, bool)
    valid[[0, 5, 30]] = False  # 0 and 5 are ground too
    assert assert_split_is_subsets(msg, ground, valid) == (20, 19, 3)


def test_split_cloud_bad_masks():
    msg = cloud(XYZ, 12, bytes(36), 3)
    for ground, valid in ((np.ones(4, bool), np.ones(3, bool)),
                          (np.ones(3, bool), np.ones((3, 1), bool)),
                          (np.ones(3, int), np.ones(3, bool))):
        with pytest.raises(ValueError, match='mask'):
            split_cloud(msg, ground, valid)
    with pytest.raises(CloudFormatError):
        split_cloud(cloud(XYZ, 12, bytes(35), 3), np.ones(3, bool), np.ones(3, bool))


def test_split_rows_twin_is_the_compiled_pass():
    """_split_rows (numpy) and _split_rows_loop (numba) write the same rows and return the same
    counts, also when an output is shorter (cut) or longer (last rows untouched) than its
    selection and when the masks start off an 8-byte boundary."""
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    rng = np.random.default_rng(11)
    for trial in range(60):
        n = int(rng.integers(0, 400))
        step = int(rng.integers(1, 21))
        rows = rng.integers(0, 256, (n, step), dtype=np.uint8)
        if trial % 3 == 0:
            ground, valid = rng.random(n) < 0.4, rng.random(n) < 0.8
        else:
            ground, valid = _run_masks(rng, n, float(rng.choice([2, 9, 40])))
        shift = int(rng.integers(0, 8))
        longer = np.zeros((2, n + 8), dtype=bool)
        longer[0, shift:shift + n], longer[1, shift:shift + n] = ground, valid
        ground, valid = longer[0, shift:shift + n], longer[1, shift:shift + n]
        sizes = [int(ground.sum()), int((valid & ~ground).sum())]
        sizes = [max(k + int(rng.integers(-3, 4)), 0) if trial % 2 else k for k in sizes]
        results = []
        for split in (cloud_module._split_rows, cloud_module._split_rows_compiled):
            outs = [np.full((k, step), 0xAB, dtype=np.uint8) for k in sizes]
            counts = split(rows, ground, valid, *outs)
            results.append((tuple(int(c) for c in counts), outs))
        (counts, outs), (counts_c, outs_c) = results
        assert counts == counts_c
        assert counts == (int(ground.sum()), int((valid & ~ground).sum()), int((~valid).sum()))
        for a, b in zip(outs, outs_c):
            np.testing.assert_array_equal(a, b)
        k = min(sizes[0], counts[0])
        np.testing.assert_array_equal(outs[0][:k], rows[ground][:k])


# --------------------------------------------------------------------------- malformed clouds

XYZ = [pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7)]


def _raises(fn, *needles):
    with pytest.raises(CloudFormatError) as info:
        fn()
    text = str(info.value)
    assert '\n' not in text
    for needle in needles:
        assert needle in text, text
    return text


def test_data_shorter_than_rows():
    msg = cloud(XYZ, 12, bytes(12 * 9 + 5), 10)
    _raises(lambda: read_cloud(msg), '7 bytes missing')
    _raises(lambda: point_rows(msg), 'missing')
    _raises(lambda: subset_cloud(msg, [0]), 'missing')
    org = cloud(XYZ, 12, bytes(2 * 30 + 24), 2, height=3, row_step=30)  # last row incomplete
    _raises(lambda: read_cloud(org), '6 bytes missing')


def test_row_step_too_small():
    _raises(lambda: read_cloud(cloud(XYZ, 12, bytes(100), 4, row_step=40)), 'row_step 40')


def test_field_beyond_point_step():
    _raises(lambda: read_cloud(cloud(XYZ + [pf('t', 10, 6)], 12, bytes(24), 2)),
            "'t'", 'point_step 12')
    _raises(lambda: read_cloud(cloud([pf('x', 0, 7, count=4)], 12, bytes(24), 2)), "'x'")


def test_duplicate_unknown_and_count_zero():
    _raises(lambda: read_cloud(cloud(XYZ + [pf('x', 0, 7)], 12, bytes(24), 2)), 'duplicate', "'x'")
    for bad in (0, 9, 255):
        _raises(lambda: read_cloud(cloud(XYZ + [pf('q', 0, bad)], 12, bytes(24), 2)),
                f'unknown datatype {bad}')
    _raises(lambda: read_cloud(cloud(XYZ + [pf('q', 0, 2, count=0)], 12, bytes(24), 2)),
            'count 0')


def test_point_step_zero_with_points():
    _raises(lambda: read_cloud(cloud([], 0, bytes(0), 3)), 'point_step is 0')


def test_xyz_missing_or_multi_count():
    pts = read_cloud(cloud([pf('x', 0, 7), pf('y', 4, 7)], 12, bytes(24), 2))
    _raises(lambda: cloud_xyz(pts), 'z')
    pts = read_cloud(cloud([pf('x', 0, 7), pf('y', 4, 7), pf('z', 8, 7, count=2)], 16,
                           bytes(32), 2))
    _raises(lambda: cloud_xyz(pts), "'z'", 'count 2')
    with pytest.raises(CloudFormatError):
        cloud_xyz(np.zeros((3, 3)))


def test_fields_dtype_offsets_and_itemsize():
    dt = fields_dtype([pf('b', 8, 8), pf('a', 1, 3, count=2)], 20, is_bigendian=True)
    assert dt.itemsize == 20 and dt.names == ('b', 'a')
    assert dt.fields['b'][1] == 8 and dt.fields['b'][0] == np.dtype('>f8')
    assert dt.fields['a'][0] == np.dtype(('>i2', (2,)))


# --------------------------------------------------------------------------- property test

@st.composite
def layouts(draw):
    names = draw(st.lists(st.sampled_from(['x', 'y', 'z', 'intensity', 'ring', 't', 'rgb']),
                          min_size=1, max_size=5, unique=True))
    specs = [(nm, draw(st.integers(1, 8)), draw(st.integers(1, 3))) for nm in names]
    order = draw(st.permutations(range(len(specs))))
    offsets, off = {}, 0
    for i in order:  # byte placement order differs from the fields list order
        off += draw(st.integers(0, 3))
        offsets[i] = off
        off += SIZES[specs[i][1]] * specs[i][2]
    point_step = off + draw(st.integers(0, 5))
    fields = [pf(nm, offsets[i], dt, c) for i, (nm, dt, c) in enumerate(specs)]
    height = draw(st.integers(0, 3))
    width = draw(st.integers(0, 6))
    row_step = width * point_step + draw(st.integers(0, 6))
    nbytes = height * row_step + draw(st.integers(0, 4))
    seed = draw(st.integers(0, 2 ** 32 - 1))
    data = np.random.default_rng(seed).integers(0, 256, nbytes, dtype=np.uint8).tobytes()
    return cloud(fields, point_step, data, width, height=height, row_step=row_step,
                 bigendian=draw(st.booleans()), dense=draw(st.booleans()))


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(msg=layouts(), data=st.data())
def test_random_layouts_match_struct_reference(msg, data):
    pts = read_cloud(msg)
    assert_matches_reference(msg, pts)
    rows = point_rows(msg)
    assert [bytes(r) for r in rows] == reference_rows(msg)
    n = msg.height * msg.width
    mask = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype=bool)
    sub = subset_cloud(msg, mask)
    assert bytes(sub.data) == brute_force_subset(msg, np.flatnonzero(mask))
    names = [f.name for f in msg.fields]
    if all(c in names for c in 'xyz') and all(f.count == 1 for f in msg.fields if f.name in 'xyz'):
        xyz = cloud_xyz(pts)
        ref = reference_decode(msg)
        exp = np.array([[ref[c][i][0] for c in 'xyz'] for i in range(n)],
                       dtype=np.float64).reshape(n, 3)
        np.testing.assert_array_equal(xyz, exp)


# --------------------------------------------------------------------------- real data

def test_real_kitti_scan_round_trip():
    path = DATA / 'kitti_unlabeled_patchworkpp_000000.bin'
    if not path.exists():
        pytest.skip(f'real data not found at {path}')
    raw = path.read_bytes()
    dt = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])
    msg = make_cloud(Header(frame_id='velodyne'), np.frombuffer(raw, dt))
    assert msg.width == 124668 and bytes(msg.data) == raw
    xyz = cloud_xyz(read_cloud(msg))
    ground = xyz[:, 2] < -1.5
    g, o = subset_cloud(msg, ground), subset_cloud(msg, ~ground)
    assert g.width + o.width == msg.width
    rows = np.frombuffer(raw, np.uint8).reshape(-1, 16)
    assert bytes(g.data) == rows[ground].tobytes() and bytes(o.data) == rows[~ground].tobytes()


@pytest.mark.parametrize('order', ['<', '>'])
def test_cloud_xyz_keeps_float32_fields_float32_and_column_major(order):
    dt = np.dtype({'names': ['x', 'y', 'z', 'i'], 'formats': [order + 'f4'] * 3 + ['u1'],
                   'offsets': [0, 4, 8, 12], 'itemsize': 16})
    pts = np.zeros(5, dtype=dt)
    xyz = np.random.default_rng(2).normal(size=(5, 3)).astype(np.float32)
    pts['x'], pts['y'], pts['z'] = xyz.T
    assert xyz_dtype(pts) == np.float32
    out = cloud_xyz(pts, dtype=None)
    assert out.dtype == np.float32 and out.dtype.isnative and out.flags.f_contiguous
    np.testing.assert_array_equal(out, xyz)
    assert cloud_xyz(pts).dtype == np.float64  # the default stays float64
    wide = np.zeros(5, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f8')])
    assert xyz_dtype(wide) == np.float64 and cloud_xyz(wide, dtype=None).dtype == np.float64


def test_encoders_store_their_buffer_without_the_setters_copy():
    """The generated PointCloud2 keeps the array.array the encoder filled (the setter would
    store a copy of it); a message class without the generated slot gets it through its
    setter, and one whose getter does not return the slot too."""
    data = array.array('B', range(24))
    msg = PointCloud2()
    cloud_module._store_data(msg, data)
    assert msg.data is data
    double = types.SimpleNamespace()
    cloud_module._store_data(double, data)
    assert double.data is data

    class Copying:
        """A message whose setter copies and whose getter ignores ``_data``."""

        def __init__(self):
            self._stored = None
            self._data = None

        @property
        def data(self):
            return self._stored

        @data.setter
        def data(self, value):
            self._stored = array.array('B', value)

    copying = Copying()
    cloud_module._store_data(copying, data)
    assert copying.data == data and copying.data is not data
    # and what the encoders hand out is what their messages hold, byte for byte
    n, step = 30, 16
    src = cloud(XYZ, step, (np.arange(n * step) % 251).astype(np.uint8), n)
    ground = np.arange(n) % 3 == 0
    g, o, _ = split_cloud(src, ground, np.ones(n, bool))
    assert isinstance(g.data, array.array) and bytes(g.data) == bytes(
        subset_cloud(src, ground).data)
    values = np.arange(12, dtype=np.float32).reshape(3, 4)
    surface = float32_cloud(None, values, ('x', 'y', 'z', 'z_std'), PointCloud2)
    assert bytes(surface.data) == values.tobytes()


_SERIALISE_SCRIPT = '''
import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2
from gp_ground_segmentation.ros.cloud import (
    float32_cloud, make_cloud, split_cloud, with_float32_field)
rng = np.random.default_rng(3)
xyz = rng.normal(size=(500, 3)).astype(np.float32)
src = make_cloud(None, xyz)
ground = rng.random(500) < 0.6
valid = rng.random(500) < 0.9
made = list(split_cloud(src, ground, valid)[:2]) + [
    src, float32_cloud(None, xyz[:7], ('x', 'y', 'z'), PointCloud2),
    with_float32_field(src, 'h', np.arange(500.0))]
for msg in made:
    back = deserialize_message(serialize_message(msg), PointCloud2)
    assert bytes(back.data) == bytes(msg.data) and back.width == msg.width
print('ok', PointCloud2()._check_fields)
'''


@pytest.mark.parametrize('check_fields', ['0', '1'])
def test_encoded_messages_serialise_with_and_without_rosidl_field_checks(check_fields):
    """The messages keep the encoder's buffer in the generated ``_data`` slot: rclpy's
    serialiser reads it as it reads a setter-made one, whether ROS_PYTHON_CHECK_FIELDS makes the
    generated setters check their values or not (fresh interpreter: the flag is read when the
    message module is imported)."""
    env = dict(os.environ, ROS_PYTHON_CHECK_FIELDS=check_fields)
    done = subprocess.run([sys.executable, '-c', _SERIALISE_SCRIPT], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ['ok', str(check_fields == '1')]
