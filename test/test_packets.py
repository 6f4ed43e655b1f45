# SPDX-License-Identifier: Apache-2.0
"""Raw Velodyne data offline (tools/packets.py): the real VLP-16 packet bag of ../shared/data
(velodyne_msgs/VelodyneScan, 4 scans) and a .pcap written here from its packets (no sample pcap
exists: Ethernet/IPv4/UDP headers around each 1206-byte packet, a libpcap global header).

Checks: ``replay BAG OUT`` with no option finds the packet topic, writes one frame per scan with
its header at its bag time on /velodyne_points/{ground,obstacles,...}; the last frame holds the
driver's reference cloud (sensors/velodyne_vlp16.pcd: 14,831 points) within 0.5 % at a median
nearest-neighbour distance <= 1 cm; the pcap gives the same rotations; eval and batch read both;
an unsupported model, a truncated pcap, a capture without Velodyne data and a missing
velodyne-decoder are one line each, nothing written.
"""

import sys

import numpy as np
import pytest
from conftest import DATA
from test_bag import read_bag

from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
from gp_ground_segmentation.tools.cli import main
from gp_ground_segmentation.tools.io import read_points_file

pytest.importorskip('velodyne_decoder')

PACKETS_BAG = DATA / 'nebula_vlp16_bag' / '1673400471837873222'
REFERENCE = DATA / 'sensors' / 'velodyne_vlp16.pcd'
PACKETS, CLOUDS = '/velodyne_packets', '/velodyne_points'
OUTPUTS = {f'{CLOUDS}/ground', f'{CLOUDS}/obstacles', f'{CLOUDS}/ground_surface',
           '/diagnostics'}

pytestmark = pytest.mark.skipif(not PACKETS_BAG.is_dir(),
                                reason=f'real data not found: {PACKETS_BAG}')


