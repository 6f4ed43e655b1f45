# SPDX-License-Identifier: Apache-2.0
"""The core needs no ROS: import and segment a frame where ROS modules cannot be imported."""

import json
import subprocess
import sys
import textwrap

from conftest import REPO

BLOCKED = ('rclpy', 'rosbags', 'sensor_msgs', 'std_msgs', 'builtin_interfaces',
           'rcl_interfaces', 'diagnostic_msgs', 'rosidl_runtime_py', 'rosidl_parser')

SCRIPT = textwrap.dedent('''
    import json, sys

    BLOCKED = {blocked!r}

    class NoRos:
        """Raise ImportError for every ROS package, as on a machine without ROS."""

        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in BLOCKED:
                raise ImportError(f'{{name}} is blocked (no ROS here)')
            return None

    sys.meta_path.insert(0, NoRos())
    try:
        import rclpy  # noqa: F401  the block works
        sys.exit('rclpy imported')
    except ImportError:
        pass

    import numpy as np
    import gp_ground_segmentation
    from gp_ground_segmentation import GroundSegmenter, SegmenterParams
    import gp_ground_segmentation.core as core
    from gp_ground_segmentation.core import (anchor, gp, grid, labels, length_factors, lines,
                                             outliers, paciorek, params, plateau, predict,
                                             segmenter, stages, structure, surface)

    rng = np.random.default_rng(0)
    r = rng.uniform(3.0, 40.0, 20000)
    azimuth = rng.uniform(-np.pi, np.pi, r.size)
    x, y = r * np.cos(azimuth), r * np.sin(azimuth)
    z = -1.7 + 0.1 * x + rng.normal(0.0, 0.02, r.size)  # a 0.1 slope
    box = (np.abs(x - 10.0) < 1.0) & (np.abs(y) < 1.0)
    z[box] += rng.uniform(0.5, 1.5, box.sum())  # an obstacle on it
    res = GroundSegmenter(SegmenterParams()).segment(np.stack([x, y, z], axis=1))
    loaded = sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)
    print(json.dumps({{'ground_recall': float(res.ground_mask[~box].mean()),
                      'obstacle_recall': float(res.obstacle_mask[box].mean()),
                      'ros_modules': loaded}}))
''').format(blocked=BLOCKED)


def test_core_imports_and_segments_without_ros():
    out = subprocess.run([sys.executable, '-c', SCRIPT], cwd=REPO, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result['ros_modules'] == []
    # the frame is really segmented, not just imported. Measured at this seed 1.000 and 0.943
    # (2 of the box's 35 random points are called ground). The box is 35 points scattered
    # 0.5-1.5 m above a 0.1 slope: over seeds 0-39 of this very scene the obstacle recall is
    # 0.983 on average, 0.879 at worst, and with the paper's unsmoothed length factors
    # (use_length_factor_smoothing=False) 0.988 / 0.889 (RESULTS.md, "Length factors smoothed
    # along the segment"), so the limit is set for the scene, not for one lucky seed
    assert result['ground_recall'] > 0.98 and result['obstacle_recall'] > 0.9
