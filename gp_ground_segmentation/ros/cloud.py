# SPDX-License-Identifier: Apache-2.0
"""sensor_msgs/PointCloud2 <-> numpy conversion, vectorized and strict about the layout.

There is no ``sensor_msgs_py`` on PyPI, so this module plays its role. Nothing here imports
rclpy: a message is anything with the PointCloud2 attributes (``header, height, width, fields,
is_bigendian, point_step, row_step, data, is_dense``), fields anything with ``name, offset,
datatype, count``. ``make_cloud`` imports ``sensor_msgs.msg`` lazily only when no message type
is given.

Layout rules (REP-less but what every driver and ``sensor_msgs_py`` assume):

* point ``i`` of row ``r`` starts at byte ``r * row_step + i * point_step``;
* a field occupies ``offset .. offset + size(datatype) * count`` inside ``point_step``; bytes not
  covered by any field are padding and are kept untouched by ``point_rows``/``subset_cloud``/
  ``split_cloud``;
* ``row_step >= width * point_step``; bytes past ``width * point_step`` in a row are row padding
  and are never returned as points;
* ``len(data) >= height * row_step``. Data *longer* than that is accepted: the extra trailing
  bytes are not points and are ignored (some drivers over-allocate the buffer). Shorter data is an
  error, because points would be missing.

Speed notes (measured with rclpy 7.1 Jazzy generated messages, 124,668 x 16-byte points):
assigning ``msg.data`` from a numpy array iterates element-wise (~110 ms) and, with
``ROS_PYTHON_CHECK_FIELDS=1``, so does a ``bytes`` assignment; an ``array.array('B')`` is stored
as is with ``ROS_PYTHON_CHECK_FIELDS=1`` and copied with one memcpy without it (the default:
``array.array('B', value)``; < 0.1 ms). So encoders build ``array.array('B')`` with
``frombytes`` (one memcpy), or fill one in place (``split_cloud``), and store it in the
generated message's ``_data`` slot, which the setter would have filled with a copy of it
(``_store_data``; any other message class goes through its setter). The getter returns the
stored ``array.array`` (or ``bytes`` after some deserialisers), which ``np.frombuffer`` wraps
without copying.
"""

import array
import copy

import numpy as np

from ..core import compiled

__all__ = ['CloudFormatError', 'POINTFIELD_DTYPES', 'fields_dtype', 'read_cloud', 'cloud_xyz',
           'xyz_dtype', 'point_rows', 'subset_cloud', 'split_cloud', 'make_cloud', 'set_data',
           'float32_cloud', 'with_float32_field', 'cloud_with_fields']


class CloudFormatError(ValueError):
    """A PointCloud2 whose layout is inconsistent or unusable; the message is one line."""


# sensor_msgs/PointField datatype constants -> numpy base types (byte order added per cloud).
POINTFIELD_DTYPES = {
    1: np.dtype(np.int8),     # INT8
    2: np.dtype(np.uint8),    # UINT8
    3: np.dtype(np.int16),    # INT16
    4: np.dtype(np.uint16),   # UINT16
    5: np.dtype(np.int32),    # INT32
    6: np.dtype(np.uint32),   # UINT32
    7: np.dtype(np.float32),  # FLOAT32
    8: np.dtype(np.float64),  # FLOAT64
}
UINT8 = 2  # sensor_msgs/PointField.UINT8
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
_DATATYPE_NAMES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                   7: 'FLOAT32', 8: 'FLOAT64'}
# numpy (kind, itemsize) -> PointField datatype, for make_cloud.
_NUMPY_TO_DATATYPE = {(dt.kind, dt.itemsize): code for code, dt in POINTFIELD_DTYPES.items()}


def _as_int(value, what):
    """Message integers must be non-negative Python/numpy ints (uint32 in the message)."""
    try:
        iv = int(value)
    except (TypeError, ValueError):
        raise CloudFormatError(f'{what} is not an integer: {value!r}') from None
    if iv != value or iv < 0:
        raise CloudFormatError(f'{what} must be a non-negative integer, got {value!r}')
    return iv


