# SPDX-License-Identifier: Apache-2.0
"""Offline bag replay: read PointCloud2 frames from a bag (or point files), segment them with the
node's own pipeline, and write a ROS 2 bag with ``<topic>/ground``, ``<topic>/obstacles``,
``<topic>/ground_surface`` (when ``publish_ground_surface`` is on, the default),
``<topic>/labeled`` (when asked for) and ``/diagnostics``.

Reading and writing use ``rosbags`` (AnyReader: ROS 2 mcap/sqlite3 directories or bare
``.mcap``/``.db3`` files, ROS 1 ``.bag``; rosbag2 Writer), but messages are (de)serialised with
``rclpy.serialization`` so the replay runs exactly the message classes and the code path of the
node (``pipeline.process_cloud``), with the parameters of the node's YAML file
(``config.load_params_file``). ROS 1 messages are decoded by rosbags and copied into the rclpy
class. Raw Velodyne data, a bag of ``velodyne_msgs/VelodyneScan`` or a ``.pcap`` capture, is
decoded into clouds by ``packets.py`` (velodyne-decoder, an optional extra), and an IMU topic of
the bag can level each cloud (``--imu-topic``, ``bag_imu.py``).

An output bag is written into a hidden temporary sibling directory and renamed into place only
after the writer closed cleanly, so an interrupted or failed replay never leaves a bag that looks
complete. Every expected failure is raised as :class:`BagError` with a one-line message.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ..core import compiled, stages
from ..core.params import SegmenterParams
from ..core.segmenter import GroundSegmenter
from ..ros import pipeline
from ..ros.cloud import CloudFormatError, make_cloud, set_data
from ..ros.config import load_params_file, node_param_defaults
from ..ros.diagnostics import ProcessingWindow, diagnostics_array, diagnostics_status
from .bag_imu import BagGravity
from .errors import BagError, one_line
from .io import PointFileError, read_points_file
from .packets import VELODYNE_SCAN, ScanDecoder, cloud_topic, packet_typestore, pcap_clouds

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
DEFAULT_TOPIC = '/velodyne_points'
DIAGNOSTICS_TOPIC = '/diagnostics'
POINT_FILE_SUFFIXES = ('.bin', '.pcd')
PCAP_SUFFIX = '.pcap'  # a Velodyne packet capture (tools/packets.py)
SYNTHETIC_PERIOD_NS = 100_000_000  # point files get stamps i * 0.1 s (a 10 Hz spinning LiDAR)
SYNTHETIC_FRAME_ID = 'velodyne'


def _one_line(err: BaseException) -> str:
    """A reader's error in one line, short enough to sit inside a sentence naming the bag."""
    return one_line(err, limit=300)


def _reader_errors() -> tuple:
    """Exceptions that mean 'this bag is unreadable'.

    rosbags raises its own errors for bad metadata and magic numbers, but a truncated or
    corrupted storage file surfaces from deeper down as struct, EOF, index, unicode, sqlite3 or
    zstd/lz4 errors. Reading a bag has no other failure mode worth a traceback, so everything
    derived from Exception raised *by the reader* is reported as a corrupt bag (our own code is
    never inside these try blocks).
    """
    return (Exception,)


# ---------------------------------------------------------------------------------------------
# Input
# ---------------------------------------------------------------------------------------------

@dataclass
class InputFrame:
    """One input cloud: its position, bag receive time (ns) and the rclpy PointCloud2."""

    index: int
    timestamp_ns: int
    msg: object


def _about(path, err: BaseException) -> str:
    """One line on ``err`` that names ``path`` once (io's errors already start with it)."""
    text = _one_line(err)
    return text if str(path) in text else f'{path}: {text}'


# A fully qualified ROS 2 topic name: '/'-separated tokens of letters, digits and '_' that do
# not start with a digit (rcl's rules without the '~' and '{}' substitutions, which a bag's
# topics never hold)
_TOPIC_NAME = re.compile(r'(/[A-Za-z_][A-Za-z0-9_]*)+')


def normalize_topic(topic: Optional[str], what: str = 'topic',
                    strict: bool = False) -> Optional[str]:
    """Bag topics are absolute: 'velodyne_points' means '/velodyne_points' (a trailing '/' is
    dropped). ``strict``: BagError (one line) for a name that is not a valid ROS 2 topic name,
    for names that rclpy will use (``what`` names the option); reading a bag only matches the
    name against its topics, and ROS 1 bags may hold names such as '/lidar/0/points'."""
    if topic is None:
        return None
    topic = topic.strip().rstrip('/')
    if not topic:
        raise BagError(f'empty {what} name')
    topic = topic if topic.startswith('/') else '/' + topic
    if strict and not _TOPIC_NAME.fullmatch(topic):
        raise BagError(f'{what} {topic!r} is not a valid ROS 2 topic name (tokens of letters, '
                       "digits and '_' separated by single '/', none starting with a digit)")
    return topic


