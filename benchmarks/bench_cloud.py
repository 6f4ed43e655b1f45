# SPDX-License-Identifier: Apache-2.0
"""Time PointCloud2 <-> numpy conversion on a real KITTI scan (124,668 points, 16 bytes each).

Usage: python benchmarks/bench_cloud.py [path/to/scan.bin]
Prints the median of 20 runs (ms) for decode (read_cloud), xyz (cloud_xyz), subset (two
complementary subset_cloud calls: ground + obstacles), make_cloud, the rclpy ``msg.data``
setter paths, and LZF decompression of a ~1 MB PCD block.
"""

import array
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gp_ground_segmentation.ros.cloud import (  # noqa: E402
    cloud_xyz, make_cloud, read_cloud, subset_cloud)
from gp_ground_segmentation.tools.io import lzf_decompress, read_points_file  # noqa: E402
from scenes.real_data import DATA_DIR  # noqa: E402

DEFAULT = DATA_DIR / 'kitti_unlabeled_patchworkpp_000000.bin'


def median_ms(fn, repeats=20):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def lzf_block(data):
    """Literal-only LZF stream (worst case for the decoder's loop: 32-byte steps)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def main():
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT
    pts = read_points_file(path)
    msg = make_cloud(Header(frame_id='velodyne'), pts)
    n = msg.width
    mask = cloud_xyz(read_cloud(msg))[:, 2] < -1.5
    decoded = read_cloud(msg)
    raw = bytes(msg.data)
    rows = [
        ('decode (read_cloud)', median_ms(lambda: read_cloud(msg))),
        ('xyz (cloud_xyz)', median_ms(lambda: cloud_xyz(decoded))),
        ('decode + xyz', median_ms(lambda: cloud_xyz(read_cloud(msg)))),
        ('subset x2 (ground + obstacles)',
         median_ms(lambda: (subset_cloud(msg, mask), subset_cloud(msg, ~mask)))),
        ('make_cloud', median_ms(lambda: make_cloud(msg.header, decoded))),
    ]
    setter = PointCloud2(check_fields=False)
    checked = PointCloud2(check_fields=True)
    u8 = np.frombuffer(raw, np.uint8)

    def as_array(buf):
        a = array.array('B')
        a.frombytes(buf)
        return a
    rows += [
        ('msg.data = array.array (frombytes)',
         median_ms(lambda: setattr(setter, 'data', as_array(u8)))),
        ('msg.data = bytes', median_ms(lambda: setattr(setter, 'data', raw))),
        ('msg.data = bytearray', median_ms(lambda: setattr(setter, 'data', bytearray(raw)))),
        ('msg.data = numpy uint8', median_ms(lambda: setattr(setter, 'data', u8), 3)),
        ('checked msg.data = array.array',
         median_ms(lambda: setattr(checked, 'data', as_array(u8)))),
        ('checked msg.data = bytes', median_ms(lambda: setattr(checked, 'data', raw), 3)),
        ('np.frombuffer(msg.data)', median_ms(lambda: np.frombuffer(msg.data, np.uint8))),
    ]
    block = raw[:1 << 20]
    comp = lzf_block(block)
    rows.append(('LZF decompress 1 MiB (literal runs)',
                 median_ms(lambda: lzf_decompress(comp, len(block)), 5)))
    # Worst case for the loop: every token a 3-byte back-reference (1 MiB / 3 iterations).
    short = b'\x02abc' + b'\x20\x02' * ((1 << 20) // 3 - 1)
    out_len = 3 * ((1 << 20) // 3)
    rows.append(('LZF decompress 1 MiB (3-byte matches)',
                 median_ms(lambda: lzf_decompress(short, out_len), 5)))
    print(f'{path.name}: {n} points x {msg.point_step} B; ground mask keeps {int(mask.sum())}')
    print(f"{'step':40s} {'median ms':>10s}")
    for name, ms in rows:
        print(f'{name:40s} {ms:10.3f}')
    print('(numpy / checked-bytes setters: median of 3; LZF: of 5; others: of 20;')
    print(" 'checked' = message built with check_fields=True, i.e. ROS_PYTHON_CHECK_FIELDS=1)")


if __name__ == '__main__':
    main()
