# SPDX-License-Identifier: Apache-2.0
"""One frame through the segmenter: PointCloud2 -> numpy -> GroundSegmenter -> output PointCloud2s.

This is the single code path shared by the ROS node and the offline bag replay, so that both
publish exactly the same clouds and report the same timings. Nothing here needs ``rclpy.init()``.

Output clouds keep the input header (stamp, frame_id), fields, point_step and byte order, and
every selected point's bytes unchanged (``cloud.split_cloud``: ``cloud.subset_cloud`` of the
ground and obstacle masks, both built in one compiled pass), so intensity/ring/time survive.
Invalid points (NaN/Inf or the (0, 0, 0) no-return value) go to neither output; they are counted
in ``result.num_invalid``. Before returning, the split is checked (with the pass's counts):
ground + obstacles + invalid must equal the input point count with no point in both, otherwise
``RuntimeError`` is raised and nothing should be published (never a split that silently misses
points). :func:`warm_up` queues that pass's compilation; the node and bag replay call it after
the segmenter's warm-up.

The points are decoded as a read-only view on msg.data where the layout allows
(``cloud.cloud_xyz(copy=False)``): the result's ``point_z`` (and so ``height_above_ground``)
then reads the message's buffer, which it keeps alive; do not write into ``msg.data`` while
using the result.

Optional outputs (node parameters of the same names): ``publish_ground_surface`` adds the GP
ground surface (``surface_cloud``: x, y, z, z_std FLOAT32 at the supported prediction points,
input header); ``add_height_above_ground_field`` appends a FLOAT32 ``height_above_ground``
field (z - z_hat, m) to the ground and obstacle clouds after every original byte. The labelled
cloud (``labeled_cloud``: every valid point's bytes plus ``ground`` and
``height_above_ground``, in input order; ``labels.py``) has no parameter: ``labeled=True``
or :func:`add_labeled` builds it (the node does while its ``labeled`` topic has a subscriber).
"""

from __future__ import annotations

import time
import types
from dataclasses import dataclass, field

import numpy as np

from .cloud import (FLOAT32, UINT8, cloud_with_fields, cloud_xyz, float32_cloud, read_cloud,
                    split_cloud, with_float32_field)
from ..core.segmenter import SegmentationResult
from ..core.sensor_frame import cloud_notes
from ..labels import GROUND_FIELD, HEIGHT_FIELD, labeled_points

__all__ = ['FrameOutput', 'process_cloud', 'add_surface', 'add_labeled', 'input_warnings',
           'STAGES', 'frame_timings', 'surface_cloud', 'labeled_cloud', 'warm_up',
           'GROUND_FIELD', 'HEIGHT_FIELD', 'OUTPUT_SWITCHES', 'SURFACE_FIELDS']

# Node parameters (config.NODE_PARAMS) that switch the optional outputs: process_cloud keywords
OUTPUT_SWITCHES = ('publish_ground_surface', 'add_height_above_ground_field')
SURFACE_FIELDS = ('x', 'y', 'z', 'z_std')  # fields of the ground surface cloud (m)

# Stages reported in diagnostics, in pipeline order (segmenter stages from result.timings_ms).
STAGES = ('decode', 'grid', 'lines', 'gp_fit', 'predict', 'label', 'structure', 'encode',
          'total')


@dataclass
class FrameOutput:
    """Result of ``process_cloud`` for one input message."""

    ground: object  # sensor_msgs/PointCloud2 (same type as the input), ground points
    obstacles: object  # same, valid non-ground points
    result: SegmentationResult
    decode_ms: float  # PointCloud2 -> (N, 3) x, y, z in the cloud's precision (ms)
    encode_ms: float  # both subset clouds built, and the surface cloud when asked for (ms)
    # wall time of process_cloud (ms): decode + segment + encode + the input checks
    # (input_warnings, ~0.3 ms on 124k points); add_surface adds the surface cloud's time
    total_ms: float = float('nan')
    # One-line notes about a usable but suspicious input (empty, no valid point, trailing
    # bytes, not sensor-centred); the node reports them as a diagnostics WARN. Empty for a
    # normal frame.
    warnings: list = field(default_factory=list)
    surface: object = None  # PointCloud2 of the ground surface, when asked for
    # Part of encode_ms spent on the surface cloud (its deferred ground offset and z_std
    # included); NaN when no surface was built.
    surface_ms: float = float('nan')
    labeled: object = None  # PointCloud2 of the labelled valid points, when asked for
    labeled_ms: float = float('nan')  # part of encode_ms spent on it; NaN when not built

    @property
    def num_points(self) -> int:
        return int(self.result.valid_mask.size)