def is_point_file(path: Path) -> bool:
    return path.suffix.lower() in POINT_FILE_SUFFIXES


def _expand_inputs(inputs: Sequence) -> tuple[str, list[Path]]:
    """Classify the inputs: ('bag', [path]) or ('files', [sorted point files])."""
    paths = [Path(p) for p in inputs]
    if not paths:
        raise BagError('no input given')
    for p in paths:
        if not p.exists():
            raise BagError(f'{p}: no such file or directory')
    if any(p.suffix.lower() == PCAP_SUFFIX for p in paths):
        if len(paths) > 1 or not paths[0].is_file():
            raise BagError('give one .pcap file alone (one capture per run)')
        return 'pcap', paths
    if len(paths) == 1 and paths[0].is_dir() and not (paths[0] / 'metadata.yaml').exists():
        files = sorted(f for f in paths[0].iterdir() if f.is_file() and is_point_file(f))
        if not files:
            raise BagError(f'{paths[0]}: neither a rosbag2 directory (no metadata.yaml) nor a '
                           f'directory of .bin/.pcd files')
        return 'files', files
    if all(p.is_file() and is_point_file(p) for p in paths):
        return 'files', paths
    if any(is_point_file(p) for p in paths):
        raise BagError('give either one bag or point files (.bin/.pcd), not a mix')
    if len(paths) > 1 and not all(p.suffix == '.bag' for p in paths):
        raise BagError('give one ROS 2 bag (several inputs are only allowed for ROS 1 .bag files)')
    return 'bag', paths


def _pointfile_cloud(path: Path, index: int, frame_id: str = SYNTHETIC_FRAME_ID):
    """A PointCloud2 from a KITTI .bin or a .pcd, stamped i * 0.1 s (from 0, i.e. 1970: point
    files have no time), with ``frame_id``."""
    points = read_points_file(path)
    points = np.asarray(points)
    if points.dtype.names is None:
        # (N, 4) KITTI x, y, z, intensity or (N, 3) x, y, z -> named float32 fields
        if points.ndim != 2 or points.shape[1] not in (3, 4):
            raise BagError(f'{path}: expected (N, 3|4) points, got shape {points.shape}')
        names = ['x', 'y', 'z', 'intensity'][:points.shape[1]]
        points = np.ascontiguousarray(points, dtype='<f4').view(
            np.dtype([(n, '<f4') for n in names])).reshape(-1)
    stamp_ns = index * SYNTHETIC_PERIOD_NS
    header = Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
                    frame_id=frame_id)
    return make_cloud(header, points), stamp_ns


