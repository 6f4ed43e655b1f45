# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg play`` and ``gp-ground-seg hz``: a live ROS 2 graph without the ros2 CLI.

A pip-only user has no ``ros2 bag play`` and no ``ros2 topic hz``. ``play`` publishes the
PointCloud2 frames of a bag (or of .bin/.pcd files, stamped i * 0.1 s) with their recorded
timing and sensor-data QoS, so that the node can be run live on the shipped sample; ``hz``
subscribes to topics and prints their rates (and, per message type, a one-line summary).

    gp-ground-seg play data/kitti00_sample --loop
    gp-ground-seg hz /ground /obstacles /diagnostics --duration 10

Both end on Ctrl-C (or SIGTERM) with exit status 0 and a closing summary line.
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
from collections import deque

import rclpy
from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from ..ros.shutdown import QuietShutdown, shutdown_context
from .bag import SYNTHETIC_PERIOD_NS, FrameSource, normalize_topic
from .errors import CliError
from .options import add_frame_id_option

CLOCK_PERIOD_S = 0.025  # /clock at 40 Hz while waiting between frames (ros2 bag play's default)


def _ros_context():
    """A private rclpy context without rclpy's signal handlers: with ``QuietShutdown`` the first
    Ctrl-C or SIGTERM raises KeyboardInterrupt wherever the loop is (sleeping included) and
    further ones are ignored."""
    context = rclpy.Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    return context


def _to_time_msg(ns: int):
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


RELIABILITY_CHOICES = ('best_effort', 'reliable')


def qos_profile(reliability: str, depth: int):
    """A keep-last QoS profile of ``depth`` with ``reliability`` (one of RELIABILITY_CHOICES,
    the spelling of ``ros2 topic --qos-reliability``), volatile, as the sensor-data profile."""
    policy = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
              'reliable': ReliabilityPolicy.RELIABLE}[reliability]
    return QoSProfile(depth=depth, reliability=policy)


def add_qos_options(parser, depth: int, what: str, reliable_note: str) -> None:
    """--qos-reliability / --qos-depth, named as in ``ros2 topic echo``."""
    parser.add_argument('--qos-reliability', choices=RELIABILITY_CHOICES, default='best_effort',
                        help=f'reliability of the {what} (default best_effort; reliable loses '
                        f'no message between reliable endpoints, {reliable_note})')
    parser.add_argument('--qos-depth', type=_positive_int, default=depth, metavar='N',
                        help=f'keep-last history depth of the {what} (default {depth})')


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f'expected an integer >= 1, got {text!r}')
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f'expected a finite number > 0, got {text!r}')
    return value


# ---------------------------------------------------------------------------------------------
# play
# ---------------------------------------------------------------------------------------------

class _Player:
    """Publishes frames at their recorded pace (bag time / rate), optionally /clock."""

    def __init__(self, node, topic: str, rate: float, restamp: bool, clock: bool,
                 reliability: str = 'best_effort', depth: int = 5):
        self.node = node
        self.rate = rate
        self.restamp = restamp
        self.pub = node.create_publisher(PointCloud2, topic, qos_profile(reliability, depth))
        self.clock_pub = None
        if clock:
            self.clock_pub = node.create_publisher(Clock, '/clock', 10)
        self.offset_ns = 0  # added to bag time on every loop pass, so time never goes back
        self.published = 0
        self._anchor = None  # (wall monotonic s, bag time ns) of the first frame

    def sim_time_ns(self) -> int:
        wall0, bag0 = self._anchor
        return bag0 + int((time.monotonic() - wall0) * self.rate * 1e9)

    def _publish_clock(self) -> None:
        if self.clock_pub is not None and self._anchor is not None:
            self.clock_pub.publish(Clock(clock=_to_time_msg(self.sim_time_ns())))

    def wait_until(self, bag_ns: int) -> None:
        """Sleep until the wall time of bag time ``bag_ns``, publishing /clock meanwhile."""
        if self._anchor is None:
            self._anchor = (time.monotonic(), bag_ns)
        wall0, bag0 = self._anchor
        due = wall0 + (bag_ns - bag0) / 1e9 / self.rate
        while True:
            self._publish_clock()
            left = due - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, CLOCK_PERIOD_S) if self.clock_pub is not None else left)

    def publish(self, msg, bag_ns: int) -> None:
        if self.restamp:
            msg.header.stamp = (_to_time_msg(bag_ns) if self.clock_pub is not None
                                else self.node.get_clock().now().to_msg())
        self.pub.publish(msg)
        self.published += 1

    def flush(self, timeout_s: float = 5.0) -> None:
        """Reliable publishers (the frames' if so, /clock's always): wait (at most
        ``timeout_s`` each) until every subscriber has acknowledged every message, so that
        leaving right after the last one loses nothing."""
        for pub in (self.pub, self.clock_pub):
            if pub is not None and pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                pub.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9)))