def fields_dtype(fields, point_step, is_bigendian=False):
    """Structured dtype for one point: field offsets as given, ``itemsize = point_step``.

    ``fields``: sequence of PointField-like objects; ``point_step``: bytes per point;
    ``is_bigendian``: byte order of every multi-byte field. ``count > 1`` becomes a subarray
    field of shape ``(count,)``. Raises CloudFormatError for an unknown datatype, ``count == 0``,
    duplicate or empty names, or a field that does not fit in ``point_step``.
    """
    point_step = _as_int(point_step, 'point_step')
    order = '>' if is_bigendian else '<'
    names, formats, offsets = [], [], []
    for f in fields:
        name = f.name
        if not isinstance(name, str) or not name:
            raise CloudFormatError(f'field name must be a non-empty string, got {name!r}')
        if name in names:
            raise CloudFormatError(f"duplicate field name '{name}'")
        datatype = _as_int(f.datatype, f"field '{name}' datatype")
        if datatype not in POINTFIELD_DTYPES:
            raise CloudFormatError(f"field '{name}' has unknown datatype {datatype} (valid: 1..8)")
        count = _as_int(f.count, f"field '{name}' count")
        if count == 0:
            raise CloudFormatError(f"field '{name}' has count 0")
        offset = _as_int(f.offset, f"field '{name}' offset")
        base = POINTFIELD_DTYPES[datatype].newbyteorder(order)
        end = offset + base.itemsize * count
        if end > point_step:
            raise CloudFormatError(
                f"field '{name}' ({_DATATYPE_NAMES[datatype]} x{count} at offset {offset}) "
                f'ends at byte {end}, beyond point_step {point_step}')
        names.append(name)
        formats.append(base if count == 1 else np.dtype((base, (count,))))
        offsets.append(offset)
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': point_step})


def _data_buffer(msg):
    """``msg.data`` as a flat uint8 array, without a copy when it supports the buffer protocol."""
    data = msg.data
    try:
        buf = np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError):
        # Lists/tuples (hand-built duck-typed messages) or exotic buffers: copy once.
        buf = np.asarray(data, dtype=np.uint8)
    return buf.reshape(-1)


def _layout(msg):
    """Validate the message geometry; return (dtype, height, width, point_step, row_step, buf)."""
    height = _as_int(msg.height, 'height')
    width = _as_int(msg.width, 'width')
    point_step = _as_int(msg.point_step, 'point_step')
    row_step = _as_int(msg.row_step, 'row_step')
    dtype = fields_dtype(msg.fields, point_step, bool(msg.is_bigendian))
    n = height * width
    if n > 0 and point_step == 0:
        raise CloudFormatError(f'point_step is 0 but the cloud has {n} points')
    if height > 0 and row_step < width * point_step:
        raise CloudFormatError(
            f'row_step {row_step} < width {width} * point_step {point_step} = '
            f'{width * point_step}')
    buf = _data_buffer(msg)
    need = height * row_step if n > 0 else 0
    if buf.size < need:
        raise CloudFormatError(
            f'data has {buf.size} bytes but height {height} * row_step {row_step} = {need} '
            f'bytes are required ({need - buf.size} bytes missing)')
    return dtype, height, width, point_step, row_step, buf


def _rows_u8(buf, height, width, point_step, row_step):
    """uint8 (N, point_step): a view when rows are unpadded, else one vectorized copy."""
    n = height * width
    if n == 0:
        return np.zeros((0, point_step), dtype=np.uint8)
    if row_step == width * point_step or height == 1:
        return buf[:n * point_step].reshape(n, point_step)
    # Drop the row padding: (height, row_step) view -> first width*point_step bytes of each row.
    grid = buf[:height * row_step].reshape(height, row_step)[:, :width * point_step]
    return np.ascontiguousarray(grid).reshape(n, point_step)


