# SPDX-License-Identifier: Apache-2.0
"""segment() vs Patchwork++ per scan on every sensor cloud, same run, plus the first call.

Usage::

    python benchmarks/bench_sensors.py [--runs N] [--no-first-call] [--no-write]

Clouds (each absent file is skipped with a printed reason):

* real: the Velodyne VLP-16, VLP-32C and Hesai PandarXT-32 scans of ../shared/data/sensors
  (indoor, floor about 0.5 m below the sensor), the 124,668-point KITTI 00 scan and the
  123,389-point SemanticKITTI scan;
* synthetic: 16/32/64/128-beam scans of ``scenes.synthetic`` (family ``beamsB``, seed 0, rays
  without a return dropped), with the firings per revolution chosen so the clouds span
  10k-100k points.

Both methods get the same (N, 3) float32 array. This project runs with ``SegmenterParams()``
defaults, one segmenter per cloud fed the same scan repeatedly (theta warm-started, as in the
node); Patchwork++ with its defaults, the mount height (KITTI 1.73 m, the indoor scans 0.5 m)
and, below a 1 m mount, a 0.3 m minimum range (as bench_quality). Timings are the median (and
p95) of ``--runs`` warm calls (default 30) after 3 untimed ones, the two methods interleaved
call by call so that machine load hits both alike; the ratio is GP / Patchwork++ of the medians.

First call: a fresh Python process per cloud imports the package, loads the cloud, times
``GroundSegmenter.warm_up()`` (loads the compiled functions from numba's on-disk cache, or
compiles them; the node calls it before its first cloud) and then its first ``segment()`` (a
cold start: theta learned from scratch) and second one. Every row but the last runs with
numba's cache as this run left it; the last with an empty, temporary ``NUMBA_CACHE_DIR``: the
very first run on a new install, which compiles (and fills that cache).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402
from gp_ground_segmentation.core import compiled  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
INDOOR_MOUNT_M = 0.5  # the sensors/ scans: floor at z = -0.4 to -0.6 m (data README)
LOW_MOUNT_M, LOW_MOUNT_MIN_RANGE_M = 1.0, 0.3  # as bench_quality.peer_settings
# beams -> firings per revolution; about half the rays return: 20k, 33k, 66k, 94k points
SYNTHETIC_AZIMUTH_STEPS = {16: 2500, 32: 1400, 64: 2048, 128: 1500}
# segment()'s stages in the table (medians over the warm calls), in pipeline order
STAGE_COLUMNS = ('grid', 'lines', 'gp_fit', 'predict', 'label', 'structure')


def load_clouds() -> list:
    """[(name, description, (N, 3) float32 points, mount height m)] of every available cloud."""
    clouds = []
    for ds in common.load_sensor_pcds():
        pts = np.ascontiguousarray(ds.frames[0].points[:, :3], dtype=np.float32)
        clouds.append((ds.name, 'real, indoor', pts, INDOOR_MOUNT_M))
    for loader, name in ((common.load_unlabeled_kitti, 'kitti00_000000'),
                         (common.load_labeled_kitti, 'kitti_spvnas')):
        ds = loader()
        if ds is not None:
            pts = np.ascontiguousarray(ds.frames[0].points[:, :3], dtype=np.float32)
            clouds.append((name, 'real, KITTI HDL-64E', pts, common.KITTI_SENSOR_HEIGHT_M))
    try:
        from scenes import synthetic
    except ImportError as exc:
        print(f'[data] skipped synthetic clouds: {exc}', file=sys.stderr)
        return clouds
    for beams, steps in SYNTHETIC_AZIMUTH_STEPS.items():
        member = synthetic.family_scene(f'beams{beams}', 0)
        kwargs = dict(member.scan_kwargs, azimuth_steps=steps, organized=False)
        scan = synthetic.simulate_scan(member.scene, seed=0, **kwargs)
        pts = np.ascontiguousarray(scan.points, dtype=np.float32)
        clouds.append((f'synthetic_{beams}', f'synthetic, {beams} beams', pts,
                       member.sensor_height_m))
    return clouds


def make_patchworkpp(mount_m: float):
    """Patchwork++ with its defaults and the mount as bench_quality sets it; None if missing."""
    try:
        import pypatchworkpp
    except ImportError:
        return None
    params = pypatchworkpp.Parameters()
    params.sensor_height = mount_m
    params.verbose = False
    params.enable_RNR = False  # no intensity given to either method
    if mount_m < LOW_MOUNT_M:
        params.min_range = LOW_MOUNT_MIN_RANGE_M
    with common.quiet_stdout():
        return pypatchworkpp.patchworkpp(params)


def time_cloud(points: np.ndarray, mount_m: float, runs: int, warmup: int = 3) -> dict:
    """Interleaved warm timings (s) of segment() and Patchwork++ on one cloud."""
    seg = GroundSegmenter(SegmenterParams())
    seg.warm_up()  # every compiled stage loaded: warm calls, not numba's background loading
    compiled.wait(60.0)
    pwpp = make_patchworkpp(mount_m)
    gp_s, pw_s, stages = [], [], []
    for i in range(warmup + runs):
        t0 = time.perf_counter()
        result = seg.segment(points)
        t1 = time.perf_counter()
        if pwpp is not None:
            pwpp.estimateGround(points)
        t2 = time.perf_counter()
        if i >= warmup:
            gp_s.append(t1 - t0)
            pw_s.append(t2 - t1)
            stages.append(result.timings_ms)
    stage_median = {k: float(np.median([s[k] for s in stages])) for k in stages[0]}
    return {'gp': common.summary_ms(gp_s), 'pwpp': common.summary_ms(pw_s) if pwpp else None,
            'stages': stage_median, 'stats': result.stats,
            'ground_fraction': float(result.ground_mask.mean())}


_FIRST_CALL_SCRIPT = r'''
import sys, time, json
t_import = time.perf_counter()
sys.path.insert(0, {bench_dir!r})
import numpy as np
from gp_ground_segmentation import GroundSegmenter, SegmenterParams
t_loaded = time.perf_counter()
points = np.load({path!r})
seg = GroundSegmenter(SegmenterParams())
t_warm = time.perf_counter()
seg.warm_up()
t0 = time.perf_counter()
seg.segment(points)
t1 = time.perf_counter()
seg.segment(points)
t2 = time.perf_counter()
print(json.dumps({{'import_s': t_loaded - t_import, 'warm_up_s': t0 - t_warm,
                  'first_s': t1 - t0, 'second_s': t2 - t1}}))
'''


def first_call(points: np.ndarray, cache_dir: str | None = None) -> dict:
    """Package import, warm_up(), first and second segment() (s) of a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, 'cloud.npy')
        np.save(path, points)
        env = dict(os.environ)
        if cache_dir is not None:
            env['NUMBA_CACHE_DIR'] = cache_dir
        script = _FIRST_CALL_SCRIPT.format(bench_dir=str(Path(__file__).resolve().parent),
                                           path=path)
        out = subprocess.run([sys.executable, '-c', script], env=env, check=True,
                             capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--runs', type=int, default=30, help='timed warm calls per cloud (>= 20)')
    ap.add_argument('--no-first-call', action='store_true', help='skip the fresh processes')
    ap.add_argument('--no-write', action='store_true', help='do not update RESULTS.md')
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error('--runs must be >= 1')

    # glibc's malloc settings as the node's main() and the command line set them (README,
    # "Memory"): without them, whether a process pays hundreds of minor page faults a frame
    # depends on what it allocated and freed before, for both methods alike
    from gp_ground_segmentation.core.allocator import keep_freed_memory
    allocator_note = keep_freed_memory()
    clouds = load_clouds()
    if not clouds:
        sys.exit('no clouds found (see ../shared/data/README.md)')
    rows, first_rows = [], []
    for name, kind, pts, mount in clouds:
        res = time_cloud(pts, mount, args.runs)
        pw = res['pwpp']['median'] if res['pwpp'] else float('nan')
        gp = res['gp']['median']
        st = res['stages']
        row = [name, kind, f'{len(pts):,}', common.fmt(gp, 2), common.fmt(res['gp']['p95'], 2),
               common.fmt(pw, 2), common.fmt(gp / pw, 2) if pw == pw else 'n/a',
               ' / '.join(common.fmt(st.get(k, float('nan')), 2)
                          for k in STAGE_COLUMNS),
               str(res['stats'].get('training_candidates', '')),
               common.fmt(100 * res['ground_fraction'], 1)]
        rows.append(row)
        print(' | '.join(row), flush=True)
    headers = ['cloud', 'kind', 'points', 'GP median ms', 'GP p95 ms', 'Patchwork++ median ms',
               'GP / PW++', 'stages ms: ' + ' / '.join(STAGE_COLUMNS),
               'GP training points', 'GP ground %']
    text = ['## Every sensor: this project vs Patchwork++ per scan (`bench_sensors.py`)', '',
            common.machine_markdown(common.command_line()), '',
            f'Warm calls: median of {args.runs} after 3 untimed, GP and Patchwork++ '
            'interleaved call by call in one process; (N, 3) float32 input to both; '
            + ('glibc malloc thresholds set as the node sets them (core/allocator.py).'
               if allocator_note is None else f'malloc settings unchanged: {allocator_note}.'),
            '',
            common.markdown_table(headers, rows)]

    if not args.no_first_call:
        runs = [(name, pts, None) for name, _, pts, _ in clouds]
        empty_cache = tempfile.TemporaryDirectory()
        runs.append((f'{clouds[0][0]}, empty NUMBA_CACHE_DIR (new install)', clouds[0][2],
                     empty_cache.name))
        for name, pts, cache_dir in runs:
            fc = first_call(pts, cache_dir)
            keys = ('import_s', 'warm_up_s', 'first_s', 'second_s')
            first_rows.append([name, f'{len(pts):,}'] + [common.fmt(fc[k] * 1e3, 1)
                                                         for k in keys])
            print('first call', ' | '.join(first_rows[-1]), flush=True)
        empty_cache.cleanup()
        text += ['', 'Fresh processes (`python -c`, one per row): numba\'s on-disk cache as this '
                 'run left it, except the last row (empty cache: compiles). First segment() '
                 '= cold start (up to 40 likelihood evaluations).', '',
                 common.markdown_table(['cloud', 'points', 'import ms', 'warm_up() ms',
                                        'first segment() ms', 'second segment() ms'],
                                       first_rows)]
    text = '\n'.join(text)
    print(text)
    if not args.no_write:
        common.update_results_section(RESULTS, 'bench_sensors', text)


if __name__ == '__main__':
    main()