def frame_timings(out: FrameOutput) -> dict:
    """stage -> ms for one frame: decode/encode/total from the pipeline, the rest from the core.

    A core stage that the segmenter did not report is left out (not faked as 0).
    """
    timings = {'decode': out.decode_ms, 'encode': out.encode_ms, 'total': out.total_ms}
    for stage, ms in (('surface', out.surface_ms), ('labeled', out.labeled_ms)):
        if np.isfinite(ms):
            timings[stage] = ms
    for stage in STAGES:
        if stage not in timings and stage in out.result.timings_ms:
            timings[stage] = float(out.result.timings_ms[stage])
    if 'segment' not in timings and 'total' in out.result.timings_ms:
        timings['segment'] = float(out.result.timings_ms['total'])
    return timings


def surface_cloud(header, surface, msg_type=None):
    """PointCloud2 (x, y, z, z_std FLOAT32, ``header`` copied) of a GroundSurface's supported
    prediction points."""
    values = surface.points(supported_only=True)  # (K, 4) float32, C order: x, y, z, z_std
    return float32_cloud(header, values, SURFACE_FIELDS, msg_type)


def labeled_cloud(msg, result):
    """PointCloud2 of ``type(msg)``: one row per valid point of ``msg`` in input order, its bytes
    unchanged, then ``ground`` (UINT8, 1 = ground) and ``height_above_ground`` (FLOAT32, m) in
    the cloud's byte order (``labels.labeled_points``); ``msg``'s header. ``result``: the
    SegmentationResult of ``msg``'s points. is_dense is true: invalid points are left out."""
    rows = labeled_points(read_cloud(msg), result, '>' if msg.is_bigendian else '<')
    fields = rows.dtype.fields
    out = cloud_with_fields(msg, rows, [(GROUND_FIELD, fields[GROUND_FIELD][1], UINT8),
                                        (HEIGHT_FIELD, fields[HEIGHT_FIELD][1], FLOAT32)])
    out.is_dense = True
    return out


def process_cloud(msg, segmenter, *, publish_ground_surface: bool = False,
                  add_height_above_ground_field: bool = False,
                  labeled: bool = False) -> FrameOutput:
    """Split ``msg`` (sensor_msgs/PointCloud2) into ground and obstacle clouds with ``segmenter``;
    the keywords add the optional outputs of the module docstring.

    Raises ``cloud.CloudFormatError`` (a ValueError, one-line message) for an unusable layout
    (missing x/y/z, data too short, ...), and RuntimeError if the split is inconsistent.
    """
    t0 = time.perf_counter()
    points = read_cloud(msg)
    # float32 for float32 fields (same labels, less work), a view on msg.data where possible
    xyz = cloud_xyz(points, dtype=None, copy=False)
    t1 = time.perf_counter()
    result = segmenter.segment(xyz)
    t2 = time.perf_counter()
    n = xyz.shape[0]
    ground_mask = np.asarray(result.ground_mask, dtype=bool)
    valid_mask = np.asarray(result.valid_mask, dtype=bool)
    if ground_mask.shape != (n,) or valid_mask.shape != (n,):
        raise RuntimeError(f'segmenter returned masks of shape {ground_mask.shape}, '
                           f'expected ({n},)')
    # obstacles: result.obstacle_mask (valid & ~ground), so no point can be in both outputs;
    # the counts add up unless a ground point is invalid
    ground, obstacles, (n_ground, n_obstacles, n_invalid) = split_cloud(msg, ground_mask,
                                                                        valid_mask)
    if n_ground + n_obstacles + n_invalid != n:
        raise RuntimeError(
            f'inconsistent split: {n_ground} ground + {n_obstacles} obstacles + '
            f'{n_invalid} invalid != {n} points')
    if add_height_above_ground_field:
        height = result.height_above_ground
        ground = with_float32_field(ground, HEIGHT_FIELD, height[ground_mask])
        obstacles = with_float32_field(obstacles, HEIGHT_FIELD, height[result.obstacle_mask])
    t3 = time.perf_counter()
    warnings = input_warnings(msg, result, xyz, getattr(segmenter, 'params', None))
    out = FrameOutput(ground=ground, obstacles=obstacles, result=result,
                      decode_ms=(t1 - t0) * 1e3, encode_ms=(t3 - t2) * 1e3,
                      total_ms=(time.perf_counter() - t0) * 1e3, warnings=warnings)
    if publish_ground_surface:
        add_surface(out, msg)
    if labeled:
        add_labeled(out, msg)
    return out