def read_cloud(msg):
    """Decode a PointCloud2 into a structured array of shape ``(height * width,)``.

    The dtype follows the message: field offsets, padding (``itemsize = point_step``), subarrays
    for ``count > 1`` and the message byte order (big-endian clouds give a '>' dtype; numpy
    converts on any arithmetic or ``astype``, see ``cloud_xyz``). Row padding is removed.
    When rows are unpadded the result is a zero-copy **view on msg.data**: ``.copy()`` before
    writing into it. Raises CloudFormatError on an inconsistent layout.
    """
    dtype, height, width, point_step, row_step, buf = _layout(msg)
    rows = _rows_u8(buf, height, width, point_step, row_step)
    n = height * width
    if n == 0:
        return np.zeros((0,), dtype=dtype)
    return np.ndarray(shape=(n,), dtype=dtype, buffer=rows.data if rows.flags.c_contiguous
                      else np.ascontiguousarray(rows).data)


def cloud_xyz(points, dtype=np.float64, copy=True):
    """``(N, 3)`` x, y, z (native byte order, ``dtype``) from a structured point array.

    x, y, z may be any PointField numeric type. ``dtype``: float64 (default), float32, or None
    for the cloud's own precision (:func:`xyz_dtype`). The result is column-major, so each
    coordinate is one contiguous array. Raises CloudFormatError when one is missing or has
    ``count != 1``.

    ``copy=False``: when x, y, z are already ``dtype`` in native byte order, side by side and
    aligned (x, y, z at offsets o, o + 4, o + 8 of every FLOAT32 point, as every LiDAR driver
    writes them), a read-only strided **view** on the points (on msg.data after read_cloud):
    the segmenter's first pass reads the rows once instead of this function copying them into
    columns first (benchmarks/RESULTS.md, "The node's decode as a view"). Otherwise the copy,
    as with ``copy=True``.
    """
    names = points.dtype.names
    if names is None:
        raise CloudFormatError('cloud_xyz needs a structured point array (from read_cloud)')
    missing = [c for c in ('x', 'y', 'z') if c not in names]
    if missing:
        raise CloudFormatError(f"cloud has no field {', '.join(missing)} (fields: {list(names)})")
    for c in ('x', 'y', 'z'):
        ft = points.dtype.fields[c][0]
        if ft.shape != ():
            raise CloudFormatError(f"field '{c}' has count {int(np.prod(ft.shape))}, expected 1")
    dtype = xyz_dtype(points) if dtype is None else np.dtype(dtype)
    if not copy:
        view = _xyz_view(points, dtype)
        if view is not None:
            return view
    out = np.empty((points.shape[0], 3), dtype=dtype, order='F')
    # Signalling-NaN bit patterns (driver garbage) raise FE_INVALID when widened; they still
    # become NaN, which the segmenter treats as invalid, so the warning is only noise.
    with np.errstate(invalid='ignore'):
        for j, c in enumerate(('x', 'y', 'z')):
            out[:, j] = points[c]  # casts and byte-swaps to native order in one pass
    return out


def _xyz_view(points, dtype):
    """(N, 3) read-only view of x, y, z in ``points`` when they are ``dtype`` (native order),
    consecutive and aligned; None otherwise (:func:`cloud_xyz`)."""
    fields = points.dtype.fields
    size = dtype.itemsize
    offsets = [fields[c][1] for c in ('x', 'y', 'z')]
    if (any(fields[c][0] != dtype for c in ('x', 'y', 'z'))  # type, and native byte order
            or offsets != [offsets[0], offsets[0] + size, offsets[0] + 2 * size]
            or points.ndim != 1 or not points.flags.c_contiguous or points.shape[0] == 0):
        return None  # (an empty buffer cannot hold a view that starts at an offset)
    view = np.ndarray((points.shape[0], 3), dtype=dtype, buffer=points,
                      offset=offsets[0], strides=(points.strides[0], size))
    if not view.flags.aligned:
        return None
    view.flags.writeable = False
    return view


def xyz_dtype(points) -> np.dtype:
    """float32 when x, y and z are all FLOAT32 fields (every LiDAR driver), else float64.

    float32 loses nothing for such a cloud, and the segmenter gives the same result for float32
    input as for the same values in float64 (its grid decides in float64, grid.py).
    """
    fields = points.dtype.fields or {}
    kinds = {fields[c][0].base.newbyteorder('=') for c in ('x', 'y', 'z') if c in fields}
    return np.dtype(np.float32) if kinds == {np.dtype(np.float32)} else np.dtype(np.float64)


