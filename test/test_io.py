# SPDX-License-Identifier: Apache-2.0
"""Tests for gp_ground_segmentation.tools.io: KITTI .bin/.label and PCD (ascii, binary, LZF)."""

import struct

import numpy as np
import pytest

from gp_ground_segmentation.tools.io import (
    PointFileError, lzf_decompress, read_kitti_bin, read_pcd, read_points_file,
    read_semantickitti_labels, write_pcd)
from scenes.real_data import DATA_DIR as DATA


def need(path):
    if not path.exists():
        pytest.skip(f'real data not found at {path}')
    return path


# --------------------------------------------------------------------------- real data

@pytest.mark.parametrize('name,count', [('velodyne_vlp16.pcd', 14831),
                                        ('velodyne_vlp32.pcd', 26216),
                                        ('hesai_xt32.pcd', 63021)])
def test_real_pcds(name, count):
    arr = read_points_file(need(DATA / 'sensors' / name))
    assert arr.shape == (count,)
    for c in 'xyz':
        assert arr.dtype[c] == np.float32
        assert np.isfinite(arr[c]).all()
    # Indoor captures a few metres across: z in a plausible band (README: -0.71..2.20 for VLP-16).
    assert -5 < arr['z'].min() < 0 < arr['z'].max() < 10


def test_real_vlp16_field_layout():
    arr = read_pcd(need(DATA / 'sensors' / 'velodyne_vlp16.pcd'))
    assert arr.dtype.names == ('x', 'y', 'z', 'intensity', 'return_type', 'channel', 'azimuth',
                               'elevation', 'distance', 'time_stamp')
    assert arr.dtype['channel'] == np.uint16 and arr.dtype['time_stamp'] == np.uint32
    assert len(np.unique(arr['channel'])) == 15  # README: 15 channel ids present
    dist = np.sqrt(arr['x'].astype(np.float64) ** 2 + arr['y'] ** 2 + arr['z'] ** 2)
    np.testing.assert_allclose(dist, arr['distance'], atol=0.02)


def test_real_kitti_bin_and_labels():
    scan = read_kitti_bin(need(DATA / 'kitti_sequnknown_spvnas_000000.bin'))
    assert scan.shape == (123389, 4) and scan.dtype == np.float32
    labels = read_semantickitti_labels(DATA / 'kitti_sequnknown_spvnas_000000.label',
                                       expected_points=scan.shape[0])
    assert labels.dtype == np.uint32 and labels.shape == (123389,)
    assert np.isin(labels, [40, 44, 48, 49, 60, 72]).sum() == 82076  # README ground count
    assert (labels == 40).sum() == 20975
    other = read_points_file(need(DATA / 'kitti_unlabeled_patchworkpp_000000.bin'))
    assert other.shape == (124668,) and other.dtype.names == ('x', 'y', 'z', 'intensity')


def test_label_count_mismatch(tmp_path):
    p = tmp_path / 'a.label'
    np.array([1 | (7 << 16), 40, 0xFFFF0048], dtype='<u4').tofile(p)
    np.testing.assert_array_equal(read_semantickitti_labels(p), [1, 40, 0x48])
    with pytest.raises(PointFileError, match='3 labels but the scan has 4 points'):
        read_semantickitti_labels(p, expected_points=4)
    p.write_bytes(b'\x00' * 6)
    with pytest.raises(PointFileError, match='multiple of 4'):
        read_semantickitti_labels(p)


