# SPDX-License-Identifier: Apache-2.0
"""Clouds not in the sensor frame: F1 without and with the sensor_* pose parameters (issue 12).

The SemanticKITTI-labelled scan is moved as a cloud published in another frame would be:
shifted 20 m in x (an odom/map frame), put in a base_link with the sensor 1.5 m ahead and
1.8 m up, and tilted (roll 0.05, pitch 0.15 rad, a tilted mount publishing in its own frame).
Each is segmented with the default parameters, then with the pose that describes it, and
whether the 'not sensor-centred' check fires is shown.

    python benchmarks/bench_sensor_frame.py [--no-write]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from common import (REPO, command_line, load_labeled_kitti, machine_markdown, markdown_table,
                    update_results_section)

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402
from gp_ground_segmentation.core.sensor_frame import SensorPose, centring_note  # noqa: E402
from gp_ground_segmentation.tools.evaluation import truth_metrics  # noqa: E402


def cases(points):
    xyz = points[:, :3].astype(np.float64)
    tilt = SensorPose(roll=0.05, pitch=0.15)
    return [
        ('sensor frame (as recorded)', xyz, SensorPose()),
        ('shifted 20 m in x (odom/map-like)', xyz + [20.0, 0.0, 0.0], SensorPose(x=20.0)),
        ('base_link: sensor at (1.5, 0, 1.8) m', xyz + [1.5, 0.0, 1.8],
         SensorPose(x=1.5, z=1.8)),
        ('tilted mount: roll 0.05, pitch 0.15 rad', xyz @ tilt.rotation(), tilt),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--no-write', action='store_true', help='print only, do not touch RESULTS.md')
    args = ap.parse_args(argv)
    data = load_labeled_kitti()
    if data is None:
        print('the labelled scan is needed', file=sys.stderr)
        return 1
    frame = data.frames[0]
    rows = []
    for name, cloud, pose in cases(frame.points):
        cloud = cloud.astype(np.float32)
        f1 = []
        for p in (SensorPose(), pose):
            params = SegmenterParams(sensor_x_m=p.x, sensor_y_m=p.y, sensor_z_m=p.z,
                                     sensor_roll_rad=p.roll, sensor_pitch_rad=p.pitch)
            result = GroundSegmenter(params).segment(cloud)
            f1.append(truth_metrics(result.ground_mask, frame.truth, frame.evaluated)['f1'])
        note = centring_note(cloud)
        rows.append([name, f'{f1[0]:.4f}', f'{f1[1]:.4f}' if not pose.is_identity else '-',
                     'yes' if note else 'no'])
    table = markdown_table(['cloud', 'F1 default params', 'F1 with the sensor_* pose',
                            "'not sensor-centred' warning"], rows)
    print(table)
    if args.no_write:
        return 0
    text = ('## Clouds not in the sensor frame (`bench_sensor_frame.py`)\n\n'
            + machine_markdown(command_line()) + '\n'
            + 'SemanticKITTI-labelled scan (123,389 points), default parameters, one cold '
            'frame each; F1 of ground as in bench_peers.\n\n' + table + '\n')
    update_results_section(REPO / 'benchmarks' / 'RESULTS.md', 'bench_sensor_frame', text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
