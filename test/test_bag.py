# SPDX-License-Identifier: Apache-2.0
"""Offline bag replay (gp-ground-seg replay) on the real KITTI bag, and its handling of bad input.

Checks: message counts per output topic, output headers and bag times equal the input's, every
frame's ground and obstacle clouds are an exact partition of the input point rows (byte for
byte, in input order, equal to the pipeline's own split), the output bag reopens with rosbags
(mcap and sqlite3), ROS 1 .bag and .bin/.pcd inputs, refusal to overwrite, no half-written bag
left behind, and one-line errors with exit status 2 for corrupt/truncated/empty/wrong bags.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, REPO, assert_output_like_input, module_env

BAG = DATA / 'kitti00_velodyne_points'
TOPIC = '/velodyne_points'

pytestmark = pytest.mark.skipif(not BAG.is_dir(), reason=f'real data not found: {BAG} '
                                '(../shared/data beside the repo)')


def read_bag(path, topic=None):
    """{topic: [(bag_time_ns, rclpy message)]} of a bag, deserialised with rclpy."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2
    classes = {'sensor_msgs/msg/PointCloud2': PointCloud2,
               'diagnostic_msgs/msg/DiagnosticArray': DiagnosticArray}
    out = {}
    with AnyReader([Path(path)]) as reader:
        conns = [c for c in reader.connections if topic is None or c.topic == topic]
        for c in conns:
            out.setdefault(c.topic, [])
        for c, t, raw in reader.messages(connections=conns):
            out[c.topic].append((t, deserialize_message(bytes(raw), classes[c.msgtype])))
    return out


def rows(msg):
    from gp_ground_segmentation.ros.cloud import point_rows
    return np.ascontiguousarray(point_rows(msg))


def as_items(r):
    """(N, point_step) uint8 -> (N,) opaque items, comparable and sortable row by row."""
    return r.view(np.dtype((np.void, r.shape[1]))).reshape(-1)


def assert_partition(inp, ground, obstacles):
    """ground and obstacles hold every input row exactly once, in input order, fields intact."""
    for out in (ground, obstacles):
        assert_output_like_input(inp, out)
    r_in, r_g, r_o = as_items(rows(inp)), as_items(rows(ground)), as_items(rows(obstacles))
    assert r_g.size > 0 and r_o.size > 0
    assert r_g.size + r_o.size == r_in.size  # KITTI has no invalid points
    # multiset equality: the union is the input, nothing lost, nothing duplicated
    assert np.array_equal(np.sort(np.concatenate([r_g, r_o])), np.sort(r_in))
    return r_in, r_g, r_o


@pytest.fixture(scope='module')
def input_frames():
    return read_bag(BAG, TOPIC)[TOPIC]


@pytest.fixture(scope='module')
def replayed(tmp_path_factory):
    from gp_ground_segmentation.tools.bag import replay
    out = tmp_path_factory.mktemp('replay') / 'nested' / 'out_bag'  # parent dirs created
    summary = replay([BAG], out)
    return out, summary


def test_counts_headers_and_partition(replayed, input_frames):
    from gp_ground_segmentation.ros.pipeline import process_cloud
    from gp_ground_segmentation.core.segmenter import GroundSegmenter

    out, summary = replayed
    assert summary.frames == len(input_frames) == 6 and summary.skipped == 0
    topics = read_bag(out)
    assert set(topics) == {f'{TOPIC}/ground', f'{TOPIC}/obstacles', f'{TOPIC}/ground_surface',
                           '/diagnostics'}
    ground, obstacles = topics[f'{TOPIC}/ground'], topics[f'{TOPIC}/obstacles']
    diags = topics['/diagnostics']
    surfaces = topics[f'{TOPIC}/ground_surface']
    assert len(ground) == len(obstacles) == len(diags) == len(surfaces) == len(input_frames)
    for (t_in, m_in), (t_s, m_s) in zip(input_frames, surfaces):
        assert t_s == t_in and m_s.header.stamp == m_in.header.stamp
        assert [f.name for f in m_s.fields] == ['x', 'y', 'z', 'z_std'] and m_s.width > 1000
    reference = GroundSegmenter()  # same default params, same frame order -> same warm start
    n_ground = 0
    for (t_in, m_in), (t_g, m_g), (t_o, m_o), (t_d, m_d) in zip(
            input_frames, ground, obstacles, diags):
        assert t_in == t_g == t_o == t_d  # written at the input's bag time
        r_in, r_g, r_o = assert_partition(m_in, m_g, m_o)
        ref = process_cloud(m_in, reference).result.ground_mask
        assert np.array_equal(r_g, r_in[ref]) and np.array_equal(r_o, r_in[~ref])
        assert m_d.header.stamp == m_in.header.stamp
        n_ground += r_g.size
    assert summary.ground == n_ground
    assert summary.points == sum(m.width * m.height for _, m in input_frames)