def point_rows(msg):
    """uint8 ``(N, point_step)``: each point's raw bytes (every field and padding, original byte
    order), row padding removed. A view on msg.data when rows are unpadded."""
    _, height, width, point_step, row_step, buf = _layout(msg)
    return _rows_u8(buf, height, width, point_step, row_step)


def _store_data(msg, data) -> None:
    """``msg.data = data`` for an ``array.array('B')`` ``data``, without the generated setter's
    copy where the message keeps the field in the generated ``_data`` slot.

    rosidl's Python setter stores ``array.array('B', value)`` -- a fresh copy of an
    array.array too -- unless ``ROS_PYTHON_CHECK_FIELDS`` is set, when it stores an
    array.array('B') as is: the message then holds the same object either way, one memcpy of
    the cloud (~0.1 ms per 1 MB) and its allocation fewer. Any other message class (a test
    double, a future layout whose getter does not return that slot) goes through its setter.
    """
    try:
        msg._data = data
    except AttributeError:
        msg.data = data
        return
    if getattr(msg, 'data', None) is not data:
        msg.data = data


def set_data(msg, contiguous) -> None:
    """Set ``msg.data`` to a copy of the bytes of the C-contiguous numpy array ``contiguous``:
    one memcpy into an array.array('B'), which the message keeps as is (:func:`_store_data`)."""
    _store_data(msg, _u8_array(contiguous))


def _u8_array(contiguous):
    """array.array('B') holding a copy of a C-contiguous numpy array's bytes (fast setter path)."""
    out = array.array('B')
    out.frombytes(contiguous.reshape(-1).view(np.uint8))
    return out


def _copy_header(header):
    """A new header of the same class with the same stamp and frame_id."""
    try:
        stamp = header.stamp
        new_stamp = type(stamp)(sec=stamp.sec, nanosec=stamp.nanosec)
        return type(header)(stamp=new_stamp, frame_id=header.frame_id)
    except (TypeError, AttributeError):
        return copy.deepcopy(header)


def _copy_fields(fields):
    out = []
    for f in fields:
        try:
            out.append(type(f)(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count))
        except TypeError:
            out.append(copy.deepcopy(f))
    return out


def subset_cloud(msg, selection):
    """A new message of ``type(msg)`` holding the selected points' bytes unchanged.

    ``selection``: bool mask of shape ``(height * width,)`` or integer indices into the flattened
    cloud (order kept, repeats allowed). Header (new object, same stamp and frame_id), fields,
    point_step, is_bigendian and is_dense are copied; height = 1, width = k,
    row_step = k * point_step. Raises CloudFormatError for a bad input layout, ValueError for a
    mask of the wrong length and IndexError for an index out of range.
    """
    _, height, width, point_step, row_step, buf = _layout(msg)
    rows = _rows_u8(buf, height, width, point_step, row_step)
    n = rows.shape[0]
    sel = np.asarray(selection)
    if sel.dtype == bool:
        if sel.shape != (n,):
            raise ValueError(f'selection mask has shape {sel.shape}, cloud has {n} points')
    else:
        if sel.size == 0:
            sel = sel.astype(np.intp)
        if sel.ndim != 1 or not np.issubdtype(sel.dtype, np.integer):
            raise ValueError('selection must be a bool mask or a 1-D array of integer indices')
        if sel.size and (sel.min() < 0 or sel.max() >= n):
            raise IndexError(f'selection index out of range 0..{n - 1}')
    if n == 0:
        picked = np.zeros((0,), dtype=np.uint8)  # indices were checked above: none can be valid
    else:
        # One opaque item per point: numpy copies each selected point with one memcpy instead
        # of point_step single bytes.
        picked = _items(rows)[sel]
    return _points_message(msg, point_step, int(picked.shape[0]),
                           _u8_array(np.ascontiguousarray(picked)))


