# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg batch on a real Dask LocalCluster (2 worker processes) and in-process.

Checks: every input's ground and obstacle clouds are identical to `gp-ground-seg replay` of
the same input (bag times, headers, layout, point bytes); a corrupt input among good ones is a
failed row with replay's one-line error while the others complete (exit 1); summary.json/csv
hold every input; a rerun skips finished inputs and --force redoes them; Ctrl-C
(KeyboardInterrupt in the client) leaves only complete outputs and no hidden leftovers; paths a
worker cannot see are refused up front.
"""

import csv
import json
import shutil
from pathlib import Path

import pytest

from conftest import DATA, REPO  # noqa: E402

pytest.importorskip('distributed')

BAG = DATA / 'kitti00_velodyne_points'
BINS = [DATA / 'labeled' / f'semantickitti_seq00_00000{i}.bin' for i in (0, 1)]
TOPIC = '/velodyne_points'

pytestmark = pytest.mark.skipif(not BAG.is_dir(), reason=f'real data not found: {BAG}')


def cloud_bytes(bag):
    """{topic: [(bag time, every PointCloud2 field, point data bytes)]} of the cloud topics
    (ground, obstacles, ground surface) of an output bag.

    Not the raw CDR: rclpy's serializer leaves the alignment padding after the frame_id string
    uninitialised, so two serialisations of one message can differ in those bytes.
    """
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2
    out = {}
    with AnyReader([Path(bag)]) as reader:
        conns = [c for c in reader.connections if c.topic != '/diagnostics']
        for c, t, raw in reader.messages(connections=conns):
            m = deserialize_message(bytes(raw), PointCloud2)
            out.setdefault(c.topic, []).append((
                t, m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id, m.height,
                m.width, [(f.name, f.offset, f.datatype, f.count) for f in m.fields],
                m.is_bigendian, m.point_step, m.row_step, m.is_dense, bytes(m.data)))
    return out


@pytest.fixture(scope='module')
def inputs(tmp_path_factory):
    """A 3-frame real KITTI bag, a directory of two real .bin scans and a truncated bag."""
    from gp_ground_segmentation.tools.bag import write_sample_bag
    root = tmp_path_factory.mktemp('inputs')
    write_sample_bag(BAG, root / 'bag_a', frames=3)
    (root / 'scans').mkdir()
    for b in BINS:
        shutil.copy(b, root / 'scans' / b.name)
    mcap = next((root / 'bag_a').glob('*.mcap'))
    (root / 'broken.mcap').write_bytes(mcap.read_bytes()[:5000])
    return root


@pytest.fixture(scope='module')
def cluster():
    from gp_ground_segmentation.tools.engine import open_engine
    with open_engine(jobs=2) as engine:
        assert engine.workers == 2
        yield engine


def test_cluster_batch_equals_replay_and_isolates_the_corrupt_input(inputs, tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    good = [inputs / 'bag_a', inputs / 'scans']
    bad = inputs / 'broken.mcap'
    out = tmp_path / 'out'
    rc = main(['batch', str(good[0]), str(bad), str(good[1]), '--out', str(out), '--jobs', '2'])
    captured = capsys.readouterr()
    assert rc == 1
    assert 'FAILED' in captured.out and '2 done, 0 skipped (output existed), 1 failed' \
        in captured.out
    # replay of each input in this process: the reference
    for src in good:
        ref = tmp_path / f'ref_{src.name}'
        assert main(['replay', str(src), str(ref)]) == 0
        got, want = cloud_bytes(out / src.name), cloud_bytes(ref)
        assert set(got) == {f'{TOPIC}/ground', f'{TOPIC}/obstacles', f'{TOPIC}/ground_surface'}
        assert got == want
    assert main(['replay', str(bad), str(tmp_path / 'ref_bad')]) == 2
    replay_error = capsys.readouterr().err.strip().split('error: ', 1)[1]
    assert not (out / 'broken').exists()
    doc = json.loads((out / 'summary.json').read_text())
    rows = {Path(r['input']).name: r for r in doc['inputs']}
    assert [Path(r['input']).name for r in doc['inputs']] == ['bag_a', 'broken.mcap', 'scans']
    assert rows['broken.mcap']['status'] == 'failed'
    assert rows['broken.mcap']['error'] == replay_error
    assert rows['bag_a']['frames'] == 3 and rows['scans']['frames'] == 2
    assert rows['scans']['points'] == sum(b.stat().st_size // 16 for b in BINS)
    for name in ('bag_a', 'scans'):
        r = rows[name]
        assert r['status'] == 'ok' and 0.3 < r['ground_share'] < 0.8
        assert 0 < r['total_ms_p50'] <= r['total_ms_p95']
        assert set(r['theta_range']) == {'sigma_f', 'gain', 'sigma_n'}
    assert doc['failed'] == 1 and doc['frames'] == 5 and len(doc['worker_peak_rss_mb']) == 2
    with open(out / 'summary.csv', newline='') as fh:
        table = list(csv.DictReader(fh))
    assert [Path(r['input']).name for r in table] == ['bag_a', 'broken.mcap', 'scans']
    assert table[1]['error'] == replay_error and table[0]['frames'] == '3'
    assert float(table[0]['sigma_f_min']) <= float(table[0]['sigma_f_max'])


def test_rerun_skips_finished_inputs_and_force_redoes_them(inputs, tmp_path, cluster,
                                                           monkeypatch):
    from gp_ground_segmentation.tools.batch import run_batch
    # relative inputs, and a working directory the (already running) workers do not share
    monkeypatch.chdir(inputs)
    good = ['bag_a', 'scans']
    out = tmp_path / 'out'
    first = run_batch(good + ['broken.mcap'], out, cluster)
    assert first.rows[0]['input'] == 'bag_a'
    assert [r['status'] for r in first.rows] == ['ok', 'ok', 'failed']
    stamp = (out / 'bag_a' / 'metadata.yaml').stat().st_mtime_ns
    again = run_batch(good + ['broken.mcap'], out, cluster)
    assert [r['status'] for r in again.rows] == ['skipped', 'skipped', 'failed']
    assert again.rows[0]['frames'] == 3  # the earlier run's numbers are kept for skipped rows
    assert (out / 'bag_a' / 'metadata.yaml').stat().st_mtime_ns == stamp
    forced = run_batch(good, out, cluster, force=True)
    assert [r['status'] for r in forced.rows] == ['ok', 'ok']
    assert (out / 'bag_a' / 'metadata.yaml').stat().st_mtime_ns != stamp
    assert cloud_bytes(out / 'bag_a') == cloud_bytes(tmp_path / 'out' / 'bag_a')


def test_ctrl_c_leaves_only_complete_outputs(inputs, tmp_path):
    """KeyboardInterrupt in the client after the first task finished: the cluster is shut down;
    what is left in DIR is complete bags only, and a rerun finishes the rest."""
    from gp_ground_segmentation.tools.batch import run_batch
    from gp_ground_segmentation.tools.engine import InProcessEngine, open_engine
    srcs = []
    for i in range(4):
        dst = tmp_path / 'in' / f'bag_{i}'
        shutil.copytree(inputs / 'bag_a', dst)
        srcs.append(str(dst))
    out = tmp_path / 'out'
    # what a worker killed mid-replay leaves (replay's hidden sibling): must be gone afterwards
    (out / '.bag_3.partial-99999').mkdir(parents=True)
    (out / '.bag_3.partial-99999' / 'bag_3.mcap').write_bytes(b'half')

    def interrupt(row):
        raise KeyboardInterrupt

    with open_engine(jobs=2) as engine:
        with pytest.raises(KeyboardInterrupt):
            run_batch(srcs, out, engine, report=interrupt)
    left = sorted(p.name for p in out.iterdir())
    assert not [n for n in left if n.startswith('.')], left  # no partial or probe files
    bags = [n for n in left if n.startswith('bag_')]
    assert len(bags) >= 1  # the cluster may finish a running task while it shuts down
    for name in bags:
        assert len(cloud_bytes(out / name)[f'{TOPIC}/ground']) == 3
    doc = json.loads((out / 'summary.json').read_text())
    assert doc['interrupted'] is True
    statuses = [r['status'] for r in doc['inputs']]
    assert statuses.count('ok') == 1 and statuses.count('interrupted') == 3
    result = run_batch(srcs, out, InProcessEngine())
    statuses = [r['status'] for r in result.rows]
    assert statuses.count('skipped') == len(bags) and statuses.count('ok') == 4 - len(bags)


def test_batch_in_process_and_bad_arguments(inputs, tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'out'
    assert main(['batch', str(inputs / 'scans'), '--out', str(out)]) == 0
    assert '1 done' in capsys.readouterr().out
    assert (out / 'scans' / 'metadata.yaml').is_file()
    for argv, words in (
            (['batch', str(inputs / 'scans'), str(inputs / 'scans'), '--out', str(out)],
             'would both be written'),
            (['batch', str(inputs / 'scans'), '--out', str(out), '--params', '/nope.yaml'],
             'parameter file not found'),
            (['batch', str(inputs / 'scans'), '--out', str(out), '--jobs', '0'],
             '--jobs must be at least 1')):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err


def test_without_dask_one_line(monkeypatch, inputs, tmp_path, capsys):
    import sys

    from gp_ground_segmentation.tools.cli import main
    monkeypatch.setitem(sys.modules, 'distributed', None)  # import distributed -> ImportError
    assert main(['batch', str(inputs / 'scans'), '--out', str(tmp_path / 'o'), '--jobs',
                 '2']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'gp_ground_segmentation[scale]'" in err[0]


class _Client:
    """Stands in for a distributed.Client whose workers see other storage than this process."""

    def __init__(self, answer):
        self.answer = answer

    def run(self, fn, *args):
        return {'tcp://10.0.0.7:40000': self.answer(*args)}


def test_paths_workers_cannot_see_are_refused_up_front(inputs, tmp_path):
    from gp_ground_segmentation.tools.errors import CliError
    from gp_ground_segmentation.tools.engine import DaskEngine, _visible
    assert _visible([str(inputs / 'scans'), '/nope'], None) == {'missing': ['/nope'],
                                                                'token': True}
    blind = DaskEngine(_Client(lambda paths, token: {'missing': paths[:1], 'token': True}))
    with pytest.raises(CliError, match='not visible on worker tcp://10.0.0.7:40000'):
        blind.check_shared([str(inputs / 'scans')], tmp_path / 'out')
    other_disk = DaskEngine(_Client(lambda paths, token: {'missing': [], 'token': False}))
    with pytest.raises(CliError, match='not the same storage on worker'):
        other_disk.check_shared([str(inputs / 'scans')], tmp_path / 'out')
    assert list((tmp_path / 'out').iterdir()) == []  # the probe file is removed


def _malloc_env():
    import os
    return os.environ.get('MALLOC_TRIM_THRESHOLD_')


def test_workers_keep_glibc_malloc_defaults(cluster):
    """Dask's MALLOC_TRIM_THRESHOLD_ doubles the CPU per frame (engine.py); LocalCluster workers
    must not get it, and the shipped config for `dask worker` removes the same key."""
    import yaml

    from gp_ground_segmentation.tools.engine import WORKER_MALLOC_KEY
    assert set(cluster.run_on_workers(_malloc_env).values()) == {None}
    doc = yaml.safe_load((REPO / 'config' / 'dask' / 'gp-ground-seg-worker.yaml').read_text())
    node = doc
    for part in WORKER_MALLOC_KEY.split('.'):
        assert list(node) == [part]
        node = node[part]
    assert node is None


def test_progress_counts_frames_across_the_batch(inputs, tmp_path):
    import io

    from gp_ground_segmentation.tools.batch import run_batch
    from gp_ground_segmentation.tools.engine import InProcessEngine

    class Tty(io.StringIO):
        def isatty(self):
            return True

    stream = Tty()
    rows = []
    result = run_batch([str(inputs / 'bag_a'), str(inputs / 'broken.mcap'),
                        str(inputs / 'scans')], tmp_path / 'out', InProcessEngine(),
                       report=rows.append, progress_stream=stream)
    assert result.failed == 1 and [r['status'] for r in rows] == ['ok', 'failed', 'ok']
    bars = stream.getvalue().split('\r')
    assert any(' 3/5 frames' in b for b in bars) and ' 5/5 frames' in bars[-1]