def _scan(n=4000, seed=0):
    """A plausible KITTI-like scan: ground ring and walls, remission in [0, 1]."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(3, 60, n), rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1.8, 2.0, n),
                            rng.uniform(0, 1, n)]).astype('<f4')


@pytest.mark.parametrize('write, words', [
    (lambda pts, p: pts.astype('<f8').tofile(p), r'x, y, z of [1-9]\d* % .*float64 values'),
    (lambda pts, p: pts[:, :3].copy().tofile(p), r'4th value of [1-9]\d* % .*like a coordinate'),
    (lambda pts, p: np.arange(len(pts), dtype='<u4').tofile(p), r'x, y, z of 100 % .*\.label'),
    (lambda pts, p: (pts * [1000, 1000, 1000, 1]).astype('<f4').tofile(p), 'millimetres'),
], ids=['float64', 'xyz_only', 'labels', 'millimetres'])
def test_kitti_bin_in_another_layout_is_refused(tmp_path, write, words):
    # the sizes still split into 16-byte records: only the values give the layout away
    points = _scan(4000)
    points[:, 2] -= 1.0  # ground below the sensor: negative z, as in every real scan
    path = tmp_path / 'scan.bin'
    write(points, path)
    assert path.stat().st_size % 16 == 0
    with pytest.raises(PointFileError, match=words) as info:
        read_kitti_bin(path)
    assert 'float32' in str(info.value) and str(path) in str(info.value)
    good = tmp_path / 'good.bin'
    bad_returns = points.copy()
    bad_returns[:20, 0] = 1e9  # 0.5 % of absurd returns are tolerated
    bad_returns.tofile(good)
    assert read_kitti_bin(good).shape == points.shape


@pytest.mark.parametrize('fourth', ['time_offset', 'intensity_16bit', 'signed_gain', 'zero'])
def test_kitti_bin_takes_any_4th_value_a_sensor_writes(tmp_path, fourth):
    # the segmenter never reads it: time offsets around the scan's middle (+-50 ms), 16-bit
    # intensities, a signed normalised value, nothing
    points = _scan(4000, seed=1)
    rng = np.random.default_rng(2)
    points[:, 3] = {'time_offset': rng.uniform(-0.05, 0.05, len(points)),
                    'intensity_16bit': rng.uniform(0, 65535, len(points)),
                    'signed_gain': rng.uniform(-1, 1, len(points)),
                    'zero': np.zeros(len(points))}[fourth]
    path = tmp_path / 'scan.bin'
    points.tofile(path)
    assert np.array_equal(read_kitti_bin(path), points)


def test_kitti_bin_truncated(tmp_path):
    p = tmp_path / 'scan.bin'
    p.write_bytes(np.arange(8, dtype='<f4').tobytes() + b'\x00' * 5)
    with pytest.raises(PointFileError) as info:
        read_kitti_bin(p)
    assert str(p) in str(info.value) and 'multiple of 16' in str(info.value)
    with pytest.raises(PointFileError):
        read_points_file(p)


# --------------------------------------------------------------------------- PCD round trips

def sample_points(n=25, seed=0):
    rng = np.random.default_rng(seed)
    dt = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', 'u1'),
                   ('ring', '<u2'), ('t', '<f8'), ('id', '<i8'), ('normal', '<f4', (3,)),
                   ('s', 'i1')])
    pts = np.zeros(n, dtype=dt)
    for c in 'xyz':
        pts[c] = rng.normal(scale=30, size=n)
    pts['x'][:1] = np.nan
    pts['intensity'] = rng.integers(0, 256, n)
    pts['ring'] = rng.integers(0, 65536, n)
    pts['t'] = rng.random(n) * 1e9
    pts['id'] = rng.integers(-2 ** 62, 2 ** 62, n)
    pts['normal'] = rng.normal(size=(n, 3))
    pts['s'] = rng.integers(-128, 128, n)
    return pts


@pytest.mark.parametrize('binary', [True, False])
def test_pcd_write_read_round_trip(tmp_path, binary):
    pts = sample_points()
    p = tmp_path / 'c.pcd'
    write_pcd(p, pts, binary=binary)
    back = read_pcd(p)
    assert back.dtype == pts.dtype
    for name in pts.dtype.names:
        np.testing.assert_array_equal(back[name], pts[name])
    assert ('DATA binary' if binary else 'DATA ascii') in p.read_bytes().decode('latin1')


def test_pcd_empty_round_trip(tmp_path):
    pts = sample_points(0)
    for binary in (True, False):
        write_pcd(tmp_path / 'e.pcd', pts, binary=binary)
        assert read_pcd(tmp_path / 'e.pcd').shape == (0,)


def test_pcd_padding_fields_dropped(tmp_path):
    # PCL-style alignment padding: an '_' field of 3 bytes and another of 4.
    header = ('# .PCD v0.7\nVERSION 0.7\nFIELDS x y z _ intensity _\nSIZE 4 4 4 1 4 1\n'
              'TYPE F F F U F U\nCOUNT 1 1 1 3 1 4\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n'
              'POINTS 2\nDATA binary\n')
    body = b''.join(struct.pack('<fff3sf4s', i, 2 * i, 3 * i, b'PAD', 0.5 * i, b'pppp')
                    for i in range(2))
    p = tmp_path / 'pad.pcd'
    p.write_bytes(header.encode() + body)
    arr = read_points_file(p)
    assert arr.dtype.names == ('x', 'y', 'z', 'intensity')
    np.testing.assert_array_equal(arr['y'], [0, 2])
    np.testing.assert_array_equal(arr['intensity'], [0, 0.5])


def test_pcd_ascii_hand_written_organized(tmp_path):
    text = ('VERSION .7\nFIELDS x y z rgb\nSIZE 4 4 4 1\nTYPE F F F U\nCOUNT 1 1 1 3\n'
            'WIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n'
            '1 2 3 1 2 3\nnan nan nan 0 0 0\n-1.5 0 1e3 255 0 7\n0.1 0.2 0.3 4 5 6\n')
    p = tmp_path / 'a.pcd'
    p.write_text(text)
    arr = read_pcd(p)
    assert arr.shape == (4,)
    assert np.isnan(arr['x'][1]) and arr['z'][2] == np.float32(1e3)
    np.testing.assert_array_equal(arr['rgb'][2], [255, 0, 7])


# --------------------------------------------------------------------------- LZF

def lzf_compress(data):
    """Small greedy LZF compressor (test only) producing literal runs and back-references."""
    out, lit, table, i, n = bytearray(), bytearray(), {}, 0, len(data)

    def flush():
        while lit:
            chunk = lit[:32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
            del lit[:32]

    while i < n:
        if i + 3 <= n:
            key = data[i:i + 3]
            ref = table.get(key)
            table[key] = i
            if ref is not None and i - ref - 1 < 8192:
                length, limit = 3, min(264, n - i)
                while length < limit and data[ref + length] == data[i + length]:
                    length += 1
                flush()
                off, code = i - ref - 1, length - 2
                if code < 7:
                    out.append((code << 5) | (off >> 8))
                else:
                    out.append((7 << 5) | (off >> 8))
                    out.append(code - 7)
                out.append(off & 0xFF)
                i += length
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


def test_lzf_known_stream():
    # literal 'abc', then a back-reference of length 5 at distance 3 (overlapping copy)
    assert lzf_decompress(b'\x02abc\x60\x02', 8) == b'abcabcab'
    with pytest.raises(ValueError):
        lzf_decompress(b'\x02abc\x60\x05', 8)  # reference before the start
    with pytest.raises(ValueError):
        lzf_decompress(b'\x05ab', 6)  # literal run past the end


@pytest.mark.parametrize('seed', range(3))
def test_lzf_round_trip(seed):
    rng = np.random.default_rng(seed)
    parts = [rng.integers(0, 4, 3000, dtype=np.uint8).tobytes(), b'\x00' * 5000,
             rng.integers(0, 256, 2000, dtype=np.uint8).tobytes(), b'xy' * 700]
    data = b''.join(parts[i] for i in rng.permutation(4))
    comp = lzf_compress(data)
    assert len(comp) < len(data)
    assert lzf_decompress(comp, len(data)) == data


def write_compressed_pcd(path, pts):
    names = pts.dtype.names
    cols = b''.join(np.ascontiguousarray(pts[n]).tobytes() for n in names)
    comp = lzf_compress(cols)
    sizes = ' '.join(str(pts.dtype[n].base.itemsize) for n in names)
    types_ = ' '.join({'f': 'F', 'i': 'I', 'u': 'U'}[pts.dtype[n].base.kind] for n in names)
    counts = ' '.join(str(int(np.prod(pts.dtype[n].shape))) for n in names)
    head = (f'VERSION 0.7\nFIELDS {" ".join(names)}\nSIZE {sizes}\nTYPE {types_}\n'
            f'COUNT {counts}\nWIDTH {len(pts)}\nHEIGHT 1\nPOINTS {len(pts)}\n'
            'DATA binary_compressed\n')
    path.write_bytes(head.encode() + struct.pack('<II', len(comp), len(cols)) + comp)


def test_pcd_binary_compressed(tmp_path):
    pts = sample_points(300, seed=4)
    pts['intensity'][:150] = 9  # some runs for the compressor
    p = tmp_path / 'c.pcd'
    write_compressed_pcd(p, pts)
    back = read_pcd(p)
    for name in pts.dtype.names:
        np.testing.assert_array_equal(back[name], pts[name])
    # a truncated compressed block is reported, not decoded into garbage
    raw = p.read_bytes()
    p.write_bytes(raw[:-10])
    with pytest.raises(PointFileError, match='truncated'):
        read_pcd(p)


def test_real_pcd_as_compressed(tmp_path):
    """The real VLP-16 cloud re-packed as binary_compressed decodes to the same values."""
    arr = read_pcd(need(DATA / 'sensors' / 'velodyne_vlp16.pcd'))
    p = tmp_path / 'vlp16c.pcd'
    write_compressed_pcd(p, arr)
    back = read_pcd(p)
    for name in arr.dtype.names:
        np.testing.assert_array_equal(back[name], arr[name])


# --------------------------------------------------------------------------- errors

HEAD = ('VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n'
        'POINTS 3\n')


@pytest.mark.parametrize('content,needle', [
    (HEAD + 'DATA binary\n' + 'x' * 35, 'truncated file'),
    (HEAD + 'DATA ascii\n1 2 3\n4 5 6\n7 8\n', 'truncated file'),
    (HEAD + 'DATA ascii\n1 2 3\n4 5 6\n7 8 zz\n', "bad ascii value in field 'z'"),
    (HEAD + 'DATA binary_lz4\n', "unsupported DATA 'binary_lz4'"),
    (HEAD.replace('TYPE F F F', 'TYPE F F Q') + 'DATA ascii\n', 'bad header'),
    (HEAD.replace('SIZE 4 4 4', 'SIZE 4 4') + 'DATA ascii\n', 'bad header'),
    (HEAD.replace('POINTS 3', 'POINTS 4') + 'DATA ascii\n', 'bad header'),
    (HEAD.replace('WIDTH 3', 'WIDTH three') + 'DATA ascii\n', 'bad header'),
    (HEAD, 'no DATA line'),
    ('hello world\n', 'bad header'),
    (HEAD.replace('FIELDS x y z', 'FIELDS x y x') + 'DATA ascii\n', 'duplicate'),
])
def test_pcd_errors(tmp_path, content, needle):
    p = tmp_path / 'bad.pcd'
    p.write_bytes(content.encode())
    with pytest.raises(PointFileError) as info:
        read_pcd(p)
    msg = str(info.value)
    assert msg.startswith(str(p)) and needle in msg and '\n' not in msg


def test_points_file_missing_xyz_and_unknown_type(tmp_path):
    p = tmp_path / 'noz.pcd'
    pts = np.zeros(3, dtype=[('x', '<f4'), ('y', '<f4'), ('intensity', '<f4')])
    write_pcd(p, pts)
    with pytest.raises(PointFileError, match='missing field z'):
        read_points_file(p)
    q = tmp_path / 'cloud.ply'
    q.write_bytes(b'ply\n')
    with pytest.raises(PointFileError, match="unsupported file type '.ply'"):
        read_points_file(q)
    with pytest.raises(PointFileError, match='cannot read'):
        read_points_file(tmp_path / 'absent.pcd')
    assert issubclass(PointFileError, ValueError)