def _items(rows):
    """(N,) opaque items of point_step bytes, one per row of the uint8 ``rows`` (N, point_step):
    numpy copies a selected item with one memcpy instead of point_step single bytes."""
    n, point_step = rows.shape
    return np.ascontiguousarray(rows).view(np.dtype((np.void, point_step))).reshape(n)


def _points_message(msg, point_step, k, data):
    """A new unorganized message of ``type(msg)`` holding ``k`` points, ``data`` (an
    array.array('B') of k * point_step bytes): header, fields, byte order and is_dense of ``msg``
    (subset_cloud, split_cloud)."""
    out = type(msg)()
    out.header = _copy_header(msg.header)
    out.height = 1
    out.width = k
    out.fields = _copy_fields(msg.fields)
    out.is_bigendian = bool(msg.is_bigendian)
    out.point_step = point_step
    out.row_step = k * point_step
    _store_data(out, data)
    out.is_dense = bool(msg.is_dense)
    return out


def split_cloud(msg, ground_mask, valid_mask):
    """``(ground, obstacles, counts)``: the messages ``subset_cloud(msg, ground_mask)`` and
    ``subset_cloud(msg, valid_mask & ~ground_mask)``, byte for byte, built in one compiled pass
    over the points (:func:`_split_rows_loop`; its numpy twin while it compiles, or without
    numba), and ``counts = (ground, obstacles, invalid)``: the numbers of points in
    ``ground_mask``, in ``valid_mask & ~ground_mask`` and not in ``valid_mask``. They add up to
    the cloud's points unless a ground point is not valid (a point in neither output's mask
    is counted invalid; none can be in both).

    ``ground_mask``, ``valid_mask``: bool (height * width,). Raises CloudFormatError for a bad
    input layout and ValueError for a mask of the wrong shape, as subset_cloud.

    The outputs' bytes are written where the messages keep them (array.array('B'), sized from
    the masks' counts) instead of picked into numpy arrays and copied into array.arrays, and the
    layout is checked once, not once per output (benchmarks/RESULTS.md, "The output clouds in
    one pass").
    """
    _, height, width, point_step, row_step, buf = _layout(msg)
    rows = _read_only(_rows_u8(buf, height, width, point_step, row_step))
    n = rows.shape[0]
    masks = []
    for name, mask in (('ground_mask', ground_mask), ('valid_mask', valid_mask)):
        mask = np.asarray(mask)
        if mask.dtype != bool or mask.shape != (n,):  # before ascontiguousarray makes 0-d 1-d
            raise ValueError(f'{name} must be a bool mask of shape ({n},), got {mask.dtype} '
                             f'{mask.shape}')
        masks.append(_read_only(np.ascontiguousarray(mask)))
    ground, valid = masks
    n_ground = int(np.count_nonzero(ground))
    # exact when every ground point is valid; otherwise the pass reports more and runs again
    n_obstacles = max(int(np.count_nonzero(valid)) - n_ground, 0)
    while True:
        ground_data, ground_rows = _zeroed_rows(n_ground, point_step)
        obstacle_data, obstacle_rows = _zeroed_rows(n_obstacles, point_step)
        counts = compiled.run(True, _split_rows_compiled, _split_rows, rows, ground, valid,
                              ground_rows, obstacle_rows)
        counts = tuple(int(c) for c in counts)
        if counts[0] != n_ground:  # count_nonzero and the pass disagree: never seen
            raise RuntimeError(f'split_cloud: {counts[0]} ground rows written, '
                               f'{n_ground} expected')
        if counts[1] == n_obstacles:
            break
        n_obstacles = counts[1]
    return (_points_message(msg, point_step, n_ground, ground_data),
            _points_message(msg, point_step, n_obstacles, obstacle_data), counts)


def _read_only(array_):
    """A read-only view of ``array_``: split_cloud only reads its inputs, so numba compiles one
    signature whether msg.data is writable (array.array) or not (bytes)."""
    view = array_.view()
    view.flags.writeable = False
    return view


def _zeroed_rows(k, point_step):
    """(array.array('B') of k * point_step zero bytes, a writable (k, point_step) uint8 view of
    it): a message's data, filled in place (one memset, not numpy's copy plus frombytes')."""
    data = array.array('B', b'\0') * (k * point_step)
    return data, np.frombuffer(data, dtype=np.uint8).reshape(k, point_step)