def cmd_play(args) -> int:
    if not args.rate > 0:
        raise CliError('--rate must be > 0')
    if not args.delay >= 0:
        raise CliError('--delay must be >= 0')
    source = FrameSource(args.inputs, args.topic, args.max_frames, args.frame_id)
    with source:  # opened and its first frame decoded up front, as replay does: bad input is
        next(iter(source))  # reported before the ROS graph starts and the subscriber wait
    # it publishes on it (a packet bag's clouds on the driver's cloud topic): rclpy's rules apply
    topic = normalize_topic(source.cloud_topic, strict=True)
    prog = 'gp-ground-seg play'
    if source.note:
        print(f'{prog}: note: {source.note}', file=sys.stderr)
    quiet = QuietShutdown()
    quiet.install()
    context = _ros_context()
    node = player = None
    t0 = time.monotonic()
    passes = 0
    try:
        node = rclpy.create_node('gp_ground_seg_play', context=context)
        player = _Player(node, topic, args.rate, args.restamp, args.clock,
                         args.qos_reliability, args.qos_depth)
        deadline = time.monotonic() + args.wait_for_subscriber
        while player.pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        # Our side sees the subscriber before its side has matched us: a volatile reader
        # ignores what is sent before it matched, so the first frames could be lost.
        time.sleep(args.delay)
        subs = player.pub.get_subscription_count()
        print(f'{prog}: publishing {source.count} frame(s) of {source.description} on '
              f'{topic} (rate x{args.rate:g}{", loop" if args.loop else ""}'
              f'{", restamped" if args.restamp else ""}{", /clock" if args.clock else ""}; '
              f'{subs} subscriber(s))', file=sys.stderr)
        period_ns = 0
        while True:
            first_ns = last_ns = None
            with FrameSource(args.inputs, args.topic, args.max_frames, args.frame_id) as src:
                for frame in src:
                    bag_ns = frame.timestamp_ns + player.offset_ns
                    if first_ns is None:
                        first_ns = bag_ns
                    elif last_ns is not None:
                        period_ns = bag_ns - last_ns
                    player.wait_until(bag_ns)
                    player.publish(frame.msg, bag_ns)
                    last_ns = bag_ns
            passes += 1
            if not args.loop:
                player.flush()
                break
            # next pass starts one frame period after this one ended: time keeps increasing
            player.offset_ns += (last_ns - first_ns) + (period_ns or SYNTHETIC_PERIOD_NS)
    except KeyboardInterrupt:
        pass
    finally:
        quiet.ignore_signals()
        if node is not None:
            node.destroy_node()
        shutdown_context(context)
    wall = time.monotonic() - t0
    published = player.published if player is not None else 0
    print(f'{prog}: published {published} frame(s) in {wall:.1f} s ({passes} full pass(es))',
          file=sys.stderr)
    return 0


# ---------------------------------------------------------------------------------------------
# hz
# ---------------------------------------------------------------------------------------------

