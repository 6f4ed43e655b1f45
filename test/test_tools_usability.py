# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg rough edges found by a new user: raw-packet bags, topic names without a slash,
--frame-id / --output-prefix of replay, plot --force, eval of an empty file, replay warm-up."""

from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from gp_ground_segmentation.tools.cli import main

SAMPLE = REPO / 'data' / 'kitti00_sample'


def _topics(bag):
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(bag)]) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def _first_message(bag, topic):
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2
    with AnyReader([Path(bag)]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for _, _, raw in reader.messages(connections=conns):
            return deserialize_message(bytes(raw), PointCloud2)


def _ouster_packet_bag(path):
    """A bag of one raw Ouster packet (ouster_sensor_msgs/msg/PacketMsg, the driver's type)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    name = 'ouster_sensor_msgs/msg/PacketMsg'
    typestore.register(get_types_from_msg('uint8[] buf\n', name))
    packet = typestore.types[name](buf=np.zeros(12609, np.uint8))
    with Writer(path, version=9) as writer:
        conn = writer.add_connection('/ouster/lidar_packets', name, typestore=typestore)
        writer.write(conn, 1, typestore.serialize_cdr(packet, name))
    return path


@pytest.mark.parametrize('extra', [[], ['--topic', '/ouster/lidar_packets']])
def test_raw_packet_bag_of_another_sensor_names_its_type(tmp_path, capsys, extra):
    # Velodyne packets are decoded (test_packets.py); other sensors' are not
    bag = _ouster_packet_bag(tmp_path / 'ouster')
    assert main(['replay', str(bag), str(tmp_path / 'out'), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert 'ouster_sensor_msgs/msg/PacketMsg' in err and 'PointCloud2' in err
    assert 'corrupt' not in err and 'default_typestore' not in err
    assert not (tmp_path / 'out').exists()


def test_topic_without_leading_slash(tmp_path):
    out = tmp_path / 'out'
    assert main(['replay', str(SAMPLE), str(out), '--topic', 'velodyne_points',
                 '--max-frames', '1']) == 0
    assert '/velodyne_points/ground' in _topics(out)


def test_replay_output_prefix_and_frame_id(tmp_path):
    from gp_ground_segmentation.tools.io import write_pcd
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-20, 20, (3000, 2)), rng.normal(-1.7, 0.02, 3000)].astype('<f4')
    pcd = tmp_path / 'scan.pcd'
    write_pcd(pcd, xyz.view([('x', '<f4'), ('y', '<f4'), ('z', '<f4')]).reshape(-1))
    out = tmp_path / 'out'
    assert main(['replay', str(pcd), str(out), '--frame-id', 'base_lidar',
                 '--output-prefix', '']) == 0
    assert set(_topics(out)) == {'/ground', '/obstacles', '/ground_surface', '/diagnostics'}
    assert _first_message(out, '/ground').header.frame_id == 'base_lidar'


def test_plot_does_not_overwrite_without_force(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    fig = tmp_path / 'fig.png'
    fig.write_bytes(b'keep me')
    assert main(['plot', f'{SAMPLE}:0', '--out', str(fig)]) == 2
    err = capsys.readouterr().err
    assert '--force' in err and len(err.strip().splitlines()) == 1
    assert fig.read_bytes() == b'keep me'
    assert main(['plot', f'{SAMPLE}:0', '--out', str(fig), '--force']) == 0
    assert fig.read_bytes()[:4] == b'\x89PNG'


def test_eval_of_an_empty_scan_is_an_error(tmp_path, capsys):
    empty = tmp_path / 'empty.bin'
    empty.write_bytes(b'')
    assert main(['eval', str(empty)]) == 2
    err = capsys.readouterr().err
    assert 'no valid point' in err and str(empty) in err


def test_replay_loads_the_compiled_kernel_before_the_first_frame(tmp_path, monkeypatch):
    import gp_ground_segmentation.core.stages as stages
    import gp_ground_segmentation.ros.pipeline as pipeline
    from gp_ground_segmentation.core.segmenter import GroundSegmenter
    calls = []
    real_warm_up, real_process = stages.compile_round_off, pipeline.process_cloud
    monkeypatch.setattr(stages, 'compile_round_off',
                        lambda **kw: (calls.append('warm_up'), real_warm_up(**kw))[1])
    real_segmenter_warm_up = GroundSegmenter.warm_up  # every compiled stage a frame needs
    monkeypatch.setattr(GroundSegmenter, 'warm_up', lambda self: (
        calls.append('segmenter'), real_segmenter_warm_up(self))[1])
    monkeypatch.setattr(pipeline, 'process_cloud',
                        lambda *a, **kw: (calls.append('frame'), real_process(*a, **kw))[1])
    real_outputs = pipeline.warm_up  # the output clouds' compiled pass, queued after the GP
    monkeypatch.setattr(pipeline, 'warm_up', lambda: (calls.append('outputs'), real_outputs())[1])
    assert main(['replay', str(SAMPLE), str(tmp_path / 'out'), '--max-frames', '2']) == 0
    # the GP with its std first (the surface reads it), the segmenter's stages (its own GP
    # warm-up is then a cache hit), the output pass, then the frames
    assert calls == ['warm_up', 'segmenter', 'warm_up', 'outputs', 'frame', 'frame']