def _split_rows(rows, ground, valid, out_ground, out_obstacles):
    """Copy the ``rows`` (N, point_step) uint8 of the points in bool ``ground`` (N,), in order,
    into ``out_ground`` and those in ``valid & ~ground`` into ``out_obstacles`` (uint8
    (K, point_step) each, filled up to their K rows: a longer selection is cut there, a shorter
    one leaves the last rows as they were); return the numbers of points in ``ground``, in
    ``valid & ~ground`` and not in ``valid``, the whole selections' counts. The numpy reference
    of :func:`_split_rows_loop`."""
    n_points, point_step = rows.shape
    obstacles = valid & ~ground
    if n_points and point_step:
        items = _items(rows)
        for mask, out in ((ground, out_ground), (obstacles, out_obstacles)):
            picked = items[mask]
            k = min(picked.shape[0], out.shape[0])
            _items(out)[:k] = picked[:k]
    return (np.count_nonzero(ground), np.count_nonzero(obstacles),
            n_points - np.count_nonzero(valid))


def _split_rows_loop(rows, ground, valid, out_ground, out_obstacles):
    """:func:`_split_rows` in one pass over the points (compiled with numba). The masks have
    long runs of one class (ground, obstacle, invalid: ~60 points a run on KITTI's frames), so
    the pass goes from run to run (:func:`_run_end`, 8 points a step) and copies each run's rows
    as one block (:func:`_copy_rows`): 0.11 ms on a 124k-point KITTI frame (16-byte rows),
    warm caches, alone; copying point by point took 0.6 ms (8-byte words) to 2.1 ms (bytes),
    finding the runs a byte at a time 0.24 ms."""
    n_points = rows.shape[0]
    point_step = rows.shape[1]
    source = rows.reshape(-1)
    ground_out = out_ground.reshape(-1)
    obstacle_out = out_obstacles.reshape(-1)
    ground_bytes = ground.view(np.uint8)
    valid_bytes = valid.view(np.uint8)
    n_ground = 0
    n_obstacles = 0
    n_valid = 0
    i = 0
    while i < n_points:
        end = _run_end(valid_bytes, i, _run_end(ground_bytes, i, n_points))
        count = end - i
        if valid_bytes[i] != 0:
            n_valid += count
        if ground_bytes[i] != 0:
            _copy_rows(ground_out, n_ground, source, i,
                       max(min(count, out_ground.shape[0] - n_ground), 0), point_step)
            n_ground += count
        elif valid_bytes[i] != 0:
            _copy_rows(obstacle_out, n_obstacles, source, i,
                       max(min(count, out_obstacles.shape[0] - n_obstacles), 0), point_step)
            n_obstacles += count
        i = end
    return n_ground, n_obstacles, n_points - n_valid