def _scans(bag=PACKETS_BAG):
    """[(bag time ns, VelodyneScan as rosbags decodes it)] of the packet bag."""
    from rosbags.highlevel import AnyReader

    from gp_ground_segmentation.tools.packets import packet_typestore
    with AnyReader([bag], default_typestore=packet_typestore()) as reader:
        return [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def write_pcap(path, scans, cut=0):
    """A libpcap capture of the scans' packets, each in UDP/IPv4/Ethernet as a VLP-16 sends
    it (port 2368, broadcast), stamped with the packet's stamp; ``cut`` bytes cut off the end."""
    import dpkt
    with open(path, 'wb') as f:
        writer = dpkt.pcap.Writer(f, linktype=dpkt.pcap.DLT_EN10MB)
        for _, scan in scans:
            for packet in scan.packets:
                udp = dpkt.udp.UDP(sport=2368, dport=2368, data=bytes(packet.data))
                udp.ulen = len(udp)
                ip = dpkt.ip.IP(src=bytes([192, 168, 1, 201]), dst=bytes([255] * 4),
                                p=dpkt.ip.IP_PROTO_UDP, data=udp)
                ip.len = len(ip)
                frame = dpkt.ethernet.Ethernet(src=bytes.fromhex('607688000001'),
                                               dst=b'\xff' * 6, type=dpkt.ethernet.ETH_TYPE_IP,
                                               data=ip)
                writer.writepkt(bytes(frame), ts=_stamp_ns(packet.stamp) / 1e9)
    if cut:
        with open(path, 'r+b') as f:
            f.truncate(path.stat().st_size - cut)
    return path


def _xyz(msgs):
    return np.concatenate([cloud_xyz(read_cloud(m)).astype(np.float64) for m in msgs])


def test_replay_of_the_packet_bag_with_no_option(tmp_path, capsys):
    from scipy.spatial import cKDTree
    out = tmp_path / 'out'
    assert main(['replay', str(PACKETS_BAG), str(out)]) == 0
    assert 'using /velodyne_packets (Velodyne packets' in capsys.readouterr().err
    topics = read_bag(out)
    assert set(topics) == OUTPUTS
    scans = _scans()
    ground, obstacles = topics[f'{CLOUDS}/ground'], topics[f'{CLOUDS}/obstacles']
    assert len(ground) == len(obstacles) == len(scans) == 4
    for (t, scan), (t_g, m_g), (t_o, m_o) in zip(scans, ground, obstacles):
        assert t_g == t_o == t  # at the scan's bag time, with its header
        for m in (m_g, m_o):
            assert _stamp_ns(m.header.stamp) == _stamp_ns(scan.header.stamp)
            assert m.header.frame_id == scan.header.frame_id == 'velodyne'
        names = [f.name for f in m_g.fields]
        assert names[:4] == ['x', 'y', 'z', 'intensity'] and {'ring', 'time'} <= set(names)
        times = read_cloud(m_g)['time']  # s after the header stamp, within one rotation
        assert 0.0 <= times.min() and times.max() < 0.11
    last = _xyz([ground[-1][1], obstacles[-1][1]])
    ref = read_points_file(REFERENCE)
    ref_xyz = np.stack([ref[c] for c in 'xyz'], axis=1).astype(np.float64)
    distance, _ = cKDTree(ref_xyz).query(last)
    print(f'last scan: {len(last)} points decoded vs {len(ref_xyz)} in the driver\'s cloud '
          f'({len(last) / len(ref_xyz) - 1:+.2%}), median nearest-neighbour distance '
          f'{np.median(distance) * 1000:.1f} mm')
    assert len(ref_xyz) == 14831
    assert abs(len(last) - len(ref_xyz)) <= 0.005 * len(ref_xyz)
    assert np.median(distance) <= 0.01


def test_a_pcap_of_the_bags_packets_gives_its_rotations(tmp_path, capsys):
    scans = _scans()
    pcap = write_pcap(tmp_path / 'vlp16.pcap', scans)
    from_bag, from_pcap = tmp_path / 'bag_out', tmp_path / 'pcap_out'
    assert main(['replay', str(PACKETS_BAG), str(from_bag)]) == 0
    assert main(['replay', str(pcap), str(from_pcap), '--frame-id', 'lidar']) == 0
    bag_frames = read_bag(from_bag, f'{CLOUDS}/ground')[f'{CLOUDS}/ground']
    pcap_topics = read_bag(from_pcap)
    assert set(pcap_topics) == OUTPUTS
    pcap_frames = pcap_topics[f'{CLOUDS}/ground']
    assert len(pcap_frames) == len(scans) == 4
    for (_, scan), (t, m_pcap), (_, m_bag) in zip(scans, pcap_frames, bag_frames):
        # cut at azimuth 0 as the driver's scans, stamped with the first packet's capture time
        assert t == _stamp_ns(m_pcap.header.stamp)
        assert abs(t - _stamp_ns(scan.packets[0].stamp)) < 1000  # pcap stamps are in us
        assert m_pcap.header.frame_id == 'lidar'
        assert np.array_equal(_xyz([m_pcap]), _xyz([m_bag]))


def test_eval_and_batch_read_packet_bags_and_pcaps(tmp_path, capsys):
    import json
    pcap = write_pcap(tmp_path / 'vlp16.pcap', _scans())
    assert main(['eval', str(PACKETS_BAG), f'{pcap}:3', '--json']) == 0
    frames = json.loads(capsys.readouterr().out)['frames']
    assert [f['input'] for f in frames] == [f'{PACKETS_BAG}:{i}' for i in range(4)] + [
        f'{pcap}:3']
    assert frames[3]['points'] == frames[4]['points'] > 14000
    assert main(['batch', str(PACKETS_BAG), str(pcap), '--out', str(tmp_path / 'res')]) == 0
    for name in (PACKETS_BAG.name, 'vlp16'):
        assert len(read_bag(tmp_path / 'res' / name, f'{CLOUDS}/ground')[
            f'{CLOUDS}/ground']) == 4


def _packet_bag_of_model(path, model_id: int):
    """The packet bag with every packet's factory byte (its last) set to ``model_id``."""
    from rosbags.rosbag2 import Writer

    from gp_ground_segmentation.tools.packets import VELODYNE_SCAN, packet_typestore
    typestore = packet_typestore()
    with Writer(path, version=9) as writer:
        conn = writer.add_connection(PACKETS, VELODYNE_SCAN, typestore=typestore)
        for t, scan in _scans():
            for packet in scan.packets:
                packet.data = packet.data.copy()  # rosbags' arrays view the bag's bytes
                packet.data[-1] = model_id
            writer.write(conn, t, typestore.serialize_cdr(scan, VELODYNE_SCAN))
    return path


def _bad_input(case, tmp_path):
    scans = _scans()
    if case == 'model':
        return _packet_bag_of_model(tmp_path / 'model_153', 153)
    if case == 'truncated':  # in the last packet's payload
        return write_pcap(tmp_path / 'cut.pcap', scans, cut=600)
    if case == 'truncated header':  # in the last record's 16-byte header
        return write_pcap(tmp_path / 'cut.pcap', scans, cut=1206 + 42 + 8)
    path = tmp_path / 'empty.pcap'  # a capture without one Velodyne data packet
    write_pcap(path, [])
    return path


@pytest.mark.parametrize('case, words', [
    ('model', 'unsupported Velodyne model'), ('truncated', 'truncated pcap'),
    ('truncated header', 'truncated pcap'), ('no data', 'no Velodyne data packet')])
@pytest.mark.parametrize('command', ['replay', 'eval', 'batch'])
def test_bad_packet_input_is_one_line_and_writes_nothing(case, words, command, tmp_path,
                                                         capsys):
    bad = _bad_input(case, tmp_path)
    out = tmp_path / 'out'
    argv = {'replay': ['replay', str(bad), str(out)], 'eval': ['eval', str(bad)],
            'batch': ['batch', str(bad), '--out', str(out)]}[command]
    assert main(argv) == (1 if command == 'batch' else 2)
    captured = capsys.readouterr()
    text = captured.out if command == 'batch' else captured.err
    lines = [ln for ln in text.strip().splitlines() if words in ln]
    assert len(lines) == 1, text
    if command == 'batch':  # the failed row; no output bag
        assert not (out / bad.stem).exists()
    else:
        assert len(captured.err.strip().splitlines()) == 1 and not out.exists()


def test_without_velodyne_decoder_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, 'velodyne_decoder', None)
    assert main(['replay', str(PACKETS_BAG), str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'gp_ground_segmentation[packets]'" in err[0]
    assert not (tmp_path / 'out').exists()
