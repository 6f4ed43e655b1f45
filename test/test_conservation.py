# SPDX-License-Identifier: Apache-2.0
"""Conservation property (issue 7 point 2): for every valid cloud, whatever its layout,
``pipeline.process_cloud`` returns ground ∪ obstacles = all valid input points, disjoint, each
point's bytes (every field and the padding inside point_step) unchanged, header copied.

Valid = finite x, y, z and not exactly (0, 0, 0), computed here from the values the cloud was
encoded from. Layouts are drawn by hypothesis: x, y, z as float32 or float64 in any order among
extra fields of every PointField datatype (count 1..3), gaps and trailing padding inside
point_step, little or big endian, organized clouds (height > 1) with row padding, trailing bytes
after the last row, 0..5000 points with random NaN/Inf/(0, 0, 0) rows. The clouds are encoded
here with numpy (not with ``cloud.make_cloud``) so the decoder is checked against an
independent encoder. One segmenter is shared by all examples, so its warm-started state sees
every kind of cloud in turn, as the node's does.
"""

import array

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from conftest import assert_output_like_input
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from gp_ground_segmentation import GroundSegmenter
from gp_ground_segmentation.ros.cloud import point_rows
from gp_ground_segmentation.ros.pipeline import process_cloud

_TYPES = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
SEGMENTER = GroundSegmenter()


@st.composite
def clouds(draw):
    """(msg, xyz truth (N, 3) float64, rows truth uint8 (N, point_step))."""
    xyz_code = draw(st.sampled_from([7, 8]))
    extras = draw(st.lists(st.tuples(st.sampled_from(sorted(_TYPES)), st.integers(1, 3)),
                           max_size=4))
    fields = [('x', xyz_code, 1), ('y', xyz_code, 1), ('z', xyz_code, 1)]
    fields += [(f'f{i}', code, count) for i, (code, count) in enumerate(extras)]
    order = draw(st.permutations(range(len(fields))))
    gaps = draw(st.lists(st.integers(0, 3), min_size=len(fields), max_size=len(fields)))
    big = draw(st.booleans())
    height = draw(st.sampled_from([1, 1, 2, 3, 4]))
    width = draw(st.integers(0, 5000 // height))
    row_pad = draw(st.integers(0, 7)) if height > 1 else draw(st.sampled_from([0, 0, 5]))
    tail = draw(st.integers(0, 3))
    p_bad = draw(st.sampled_from([0.0, 0.01, 0.2, 1.0]))
    seed = draw(st.integers(0, 2**32 - 1))

    o = '>' if big else '<'
    names, formats, offsets, pf = [], [], [], []
    offset = 0
    for k, gap in zip(order, gaps):
        name, code, count = fields[k]
        offset += gap
        fmt = np.dtype(o + _TYPES[code])
        names.append(name)
        formats.append(fmt if count == 1 else np.dtype((fmt, (count,))))
        offsets.append(offset)
        pf.append(PointField(name=name, offset=offset, datatype=code, count=count))
        offset += fmt.itemsize * count
    step = offset + draw(st.integers(0, 8))
    dt = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': step})

    rng = np.random.default_rng(seed)
    n = height * width
    r = rng.uniform(0.5, 60.0, n)
    a = rng.uniform(-np.pi, np.pi, n)
    xyz = np.c_[r * np.cos(a), r * np.sin(a), -1.7 + 0.03 * rng.standard_normal(n)]
    objects = rng.random(n) < 0.2
    xyz[objects, 2] += rng.uniform(0.1, 3.0, objects.sum())
    bad = np.flatnonzero(rng.random(n) < p_bad)
    kinds = rng.integers(0, 4, bad.size)
    xyz[bad[kinds == 0], rng.integers(0, 3)] = np.nan
    xyz[bad[kinds == 1], rng.integers(0, 3)] = np.inf
    xyz[bad[kinds == 2], 2] = -np.inf
    xyz[bad[kinds == 3]] = 0.0
    raw = rng.integers(0, 256, n * step, dtype=np.uint8)  # random padding and extra fields
    pts = raw.view(dt)
    for j, c in enumerate('xyz'):
        pts[c] = xyz[:, j]
    truth = np.stack([pts[c].astype(np.float64) for c in 'xyz'], axis=1)  # after rounding
    rows = raw.reshape(n, step).copy()
    grid = rows.reshape(height, width * step)
    data = np.hstack([grid, rng.integers(0, 256, (height, row_pad), dtype=np.uint8)])

    msg = PointCloud2()
    msg.header = Header(frame_id=f'lidar_{seed % 7}')
    msg.header.stamp.sec, msg.header.stamp.nanosec = seed % 100000, seed % 10**9
    msg.height, msg.width = height, width
    msg.fields = pf
    msg.is_bigendian = big
    msg.point_step = step
    msg.row_step = width * step + row_pad
    buf = array.array('B')
    buf.frombytes(data.tobytes() + bytes(tail))
    msg.data = buf
    msg.is_dense = p_bad == 0.0
    return msg, truth, rows


def _sorted(rows):
    rows = np.ascontiguousarray(rows)
    if rows.shape[0] == 0:
        return []
    return np.sort(rows.view(np.dtype((np.void, rows.shape[1]))).reshape(-1))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.data_too_large])
@given(clouds())
def test_ground_and_obstacles_partition_the_valid_points(cloud):
    msg, xyz, rows = cloud
    valid = np.isfinite(xyz).all(axis=1) & ~(xyz == 0).all(axis=1)
    out = process_cloud(msg, SEGMENTER)
    assert np.array_equal(out.result.valid_mask, valid)
    assert out.result.num_invalid == int((~valid).sum())
    assert not np.any(out.result.ground_mask & ~valid)
    for cloud_out in (out.ground, out.obstacles):
        assert_output_like_input(msg, cloud_out)
        assert cloud_out.header is not msg.header
    g, o = point_rows(out.ground), point_rows(out.obstacles)
    # The masks say which input rows went where: byte-identical rows, no row in both.
    assert np.array_equal(g, rows[out.result.ground_mask])
    assert np.array_equal(o, rows[valid & ~out.result.ground_mask])
    # And as multisets, independently of the masks: union == valid rows (so also disjoint).
    assert g.shape[0] + o.shape[0] == int(valid.sum())
    both = np.concatenate([g, o]) if rows.shape[0] else rows
    assert np.array_equal(_sorted(both), _sorted(rows[valid]))