def warm_up() -> None:
    """Queue the compilation (or the load from numba's cache) of the pass that builds the two
    output clouds (``cloud.split_cloud``) on the background compiler (core/compiled.py), for the
    argument types of every frame: call it after ``GroundSegmenter.warm_up()`` (a frame needs
    the segmenter's stages first); until it is ready the pass's numpy twin builds the same
    clouds. test_pipeline_warm_up_queues_the_output_pass checks nothing is missed."""
    point = types.SimpleNamespace
    msg = point(header=None, height=1, width=2, is_bigendian=False, point_step=12, row_step=24,
                fields=[point(name=c, offset=4 * i, datatype=FLOAT32, count=1)
                        for i, c in enumerate('xyz')],
                data=bytes(24), is_dense=True)
    split_cloud(msg, np.array([True, False]), np.array([True, True]))


def add_surface(out: FrameOutput, msg) -> FrameOutput:
    """Build the ground surface cloud of a frame that ``process_cloud`` split without it
    (``msg``: that frame's input message): ``out.surface`` and ``out.surface_ms`` are set, and
    ``encode_ms`` and ``total_ms`` grow by it, as when ``process_cloud`` builds it. The node
    publishes ground and obstacles first and builds the surface cloud after, so that their
    subscribers do not wait for it. No-op when the surface is there already or the segmenter
    gave none."""
    if out.surface is None and out.result.ground_surface is not None:
        _add_output(out, 'surface', lambda: surface_cloud(msg.header, out.result.ground_surface,
                                                          type(msg)))
    return out


def add_labeled(out: FrameOutput, msg) -> FrameOutput:
    """Build the labelled cloud (:func:`labeled_cloud`) of a frame that ``process_cloud`` split
    without it, as :func:`add_surface` builds the surface: ``out.labeled`` and
    ``out.labeled_ms`` set, ``encode_ms`` and ``total_ms`` grown by it. No-op when it is there
    already."""
    if out.labeled is None:
        _add_output(out, 'labeled', lambda: labeled_cloud(msg, out.result))
    return out


def _add_output(out: FrameOutput, name: str, build) -> None:
    """``out.<name> = build()``, its time in ``out.<name>_ms`` and added to encode and total."""
    t0 = time.perf_counter()
    setattr(out, name, build())
    ms = (time.perf_counter() - t0) * 1e3
    setattr(out, f'{name}_ms', ms)
    out.encode_ms += ms
    out.total_ms += ms


def input_warnings(msg, result, xyz=None, params=None) -> list:
    """One-line notes on a cloud that decoded fine but deserves a look (see FrameOutput).

    With ``xyz`` (the decoded points): also whether the cloud looks sensor-centred, around
    the sensor position of ``params`` (SegmenterParams) when given.
    """
    notes = []
    if xyz is not None:
        notes += cloud_notes(xyz, getattr(params, 'sensor_pose', None))
    n = int(result.valid_mask.size)
    if n == 0:
        notes.append('empty cloud (0 points)')
    elif result.num_invalid == n:
        notes.append(f'no valid point: all {n} points are NaN/Inf or (0, 0, 0)')
    try:
        extra = len(msg.data) - int(msg.height) * int(msg.row_step)
    except (TypeError, ValueError):
        extra = 0
    if extra > 0 and n > 0:
        notes.append(f'data has {extra} bytes beyond height * row_step '
                     f'{int(msg.height) * int(msg.row_step)} (ignored)')
    return notes
