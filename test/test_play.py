# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg play / hz against the live node (real rclpy, separate processes)."""

import os
import signal
import subprocess
import threading
import time
import uuid

import numpy as np
import pytest

from conftest import lines_until, start_module, wait_for
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
    return start_module('gp_ground_segmentation.tools.cli', *args, stderr=subprocess.PIPE)


def _stop(proc):
    """Kill ``proc`` if a failed test left it running, and reap it."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=30)


def test_play_feeds_the_live_node_with_restamp_and_clock(pcd_dir, ros_harness, request):
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2
    # Topics of our own: other test runs on this machine may share the DDS domain.
    prefix = f'/gp_play_{os.getpid()}_{uuid.uuid4().hex[:8]}'
    # Every frame must arrive, so nothing on the way may drop one: a slot for every frame
    # (under load the latest-wins slot would rightly drop some) and reliable keep-last FRAMES
    # on every link (play -> node, node -> peer and hz) through the node's qos_overrides. With
    # the default best-effort / depth-1 links a loaded machine loses frames by design.
    overrides = [Parameter('queue_size', value=FRAMES),
                 Parameter(f'qos_overrides.{prefix}/points.subscription.reliability',
                           value='reliable'),
                 Parameter(f'qos_overrides.{prefix}/points.subscription.depth', value=FRAMES)]
    overrides += [Parameter(f'qos_overrides.{prefix}/{out}.publisher.depth', value=FRAMES)
                  for out in ('ground', 'obstacles')]
    h = ros_harness(context_args=['--ros-args', '-r', f'points:={prefix}/points',
                                  '-r', f'ground:={prefix}/ground',
                                  '-r', f'obstacles:={prefix}/obstacles'],
                    node_kwargs={'parameter_overrides': overrides})
    [endpoint] = [e for e in h.node.get_subscriptions_info_by_topic(f'{prefix}/points')
                  if e.node_name == h.node.get_name()]
    assert endpoint.qos_profile.reliability == ReliabilityPolicy.RELIABLE  # override applied
    clocks, ground, obstacles = [], [], []
    deep = QoSProfile(depth=FRAMES, reliability=ReliabilityPolicy.RELIABLE)
    h.peer.create_subscription(Clock, '/clock', lambda m: clocks.append(m), 10)
    h.peer.create_subscription(PointCloud2, f'{prefix}/ground', ground.append, deep)
    h.peer.create_subscription(PointCloud2, f'{prefix}/obstacles', obstacles.append, deep)
    # hz runs until it is interrupted below, once its periodic lines show every frame counted:
    # a fixed --duration would start counting before play has even started (a few seconds,
    # more on a loaded machine) and could close before the last frame; and a frame acked by
    # hz's reader may still wait in its queue. --duration is a safety net.
    hz = start_module('gp_ground_segmentation.tools.cli', 'hz', f'{prefix}/ground',
                      f'{prefix}/obstacles', '--duration', '300', '--period', '0.2',
                      '--qos-reliability', 'reliable', '--qos-depth', str(FRAMES))
    request.addfinalizer(lambda: _stop(hz))
    hz_lines = []  # stdout and stderr, read as they come

    def read_hz():
        for line in hz.stdout:
            hz_lines.append(line)
    hz_reader = threading.Thread(target=read_hz, daemon=True)
    hz_reader.start()
    # hz subscribes once it has seen the topics: wait for it (2 peer subscriptions + hz)
    assert wait_for(lambda: h.node.count_subscribers(f'{prefix}/ground') >= 3
                    and h.node.count_subscribers(f'{prefix}/obstacles') >= 3, 60.0)
    play = _tool('play', str(pcd_dir), '--topic', f'{prefix}/points', '--frame-id', 'base_lidar',
                 '--rate', '2', '--restamp', '--clock', '--wait-for-subscriber', '10',
                 '--delay', '1', '--qos-reliability', 'reliable', '--qos-depth', str(FRAMES))
    request.addfinalizer(lambda: _stop(play))
    out, err = play.communicate(timeout=60)
    assert play.returncode == 0, err
    assert f'published {FRAMES} frame(s)' in err and 'Traceback' not in err
    assert wait_for(lambda: len(ground) >= FRAMES and len(obstacles) >= FRAMES, 30.0), \
        (len(ground), len(obstacles), h.node.window.frames_received,
         [m.header.stamp.nanosec for m in ground])
    assert len(ground) == len(obstacles) == FRAMES
    assert ground[0].header.frame_id == 'base_lidar'
    # --restamp --clock: stamps are the bag time (i * 0.1 s), and /clock ran with it
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in ground]
    assert stamps == pytest.approx([0.1 * i for i in range(FRAMES)], abs=1e-6)
    assert clocks and max(c.clock.sec + 1e-9 * c.clock.nanosec for c in clocks) >= 0.4 - 1e-6

    def hz_counted_all():
        last = {}
        for line in list(hz_lines):
            last[line.split(':')[0]] = line
        return all(f' {FRAMES} message(s)' in last.get(f'{prefix}/{t}', '')
                   for t in ('ground', 'obstacles'))
    assert wait_for(hz_counted_all, 60.0), ''.join(hz_lines[-6:])
    hz.send_signal(signal.SIGINT)  # Ctrl-C: hz prints its summary and exits 0
    assert hz.wait(timeout=60) == 0, ''.join(hz_lines)
    hz_reader.join(timeout=10)
    text = ''.join(hz_lines)
    assert 'gp-ground-seg hz: summary' in text and 'Traceback' not in text, text
    summary = text.split('gp-ground-seg hz: summary')[-1].splitlines()
    [ground_line] = [ln for ln in summary if ln.startswith(f'{prefix}/ground:')]
    assert f'{FRAMES} message(s)' in ground_line and "frame_id 'base_lidar'" in ground_line


def test_play_keeps_the_recorded_pace(pcd_dir):
    # 5 frames recorded 0.1 s apart, played at rate 2: at least 0.2 s from first to last.
    start = time.monotonic()
    play = _tool('play', str(pcd_dir), '--topic', '/gp_test_pace', '--rate', '2',
                 '--wait-for-subscriber', '0')
    _, err = play.communicate(timeout=60)
    assert play.returncode == 0 and f'published {FRAMES} frame(s)' in err, err
    assert time.monotonic() - start >= 0.2


def test_play_loop_stops_cleanly_on_sigint(pcd_dir):
    play = _tool('play', str(pcd_dir), '--topic', '/gp_test_loop', '--loop',
                 '--wait-for-subscriber', '0')
    try:
        # started: the graph is up and frames are going out (the lines kept for the message)
        started = lines_until(play, play.stderr, 'publishing', 120.0)
        time.sleep(1.0)
        play.send_signal(signal.SIGINT)
        play.send_signal(signal.SIGINT)
        _, err = play.communicate(timeout=30)
    finally:
        if play.poll() is None:
            play.kill()
    err = ''.join(started) + err
    assert play.returncode == 0 and 'Traceback' not in err, err
    assert 'full pass(es)' in err, err


def test_play_bad_input_is_one_line(tmp_path, capsys):
    assert main(['play', str(tmp_path / 'nothing')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('gp-ground-seg play: error:') and len(err.strip().splitlines()) == 1
    assert main(['play', str(tmp_path), '--rate', '0']) == 2
    assert main(['play', str(tmp_path), '--delay', '-1']) == 2
    capsys.readouterr()
    with pytest.raises(SystemExit) as bad_depth:  # argparse: usage + one error line, status 2
        main(['play', str(tmp_path), '--qos-depth', '0'])
    assert bad_depth.value.code == 2
    assert 'expected an integer >= 1' in capsys.readouterr().err


@pytest.mark.parametrize('content', [b'abcdefg', b''])
def test_play_checks_the_first_frame_before_waiting_for_subscribers(tmp_path, capsys,
                                                                    monkeypatch, content):
    # a truncated .bin (or an empty one: no point) is only found by reading it: it must be
    # read before the node is created and the 5 s subscriber wait starts, as replay does
    from gp_ground_segmentation.tools import play
    scan = tmp_path / 'scan.bin'
    scan.write_bytes(content)

    def no_graph(*args, **kwargs):
        raise AssertionError('the ROS graph was started before the input was checked')
    monkeypatch.setattr(play.rclpy, 'create_node', no_graph)
    if content:
        assert main(['play', str(scan)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and 'not a multiple of 16' in err[0], err
    else:  # an empty scan is a frame (the node reports it): it gets to the graph
        with pytest.raises(AssertionError, match='ROS graph was started'):
            main(['play', str(scan)])
