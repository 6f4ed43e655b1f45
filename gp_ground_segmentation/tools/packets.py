# SPDX-License-Identifier: Apache-2.0
"""Raw Velodyne data offline: packet bags (``velodyne_msgs/VelodyneScan``) and ``.pcap`` captures
decoded into PointCloud2 frames with ``velodyne-decoder`` (the optional extra ``packets``,
imported here only when a packet input is read; it detects the model from the packets and
brings every model's factory calibration, except the HDL-64E's, which is in its own stream).

* A packet bag gives one frame per VelodyneScan message (a driver's scan is one rotation), with
  the message's header (stamp, frame_id) at its bag time. rosbags has no velodyne_msgs type
  built in and bags before rosbag2 metadata 8 carry no definitions: :func:`packet_typestore`
  registers the ROS 2 driver's definitions (:data:`VELODYNE_MSGS`).
* A ``.pcap`` (classic libpcap format, Ethernet/IPv4/UDP; pcapng: convert with
  ``editcap -F pcap``) is cut into rotations at azimuth 0 (``cut_angle`` 0: a capture of the
  packets of a driver's bag gives back its scans), each stamped with the capture time of its
  first packet, ``frame_id`` given by the caller. Only 1206-byte UDP payloads are data packets;
  the 512-byte position packets and any other traffic are passed over. A record cut short (a
  truncated file) is an error, not a shorter frame.

The clouds carry velodyne-decoder's fields: x, y, z, intensity, ``time`` (FLOAT32, s after
header.stamp), column (UINT16), ring and return_type (UINT8). Every failure (velodyne-decoder
missing, an unsupported model, a truncated pcap) is a ``BagError`` with one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from builtin_interfaces.msg import Time
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import Header

from ..ros.cloud import make_cloud
from ..ros.imu import stamp_seconds
from .errors import BagError, one_line

VELODYNE_SCAN = 'velodyne_msgs/msg/VelodyneScan'
# The ROS 2 velodyne driver's message definitions (velodyne_msgs/msg/*.msg)
VELODYNE_MSGS = {
    'velodyne_msgs/msg/VelodynePacket': 'builtin_interfaces/Time stamp\nuint8[1206] data\n',
    VELODYNE_SCAN: 'std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n',
}
PACKETS_MISSING = ("reading Velodyne packets needs velodyne-decoder, which is not installed: pip "
                   "install 'gp_ground_segmentation[packets]' (or: pip install velodyne-decoder)")
DATA_PACKET_BYTES = 1206  # a Velodyne data packet's UDP payload
PCAP_CUT_ANGLE_DEG = 0.0  # where a .pcap's rotations are cut (deg of azimuth)
TIME_FIELD = 'time'  # s after the cloud's stamp


def packet_typestore():
    """A ROS 2 Jazzy typestore that also knows :data:`VELODYNE_MSGS` (a new one: the shared
    default is left alone)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in VELODYNE_MSGS.items():
        types.update(get_types_from_msg(text, name))
    typestore.register(types)
    return typestore


def _velodyne_decoder():
    """The velodyne_decoder module (the ``packets`` extra), or BagError saying how to get it."""
    try:
        import velodyne_decoder
    except ImportError:
        raise BagError(PACKETS_MISSING) from None
    return velodyne_decoder


def _dpkt():
    """dpkt (velodyne-decoder's pcap reader, in the ``packets`` extra too)."""
    try:
        import dpkt
    except ImportError:
        raise BagError(PACKETS_MISSING) from None
    return dpkt


def _decoded(decode, where: str, *args):
    """``decode(*args)`` of velodyne-decoder; its errors (an unsupported model, a packet it
    cannot read) as one BagError line saying ``where``."""
    try:
        return decode(*args)
    except (RuntimeError, ValueError, TypeError) as err:
        raise BagError(f'{where} cannot be decoded: {one_line(err, 300)}') from None


def _cloud(points: np.ndarray, stamp_s: float, frame_id: str, decoded_stamp_s: float):
    """PointCloud2 of velodyne-decoder's points stamped ``stamp_s``; their ``time`` field,
    relative to ``decoded_stamp_s`` (the decoder's stamp), is made relative to ``stamp_s``."""
    if decoded_stamp_s != stamp_s:
        points[TIME_FIELD] += np.float32(decoded_stamp_s - stamp_s)
    sec = int(np.floor(stamp_s))
    nanosec = min(int(round((stamp_s - sec) * 1e9)), 999_999_999)
    return make_cloud(Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id), points)


