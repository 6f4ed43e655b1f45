# SPDX-License-Identifier: Apache-2.0
"""Every compiled kernel indexes inside its arrays, on degenerate and adversarial clouds.

numba does not check indices unless told to: an index computed from a value nobody expected
(a NaN range, a point exactly at the sensor, 1e30 m, a grid of 8 x 4 or 1440 x 512 cells) would
read or write another array's memory, silently. Here a fresh interpreter compiles every kernel
with ``NUMBA_BOUNDSCHECK=1`` (and an empty cache, so nothing unchecked is loaded) and runs
segment() (plain and with details), the ground surface's rows, heights and std, and the node's
output-cloud pass on such clouds: an out-of-range index then raises IndexError instead (or, in
the GP step, which falls back to numpy on any error, switches the segmenter's backend: also a
failure here). Every numba kernel of the package must have run compiled at least once.
About 40-60 s (the compilation), once per test run.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = """if True:
    import numba
    import numpy as np
    from gp_ground_segmentation.core import compiled
    from gp_ground_segmentation.core.params import SegmenterParams
    from gp_ground_segmentation.core.segmenter import GroundSegmenter

    assert numba.config.BOUNDSCHECK, 'NUMBA_BOUNDSCHECK not in effect'
    rng = np.random.default_rng(0)

    def clouds():
        yield 'one point', np.array([[1.0, 0.0, -1.7]])
        yield 'two identical', np.array([[1.0, 0.0, -1.7]] * 2)
        yield 'at the sensor', np.zeros((5, 3)) + [0.0, 0.0, 1e-9]
        yield 'within 1e-12 m', rng.normal(0.0, 1e-12, (100, 3))
        yield 'huge', rng.normal(0.0, 1e30, (500, 3))
        yield 'float32 max', np.array([[3.4e38, 3.4e38, -3.4e38], [1, 1, -1.7]], np.float32)
        yield 'mixed scales', np.vstack([rng.normal(0.0, 1e6, (50, 3)),
                                         rng.normal(0.0, 10.0, (500, 3))])
        t = np.linspace(0.0, 2.0 * np.pi, 1000)
        yield 'one ring', np.c_[10.0 * np.cos(t), 10.0 * np.sin(t), np.full(1000, -1.7)]
        yield 'one segment', np.c_[np.linspace(1.0, 80.0, 2000), np.zeros(2000),
                                   -1.7 + 0.01 * rng.normal(size=2000)]
        yield 'vertical line', np.c_[np.full(300, 5.0), np.zeros(300), np.linspace(-2, 20, 300)]
        for k in range(8):
            n = int(rng.integers(1, 20000))
            pts = rng.normal(0.0, rng.choice([0.1, 5.0, 30.0, 1000.0]), (n, 3))
            pts[:, 2] = rng.normal(-1.7, rng.choice([0.01, 0.5, 5.0]), n)
            bad = rng.random(n) < rng.choice([0.0, 0.1, 0.9])
            pts[bad] = rng.choice([np.nan, np.inf, -np.inf, 0.0, 1e300, -0.0], (bad.sum(), 3))
            yield f'random {k}', pts.astype(np.float32 if k % 2 else np.float64)

    for params in (SegmenterParams(), SegmenterParams(num_segments=8, num_bins=4),
                   SegmenterParams(num_segments=1440, num_bins=512)):
        seg = GroundSegmenter(params)
        seg.warm_up()
        print('WAITED', compiled.wait(300.0))
        for name, pts in clouds():
            for _ in range(2):  # cold, then warm-started
                with np.errstate(all='ignore'):
                    result = seg.segment(pts, details=_ == 1)
                    surface = result.ground_surface
                    surface.points()
                    surface.height_at(pts[:10, 0].astype(float), pts[:10, 1].astype(float))
                    surface.z_std
                # the GP step falls back to numpy on any error, an IndexError included, and
                # says why in the frame's GP (details) or by the segmenter's backend
                error = result.details.gp.compiled_error if result.details else None
                if seg.backend != 'numba' or error is not None:
                    print('GP FELL BACK', name, error)
                    seg = GroundSegmenter(params)
        print('DONE', params.num_segments, params.num_bins)

    # the output clouds' pass: odd point steps, unaligned data, masks of every kind
    from sensor_msgs.msg import PointCloud2
    from gp_ground_segmentation.ros import cloud as ros_cloud, pipeline
    pipeline.warm_up()
    compiled.wait(300.0)
    for step in (12, 13, 16, 17, 32):
        for n in (0, 1, 7, 1000):
            dtype = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['<f4'] * 3,
                              'offsets': [0, 4, 8], 'itemsize': step})
            msg = ros_cloud.make_cloud(None, np.zeros(n, dtype), PointCloud2)
            msg.data = bytes(1) + bytes(msg.data)  # unaligned start, one byte skipped
            msg.data = bytes(msg.data)[1:]
            for kind in range(4):
                ground = rng.random(n) < (0.0, 1.0, 0.5, 0.97)[kind]
                valid = ground | (rng.random(n) < 0.5)
                ros_cloud.split_cloud(msg, ground, valid)
    print('SPLIT FINISHED')
    for kernel in compiled._failed:
        print('FAILED', getattr(kernel, 'py_func', kernel).__name__)

    # every kernel of the package ran compiled (with the index checks) at least once; a helper
    # inlined into its callers (inline='always') has no code of its own: theirs holds it
    import importlib, pkgutil
    import gp_ground_segmentation
    from numba.core.registry import CPUDispatcher
    for info in pkgutil.walk_packages(gp_ground_segmentation.__path__,
                                      'gp_ground_segmentation.'):
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if (isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == info.name
                    and not obj.signatures and obj.targetoptions.get('inline') != 'always'):
                print('NEVER COMPILED', info.name, obj.py_func.__name__)
    """


def test_kernels_index_inside_their_arrays_on_adversarial_clouds(tmp_path):
    from gp_ground_segmentation.core import compiled
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), NUMBA_BOUNDSCHECK='1')
    out = subprocess.run([sys.executable, '-c', SCRIPT], cwd=root, capture_output=True,
                         text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count('DONE') == 3 and 'WAITED False' not in out.stdout, out.stdout
    assert 'FAILED' not in out.stdout, out.stdout  # else a numpy twin ran: proves nothing
    assert 'GP FELL BACK' not in out.stdout and 'SPLIT FINISHED' in out.stdout, out.stdout
    assert 'NEVER COMPILED' not in out.stdout, out.stdout
