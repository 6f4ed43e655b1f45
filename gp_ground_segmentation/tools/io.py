# SPDX-License-Identifier: Apache-2.0
"""Point-cloud files: KITTI ``.bin``, SemanticKITTI ``.label`` and PCD v0.7 (read and write).

Every failure raises ``PointFileError`` (a ValueError) whose one-line message starts with the
file path and names the problem, so a tool can print it as is.

PCD support: ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, column-major), any
FIELDS/SIZE/TYPE/COUNT (TYPE F 4/8, I and U 1/2/4/8). Fields named ``_`` are padding (PCL writes
them for alignment) and are dropped from the result. Binary data is read as little-endian,
which is what PCL writes on every platform in use.
"""

import os

import numpy as np

__all__ = ['PointFileError', 'read_kitti_bin', 'read_semantickitti_labels', 'read_pcd',
           'write_pcd', 'read_points_file', 'lzf_decompress']


class PointFileError(ValueError):
    """A point file that cannot be read; the message is ``'<path>: <problem>'`` on one line."""


def _err(path, problem):
    return PointFileError(f'{os.fspath(path)}: {problem}')


def _read_bytes(path):
    try:
        with open(path, 'rb') as fh:
            return fh.read()
    except OSError as exc:
        raise _err(path, f'cannot read file ({exc.strerror or exc})') from None


# --------------------------------------------------------------------------- KITTI

def read_kitti_bin(path):
    """KITTI Velodyne scan -> ``(N, 4)`` float32: x, y, z (m), remission (0..1)."""
    raw = _read_bytes(path)
    if len(raw) % 16:
        raise _err(path, f'size {len(raw)} bytes is not a multiple of 16 (4 float32 per point); '
                         'truncated or not a KITTI .bin')
    points = np.frombuffer(raw, dtype='<f4').astype(np.float32).reshape(-1, 4)
    _check_kitti_values(path, points)
    return points


# A KITTI .bin holds float32 x, y, z in metres and a 4th value per point (remission 0..1 in
# KITTI; intensity, reflectivity or a time offset elsewhere: the segmenter does not read it).
# Another layout read as one gives values no scan has: float64 values or a .label file read as
# float32 put coordinates beyond any LiDAR's range or into denormals; x, y, z without a 4th
# value shift every record, so the "4th value" is a coordinate (often negative, metres large,
# where an intensity or a time offset is >= 0 or within +-1). A few bad returns are tolerated.
_MAX_PLAUSIBLE_M = 1e4
_MIN_PLAUSIBLE_M = 1e-20  # below this a nonzero coordinate is a bit pattern, not a distance
_MAX_IMPLAUSIBLE_SHARE = 0.01
_MAX_NEGATIVE_FOURTH_SHARE = 0.05
_COORDINATE_SIZED_FOURTH = 2.0  # 95th percentile of |4th value| above this: metres, not a gain


def _check_kitti_values(path, points: np.ndarray) -> None:
    """PointFileError when ``points`` (N, 4) cannot be float32 x, y, z and a 4th value."""
    finite = np.isfinite(points[:, :3]).all(axis=1)
    xyz = points[finite, :3]
    if xyz.shape[0] == 0:
        return
    magnitude = np.abs(xyz)
    odd = (magnitude > _MAX_PLAUSIBLE_M) | ((magnitude > 0) & (magnitude < _MIN_PLAUSIBLE_M))
    odd_share = float(np.mean(odd.any(axis=1)))
    if odd_share > _MAX_IMPLAUSIBLE_SHARE:
        raise _err(path, f'not 4 float32 values per point (x, y, z in metres, then e.g. '
                         f'remission): x, y, z of {100 * odd_share:.0f} % of the points lie '
                         f'beyond {_MAX_PLAUSIBLE_M:g} m or are denormal; float64 values, a '
                         '.label file or millimetres?')
    fourth = points[finite, 3]
    fourth = fourth[np.isfinite(fourth)]
    negative_share = float(np.mean(fourth < 0)) if fourth.size else 0.0
    if (negative_share > _MAX_NEGATIVE_FOURTH_SHARE
            and float(np.percentile(np.abs(fourth), 95)) > _COORDINATE_SIZED_FOURTH):
        raise _err(path, f'not 4 float32 values per point: the 4th value of '
                         f'{100 * negative_share:.0f} % of the points is negative and metres '
                         'large, like a coordinate; x, y, z without a 4th value? (convert to 4 '
                         'float32 values per point)')