def _run_end(mask, start, stop):
    """The first index in start + 1 .. stop - 1 where the bytes ``mask`` (uint8 (N,)) differ
    from ``mask[start]``, else ``stop`` (``start < stop``). Compares 8 bytes a step (one uint64
    word) from the first 8-byte aligned address on: ~5x faster than a byte loop on long runs."""
    value = mask[start]
    j = start + 1
    address = mask.ctypes.data
    while j < stop and (address + j) % 8 != 0:
        if mask[j] != value:
            return j
        j += 1
    if stop - j >= 8:
        words = mask[j:j + (stop - j) // 8 * 8].view(np.uint64)
        pattern = np.uint64(value) * np.uint64(0x0101010101010101)
        w = 0
        while w < words.size and words[w] == pattern:
            w += 1
        j += 8 * w
    while j < stop:
        if mask[j] != value:
            return j
        j += 1
    return stop


def _copy_rows(out, first_out, source, first, count, point_step):
    """Copy ``count`` rows of ``point_step`` bytes from row ``first`` of the flat uint8
    ``source`` to row ``first_out`` of the flat uint8 ``out``. Unsigned offsets: with signed
    ones numba's negative-index wraparound keeps LLVM from vectorizing the byte loop (~10x
    slower; 8-byte words gain nothing over the vectorized bytes)."""
    step = np.uint64(point_step)
    to = np.uint64(first_out) * step
    start = np.uint64(first) * step
    for b in range(np.uint64(count) * step):
        out[to + b] = source[start + b]


_run_end = compiled.kernel(_run_end) or _run_end  # before the kernel that calls them
_copy_rows = compiled.kernel(_copy_rows) or _copy_rows
_split_rows_compiled = compiled.kernel(_split_rows_loop)


def _field_class(msg_type):
    try:
        from sensor_msgs.msg import PointField
        return PointField
    except ImportError:  # duck-typed use without ROS messages installed
        import types

        def make(**kw):
            return types.SimpleNamespace(**kw)
        return make


def make_cloud(header, points, msg_type=None):
    """Encode ``points`` as an unorganized PointCloud2 (height 1), for tests and tools.

    ``points``: structured array (fields of the eight PointField types, subarrays -> count;
    offsets/itemsize kept, so padding survives) or an ``(N, 3)`` numeric array, encoded as
    x, y, z FLOAT32 (metres). ``header``: copied (same stamp/frame_id); None gives a default
    header. ``msg_type``: message class, default ``sensor_msgs.msg.PointCloud2``. Byte order: the
    array's if every multi-byte field is big-endian, otherwise little-endian (mixed-order arrays
    are converted). ``is_dense`` is True when all x, y, z are finite.
    """
    if msg_type is None:
        from sensor_msgs.msg import PointCloud2 as msg_type
    pts = np.asarray(points)
    if pts.dtype.names is None:
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f'unstructured points must have shape (N, 3), got {pts.shape}')
        xyz = np.ascontiguousarray(pts, dtype='<f4')
        pts = xyz.view(np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4')])).reshape(-1)
    if pts.ndim != 1:
        pts = pts.reshape(-1)
    dt = pts.dtype
    field_cls = _field_class(msg_type)
    multibyte_orders = set()
    specs = []
    for name in dt.names:
        ft, offset = dt.fields[name][:2]
        base, shape = (ft.subdtype if ft.subdtype is not None else (ft, ()))
        code = _NUMPY_TO_DATATYPE.get((base.kind, base.itemsize))
        if code is None or len(shape) > 1:
            raise ValueError(f"field '{name}' has dtype {ft} with no PointField equivalent")
        count = int(shape[0]) if shape else 1
        if base.itemsize > 1:
            multibyte_orders.add('>' if base.byteorder == '>' or (
                base.byteorder == '=' and np.little_endian is False) else '<')
        specs.append((name, offset, code, count))
    bigendian = multibyte_orders == {'>'}
    target = fields_dtype([field_cls(name=n, offset=o, datatype=c, count=k)
                           for n, o, c, k in specs], dt.itemsize, bigendian)
    if dt != target:
        conv = np.zeros(pts.shape, dtype=target)  # zeroed padding, deterministic bytes
        for name in dt.names:
            conv[name] = pts[name]
        pts = conv
    pts = np.ascontiguousarray(pts)
    msg = msg_type()
    if header is not None:
        msg.header = _copy_header(header)
    msg.height = 1
    msg.width = int(pts.shape[0])
    msg.fields = [field_cls(name=n, offset=o, datatype=c, count=k) for n, o, c, k in specs]
    msg.is_bigendian = bigendian
    msg.point_step = int(dt.itemsize)
    msg.row_step = int(dt.itemsize) * int(pts.shape[0])
    set_data(msg, pts.view(np.uint8) if pts.size else np.zeros(0, np.uint8))
    names = dt.names
    xyz_names = ('x', 'y', 'z')
    if (all(c in names for c in xyz_names)
            and all(pts.dtype.fields[c][0].shape == () for c in xyz_names)):
        msg.is_dense = all(bool(np.isfinite(pts[c]).all()) for c in ('x', 'y', 'z'))
    else:
        msg.is_dense = False
    return msg


def float32_cloud(header, values, names, msg_type=None):
    """``make_cloud`` of (K, F) float32 ``values`` as the structured array of F little-endian
    FLOAT32 fields ``names`` (one a column, in order, no padding): the same message, without
    make_cloud's generic dtype checks and conversion (the node's ground surface cloud)."""
    if msg_type is None:
        from sensor_msgs.msg import PointCloud2 as msg_type
    values = np.ascontiguousarray(values, dtype='<f4')
    count = len(names)
    if len(set(names)) != count:  # make_cloud's structured dtype would refuse them too
        raise ValueError(f'repeated field names in {list(names)}')
    if values.ndim != 2 or values.shape[1] != count:
        raise ValueError(f'values of shape {values.shape} for {count} fields')
    field_cls = _field_class(msg_type)
    msg = msg_type()
    if header is not None:
        msg.header = _copy_header(header)
    msg.height = 1
    msg.width = int(values.shape[0])
    msg.fields = [field_cls(name=n, offset=4 * i, datatype=FLOAT32, count=1)
                  for i, n in enumerate(names)]
    msg.is_bigendian = False
    msg.point_step = 4 * count
    msg.row_step = 4 * count * int(values.shape[0])
    set_data(msg, values)
    xyz = [i for i, n in enumerate(names) if n in ('x', 'y', 'z')]
    msg.is_dense = len(xyz) == 3 and bool(np.isfinite(values[:, xyz]).all())
    return msg


def with_float32_field(msg, name, values):
    """A copy of the unorganized cloud ``msg`` with a FLOAT32 field ``name`` appended per point.

    The new field sits after every existing byte (offset = old point_step), in the cloud's byte
    order; every original field keeps its offset and bytes. ``values``: (width,) numbers.
    Raises CloudFormatError when the cloud already has a field of that name or is organized.
    """
    if any(f.name == name for f in msg.fields):
        raise CloudFormatError(f"cloud already has a field named '{name}'")
    if int(msg.height) > 1:
        raise CloudFormatError(f'expected an unorganized cloud (height 1), got {msg.height}')
    rows = point_rows(msg)
    n, step = rows.shape
    values = np.asarray(values)
    if values.shape != (n,):
        raise ValueError(f"field '{name}': {values.shape} values for {n} points")
    packed = np.empty(n, dtype=np.dtype([('point', np.void, step),
                                         ('value', '>f4' if msg.is_bigendian else '<f4')]))
    packed['point'] = np.ascontiguousarray(rows).view(np.dtype((np.void, step))).reshape(n)
    packed['value'] = values
    out = type(msg)()
    out.header = _copy_header(msg.header)
    out.height = 1
    out.width = n
    out.fields = _copy_fields(msg.fields) + [
        _field_class(type(msg))(name=name, offset=step, datatype=FLOAT32, count=1)]
    out.is_bigendian = bool(msg.is_bigendian)
    out.point_step = step + 4
    out.row_step = n * (step + 4)
    set_data(out, packed.view(np.uint8))
    out.is_dense = bool(msg.is_dense)
    return out


def cloud_with_fields(msg, rows, new_fields):
    """A new unorganized message of ``type(msg)`` holding ``rows``: ``msg``'s header, fields,
    byte order and is_dense plus ``new_fields``, each ``(name, offset, datatype)`` (count 1).

    ``rows``: a C-contiguous structured (K,) array whose itemsize is the new point_step (the
    labelled rows of ``labels.labeled_points``: ``msg``'s point bytes, then the new fields).
    """
    rows = np.ascontiguousarray(rows)
    field_cls = _field_class(type(msg))
    out = type(msg)()
    out.header = _copy_header(msg.header)
    out.height = 1
    out.width = int(rows.shape[0])
    out.fields = _copy_fields(msg.fields) + [
        field_cls(name=name, offset=int(offset), datatype=int(datatype), count=1)
        for name, offset, datatype in new_fields]
    out.is_bigendian = bool(msg.is_bigendian)
    out.point_step = int(rows.dtype.itemsize)
    out.row_step = out.point_step * out.width
    set_data(out, rows.view(np.uint8) if rows.size else np.zeros(0, np.uint8))
    out.is_dense = bool(msg.is_dense)
    return out