class FrameSource:
    """Iterate the PointCloud2 frames of a bag topic (clouds, or Velodyne packets decoded scan
    by scan), of a Velodyne .pcap (decoded rotation by rotation) or of a list of point files.

    Use as a context manager. ``count`` is known before iterating (for the progress bar; a pcap
    is decoded once to count its rotations). Opening checks the topic exists, carries
    PointCloud2 or VelodyneScan and has messages, and decodes a packet bag's first scan;
    problems raise BagError. ``cloud_topic``: the topic of the clouds it yields.
    """

    def __init__(self, inputs: Sequence, topic: Optional[str] = None,
                 max_frames: Optional[int] = None, frame_id: str = SYNTHETIC_FRAME_ID):
        self.kind, self.paths = _expand_inputs(inputs)
        topic = normalize_topic(topic)
        self.frame_id = frame_id  # header.frame_id of clouds made from point files
        self.requested_topic = topic
        self.topic = topic or DEFAULT_TOPIC
        self.max_frames = max_frames
        self.count = 0
        self.note = ''  # a remark for the user (e.g. the topic was picked automatically)
        self._reader = None
        self._connections = []
        self._scan_decoder = None  # packets.ScanDecoder for a VelodyneScan topic

    @property
    def description(self) -> str:
        if self.kind == 'pcap':
            return f'Velodyne capture {self.paths[0]}'
        if self.kind == 'files':
            return f'{len(self.paths)} point file(s) starting with {self.paths[0]}'
        return ', '.join(str(p) for p in self.paths)

    def __enter__(self) -> 'FrameSource':
        if self.kind == 'files':
            self.count = len(self.paths)
        elif self.kind == 'pcap':
            # decoded once to count its rotations (velodyne-decoder cuts them): a truncated or
            # undecodable capture fails here, before anything is written or published
            self.count = sum(1 for _ in pcap_clouds(self.paths[0], self.frame_id))
        else:
            try:
                self._open_bag()
            except BaseException:  # e.g. the topic is not in the bag: __exit__ will not run
                self.close()
                raise
        if self.max_frames is not None:
            self.count = min(self.count, self.max_frames)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._reader is not None:
            reader, self._reader = self._reader, None
            try:
                reader.close()
            except Exception:  # closing a broken reader must not hide the real error
                pass

    def _open_bag(self) -> None:
        name = self.description
        try:
            # Older rosbag2 bags (metadata < 8) carry no message definitions: use Jazzy's
            # types, and the Velodyne driver's, which rosbags does not have
            reader = AnyReader(self.paths, default_typestore=packet_typestore())
            reader.open()
        except _reader_errors() as err:
            raise BagError(f'cannot read bag {name} (corrupt, truncated or not a bag): '
                           f'{_one_line(err)}') from None
        self._reader = reader
        topics = {}
        for c in reader.connections:
            topics.setdefault(c.topic, set()).add(c.msgtype)
        if not topics:
            raise BagError(f'bag {name} is empty: it has no topics')
        self._pick_topic(topics, name)
        if topics[self.topic] == {VELODYNE_SCAN}:  # raw packets: decoded scan by scan
            self._scan_decoder = ScanDecoder(f'bag {name}')
            self._check_first_scan(name)
        self._connections = [c for c in reader.connections if c.topic == self.topic]
        self.count = sum(c.msgcount for c in self._connections)
        if self.count == 0:
            raise BagError(f'topic {self.topic} in bag {name} has no messages')

    def _check_first_scan(self, name: str) -> None:
        """Decode the topic's first VelodyneScan (with a decoder of its own), so that packets
        velodyne-decoder cannot read (another model) fail before anything is written."""
        reader = self._reader
        conns = [c for c in reader.connections if c.topic == self.topic]
        try:
            first = next(iter(reader.messages(connections=conns)), None)
            scan = None if first is None else reader.deserialize(first[2], first[0].msgtype)
        except _reader_errors() as err:
            raise BagError(f'bag {name} is corrupt or truncated (message 0 on {self.topic}): '
                           f'{_one_line(err)}') from None
        if scan is not None:
            ScanDecoder(f'bag {name}').cloud(scan, 0)

    def _pick_topic(self, topics: dict, name: str) -> None:
        """Check ``self.topic`` (``{topic: message types}`` of the bag ``name``); without
        --topic and without DEFAULT_TOPIC, take the bag's one PointCloud2 topic, else its one
        VelodyneScan topic."""
        listing = ', '.join(f'{t} [{"|".join(sorted(m))}]' for t, m in sorted(topics.items()))
        if self.topic not in topics:
            clouds = [t for t, m in topics.items() if m == {POINTCLOUD2}]
            scans = [t for t, m in topics.items() if m == {VELODYNE_SCAN}]
            found = clouds if clouds else scans
            if self.requested_topic is None and len(found) == 1:
                what = '' if clouds else ' (Velodyne packets, one frame per scan)'
                self.note = f'topic {DEFAULT_TOPIC} not in the bag; using {found[0]}{what}'
                self.topic = found[0]
            else:
                hint = '' if found else (
                    f'; none is {POINTCLOUD2} or {VELODYNE_SCAN}: other raw sensor packets must '
                    f'be decoded to point clouds first (ouster-ros, Nebula)')
                raise BagError(f'topic {self.topic} not in bag {name}; its topics: {listing}'
                               f'{hint}')
        types = topics[self.topic]
        if types not in ({POINTCLOUD2}, {VELODYNE_SCAN}):
            raise BagError(f'topic {self.topic} carries {"|".join(sorted(types))}, not '
                           f'{POINTCLOUD2} (or Velodyne packets, {VELODYNE_SCAN}); the '
                           f'segmenter needs point clouds (decode other raw packets with the '
                           f'sensor\'s driver first); its topics: {listing}')

    @property
    def cloud_topic(self) -> str:
        """The topic of the clouds this source yields: the input topic, or for Velodyne packets
        the driver's cloud topic (packets.cloud_topic); a .pcap's are DEFAULT_TOPIC's."""
        if self.kind == 'pcap':
            return DEFAULT_TOPIC
        return cloud_topic(self.topic) if self._scan_decoder is not None else self.topic

    def __iter__(self) -> Iterator[InputFrame]:
        if self.kind == 'files':
            yield from self._iter_files()
        elif self.kind == 'pcap':
            yield from self._iter_pcap()
        else:
            yield from self._iter_bag()

    def _iter_pcap(self) -> Iterator[InputFrame]:
        for i, (stamp_ns, msg) in enumerate(pcap_clouds(self.paths[0], self.frame_id)):
            if i >= self.count:
                return
            yield InputFrame(i, stamp_ns, msg)

    def _iter_files(self) -> Iterator[InputFrame]:
        for i, path in enumerate(self.paths[:self.count]):
            try:
                msg, stamp = _pointfile_cloud(path, i, self.frame_id)
            except (PointFileError, OSError, ValueError) as err:
                raise BagError(_about(path, err)) from None
            yield InputFrame(i, stamp, msg)

    def _iter_bag(self) -> Iterator[InputFrame]:
        reader = self._reader
        errors = _reader_errors()
        it = reader.messages(connections=self._connections)
        i = 0
        while i < self.count:
            try:
                item = next(it, None)
                if item is None:
                    break
                connection, timestamp, raw = item
                if self._scan_decoder is not None:  # rosbags decodes the packets' message
                    msg = self._scan_decoder.cloud(
                        reader.deserialize(raw, connection.msgtype), i)
                elif reader.is2:
                    msg = deserialize_message(bytes(raw), PointCloud2)
                else:  # ROS 1 serialisation: rosbags decodes it, we copy into the rclpy class
                    msg = _ros1_to_rclpy_cloud(reader.deserialize(raw, connection.msgtype))
            except BagError:  # a scan velodyne-decoder cannot read: said by the decoder
                raise
            except errors as err:
                raise BagError(f'bag {self.description} is corrupt or truncated (message {i} on '
                               f'{self.topic}): {_one_line(err)}') from None
            yield InputFrame(i, int(timestamp), msg)
            i += 1
        if i < self.count:
            raise BagError(f'bag {self.description} lists {self.count} message(s) on '
                           f'{self.topic} but only {i} could be read (truncated?)')


