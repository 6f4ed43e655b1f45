# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg play / hz against the live node (real rclpy, separate processes)."""

import os
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest

from conftest import REPO, wait_for
from gp_ground_segmentation.tools.cli import main

FRAMES = 5


@pytest.fixture
def pcd_dir(tmp_path):
    """FRAMES small synthetic scans as .pcd files (small enough for any DDS transport)."""
    from gp_ground_segmentation.tools.io import write_pcd
    rng = np.random.default_rng(1)
    for i in range(FRAMES):
        xy = rng.uniform(-15, 15, (4000, 2))
        box = np.hypot(xy[:, 0] - 6, xy[:, 1]) < 1.5
        z = np.where(box, -0.5, -1.7) + rng.normal(0, 0.02, 4000)
        rows = np.zeros(4000, [('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
        rows['x'], rows['y'], rows['z'] = xy[:, 0], xy[:, 1], z
        write_pcd(tmp_path / f'{i:06d}.pcd', rows)
    return tmp_path


def _tool(*args):
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = os.pathsep.join([str(REPO), env.get('PYTHONPATH', '')])
    return subprocess.Popen([sys.executable, '-m', 'gp_ground_segmentation.tools.cli', *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_play_feeds_the_live_node_with_restamp_and_clock(pcd_dir, ros_harness):
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock
    # Topics of our own: other test runs on this machine may share the DDS domain.
    prefix = f'/gp_play_{os.getpid()}_{uuid.uuid4().hex[:8]}'
    # a slot for every frame: under load the latest-wins slot would (rightly) drop some
    h = ros_harness(context_args=['--ros-args', '-r', f'points:={prefix}/points',
                                  '-r', f'ground:={prefix}/ground',
                                  '-r', f'obstacles:={prefix}/obstacles'],
                    node_kwargs={'parameter_overrides': [Parameter('queue_size',
                                                                   value=FRAMES)]})
    clocks = []
    h.peer.create_subscription(Clock, '/clock', lambda m: clocks.append(m), 10)
    hz = _tool('hz', f'{prefix}/ground', f'{prefix}/obstacles', '--duration', '20',
               '--period', '100')
    # hz subscribes once it has seen the topics: wait for it (peer + hz on each output)
    assert wait_for(lambda: h.node.count_subscribers(f'{prefix}/ground') >= 2
                    and h.node.count_subscribers(f'{prefix}/obstacles') >= 2, 15.0)
    play = _tool('play', str(pcd_dir), '--topic', f'{prefix}/points', '--frame-id', 'base_lidar',
                 '--rate', '2', '--restamp', '--clock', '--wait-for-subscriber', '10')
    out, err = play.communicate(timeout=60)
    assert play.returncode == 0, err
    assert f'published {FRAMES} frame(s)' in err and 'Traceback' not in err
    assert wait_for(lambda: len(h.ground) >= FRAMES, 30.0), len(h.ground)
    assert len(h.ground) == len(h.obstacles) == FRAMES
    assert h.ground[0].header.frame_id == 'base_lidar'
    # --restamp --clock: stamps are the bag time (i * 0.1 s), and /clock ran with it
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in h.ground]
    assert stamps == pytest.approx([0.1 * i for i in range(FRAMES)], abs=1e-6)
    assert clocks and max(c.clock.sec + 1e-9 * c.clock.nanosec for c in clocks) >= 0.4 - 1e-6
    hz_out, hz_err = hz.communicate(timeout=60)
    assert hz.returncode == 0, hz_err
    summary = [ln for ln in hz_out.splitlines() if ln.startswith(f'{prefix}/ground:')][-1]
    assert f'{FRAMES} message(s)' in summary and "frame_id 'base_lidar'" in summary


def test_play_keeps_the_recorded_pace(pcd_dir):
    # 5 frames recorded 0.1 s apart, played at rate 2: at least 0.2 s from first to last.
    start = time.monotonic()
    play = _tool('play', str(pcd_dir), '--topic', '/gp_test_pace', '--rate', '2',
                 '--wait-for-subscriber', '0')
    _, err = play.communicate(timeout=60)
    assert play.returncode == 0 and f'published {FRAMES} frame(s)' in err, err
    assert time.monotonic() - start >= 0.2


def test_play_loop_stops_cleanly_on_sigint(pcd_dir):
    import signal
    play = _tool('play', str(pcd_dir), '--topic', '/gp_test_loop', '--loop',
                 '--wait-for-subscriber', '0')
    try:
        for line in play.stderr:  # started: the graph is up and frames are going out
            if 'publishing' in line:
                break
        time.sleep(1.0)
        play.send_signal(signal.SIGINT)
        play.send_signal(signal.SIGINT)
        _, err = play.communicate(timeout=30)
    finally:
        if play.poll() is None:
            play.kill()
    assert play.returncode == 0 and 'Traceback' not in err, err
    assert 'full pass(es)' in err


def test_play_bad_input_is_one_line(tmp_path, capsys):
    assert main(['play', str(tmp_path / 'nothing')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('gp-ground-seg play: error:') and len(err.strip().splitlines()) == 1
    assert main(['play', str(tmp_path), '--rate', '0']) == 2