class ScanDecoder:
    """VelodyneScan messages (as rosbags decodes them) -> PointCloud2, one per scan; ``name``
    (the input) is said in errors."""

    def __init__(self, name: str):
        self._vd = _velodyne_decoder()
        # the stamp of a rotation = its first packet's, as a driver's scan header
        self._decoder = self._vd.ScanDecoder(self._vd.Config(timestamp_first_packet=True))
        self.name = name

    def cloud(self, scan, index: int):
        """The PointCloud2 of scan message ``index``: its header, its points."""
        vd = self._vd
        packets = vd.PacketVector()
        for packet in scan.packets:
            packets.append(vd.VelodynePacket(stamp_seconds(packet.stamp),
                                             np.asarray(packet.data, dtype=np.uint8)))
        decoded_stamp, points = _decoded(self._decoder.decode, f'{self.name}: VelodyneScan '
                                         f'{index}', packets, True)
        return _cloud(points, stamp_seconds(scan.header.stamp), scan.header.frame_id,
                      decoded_stamp.host)


def _pcap_payloads(path: Path, dpkt) -> Iterator[tuple]:
    """(capture time s, UDP payload bytes) of every Velodyne data packet of a .pcap."""
    with open(path, 'rb') as f:
        try:
            reader = dpkt.pcap.Reader(f)
        except (ValueError, dpkt.UnpackError) as err:
            raise BagError(f'{path}: not a pcap capture ({one_line(err, 200)}; pcapng: '
                           'convert it with editcap -F pcap)') from None
        records = iter(reader)
        while True:
            try:
                item = next(records, None)
            except dpkt.UnpackError:  # a record header cut short
                raise BagError(f'{path}: truncated pcap (its last record is cut short)') from None
            if item is None:
                return
            udp = _udp_of(item[1], dpkt)
            if udp is None:
                continue
            if len(udp.data) < udp.ulen - 8:
                raise BagError(f'{path}: truncated pcap (a {udp.ulen - 8}-byte UDP payload '
                               f'holds {len(udp.data)} bytes)')
            if len(udp.data) == DATA_PACKET_BYTES:
                yield float(item[0]), bytes(udp.data)


def _udp_of(frame: bytes, dpkt):
    """The UDP datagram of an Ethernet frame, or None for anything else."""
    try:
        ip = dpkt.ethernet.Ethernet(frame).data
    except dpkt.UnpackError:
        return None
    udp = getattr(ip, 'data', None)
    return udp if isinstance(udp, dpkt.udp.UDP) else None


def pcap_clouds(path: Path, frame_id: str) -> Iterator[tuple]:
    """(stamp ns, PointCloud2) of every rotation of a Velodyne .pcap (module docstring)."""
    vd, dpkt = _velodyne_decoder(), _dpkt()
    decoder = vd.StreamDecoder(vd.Config(cut_angle=PCAP_CUT_ANGLE_DEG,
                                         timestamp_first_packet=True))
    packets = 0
    for stamp, payload in _pcap_payloads(path, dpkt):
        packets += 1
        result = _decoded(decoder.decode, f'{path}: packet {packets}', stamp, payload, True)
        if result is not None:
            yield _pcap_frame(result, frame_id)
    if packets == 0:
        raise BagError(f'{path}: no Velodyne data packet (a {DATA_PACKET_BYTES}-byte UDP '
                       'payload) in the capture')
    result = _decoded(decoder.finish, f'{path}: its last rotation', True)
    if result is not None:
        yield _pcap_frame(result, frame_id)


def _pcap_frame(result, frame_id: str) -> tuple:
    stamp, points = result
    cloud = _cloud(points, stamp.host, frame_id, stamp.host)
    return cloud.header.stamp.sec * 1_000_000_000 + cloud.header.stamp.nanosec, cloud


def cloud_topic(packet_topic: str) -> str:
    """The topic a driver publishes the clouds of ``packet_topic`` on: '.../velodyne_packets'
    -> '.../velodyne_points', else '<packet_topic>/points'."""
    head, _, last = packet_topic.rpartition('/')
    if last.endswith('packets'):
        return f'{head}/{last[:-len("packets")]}points'
    return f'{packet_topic}/points'