def _ros1_to_rclpy_cloud(m):
    """rclpy PointCloud2 from a rosbags-decoded ROS 1 PointCloud2 (header.seq is dropped)."""
    out = PointCloud2()
    stamp = Time(sec=int(m.header.stamp.sec), nanosec=int(m.header.stamp.nanosec))
    out.header = Header(stamp=stamp, frame_id=m.header.frame_id)
    out.height, out.width = int(m.height), int(m.width)
    out.fields = [PointField(name=f.name, offset=int(f.offset), datatype=int(f.datatype),
                             count=int(f.count)) for f in m.fields]
    out.is_bigendian = bool(m.is_bigendian)
    out.point_step, out.row_step = int(m.point_step), int(m.row_step)
    set_data(out, np.ascontiguousarray(m.data, dtype=np.uint8))  # one copy of the bytes
    out.is_dense = bool(m.is_dense)
    return out


def read_frame(spec: str, topic: Optional[str] = None):
    """Load one frame for plotting/eval: ``FILE.bin``, ``FILE.pcd`` or ``BAG:INDEX``.

    Returns ``(msg, description)`` with an rclpy PointCloud2.
    """
    path, index = Path(spec), None
    if not path.exists() and ':' in spec:
        head, tail = spec.rsplit(':', 1)
        if tail.isdigit():
            path, index = Path(head), int(tail)
    if not path.exists():
        raise BagError(f'{path}: no such file or directory')
    if path.is_file() and is_point_file(path):
        try:
            msg, _ = _pointfile_cloud(path, 0)
        except (PointFileError, OSError) as err:
            raise BagError(_about(path, err)) from None
        return msg, str(path)
    index = 0 if index is None else index
    with FrameSource([path], topic) as source:
        if index >= source.count:
            raise BagError(f'{path} has {source.count} frame(s) on {source.topic}; index {index} '
                           f'is out of range')
        for frame in source:
            if frame.index == index:
                topic = f' ({source.topic})' if source.kind == 'bag' else ''
                return frame.msg, f'{path}:{index}{topic}'
    raise BagError(f'frame {index} could not be read from {path}')  # pragma: no cover


# ---------------------------------------------------------------------------------------------
# Statistics, progress, summary
# ---------------------------------------------------------------------------------------------