def read_semantickitti_labels(path, expected_points=None):
    """SemanticKITTI ``.label`` -> uint32 semantic class per point (``label & 0xFFFF``).

    ``expected_points``: point count of the matching scan; a different label count is an error.
    """
    raw = _read_bytes(path)
    if len(raw) % 4:
        raise _err(path, f'size {len(raw)} bytes is not a multiple of 4 (uint32 per point)')
    labels = np.frombuffer(raw, dtype='<u4')
    if expected_points is not None and labels.size != int(expected_points):
        raise _err(path, f'has {labels.size} labels but the scan has {int(expected_points)} '
                         'points')
    return (labels & np.uint32(0xFFFF)).astype(np.uint32)


# --------------------------------------------------------------------------- LZF

def lzf_decompress(src, out_len):
    """Decompress an LZF (liblzf) block into exactly ``out_len`` bytes.

    Pure Python: one loop iteration per literal run or back-reference, slices for the copies,
    so a 1 MB block takes tens of milliseconds. Raises ValueError on corrupt input.
    """
    src = bytes(src)
    out = bytearray(out_len)
    ip, op, n_in = 0, 0, len(src)
    while ip < n_in:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n_in or op + length > out_len:
                raise ValueError('LZF literal run past the end of the data')
            out[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
        else:  # back-reference: length (3 bits, extended), distance (13 bits)
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise ValueError('LZF back-reference truncated')
                length += src[ip]
                ip += 1
            if ip >= n_in:
                raise ValueError('LZF back-reference truncated')
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0:
                raise ValueError('LZF back-reference before the start of the output')
            if op + length > out_len:
                raise ValueError('LZF output longer than declared')
            dist = op - ref
            if dist >= length:
                out[op:op + length] = out[ref:ref + length]
            else:  # overlapping copy = repetition of the last `dist` bytes
                chunk = bytes(out[ref:op])
                out[op:op + length] = (chunk * (length // dist + 1))[:length]
            op += length
    if op != out_len:
        raise ValueError(f'LZF data decompressed to {op} bytes, expected {out_len}')
    return bytes(out)


# --------------------------------------------------------------------------- PCD

_PCD_TYPES = {('F', 4): 'f4', ('F', 8): 'f8', ('I', 1): 'i1', ('I', 2): 'i2', ('I', 4): 'i4',
              ('I', 8): 'i8', ('U', 1): 'u1', ('U', 2): 'u2', ('U', 4): 'u4', ('U', 8): 'u8'}
_HEADER_KEYS = ('VERSION', 'FIELDS', 'SIZE', 'TYPE', 'COUNT', 'WIDTH', 'HEIGHT', 'VIEWPOINT',
                'POINTS', 'DATA')


def _parse_pcd_header(path, raw):
    """Return (header dict of token lists, byte offset of the data)."""
    header, pos = {}, 0
    while True:
        nl = raw.find(b'\n', pos)
        if nl < 0:
            raise _err(path, 'bad header: no DATA line (not a PCD file or truncated header)')
        line = raw[pos:nl].decode('ascii', errors='replace').strip()
        pos = nl + 1
        if not line or line.startswith('#'):
            continue
        key, *values = line.split()
        key = key.upper()
        if key not in _HEADER_KEYS:
            raise _err(path, f'bad header: unknown line {line[:40]!r}')
        header[key] = values
        if key == 'DATA':
            return header, pos


def _pcd_layout(path, header):
    """Packed file dtype (padding fields renamed) + list of kept field names + point count."""
    for key in ('FIELDS', 'SIZE', 'TYPE', 'DATA'):
        if key not in header:
            raise _err(path, f'bad header: missing {key}')
    names = header['FIELDS']
    nf = len(names)
    counts = header.get('COUNT', ['1'] * nf)
    if not (len(header['SIZE']) == len(header['TYPE']) == len(counts) == nf) or nf == 0:
        raise _err(path, f'bad header: FIELDS/SIZE/TYPE/COUNT lengths differ '
                         f"({nf}/{len(header['SIZE'])}/{len(header['TYPE'])}/{len(counts)})")
    try:
        sizes = [int(s) for s in header['SIZE']]
        counts = [int(c) for c in counts]
        width = int(header['WIDTH'][0]) if 'WIDTH' in header else None
        height = int(header['HEIGHT'][0]) if 'HEIGHT' in header else 1
        points = int(header['POINTS'][0]) if 'POINTS' in header else None
    except (ValueError, IndexError):
        raise _err(path, 'bad header: non-integer SIZE/COUNT/WIDTH/HEIGHT/POINTS') from None
    if points is None:
        if width is None:
            raise _err(path, 'bad header: neither POINTS nor WIDTH given')
        points = width * height
    elif width is not None and width * height != points:
        raise _err(path, f'bad header: WIDTH*HEIGHT = {width * height} != POINTS {points}')
    if points < 0:
        raise _err(path, 'bad header: negative point count')
    fnames, formats, kept = [], [], []
    for i, (name, size, typ, count) in enumerate(zip(names, sizes, header['TYPE'], counts)):
        code = _PCD_TYPES.get((typ.upper(), size))
        if code is None:
            raise _err(path, f"bad header: field '{name}' has unsupported TYPE {typ} SIZE {size}")
        if count < 1:
            raise _err(path, f"bad header: field '{name}' has COUNT {count}")
        if name == '_':
            fname = f'_pad{i}'
        else:
            if name in kept:
                raise _err(path, f"bad header: duplicate field '{name}'")
            fname = name
            kept.append(name)
        fnames.append(fname)
        formats.append('<' + code if count == 1 else (np.dtype('<' + code), (count,)))
    return np.dtype({'names': fnames, 'formats': formats}), kept, points


def _drop_padding(arr, kept):
    """Structured array with only the named fields, packed (padding '_' fields removed)."""
    if list(arr.dtype.names) == kept:
        return arr
    out = np.empty(arr.shape, dtype=[(n, arr.dtype.fields[n][0]) for n in kept])
    for n in kept:
        out[n] = arr[n]
    return out


def read_pcd(path):
    """Read a PCD v0.7 file -> structured array ``(POINTS,)`` (organized clouds flattened).

    Field dtypes follow SIZE/TYPE (little-endian), COUNT > 1 gives subarray fields, '_' padding
    fields are dropped. Raises PointFileError for a bad header, unsupported DATA or truncated data.
    """
    raw = _read_bytes(path)
    header, pos = _parse_pcd_header(path, raw)
    ftype, kept, n = _pcd_layout(path, header)
    mode = header['DATA'][0].lower() if header['DATA'] else ''
    body = raw[pos:]
    if mode == 'binary':
        need = n * ftype.itemsize
        if len(body) < need:
            raise _err(path, f'truncated file: {n} points need {need} bytes of binary data, '
                             f'found {len(body)}')
        arr = np.frombuffer(body, dtype=ftype, count=n).copy()
    elif mode == 'binary_compressed':
        if len(body) < 8:
            raise _err(path, 'truncated file: binary_compressed data has no size words')
        csize, usize = (int(v) for v in np.frombuffer(body[:8], dtype='<u4'))
        need = n * ftype.itemsize
        if usize != need:
            raise _err(path, f'bad header: compressed block holds {usize} bytes, {n} points '
                             f'need {need}')
        if len(body) < 8 + csize:
            raise _err(path, f'truncated file: compressed block of {csize} bytes, '
                             f'found {len(body) - 8}')
        try:
            plain = lzf_decompress(body[8:8 + csize], usize)
        except ValueError as exc:
            raise _err(path, f'corrupt binary_compressed data ({exc})') from None
        # Column-major: all values of field 0, then all of field 1, ...
        arr = np.empty(n, dtype=ftype)
        start = 0
        for name in ftype.names:
            ft = ftype.fields[name][0]
            nbytes = n * ft.itemsize
            col = np.frombuffer(plain, dtype=ft.base, count=nbytes // ft.base.itemsize,
                                offset=start)
            arr[name] = col.reshape((n,) + ft.shape)
            start += nbytes
    elif mode == 'ascii':
        arr = _read_pcd_ascii(path, body, ftype, n)
    else:
        raise _err(path, f"unsupported DATA '{' '.join(header['DATA'])}' "
                         '(ascii, binary, binary_compressed)')
    return _drop_padding(arr, kept)


def _read_pcd_ascii(path, body, ftype, n):
    ncols = sum(int(np.prod(ftype.fields[nm][0].shape, dtype=np.int64)) for nm in ftype.names)
    tokens = body.split()
    if len(tokens) < n * ncols:
        raise _err(path, f'truncated file: {n} points x {ncols} values need {n * ncols} ascii '
                         f'values, found {len(tokens)}')
    table = np.array(tokens[:n * ncols]).reshape(n, ncols)
    arr = np.empty(n, dtype=ftype)
    col = 0
    for name in ftype.names:
        ft = ftype.fields[name][0]
        width = int(np.prod(ft.shape, dtype=np.int64))
        cols = table[:, col:col + width]
        try:
            if ft.base.kind == 'f':
                vals = cols.astype(np.float64).astype(ft.base)
            else:
                vals = cols.astype(ft.base)
        except (ValueError, OverflowError):
            raise _err(path, f"bad ascii value in field '{name}'") from None
        arr[name] = vals.reshape((n,) + ft.shape)
        col += width
    return arr


def _pcd_type(path, name, dt):
    base = dt.base
    kind = {'f': 'F', 'i': 'I', 'u': 'U'}.get(base.kind)
    if kind is None or (kind, base.itemsize) not in _PCD_TYPES:
        raise _err(path, f"field '{name}' has dtype {dt} with no PCD TYPE")
    return kind, base.itemsize, int(np.prod(dt.shape, dtype=np.int64)) if dt.shape else 1


def write_pcd(path, points, binary=True):
    """Write a structured array as PCD v0.7 (``DATA binary`` or ``ascii``), unorganized.

    Fields keep their order; subarray fields get COUNT > 1; numeric kinds f/i/u only. The binary
    body is packed little-endian (padding between fields is not written).
    """
    pts = np.asarray(points).reshape(-1)
    if pts.dtype.names is None:
        raise _err(path, 'write_pcd needs a structured array')
    specs = [(nm,) + _pcd_type(path, nm, pts.dtype.fields[nm][0]) for nm in pts.dtype.names]
    n = pts.shape[0]
    head = ['# .PCD v0.7 - Point Cloud Data file format', 'VERSION 0.7',
            'FIELDS ' + ' '.join(s[0] for s in specs),
            'SIZE ' + ' '.join(str(s[2]) for s in specs),
            'TYPE ' + ' '.join(s[1] for s in specs),
            'COUNT ' + ' '.join(str(s[3]) for s in specs),
            f'WIDTH {n}', 'HEIGHT 1', 'VIEWPOINT 0 0 0 1 0 0 0', f'POINTS {n}',
            'DATA ' + ('binary' if binary else 'ascii')]
    packed_dt = np.dtype([(nm, np.dtype('<' + _PCD_TYPES[(k, s)]) if c == 1
                           else (np.dtype('<' + _PCD_TYPES[(k, s)]), (c,)))
                          for nm, k, s, c in specs])
    packed = np.empty(n, dtype=packed_dt)
    for nm in pts.dtype.names:
        packed[nm] = pts[nm]
    with open(path, 'wb') as fh:
        fh.write(('\n'.join(head) + '\n').encode('ascii'))
        if binary:
            fh.write(packed.tobytes())
        else:
            cols, fmts = [], []
            for nm, kind, size, count in specs:
                v = packed[nm].reshape(n, count)
                # Shortest repr that round-trips the stored precision.
                fmt = ('%.9g' if size == 4 else '%.17g') if kind == 'F' else '%d'
                cols.append(v.astype(np.float64) if kind == 'F' else v)
                fmts += [fmt] * count
            if n:
                lines = []
                obj = np.concatenate([c.astype(object) for c in cols], axis=1)
                line_fmt = ' '.join(fmts)
                for row in obj:
                    lines.append(line_fmt % tuple(row))
                fh.write(('\n'.join(lines) + '\n').encode('ascii'))


# --------------------------------------------------------------------------- dispatch

_KITTI_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])


def read_points_file(path):
    """Structured point array with at least x, y, z from a ``.bin`` (KITTI) or ``.pcd`` file.

    ``.bin`` gives fields x, y, z, intensity (float32). Raises PointFileError for other
    extensions or a file without x, y and z.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == '.bin':
        return read_kitti_bin(path).view(_KITTI_DTYPE).reshape(-1)
    if ext == '.pcd':
        arr = read_pcd(path)
        missing = [c for c in ('x', 'y', 'z') if c not in arr.dtype.names]
        if missing:
            raise _err(path, f"missing field {', '.join(missing)} (fields: "
                             f"{' '.join(arr.dtype.names)})")
        return arr
    raise _err(path, f"unsupported file type '{ext or '(none)'}' (expected .bin or .pcd)")