def test_diagnostics_per_frame(replayed):
    out, _ = replayed
    diags = read_bag(out, '/diagnostics')['/diagnostics']
    for i, (_, arr) in enumerate(diags):
        (status,) = arr.status
        values = {kv.key: kv.value for kv in status.values}
        assert values['frames_processed'] == str(i + 1)
        assert values['frames_failed'] == '0' and values['frame_index'] == str(i)
        assert float(values['total_ms_max']) > 0
        assert status.level != b'\x02'  # never ERROR on good frames


def test_summary_table_lists_stages_and_theta(replayed):
    _, summary = replayed
    text = summary.table()
    for word in ('frames', 'points', 'ground share', 'theta range', 'p50 ms', 'p95 ms',
                 'max ms', 'decode', 'encode', 'total'):
        assert word in text


def test_cli_refuses_overwrite_then_force_replaces(tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'marker').write_text('old')
    assert main(['replay', str(BAG), str(out), '--max-frames', '1', '--force']) == 2
    assert 'not a rosbag2 directory' in capsys.readouterr().err  # --force never wipes a non-bag
    (out / 'metadata.yaml').write_text('old bag')
    assert main(['replay', str(BAG), str(out), '--max-frames', '1']) == 2
    err = capsys.readouterr().err
    assert 'exists' in err and '--force' in err and len(err.strip().splitlines()) == 1
    assert (out / 'marker').exists()
    assert main(['replay', str(BAG), str(out), '--max-frames', '1', '--force']) == 0
    assert not (out / 'marker').exists()
    assert (out / 'metadata.yaml').exists() and (out / 'out.mcap').exists()
    counts = {k: len(v) for k, v in read_bag(out).items()}
    assert counts == {f'{TOPIC}/ground': 1, f'{TOPIC}/obstacles': 1,
                      f'{TOPIC}/ground_surface': 1, '/diagnostics': 1}
    assert [p.name for p in tmp_path.iterdir()] == ['out']  # no temporary siblings left


def test_sqlite3_storage(tmp_path, input_frames):
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'sq'
    assert main(['replay', str(BAG), str(out), '--storage', 'sqlite3', '--max-frames', '2']) == 0
    assert (out / 'sq.db3').exists()
    topics = read_bag(out)
    assert len(topics[f'{TOPIC}/ground']) == 2
    for (_, m_in), (_, g), (_, o) in zip(input_frames, topics[f'{TOPIC}/ground'],
                                         topics[f'{TOPIC}/obstacles']):
        assert_partition(m_in, g, o)


def test_progress_bar_only_on_a_tty():
    import io

    from gp_ground_segmentation.tools.bag import Progress

    class Tty(io.StringIO):
        def isatty(self):
            return True
    quiet, tty = io.StringIO(), Tty()
    for stream in (quiet, tty):
        p = Progress(4, stream=stream)
        p.update(1)
        p.update(4)
        p.close()
    assert quiet.getvalue() == ''
    text = tty.getvalue()
    assert '\r[' in text and '4/4 frames' in text and 'fps' in text and 'ETA' in text