@dataclass
class ReplaySummary:
    """Totals and per-stage timing of a replay."""

    frames: int = 0
    skipped: int = 0
    skipped_reasons: list = field(default_factory=list)
    points: int = 0
    valid: int = 0
    ground: int = 0
    obstacles: int = 0
    invalid: int = 0
    stage_ms: dict = field(default_factory=dict)  # stage -> list of per-frame ms
    thetas: list = field(default_factory=list)  # Hyperparameters per frame
    wall_s: float = 0.0
    output: str = ''
    topic: str = ''
    note: str = ''
    # s of warm_up_before_timing: numba's kernels compiled or loaded before the first frame,
    # so that no frame's timing holds a compilation
    warm_up_s: float = float('nan')
    imu: Optional[dict] = None  # bag_imu.BagGravity.summary() with --imu-topic

    def add_stage(self, name: str, ms: float) -> None:
        self.stage_ms.setdefault(name, []).append(float(ms))

    def add_frame(self, out, points: int) -> None:
        """Count one segmented frame (a pipeline.FrameOutput of ``points`` input points)."""
        res = out.result
        n_valid = int(np.count_nonzero(res.valid_mask))
        n_ground = int(np.count_nonzero(res.ground_mask))
        self.frames += 1
        self.points += points
        self.valid += n_valid
        self.ground += n_ground
        self.obstacles += n_valid - n_ground
        self.invalid += res.num_invalid
        self.thetas.append(tuple(float(v) for v in res.hyperparameters))
        for k, v in pipeline.frame_timings(out).items():  # the node's diagnostics' stage names
            self.add_stage(k, v)

    def table(self) -> str:
        """The closing summary as a fixed-width text table."""
        share = self.ground / self.valid if self.valid else float('nan')
        fps = self.frames / self.wall_s if self.wall_s > 0 else float('nan')
        lines = [f'replay summary: {self.output}',
                 f'  frames        {self.frames} processed, {self.skipped} skipped'
                 f'  ({fps:.1f} frames/s wall)',
                 f'  points        {self.points} in, {self.valid} valid, {self.invalid} invalid',
                 f'  ground share  {share:.3f} of valid points ({self.ground} ground, '
                 f'{self.obstacles} obstacles)']
        lines += self._imu_lines()
        if math.isfinite(self.warm_up_s):
            lines.append(f'  warm-up       {self.warm_up_s:.1f} s before the first frame (numba '
                         'kernels compiled, or loaded from its cache; not in the timings below)')
        if self.thetas:
            th = np.array(self.thetas, dtype=float)
            names = ('sigma_f [m]', 'gain a', 'sigma_n [m]')
            rng = ', '.join(f'{n} {th[:, k].min():.4g}..{th[:, k].max():.4g}'
                            for k, n in enumerate(names))
            lines.append(f'  theta range   {rng}')
        if self.stage_ms:
            lines.append(f'  {"stage":<14}{"p50 ms":>9}{"p95 ms":>9}{"max ms":>9}'
                         '   (segment = core total; surface, labeled = parts of encode; total = '
                         'decode+segment+encode; frame = total+write)')
            order = ('decode', 'grid', 'lines', 'gp_fit', 'predict', 'label', 'structure',
                     'segment', 'encode', 'surface', 'labeled', 'total', 'write', 'frame')
            names = sorted(self.stage_ms, key=lambda k: (order.index(k) if k in order
                                                         else len(order), k))
            for name in names:
                values = self.stage_ms[name]
                v = np.asarray(values)
                lines.append(f'  {name:<14}{np.percentile(v, 50):9.2f}'
                             f'{np.percentile(v, 95):9.2f}{v.max():9.2f}')
        for reason in self.skipped_reasons[:5]:
            lines.append(f'  skipped: {reason}')
        return '\n'.join(lines)

    def _imu_lines(self) -> list:
        """The --imu-topic lines: frames levelled by the IMU, frames with the static pose."""
        if self.imu is None:
            return []
        imu = self.imu
        lines = [f"  imu           {imu['topic']} ({imu['samples']} samples): {imu['levelled']} "
                 f"frame(s) levelled by it, {imu['static']} with the static pose (no sample "
                 f"within imu_max_age_s {imu['max_age_s']:g} s of their stamp)"]
        lines += [f'  static pose:  frame {index}: {note}' for index, note in imu['notes']]
        return lines


class Progress:
    """A one-line progress bar on stderr (frames, fps, ETA); silent unless stderr is a TTY."""

    def __init__(self, total: int, stream=None, enabled: Optional[bool] = None, width: int = 28):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = (self.stream.isatty() if enabled is None else enabled)
        self.total, self.width, self.t0, self.done = total, width, time.perf_counter(), 0

    def update(self, done: int) -> None:
        self.done = done
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.t0
        fps = done / elapsed if elapsed > 0 else 0.0
        frac = done / self.total if self.total else 1.0
        fill = int(round(frac * self.width))
        eta = (self.total - done) / fps if fps > 0 else float('nan')
        eta_txt = f'{int(eta // 60)}:{int(eta % 60):02d}' if math.isfinite(eta) else '?'
        self.stream.write(f'\r[{"#" * fill}{"." * (self.width - fill)}] {done}/{self.total} '
                          f'frames  {fps:5.1f} fps  ETA {eta_txt} ')
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write('\n')
            self.stream.flush()


# ---------------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------------

def load_params(params_file: Optional[str]):
    """(SegmenterParams, node params dict) from the node's YAML with the node's own loader
    (``config.load_params_file``), or the defaults when no file is given."""
    if params_file is None:
        return SegmenterParams(), node_param_defaults()
    path = Path(params_file)
    if path.is_dir():
        raise BagError(f'{path} is a directory; give the parameter file (e.g. '
                       'config/params.yaml)')
    if not path.is_file():
        raise BagError(f'{path}: parameter file not found')
    return load_params_file(str(path))


def load_segmenter_params(params_file: Optional[str]):
    """SegmenterParams from the node's YAML (same loader as the node), or the defaults."""
    return load_params(params_file)[0]


