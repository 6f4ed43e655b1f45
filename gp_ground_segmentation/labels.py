# SPDX-License-Identifier: Apache-2.0
"""One labelled array per frame: every field of the valid points plus ``ground`` and
``height_above_ground``, in input order (numpy only: no ROS, usable from the Python API).

The node's ``labeled`` topic is this array as a PointCloud2 (``ros.pipeline.labeled_cloud``),
and the offline tools can write the same rows. For points ``points`` (a structured array, as
``ros.cloud.read_cloud`` or ``tools.io.read_points_file`` return, or an (N, C) numeric array)
and the ``SegmentationResult`` of segmenting them:

* one row per valid point (``result.valid_mask``: finite and not the (0, 0, 0) no-return
  value), in input order;
* every input field, byte for byte at its own offset (the padding between fields too), then
  ``ground`` (uint8, 1 = ground, 0 = obstacle) at the first 4-byte boundary after the input's
  bytes and ``height_above_ground`` (float32, m: z - the GP ground height below the point,
  ``result.height_above_ground``) 4 bytes after it; the row is padded to a multiple of 4 bytes
  (zeros), so that the float of every row stays aligned;
* ``height_above_ground`` in the byte order of the input's multi-byte fields (big-endian when
  they all are, as ``ros.cloud.make_cloud`` decides), or ``byteorder`` when given.

An (N, C) numeric array has no field names: its columns become ``x``, ``y``, ``z`` and then
``column_3``, ``column_4``, ... in the array's dtype.
"""

from __future__ import annotations

import numpy as np

__all__ = ['GROUND_FIELD', 'HEIGHT_FIELD', 'LABEL_FIELDS', 'labeled_dtype', 'labeled_points',
           'structured_points']

GROUND_FIELD = 'ground'  # uint8: 1 = ground, 0 = obstacle
HEIGHT_FIELD = 'height_above_ground'  # float32, m: z - GP ground height below the point
LABEL_FIELDS = (GROUND_FIELD, HEIGHT_FIELD)


def _byteorder_of(dtype: np.dtype) -> str:
    """'>' when every multi-byte field of the structured ``dtype`` is big-endian, else '<'."""
    orders = set()
    for name in dtype.names:
        base = dtype.fields[name][0].base
        if base.itemsize > 1:
            native_big = base.byteorder == '=' and not np.little_endian
            orders.add('>' if base.byteorder == '>' or native_big else '<')
    return '>' if orders == {'>'} else '<'


def labeled_dtype(point_dtype: np.dtype, byteorder: str | None = None) -> np.dtype:
    """The structured dtype of :func:`labeled_points` rows for points of ``point_dtype``:
    its fields at their offsets, then ``ground`` and ``height_above_ground`` (module docstring).
    Raises ValueError when ``point_dtype`` already has one of those names."""
    point_dtype = np.dtype(point_dtype)
    if point_dtype.names is None:
        raise ValueError(f'labeled_dtype needs a structured dtype, got {point_dtype}')
    taken = [name for name in LABEL_FIELDS if name in point_dtype.names]
    if taken:
        raise ValueError(f"the points already have a field named {', '.join(taken)}")
    order = _byteorder_of(point_dtype) if byteorder is None else byteorder
    ground_at = -(-point_dtype.itemsize // 4) * 4  # the first 4-byte boundary after the point
    names = list(point_dtype.names) + list(LABEL_FIELDS)
    formats = [point_dtype.fields[n][0] for n in point_dtype.names] + [
        np.dtype(np.uint8), np.dtype(np.float32).newbyteorder(order)]
    offsets = [point_dtype.fields[n][1] for n in point_dtype.names] + [ground_at, ground_at + 4]
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': ground_at + 8})


def structured_points(points) -> np.ndarray:
    """``points`` as a C-contiguous structured (N,) array: a structured array as it is (made
    contiguous), an (N, C) numeric array as fields x, y, z, column_3, ... (module docstring)."""
    pts = np.asarray(points)
    if pts.dtype.names is not None:
        return np.ascontiguousarray(pts.reshape(-1))
    if pts.ndim != 2 or pts.shape[1] < 3 or pts.dtype.kind not in 'fiu':
        raise ValueError(f'points must be a structured array or an (N, >=3) numeric array, '
                         f'got {pts.dtype} {pts.shape}')
    names = ['x', 'y', 'z'] + [f'column_{i}' for i in range(3, pts.shape[1])]
    dtype = np.dtype({'names': names, 'formats': [pts.dtype] * len(names)})
    return np.ascontiguousarray(pts).view(dtype).reshape(-1)


def labeled_points(points, result, byteorder: str | None = None) -> np.ndarray:
    """The labelled rows of one frame (module docstring): a structured (K,) array of
    :func:`labeled_dtype`, K = the number of valid points, in input order.

    ``points``: the N points given to ``segment()`` (or their full records: any structured
    array of N rows); ``result``: its SegmentationResult. Raises ValueError when the counts
    differ or a label field name is taken.
    """
    pts = structured_points(points)
    valid = np.asarray(result.valid_mask, dtype=bool)
    if valid.shape != pts.shape:
        raise ValueError(f'{pts.shape[0]} points but the result labels {valid.size}')
    out = np.zeros(int(np.count_nonzero(valid)), dtype=labeled_dtype(pts.dtype, byteorder))
    if out.size:
        step = pts.dtype.itemsize
        # the input's bytes as one block per row (fields and the padding between them)
        rows = pts.view(np.dtype((np.void, step)))[valid]
        out.view(np.uint8).reshape(out.size, -1)[:, :step] = rows.view(np.uint8).reshape(
            out.size, step)
        out[GROUND_FIELD] = np.asarray(result.ground_mask, dtype=bool)[valid]
        out[HEIGHT_FIELD] = result.height_above_ground[valid]
    return out