def test_interrupted_replay_leaves_no_bag(tmp_path, monkeypatch):
    import gp_ground_segmentation.ros.pipeline as pipeline
    from gp_ground_segmentation.tools.bag import replay
    real = pipeline.process_cloud
    calls = []

    def flaky(msg, seg, **outputs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(msg, seg, **outputs)
    monkeypatch.setattr(pipeline, 'process_cloud', flaky)
    out = tmp_path / 'out'
    with pytest.raises(KeyboardInterrupt):
        replay([BAG], out)
    assert list(tmp_path.iterdir()) == []  # neither the bag nor its temporary directory


def test_bad_frame_is_skipped_and_reported(tmp_path, input_frames):
    """A malformed cloud inside a good bag is dropped and counted, like the node does."""
    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import PointCloud2

    from gp_ground_segmentation.tools.bag import replay
    src = tmp_path / 'in'
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(src, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(TOPIC, 'sensor_msgs/msg/PointCloud2', typestore=ts)
        for i, (t, m) in enumerate(input_frames[:3]):
            if i == 1:
                m = deserialize_message(serialize_message(m), PointCloud2)  # a private copy
                m.width += 10  # data now 160 bytes short of height * row_step
                m.row_step = m.width * m.point_step
            w.write(c, t, serialize_message(m))
    summary = replay([src], tmp_path / 'out')
    assert summary.frames == 2 and summary.skipped == 1
    assert 'frame 1' in summary.skipped_reasons[0] and 'bytes' in summary.skipped_reasons[0]
    topics = read_bag(tmp_path / 'out')
    assert len(topics[f'{TOPIC}/ground']) == 2 and len(topics['/diagnostics']) == 3
    status = topics['/diagnostics'][1][1].status[0]
    assert status.level == b'\x02' and 'bad input' in status.message


def test_point_file_directory_input(tmp_path):
    from gp_ground_segmentation.tools.cli import main
    src = tmp_path / 'scans'
    src.mkdir()
    bins = [DATA / 'kitti_unlabeled_patchworkpp_000000.bin',
            DATA / 'kitti_sequnknown_spvnas_000000.bin']
    for i, b in enumerate(bins):
        shutil.copy(b, src / f'{i:06d}.bin')
    (src / 'notes.txt').write_text('ignored')
    out = tmp_path / 'out'
    assert main(['replay', str(src), str(out)]) == 0
    topics = read_bag(out)
    ground, obstacles = topics[f'{TOPIC}/ground'], topics[f'{TOPIC}/obstacles']
    assert len(ground) == 2
    for i, ((t, g), (_, o), b) in enumerate(zip(ground, obstacles, bins)):
        assert t == i * 100_000_000 and g.header.frame_id == 'velodyne'
        assert (g.header.stamp.sec, g.header.stamp.nanosec) == (0, i * 100_000_000)
        assert [f.name for f in g.fields] == ['x', 'y', 'z', 'intensity']
        r_in = np.fromfile(b, dtype=np.uint8).reshape(-1, 16)
        r_in = as_items(r_in)
        r_g, r_o = as_items(rows(g)), as_items(rows(o))
        assert np.array_equal(np.sort(np.concatenate([r_g, r_o])), np.sort(r_in))


def test_ros1_bag_input(tmp_path, input_frames):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from gp_ground_segmentation.tools.bag import replay
    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    path = tmp_path / 'in.bag'
    with Writer(path) as w:
        conn = w.add_connection(TOPIC, 'sensor_msgs/msg/PointCloud2', typestore=ts)
        for t, m in input_frames[:2]:
            m1 = T['sensor_msgs/msg/PointCloud2'](
                header=T['std_msgs/msg/Header'](seq=7, stamp=T['builtin_interfaces/msg/Time'](
                    sec=m.header.stamp.sec, nanosec=m.header.stamp.nanosec),
                    frame_id=m.header.frame_id),
                height=m.height, width=m.width,
                fields=[T['sensor_msgs/msg/PointField'](name=f.name, offset=f.offset,
                                                        datatype=f.datatype, count=f.count)
                        for f in m.fields],
                is_bigendian=m.is_bigendian, point_step=m.point_step, row_step=m.row_step,
                data=np.frombuffer(bytes(m.data), np.uint8), is_dense=m.is_dense)
            w.write(conn, t, ts.serialize_ros1(m1, conn.msgtype))
    summary = replay([path], tmp_path / 'out')
    assert summary.frames == 2
    topics = read_bag(tmp_path / 'out')
    for (_, m_in), (_, g), (_, o) in zip(input_frames, topics[f'{TOPIC}/ground'],
                                         topics[f'{TOPIC}/obstacles']):
        assert_partition(m_in, g, o)


# --- bad input: one line on stderr, exit status 2, no traceback, nothing written ----------------

def _write_bag(path, entries, storage='mcap'):
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    from std_msgs.msg import String
    ts = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        for topic, msgtype, count in entries:
            c = w.add_connection(topic, msgtype, typestore=ts)
            for i in range(count):
                w.write(c, i, serialize_message(String(data='not a cloud')))


def _make_bad(kind, tmp_path):
    if kind == 'truncated_mcap':
        bag = tmp_path / 'trunc'
        bag.mkdir()
        shutil.copy(BAG / 'metadata.yaml', bag)
        data = (BAG / 'kitti00_velodyne_points.mcap').read_bytes()
        (bag / 'kitti00_velodyne_points.mcap').write_bytes(data[:len(data) // 2])
        return bag, 'corrupt'
    if kind == 'corrupt_file':
        bag = tmp_path / 'garbage.mcap'
        bag.write_bytes(np.random.default_rng(0).bytes(4096))
        return bag, 'corrupt'
    if kind == 'corrupt_chunk':  # the compressed sample bag with damaged zstd chunks
        bag = tmp_path / 'damaged'
        shutil.copytree(REPO / 'data' / 'kitti00_sample', bag)
        f = next(bag.glob('*.mcap'))
        b = bytearray(f.read_bytes())
        b[len(b) // 3:len(b) // 3 + 64] = b'\xff' * 64
        f.write_bytes(bytes(b))
        return bag, 'corrupt'
    if kind == 'empty_bag':
        bag = tmp_path / 'empty'
        _write_bag(bag, [])
        return bag, 'empty'
    if kind == 'topic_without_messages':
        bag = tmp_path / 'nomsg'
        _write_bag(bag, [(TOPIC, 'sensor_msgs/msg/PointCloud2', 0)])
        return bag, 'no messages'
    if kind == 'missing_topic':
        bag = tmp_path / 'other'
        _write_bag(bag, [('/chatter', 'std_msgs/msg/String', 2)], 'sqlite3')
        return bag, f'topic {TOPIC} not in bag'
    if kind == 'wrong_type':
        bag = tmp_path / 'wrong'
        _write_bag(bag, [(TOPIC, 'std_msgs/msg/String', 2)])
        return bag, 'std_msgs/msg/String, not sensor_msgs/msg/PointCloud2'
    if kind == 'missing_input':
        return tmp_path / 'nope', 'no such file'
    if kind == 'empty_directory':
        (tmp_path / 'emptydir').mkdir()
        return tmp_path / 'emptydir', 'neither a rosbag2 directory'
    if kind == 'bad_point_file':
        bad = tmp_path / 'bad.bin'
        bad.write_bytes(b'\x00' * 17)
        return bad, 'not a multiple of 16'
    raise AssertionError(kind)


BAD_KINDS = ['truncated_mcap', 'corrupt_file', 'corrupt_chunk', 'empty_bag',
             'topic_without_messages', 'missing_topic', 'wrong_type', 'missing_input',
             'empty_directory', 'bad_point_file']


@pytest.mark.parametrize('kind', BAD_KINDS)
def test_bad_input_one_line_exit_2(kind, tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    bad, expected = _make_bad(kind, tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    out = tmp_path / 'out'
    rc = main(['replay', str(bad), str(out)])
    captured = capsys.readouterr()
    assert rc == 2
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith('gp-ground-seg replay: error: ')
    assert expected in lines[0]
    assert 'Traceback' not in captured.err + captured.out
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_missing_topic_lists_the_bag_topics(tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    assert main(['replay', str(BAG), str(tmp_path / 'o'), '--topic', '/points']) == 2
    err = capsys.readouterr().err
    assert 'topic /points not in bag' in err and '/velodyne_points [sensor_msgs/msg/PointCloud2]' \
        in err


def test_subprocess_truncated_bag_no_traceback(tmp_path):
    bad, _ = _make_bad('truncated_mcap', tmp_path)
    proc = subprocess.run([sys.executable, '-m', 'gp_ground_segmentation.tools.cli', 'replay',
                           str(bad), str(tmp_path / 'out')], capture_output=True, text=True,
                          env=module_env(), timeout=120)
    assert proc.returncode == 2
    assert 'Traceback' not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / 'out').exists()


def test_replay_output_switches_from_params_file(tmp_path, input_frames):
    """--params switches the outputs as in the node: no surface, height_above_ground field."""
    from gp_ground_segmentation.tools.bag import replay
    params = tmp_path / 'params.yaml'
    params.write_text('ground_segmentation:\n  ros__parameters:\n'
                      '    publish_ground_surface: false\n'
                      '    add_height_above_ground_field: true\n')
    out = tmp_path / 'out'
    replay([BAG], out, params_file=str(params), max_frames=1)
    topics = read_bag(out)
    assert set(topics) == {f'{TOPIC}/ground', f'{TOPIC}/obstacles', '/diagnostics'}
    (_, m_in), (_, m_g) = input_frames[0], topics[f'{TOPIC}/ground'][0]
    assert [f.name for f in m_g.fields] == [f.name for f in m_in.fields] + [
        'height_above_ground']
    assert m_g.point_step == m_in.point_step + 4