def warm_up(log=None, segmenter=None) -> None:
    """Load the compiled kernels before the first frame, as the node's worker does, so the
    first frame's timing (and its diagnostics) is not that of numba's compile/cache load: the
    GP step with its posterior std (replay publishes the ground surface, whose z_std reads
    it), then ``segmenter.warm_up()`` (every compiled stage a frame needs) when a segmenter is
    given, then the output clouds' compiled pass (``pipeline.warm_up``)."""
    try:
        stages.compile_round_off(background_too=True)
        if segmenter is not None:
            segmenter.warm_up()
    except Exception as exc:  # noqa: BLE001 - the numpy path still works
        if log:
            log(f'compiled GP kernel unavailable ({_one_line(exc)}); the first frame loads it')
    try:
        pipeline.warm_up()
    except Exception as exc:  # noqa: BLE001 - its numpy twin builds the same clouds
        if log:
            log(f'output clouds pass unavailable ({_one_line(exc)}); using numpy')


COMPILE_WAIT_S = 300.0  # longest wait for numba's background compilations (~20 s on 2 cores)


def warm_up_before_timing(log=None, segmenter=None) -> float:
    """:func:`warm_up`, then wait (at most COMPILE_WAIT_S) for the background compilations it
    queued (core/compiled.py), so that no frame of an offline run times numba compiling (the
    node does not wait: its first frames take the numpy path meanwhile); the seconds it took.
    Without a cache (a new install) that is ~20 s on 2 cores, else ~1 s."""
    start = time.perf_counter()
    warm_up(log, segmenter)
    if not compiled.wait(COMPILE_WAIT_S) and log:
        log(f'numba still compiling after {COMPILE_WAIT_S:g} s: the first frames\' timings '
            'include the numpy fallback')
    return time.perf_counter() - start


def _storage_plugin(storage: str):
    plugins = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
    if storage not in plugins:
        raise BagError(f'unknown storage {storage!r}; choose mcap or sqlite3')
    return plugins[storage]


def _partial_dir(out: Path) -> Path:
    return out.parent / f'.{out.name}.partial-{os.getpid()}'


def _check_output(out: Path, force: bool, inputs: list[Path]) -> None:
    resolved = out.resolve()
    for p in inputs:
        rp = p.resolve()
        if rp == resolved or resolved in rp.parents:
            raise BagError(f'output {out} would overwrite the input {p}')
        if rp.is_dir() and rp in resolved.parents:  # a bag written into the input bag
            raise BagError(f'output {out} lies inside the input {p}; write it elsewhere')
    if out.exists() or out.is_symlink():
        if not force:
            raise BagError(f'{out} exists; pass --force to overwrite it')
        if not out.is_dir():
            raise BagError(f'{out} exists and is not a directory; remove it by hand')
        if any(out.iterdir()) and not (out / 'metadata.yaml').is_file():
            # --force replaces a bag, never an arbitrary directory (think of '~' or '.')
            raise BagError(f'{out} is not a rosbag2 directory (no metadata.yaml); refusing to '
                           f'overwrite it even with --force')


def _move_into_place(tmp: Path, out: Path) -> None:
    """Replace ``out`` by the finished ``tmp``; the old output goes only once the new one is in."""
    # rosbag2 names the storage file after its directory: rename it to the final name first
    meta = tmp / 'metadata.yaml'
    text = meta.read_text()
    for f in sorted(tmp.iterdir()):
        if f.name.startswith(tmp.name):
            new = f.with_name(out.name + f.name[len(tmp.name):])
            os.rename(f, new)
            text = text.replace(f.name, new.name)
    meta.write_text(text)
    trash = None
    if out.exists():
        trash = out.parent / f'.{out.name}.old-{os.getpid()}'
        os.rename(out, trash)
    os.rename(tmp, out)
    if trash is not None:
        shutil.rmtree(trash, ignore_errors=True)


