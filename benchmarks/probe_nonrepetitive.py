# SPDX-License-Identifier: Apache-2.0
"""Probe (issue 10): scans without rings, as from a non-repetitive scanning LiDAR (Livox-like).

Usage::

    python benchmarks/probe_nonrepetitive.py [--set name=value ...] [--no-write]

Everything else in the evaluation comes from spinning sensors whose returns lie on rings; a
solid-state sensor with a non-repetitive pattern (Livox Mid-70, Avia, HAP, ...) covers its
field of view with returns in no ring order. The classic scenes ``flat``, ``ramp15``, ``hill``,
``mixed`` and ``onslope15`` are ray-cast from 1.73 m along 280 elevations drawn at random
(uniform over the field of view, irregularly spaced) x 1,200 azimuths, and
:data:`POINTS_PER_SCAN` returns are kept at random (about one in five), which leaves returns
scattered over the field of view with no regular ring spacing and sparse, gappy "rings" (the
ray caster fires fans of fixed elevation; fully random directions it does not do), for two
fields of view: ``forward 70 deg`` (azimuth and elevation within +-35 deg, a Mid-70-like
cone-ish window) and ``360 deg`` (elevations -25 to +15 deg). Scored cold: this project with
``SegmenterParams()`` defaults (``--set`` changes them) and Patchwork++ with bench_quality.py's
settings (its defaults plus the mount height). Not used to choose any default; a random
direction pattern is a stand-in for a real rosette, not a model of one.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_quality  # noqa: E402
import common  # noqa: E402

from gp_ground_segmentation import GroundSegmenter  # noqa: E402
from gp_ground_segmentation.tools.evaluation import truth_metrics  # noqa: E402
from scenes.synthetic import make_scene, simulate_scan  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'
SECTION = 'probe_nonrepetitive'
SCENES = ('flat', 'ramp15', 'hill', 'mixed', 'onslope15')
MOUNT_M = 1.73
POINTS_PER_SCAN = 60_000
# field of view: (name, half azimuth width deg or None for 360, lowest and highest elevation deg)
PATTERNS = (('forward 70 deg', 35.0, -35.0, 35.0), ('360 deg', None, -25.0, 15.0))


def ringless_scan(scene: str, half_azimuth_deg, low_deg: float, high_deg: float,
                  seed: int = 0):
    """(points (K, 4), is_ground (K,), returned (K,)) of ``scene`` seen from MOUNT_M along 280
    random elevations in [low_deg, high_deg] x 1,200 azimuths, of which at most
    POINTS_PER_SCAN returns inside the field of view are kept at random (in their ray order)."""
    rng = np.random.default_rng(seed)
    elevations = np.sort(rng.uniform(low_deg, high_deg, 280))[::-1]  # top first
    scan = simulate_scan(make_scene(scene), elevations_deg=elevations, azimuth_steps=1200,
                         sensor_height_m=MOUNT_M, seed=1)
    inside = np.ones(len(scan.points), dtype=bool)
    if half_azimuth_deg is not None:
        azimuth = np.degrees(np.arctan2(scan.points[:, 1], scan.points[:, 0]))
        inside = np.abs(azimuth) <= half_azimuth_deg
    rows = np.flatnonzero(inside)
    rows = np.sort(rng.choice(rows, min(rows.size, POINTS_PER_SCAN), replace=False))
    return np.ascontiguousarray(scan.points[rows]), scan.is_ground[rows], scan.returned[rows]


def main(argv=None):
    args, params = common.probe_arguments(__doc__.split('\n')[0], argv)
    rows = []
    for pattern, half_azimuth, low, high in PATTERNS:
        for scene in SCENES:
            points, is_ground, returned = ringless_scan(scene, half_azimuth, low, high)
            result = GroundSegmenter(params).segment(points[:, :3])
            m = truth_metrics(result.ground_mask, is_ground, returned)
            frame = common.Frame(scene, points, False, is_ground, returned, MOUNT_M)
            try:
                peer = bench_quality.run_frames('patchworkpp', [frame])[0]
                peer_text = f'{peer["precision"]:.3f} / {peer["recall"]:.3f} / {peer["f1"]:.3f}'
            except ImportError:
                peer_text = 'n/a'
            rows.append([pattern, scene, f'{len(points):,}',
                         f'{m["precision"]:.3f} / {m["recall"]:.3f} / {m["f1"]:.3f}', peer_text])
            print(' | '.join(rows[-1]), flush=True)
    common.report_probe(
        args, RESULTS, SECTION,
        'Scans without rings, non-repetitive pattern (`probe_nonrepetitive.py`)',
        'Cold, one scan per row (1.73 m mount, 280 random elevations x 1,200 azimuths, a random '
        'fifth of the returns kept: no regular rings); what is set: the script\'s docstring. '
        'Not used to choose any default.',
        ['field of view', 'scene', 'points', 'this project P / R / F1',
         'Patchwork++ P / R / F1'], rows)


if __name__ == '__main__':
    main()
