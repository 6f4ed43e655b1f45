# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg batch`` in-process vs on a Dask LocalCluster (``--jobs``), same run.

Usage::

    python benchmarks/bench_batch.py [--bags 8] [--frames 50] [--jobs 2] [--repeats 5]
                                     [--no-write]

Input: ``--bags`` ROS 2 bags (mcap, uncompressed) of ``--frames`` real KITTI 00 frames each,
built in a temporary directory (deleted at the end) by copying the 6 PointCloud2 messages of
``../shared/data/kitti00_velodyne_points`` unchanged (raw CDR) in a cycle, bag time i * 0.1 s.

Each repeat runs the whole batch in this process and then on the cluster (the order alternates
between repeats so background load hits both alike), into fresh output directories, through
``batch.run_batch`` (the code of ``gp-ground-seg batch``). Timed: the batch wall time (counting
frames, replaying every bag, writing the summaries). Not in the ratio: the cluster start-up
(LocalCluster of ``--jobs`` worker processes + a 1-frame replay on every worker: imports, type
store, compiled GP kernel), timed on its own; this process gets the same warm-up, untimed.
Memory: peak RSS (ru_maxrss) of each worker process and of this process.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
TOPIC = '/velodyne_points'


def build_bags(src: Path, root: Path, bags: int, frames: int) -> list:
    """``bags`` mcap bags of ``frames`` messages cycled from the source bag's topic."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    with AnyReader([src]) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC]
        conn = conns[0]
        raws = [bytes(raw) for _, _, raw in reader.messages(connections=conns)]
    paths = []
    for b in range(bags):
        path = root / f'kitti00_cycle_{b:02d}'
        path.parent.mkdir(parents=True, exist_ok=True)
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            out = writer.add_connection(TOPIC, conn.msgtype, msgdef=conn.msgdef.data,
                                        rihs01=conn.digest)
            for i in range(frames):
                writer.write(out, i * 100_000_000, raws[(b + i) % len(raws)])
        paths.append(str(path))
    return paths


def warm_up(tiny_bag: str, out_root: str) -> None:
    """Replay a 1-frame bag: imports rclpy/rosbags/the pipeline, builds the type store and
    loads the compiled GP kernel, which every process does once."""
    import os

    from gp_ground_segmentation.tools.bag import replay
    replay([tiny_bag], Path(out_root) / f'warm_{os.getpid()}')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--bags', type=int, default=8)
    parser.add_argument('--frames', type=int, default=50)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    src = common.DATA_DIR / 'kitti00_velodyne_points'
    if not src.is_dir():
        print(f'skipped: {src} not found')
        return 0
    from gp_ground_segmentation.tools.batch import run_batch
    from gp_ground_segmentation.tools.engine import InProcessEngine, open_engine, peak_rss_mb

    load_before = common.machine_info()['load_average']
    with tempfile.TemporaryDirectory(prefix='bench_batch_') as tmp:
        root = Path(tmp)
        inputs = build_bags(src, root, args.bags, args.frames)
        (tiny,) = build_bags(src, root / 'tiny', 1, 1)
        warm_up(tiny, str(root))
        t0 = time.perf_counter()
        engine = open_engine(jobs=args.jobs)
        engine.run_on_workers(warm_up, tiny, str(root))
        startup_s = time.perf_counter() - t0
        walls = {'in-process': [], 'cluster': []}
        frames = {}
        rss = {}
        with engine:
            for r in range(args.repeats):
                order = [('in-process', InProcessEngine()), ('cluster', engine)]
                for name, eng in (order if r % 2 == 0 else order[::-1]):
                    out = root / f'out_{name}_{r}'
                    t = time.perf_counter()
                    result = run_batch(inputs, out, eng)
                    walls[name].append(time.perf_counter() - t)
                    assert result.failed == 0, result.rows
                    frames[name] = result.frames
                    if name == 'cluster':
                        rss = result.worker_peak_rss_mb
                    print(f'repeat {r + 1} {name}: {walls[name][-1]:.1f} s, {result.frames} '
                          f'frames', flush=True)
        main_rss = peak_rss_mb()
    n = frames['in-process']
    med = {k: statistics.median(v) for k, v in walls.items()}
    ratios = [a / b for a, b in zip(walls['in-process'], walls['cluster'])]
    rows = [['in-process (1 process)', f'{med["in-process"]:.1f}', n,
             f'{n / med["in-process"]:.2f}', '1.00', '-', f'{main_rss:.0f} (this process)'],
            [f'LocalCluster, --jobs {args.jobs}', f'{med["cluster"]:.1f}', frames['cluster'],
             f'{frames["cluster"] / med["cluster"]:.2f}',
             f'{med["in-process"] / med["cluster"]:.2f} (pairs: {statistics.median(ratios):.2f})',
             f'{startup_s:.1f}',
             ', '.join(f'{v:.0f}' for _, v in sorted(rss.items()))]]
    table = common.markdown_table(
        ['engine', 'wall s (median)', 'frames', 'frames/s', 'speed-up', 'start-up s',
         'peak RSS MB per worker'], rows)
    text = (f'## Batch: in-process vs Dask LocalCluster (`bench_batch.py`)\n\n'
            f'{common.machine_markdown(common.command_line())}'
            f'- Load average before the run: {load_before}.\n'
            f'- Input: {args.bags} mcap bags x {args.frames} real KITTI 00 frames '
            f'(123,924-124,668 points; the 6 frames of kitti00_velodyne_points cycled), built '
            f'in a temporary directory. Median of {args.repeats} repeat(s), order alternating; '
            f'speed-up of each repeat (in-process wall / cluster wall, run back to back): '
            f'{", ".join(f"{x:.2f}" for x in ratios)}; the table gives the ratio of the '
            f'medians and the median of these pairs.\n'
            f'- Wall = the whole `run_batch` (count frames, replay and write every bag, '
            f'summaries). Cluster start-up (LocalCluster + a 1-frame warm-up replay on each '
            f'worker; this process gets the same warm-up untimed) is timed apart and not in '
            f'the speed-up.\n\n{table}\n')
    print(text)
    if not args.no_write:
        common.update_results_section(RESULTS, 'bench_batch', text)
    return 0


if __name__ == '__main__':  # required: Dask starts worker processes with 'spawn'
    sys.exit(main())