def replay(inputs: Sequence, out_bag, *, topic: Optional[str] = None,
           params_file: Optional[str] = None, storage: str = 'mcap', force: bool = False,
           max_frames: Optional[int] = None, progress: Optional[Progress] = None,
           log=None, output_prefix: Optional[str] = None,
           frame_id: str = SYNTHETIC_FRAME_ID, labeled: bool = False,
           imu_topic: Optional[str] = None) -> ReplaySummary:
    """Segment every PointCloud2 of ``inputs`` on ``topic`` and write the result bag ``out_bag``.

    ``inputs``: one bag (directory, .mcap, .db3, or ROS 1 .bag files) or point files / a directory
    of them (``frame_id`` is their header.frame_id). Output topics:
    ``<output_prefix>/ground``, ``<output_prefix>/obstacles`` (input header and all fields
    kept, points byte for byte, plus a ``height_above_ground`` field when the parameter file's
    ``add_height_above_ground_field`` is true), ``<output_prefix>/ground_surface`` (the GP ground
    surface, unless ``publish_ground_surface`` is false), ``<output_prefix>/labeled`` with
    ``labeled`` (the node's ``labeled`` topic: every valid point's bytes plus ``ground`` and
    ``height_above_ground``, in input order; ``labels.labeled_points``) and ``/diagnostics`` (one
    DiagnosticArray per frame), each written at the input message's bag time.
    ``output_prefix`` defaults to the input topic, so the outputs sit beside their input in a
    bag that may hold several clouds; ``''`` gives ``/ground``, ``/obstacles`` and
    ``/ground_surface``, the node's names in the root namespace. ``imu_topic``: a
    sensor_msgs/Imu topic of the bag that levels each cloud as the node's ``imu_topic`` does
    (``bag_imu.py``; frames without a sample near their stamp keep the static pose, are
    counted in the summary and WARN in /diagnostics). A frame the pipeline rejects (malformed
    cloud) is skipped, counted and reported with an ERROR diagnostics entry, as the node does.
    Raises BagError.
    """
    out = Path(out_bag)
    plugin = _storage_plugin(storage)
    if max_frames is not None and max_frames < 1:
        raise BagError('--max-frames must be at least 1')
    run = _ReplayRun.start(params_file, labeled, ReplaySummary(output=str(out)), log)
    t_start = time.perf_counter()
    output_prefix = _output_prefix(output_prefix)
    with FrameSource(inputs, topic, max_frames, frame_id) as source:
        _check_output(out, force, source.paths)
        run.summary.topic, run.summary.note = source.topic, source.note
        if log and source.note:
            log(source.note)
        run.gravity = _bag_gravity(source, imu_topic, run.node_params)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = _partial_dir(out)
        if tmp.exists():
            shutil.rmtree(tmp)
        progress = progress or Progress(source.count)
        try:
            with Writer(tmp, version=9, storage_plugin=plugin) as writer:
                run.writer = writer
                run.conns = _output_connections(
                    writer, source.cloud_topic if output_prefix is None else output_prefix,
                    run.outputs)
                for frame in source:
                    _replay_frame(frame, run)
                    progress.update(frame.index + 1)
            run.finish()
            _move_into_place(tmp, out)
        except WriterError as err:
            raise BagError(f'cannot write {out}: {_one_line(err)}') from None
        finally:
            progress.close()
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    run.summary.wall_s = time.perf_counter() - t_start
    return run.summary


@dataclass
class _ReplayRun:
    """What the frames of one replay share: the segmenter and its static parameters, the node's
    parameters, output switches and diagnostics window, the writer and its connections, the
    IMU (with --imu-topic) and the summary."""

    segmenter: GroundSegmenter
    static: SegmenterParams
    node_params: dict
    outputs: dict  # process_cloud keywords
    window: ProcessingWindow
    summary: ReplaySummary
    gravity: object = None  # bag_imu.BagGravity with --imu-topic
    writer: object = None
    conns: tuple = ()

    @classmethod
    def start(cls, params_file, labeled: bool, summary: ReplaySummary, log) -> '_ReplayRun':
        """The run's parameters and a warmed-up segmenter (its time in the summary)."""
        seg_params, node_params = load_params(params_file)
        segmenter = GroundSegmenter(seg_params)
        summary.warm_up_s = warm_up_before_timing(log, segmenter)
        outputs = {name: bool(node_params[name]) for name in pipeline.OUTPUT_SWITCHES}
        outputs['labeled'] = labeled  # no node parameter: the node builds it for subscribers
        window = ProcessingWindow(int(node_params.get('diagnostics_window', 50)))
        return cls(segmenter, seg_params, node_params, outputs, window, summary)

    @property
    def budget_ms(self) -> float:
        return float(self.node_params.get('processing_budget_ms', 100.0))

    def level(self, msg, index: int):
        """With an IMU: the segmenter gets frame ``index``'s roll and pitch (as the node's
        ``_level_with_imu``); the note when the static pose is used, else None."""
        if self.gravity is None:
            return None
        note = None
        try:
            pose, params = self.gravity.frame_pose(self.static, msg.header.stamp, index)
            note = pose.note
        except ValueError as exc:  # e.g. a pose outside the parameters' range: never the frame
            params, note = self.static, f'IMU pose failed ({_one_line(exc)}): the static pose'
        if params != self.segmenter.params:
            self.segmenter.set_params(params)
        return note

    def finish(self) -> None:
        """BagError when no frame could be segmented; the IMU's counts into the summary."""
        summary = self.summary
        if summary.frames == 0:
            raise BagError(f'none of the {summary.skipped} frame(s) could be segmented: '
                           f'{summary.skipped_reasons[0] if summary.skipped_reasons else ""}')
        if self.gravity is not None:
            summary.imu = self.gravity.summary()