def _message_class(type_name: str):
    """'sensor_msgs/msg/PointCloud2' -> the rclpy class."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def _summary(msg) -> str:
    """A short description of one message of the common types (an 'echo' in one line)."""
    if hasattr(msg, 'point_step') and hasattr(msg, 'fields'):
        return f"{int(msg.width) * int(msg.height)} points, frame_id '{msg.header.frame_id}'"
    status = getattr(msg, 'status', None)
    if isinstance(status, (list, tuple)) and status and hasattr(status[0], 'level'):
        names = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
        return '; '.join(f"{names.get(ord(s.level) if isinstance(s.level, bytes) else s.level)}"
                         f' {s.message}' for s in status)
    return ''


class _TopicStats:
    def __init__(self, window: int):
        self.times = deque(maxlen=window + 1)
        self.count = 0
        self.last = ''

    def add(self, msg) -> None:
        self.times.append(time.monotonic())
        self.count += 1
        self.last = _summary(msg)

    def line(self, topic: str) -> str:
        t = list(self.times)
        if len(t) < 2:
            return f'{topic}: {self.count} message(s), rate n/a  {self.last}'.rstrip()
        periods = [b - a for a, b in zip(t, t[1:])]
        rate = (len(t) - 1) / (t[-1] - t[0]) if t[-1] > t[0] else float('nan')
        return (f'{topic}: {rate:.2f} Hz (min {min(periods):.3f} s, max {max(periods):.3f} s, '
                f'window {len(periods)}), {self.count} message(s)  {self.last}').rstrip()


def cmd_hz(args) -> int:
    topics = [normalize_topic(t, strict=True) for t in args.topics]
    quiet = QuietShutdown()
    quiet.install()
    context = _ros_context()
    node = None
    stats = {t: _TopicStats(args.window) for t in topics}
    prog = 'gp-ground-seg hz'
    try:
        node = rclpy.create_node('gp_ground_seg_hz', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        pending = set(topics)
        start = time.monotonic()
        end = start + args.duration if args.duration else None
        next_print = start + args.period
        while end is None or time.monotonic() < end:
            if pending:
                known = dict(node.get_topic_names_and_types())
                for topic in sorted(pending):
                    if topic in known:
                        msg_type = _message_class(known[topic][0])
                        # best effort (the default) matches reliable and best-effort
                        # publishers alike; reliable loses nothing from a reliable publisher
                        node.create_subscription(
                            msg_type, topic, stats[topic].add,
                            qos_profile(args.qos_reliability, args.qos_depth))
                        pending.discard(topic)
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() >= next_print:
                next_print += args.period
                for topic in topics:
                    text = (f'{topic}: not published yet' if topic in pending
                            else stats[topic].line(topic))
                    print(text, flush=True)
    except KeyboardInterrupt:
        pass
    except (ValueError, ImportError, AttributeError) as err:
        raise CliError(f'cannot subscribe: {err}') from None
    finally:
        quiet.ignore_signals()
        if node is not None:
            node.destroy_node()
        shutdown_context(context)
    print(f'{prog}: summary', file=sys.stderr)
    for topic in topics:
        print(stats[topic].line(topic), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# argument parsing (registered by cli.build_parser)
# ---------------------------------------------------------------------------------------------

def register(sub) -> None:
    """Add the ``play`` and ``hz`` subcommands to the gp-ground-seg subparsers ``sub``."""
    p = sub.add_parser('play', help='publish a bag\'s clouds live (like ros2 bag play)',
                       description='Publish the PointCloud2 frames of a bag (or of .bin/.pcd '
                       'files, 10 Hz) with their recorded timing and sensor-data QoS (best '
                       'effort, keep last 5), e.g. to run the node live on the shipped sample. '
                       'Ctrl-C stops it.')
    p.add_argument('inputs', nargs='+', metavar='IN',
                   help='bag, point files or a directory of them')
    p.add_argument('--topic', default=None,
                   help='PointCloud2 topic to read and to publish on (default /velodyne_points; '
                   'if absent, the bag\'s one PointCloud2 topic, else its one Velodyne packet '
                   'topic, whose decoded clouds go out on the driver\'s cloud topic, e.g. '
                   '/velodyne_points for /velodyne_packets)')
    p.add_argument('--rate', type=float, default=1.0, metavar='X',
                   help='play X times faster than recorded (default 1)')
    p.add_argument('--loop', action='store_true', help='start again at the end, until Ctrl-C')
    p.add_argument('--restamp', action='store_true',
                   help='set header.stamp to the time of publishing (the /clock time with '
                   '--clock), e.g. for TF lookups on a live robot')
    p.add_argument('--clock', action='store_true',
                   help='publish /clock from the bag time (for nodes with use_sim_time)')
    add_frame_id_option(p)
    p.add_argument('--max-frames', type=int, metavar='K', help='play only the first K frames')
    p.add_argument('--wait-for-subscriber', type=float, default=5.0, metavar='S',
                   help='wait up to S seconds for a subscriber before the first frame '
                   '(default 5; 0: start at once)')
    p.add_argument('--delay', type=float, default=0.0, metavar='S',
                   help='sleep S seconds after a subscriber appeared, before the first frame '
                   '(as ros2 bag play --delay): lets discovery finish on the subscriber\'s side '
                   'too, so that a reliable link loses not even the first frame (default 0)')
    add_qos_options(p, 5, 'publisher', 'and still reaches best-effort subscribers')
    p.set_defaults(func=cmd_play)

    p = sub.add_parser('hz', help='print the rates of topics (like ros2 topic hz)',
                       description='Subscribe (best effort) to TOPICs and print each one\'s rate '
                       'every PERIOD seconds, with a one-line summary of the last message '
                       '(points and frame_id of a PointCloud2, level and message of '
                       'diagnostics). Ctrl-C or --duration ends it with a summary.')
    p.add_argument('topics', nargs='+', metavar='TOPIC', help='e.g. /ground /obstacles')
    p.add_argument('--window', type=_positive_int, default=50, metavar='N',
                   help='rate over the last N messages (default 50)')
    p.add_argument('--period', type=_positive_float, default=1.0, metavar='S',
                   help='print every S seconds (default 1)')
    p.add_argument('--duration', type=_positive_float, default=None, metavar='S',
                   help='stop after S seconds')
    add_qos_options(p, 10, 'subscriptions', 'but hears nothing from a best-effort publisher')
    p.set_defaults(func=cmd_hz)