def _bag_gravity(source: 'FrameSource', imu_topic: Optional[str], node_params: dict):
    """The bag_imu.BagGravity of ``imu_topic`` in the source's bag, or None without one."""
    if imu_topic is None:
        return None
    if source.kind != 'bag':
        raise BagError('--imu-topic needs a bag input: point files and pcap captures carry no IMU')
    return BagGravity(source.paths, normalize_topic(imu_topic, '--imu-topic'), node_params)


def _output_prefix(output_prefix: Optional[str]) -> Optional[str]:
    """``--output-prefix`` as a topic prefix: None (the input topic), '' (the root: '' and '/'
    both mean it) or a valid absolute topic name."""
    if output_prefix is None:
        return None
    if not output_prefix.strip('/'):
        return ''
    return normalize_topic(output_prefix, '--output-prefix', strict=True)


# FrameOutput attribute -> output topic below the prefix, and the switch (a process_cloud
# keyword) that adds it; ground and obstacles are always written
CLOUD_OUTPUTS = (('ground', 'ground', None), ('obstacles', 'obstacles', None),
                 ('surface', 'ground_surface', 'publish_ground_surface'),
                 ('labeled', 'labeled', 'labeled'))


def _output_connections(writer, prefix: str, outputs: dict) -> tuple:
    """The writer's ({FrameOutput attribute: connection} of the clouds ``outputs`` (the
    process_cloud keywords) switch on, diagnostics connection)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    clouds = {attribute: writer.add_connection(f'{prefix}/{topic}', POINTCLOUD2,
                                               typestore=typestore)
              for attribute, topic, switch in CLOUD_OUTPUTS if switch is None or outputs[switch]}
    diagnostics = writer.add_connection(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, typestore=typestore)
    return clouds, diagnostics


def _replay_frame(frame, run: _ReplayRun) -> None:
    """Segment one frame (levelled by the IMU when there is one), write its clouds and a
    DiagnosticArray built like the node's."""
    clouds, conn_diag = run.conns
    msg, window, summary = frame.msg, run.window, run.summary
    frame_id = msg.header.frame_id
    t0 = time.perf_counter()
    bag_time_s = frame.timestamp_ns * 1e-9
    window.record_received(frame_id, now=bag_time_s)  # input rate in bag time, not wall time
    try:
        imu_note = run.level(msg, frame.index)
        out = pipeline.process_cloud(msg, run.segmenter, **run.outputs)
    except (CloudFormatError, ValueError, RuntimeError) as err:  # the node drops these too
        text = _one_line(err)
        window.record_failure(text, isinstance(err, ValueError), frame_id)
        summary.skipped += 1
        summary.skipped_reasons.append(f'frame {frame.index}: {text}')
        out = None
    t1 = time.perf_counter()
    if out is not None:
        window.record_frame(out, frame_id, list(out.warnings) + ([imu_note] if imu_note else []))
        for attribute, connection in clouds.items():
            cloud = getattr(out, attribute)
            if cloud is not None:  # no surface when the segmenter gave none
                run.writer.write(connection, frame.timestamp_ns, serialize_message(cloud))
    status = diagnostics_status(window, budget_ms=run.budget_ms, stale_after_s=None,
                                now=bag_time_s, extra={'source': 'gp-ground-seg replay',
                                                       'frame_index': frame.index})
    run.writer.write(conn_diag, frame.timestamp_ns,
                     serialize_message(diagnostics_array([status], stamp=msg.header.stamp)))
    t2 = time.perf_counter()
    if out is not None:
        summary.add_frame(out, int(msg.height) * int(msg.width))
        summary.add_stage('write', (t2 - t1) * 1e3)
        summary.add_stage('frame', (t2 - t0) * 1e3)


# ---------------------------------------------------------------------------------------------
# Sample bag shipped in data/
# ---------------------------------------------------------------------------------------------

def write_sample_bag(source_bag, out_dir, frames: int = 3, topic: str = DEFAULT_TOPIC) -> str:
    """Copy the first ``frames`` messages of ``topic`` unchanged (raw CDR bytes, same bag times)
    into a new zstd-compressed (mcap chunk compression) ROS 2 bag; return the .mcap's sha256."""
    out = Path(out_dir)
    if out.exists():
        raise BagError(f'{out} exists; remove it first')
    with AnyReader([Path(source_bag)]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise BagError(f'topic {topic} not in {source_bag}')
        writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            c = conns[0]
            conn = writer.add_connection(topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
            for i, (_, timestamp, raw) in enumerate(reader.messages(connections=conns)):
                if i >= frames:
                    break
                writer.write(conn, timestamp, bytes(raw))
    mcap = next(out.glob('*.mcap'))
    return hashlib.sha256(mcap.read_bytes()).hexdigest()
