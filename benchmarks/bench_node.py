# SPDX-License-Identifier: Apache-2.0
"""The ROS 2 node under load, in one process over real rclpy pub/sub (issue 6 and issue 7.4).

A ``GroundSegmentationNode`` and a publisher node share a private rclpy Context (own
ROS_DOMAIN_ID, discovery on localhost, Fast DDS) spun in a background thread by a
SingleThreadedExecutor (``--executor single``, the default: what the node's ``main()`` spins) or
a MultiThreadedExecutor(3) (``--executor multi``: the test harness's; ``both`` runs each). The
latter showed whole-process stalls of 0.1-1 s (late wake-ups of the sampler thread) and the
drops they cause at 10 Hz; the former none (see RESULTS.md). The 6 real KITTI frames of
``../shared/data/kitti00_velodyne_points`` (rosbags AnyReader +
``rclpy.serialization.deserialize_message``, i.e. the node's own message class) are published to
``points`` in a loop, each with a fresh header stamp, on a fixed-rate schedule.

Modes:

``--latency``   10 Hz (real time) for ``--latency-s`` (30 s): per-stage ms median / p95 of
                decode, segment, encode and total (decode + segment + encode, the pipeline's
                wall time) from the node's own ``ProcessingWindow`` (the numbers its
                diagnostics summarise), warm-up frames excluded; frames published / received /
                processed / dropped / failed; whether 10 Hz was sustained with no drops.
``--subscribers K``  with ``--latency``: K extra subscriber processes (rclpy, each subscribed
                to ground, obstacles and ground_surface with the node's RELIABLE output QoS, as
                RViz subscribes), started before the publishing and counting what they receive;
                the latency table then adds the node's hand-off (slot wait), surface and publish
                times, the overhead around ``segment()`` and the node total
                (hand-off + decode + segment + encode + publish). The issue-14 load test is
                ``--latency --latency-s 60 --subscribers 3``.
``--labeled``   with ``--subscribers``: the subscriber processes also take ``labeled`` (the node
                builds that cloud only while someone subscribes), and the table adds its
                ``labeled`` stage (part of encode). Without it nobody subscribes to it: the
                node's default cost.
``--node-process``  with ``--latency``: the node runs alone in a child process (spun by a
                SingleThreadedExecutor, as ``ros2 run`` starts it) instead of sharing this
                process - and its GIL - with the publisher, the ``ground`` subscription that
                consumes its output and the sampler thread; its ProcessingWindow is read over a
                pipe (slot occupancy only at each publish). What a deployed node sees.
                Every process gets ``config/fastdds_large_shm.xml`` as the README says, unless
                ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set (set and empty: Fast DDS defaults).
``--overload``  50 Hz (5x real time) for ``--overload-s`` (60 s): input Hz (published and
                received), processed Hz, drops as counted by the node and as reported on
                /diagnostics (with its level), maximum slot occupancy (sampled every 5 ms (and
                at every publish); must stay <= queue_size), RSS (VmRSS of this process, which
                holds node, publisher and DDS) sampled every second: at start, after warm-up,
                at the end, and its least-squares slope after warm-up (MB/min).

Neither mode asserts anything; the figures are printed as markdown and written to the
``bench_node`` section of ``benchmarks/RESULTS.md`` (``--no-write`` to skip). Running one mode
keeps the other mode's previous sub-section. Without a mode flag both run.

    python benchmarks/bench_node.py --latency
    python benchmarks/bench_node.py --latency --latency-s 60 --subscribers 3
    python benchmarks/bench_node.py --node-process --latency-s 60 --subscribers 3
    python benchmarks/bench_node.py --overload
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

# An isolated DDS domain on localhost before any rclpy context exists (same rule as the tests);
# a subscriber process (--as-subscriber) keeps the domain its parent gave it.
if '--as-subscriber' not in sys.argv and '--as-node' not in sys.argv:
    os.environ['ROS_DOMAIN_ID'] = str(1 + (os.getpid() + 37) % 100)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from common import (BAG_DIR, BAG_TOPIC, DATA_DIR, REPO, command_line, fmt,  # noqa: E402
                    machine_markdown, markdown_table, rss_bytes, update_results_section)

RESULTS = REPO / 'benchmarks' / 'RESULTS.md'
SECTION = 'bench_node'
STAGES = ('decode', 'segment', 'encode', 'total')
# With --subscribers: also the node's own stages and two sums (per frame, then percentiles):
# around = handoff + total - segment (decode, encode including the surface cloud, and the input
# checks), i.e. everything the node adds to segment() before publishing; node_total = handoff +
# total + publish (subscription callback to published); ground_published: the node's own
# measure from the callback to ground and obstacles published (before the surface cloud).
LOAD_STAGES = ('handoff', 'decode', 'segment', 'encode', 'surface', 'labeled', 'publish', 'around',
               'around_without_surface', 'total', 'node_total', 'ground_published')
MB = 1024.0 * 1024.0


def load_bag_messages(path: Path = DATA_DIR / BAG_DIR, topic: str = BAG_TOPIC) -> list:
    """The bag's PointCloud2 frames as rclpy messages (the class the node subscribes with)."""
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2

    if not path.is_dir():
        sys.exit(f'bag not found: {path} (../shared/data beside the repository)')
    msgs = []
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for _, _, raw in reader.messages(connections=conns):
            msgs.append(deserialize_message(raw, PointCloud2))
    if not msgs:
        sys.exit(f'no messages on {topic} in {path}')
    return msgs


class NodeBench:
    """Node + publisher + /diagnostics listener in one private rclpy context."""

    def __init__(self, queue_size: int = 1, diag_period_s: float = 1.0, window: int = 100000,
                 executor: str = 'multi', node_process: bool = False):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        sys.path.insert(0, str(REPO))
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        # node_process: the node alone in a child process (as `ros2 run` starts it), this
        # process only publishes and listens; else the node shares this process (and its GIL)
        # with the publisher, the output subscription and the sampler thread
        self.child = NodeProcess(queue_size, diag_period_s, window) if node_process else None
        self.node = None if node_process else make_node(queue_size, diag_period_s, window,
                                                        self.context)
        self.peer = rclpy.create_node('bench_node_publisher', context=self.context)
        self.lock = threading.Lock()
        self.statuses = []  # (monotonic time, DiagnosticStatus) of our node
        self.outputs = 0
        self.peer.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        # Outputs are consumed (so the node really publishes to a matched subscriber) but only
        # counted: keeping them would make this process's RSS grow by design.
        from gp_ground_segmentation.ros.node import OUTPUT_QOS
        self.peer.create_subscription(PointCloud2, 'ground', self._on_output, OUTPUT_QOS)
        self.pub = self.peer.create_publisher(
            PointCloud2, 'points', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        # 'single' is what the node's main() spins; 'multi' is the test harness's executor
        self.executor = (SingleThreadedExecutor(context=self.context) if executor == 'single'
                         else MultiThreadedExecutor(num_threads=3, context=self.context))
        self.executor_name = ('SingleThreadedExecutor' if executor == 'single'
                              else 'MultiThreadedExecutor(3)')
        if node_process:
            self.executor_name = 'node in its own process (SingleThreadedExecutor)'
        if self.node is not None:
            self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 15.0
        while self.pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        if self.pub.get_subscription_count() == 0:
            raise RuntimeError('node subscription not discovered within 15 s')

    def _on_diag(self, arr):
        for s in arr.status:
            if s.name == 'ground_segmentation: processing':
                with self.lock:
                    self.statuses.append((time.monotonic(), s))

    def _on_output(self, _msg):
        with self.lock:
            self.outputs += 1

    def state(self, timings: bool = False) -> dict:
        """The node's frame counts, slot occupancy and queue size (``node_state``), and every
        frame's timings when asked: from the child over its pipe, or read here."""
        if self.child is not None:
            return self.child.query('timings' if timings else 'counts')
        return node_state(self.node, timings)

    def slot_len(self) -> int:
        return self.state()['slot']

    @property
    def queue_size(self) -> int:
        return self.state()['queue_size']

    def counts(self) -> tuple:
        """The node's frames (received, processed, dropped, failed) so far."""
        return _counts(self.state())

    def idle(self) -> bool:
        state = self.state()
        received, processed, dropped, failed = _counts(state)
        return processed + dropped + failed >= received and state['slot'] == 0

    def close(self):
        import rclpy
        self.executor.shutdown(timeout_sec=5.0)
        if self.node is not None:
            self.node.destroy_node()
        if self.child is not None:
            self.child.close()
        self.peer.destroy_node()
        rclpy.try_shutdown(context=self.context)


def node_state(node, timings: bool = False) -> dict:
    """Frame counts of a node's ProcessingWindow, its slot occupancy and size, and (``timings``)
    every frame's timings: what :meth:`NodeBench.state` returns (JSON-able)."""
    snap = node.window.snapshot()
    state = {k: snap[k] for k in ('frames_received', 'frames_processed', 'frames_dropped',
                                  'frames_failed')}
    # read-only peeks at the latest-wins slot
    state.update(slot=len(node._slot), queue_size=int(node._slot.maxlen))  # noqa: SLF001
    if timings:
        state['timings'] = snap['timings']
    return state


def _counts(state: dict) -> tuple:
    return tuple(state[f'frames_{k}'] for k in ('received', 'processed', 'dropped', 'failed'))


def make_node(queue_size: int, diag_period_s: float, window: int, context=None):
    """A GroundSegmentationNode with the benchmark's parameter overrides."""
    from rclpy.parameter import Parameter

    from gp_ground_segmentation.ros.node import GroundSegmentationNode
    return GroundSegmentationNode(context=context, parameter_overrides=[
        Parameter('queue_size', value=int(queue_size)),
        Parameter('diagnostics_period_s', value=float(diag_period_s)),
        # keep every frame's timings: medians over the whole run, not the last 50
        Parameter('diagnostics_window', value=int(window))])


class NodeProcess:
    """The node alone in a child process (``--as-node``), on this process's ROS_DOMAIN_ID.

    The child spins the node with a SingleThreadedExecutor (what ``main()`` spins) and answers
    one JSON line per request line on stdin: its frame counts and slot occupancy, or (request
    ``timings``) also every frame's timings. Its main thread waits in a blocking read between
    requests, so nothing but the node runs Python in that process.
    """

    def __init__(self, queue_size: int, diag_period_s: float, window: int):
        self.proc = subprocess.Popen(
            [sys.executable, __file__, '--as-node', str(queue_size), str(diag_period_s),
             str(window)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if self.proc.stdout.readline().strip() != 'ready':
            raise RuntimeError('the node process did not start')

    def query(self, what: str = 'counts') -> dict:
        self.proc.stdin.write(what + '\n')
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError('the node process exited')
        return json.loads(line)

    def close(self):
        self.proc.stdin.close()
        try:
            self.proc.wait(10.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def node_process_main(queue_size: str, diag_period_s: str, window: str) -> int:
    """The child of :class:`NodeProcess`."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    sys.path.insert(0, str(REPO))

    from gp_ground_segmentation.core.allocator import keep_freed_memory
    keep_freed_memory()  # as the node's main() does
    rclpy.init()
    node = make_node(int(queue_size), float(diag_period_s), int(window))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    print('ready', flush=True)
    for request in sys.stdin:
        print(json.dumps(node_state(node, request.strip() == 'timings'), default=float),
              flush=True)
    # stdin closed: exit now (as subscriber_main: a clean shutdown under a spinning daemon
    # thread only aborts noisily)
    os._exit(0)


class Sampler(threading.Thread):
    """Max slot occupancy every ``slot_period_s`` and RSS every ``rss_period_s``."""

    def __init__(self, bench: NodeBench, slot_period_s=0.001, rss_period_s=1.0):
        super().__init__(daemon=True)
        self.bench = bench
        self.slot_period_s, self.rss_period_s = slot_period_s, rss_period_s
        self.max_slot = 0
        self.slot_samples = 0
        self.rss = []  # (seconds since start, bytes)
        # Wake-up lateness of this thread: a stall of the whole interpreter (GIL held by
        # another thread) or of the machine shows here as a late wake-up.
        self.stalls = []  # ms late, for every wake-up more than 20 ms late
        self.stop_event = threading.Event()
        self.t0 = time.monotonic()

    def run(self):
        next_rss = self.t0
        expected = time.monotonic()
        while not self.stop_event.is_set():
            now = time.monotonic()
            if now - expected > 0.020:
                self.stalls.append((now - expected) * 1e3)
            if self.bench.child is None:  # a child node is asked only at each publish
                self.max_slot = max(self.max_slot, self.bench.slot_len())
                self.slot_samples += 1
            if now >= next_rss:
                self.rss.append((now - self.t0, rss_bytes()[0]))
                next_rss += self.rss_period_s
            expected = time.monotonic() + self.slot_period_s
            time.sleep(self.slot_period_s)

    def stop(self):
        self.stop_event.set()
        self.join(5.0)
        self.rss.append((time.monotonic() - self.t0, rss_bytes()[0]))


def publish_loop(bench: NodeBench, msgs: list, rate_hz: float, duration_s: float,
                 sampler: Sampler | None = None, on_tick=None) -> dict:
    """Publish ``msgs`` round-robin on a fixed schedule (no catch-up bursts when late)."""
    period = 1.0 / rate_hz
    t0 = time.monotonic()
    next_t = t0
    sent = 0
    late = 0
    while True:
        now = time.monotonic()
        if now - t0 >= duration_s:
            break
        if now < next_t:
            time.sleep(next_t - now)
        elif now - next_t > period:
            late += 1
            next_t = now  # the publisher itself fell behind: skip, do not burst
        msg = msgs[sent % len(msgs)]
        stamp = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp // 10**9, stamp % 10**9
        bench.pub.publish(msg)
        sent += 1
        if sampler is not None:
            sampler.max_slot = max(sampler.max_slot, bench.slot_len())
        if on_tick is not None:
            on_tick(sent, time.monotonic() - t0)
        next_t += period
    return {'published': sent, 'seconds': time.monotonic() - t0, 'publisher_late': late}


def drain(bench: NodeBench, timeout_s: float = 10.0) -> None:
    """Wait until every received frame has a fate (processed, dropped or failed)."""
    deadline = time.monotonic() + timeout_s
    while not bench.idle() and time.monotonic() < deadline:
        time.sleep(0.01)


def with_sums(timing: dict) -> dict:
    """A frame's timings plus ``around`` and ``node_total`` (LOAD_STAGES) when it has the
    node's stages."""
    if 'handoff' not in timing or 'publish' not in timing:
        return timing
    around = timing['handoff'] + timing['total'] - timing['segment']
    out = dict(timing, around=around,
               node_total=timing['handoff'] + timing['total'] + timing['publish'])
    if 'surface' in timing:  # what the node adds with publish_ground_surface off
        out['around_without_surface'] = around - timing['surface']
    return out


def stage_stats(timings: list, stages=STAGES) -> dict:
    """stage -> (median, p95, n, max) ms over per-frame timing dicts."""
    out = {}
    timings = [with_sums(t) for t in timings]
    for stage in stages:
        v = np.array([t[stage] for t in timings if stage in t], dtype=float)
        v = v[np.isfinite(v)]
        if v.size:
            out[stage] = (float(np.median(v)), float(np.percentile(v, 95)), int(v.size),
                          float(v.max()))
    return out


SUBSCRIBER_TOPICS = ('ground', 'obstacles', 'ground_surface')
LABELED_TOPIC = 'labeled'  # with --labeled


def subscriber_topics(labeled: bool) -> tuple:
    return SUBSCRIBER_TOPICS + ((LABELED_TOPIC,) if labeled else ())


def subscriber_main(topics: tuple = SUBSCRIBER_TOPICS) -> int:
    """One extra subscriber process (``--as-subscriber``): counts the messages on the output
    topics until stdin closes, then prints the counts as one JSON line."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2
    sys.path.insert(0, str(REPO))
    from gp_ground_segmentation.ros.node import OUTPUT_QOS

    rclpy.init()
    node = rclpy.create_node(f'bench_subscriber_{os.getpid()}')
    counts = dict.fromkeys(topics, 0)

    def counter(topic):
        def on_msg(_msg):
            counts[topic] += 1
        return on_msg
    for topic in topics:
        node.create_subscription(PointCloud2, topic, counter(topic), OUTPUT_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    print('ready', flush=True)
    sys.stdin.read()  # the parent closes stdin to stop us
    print(json.dumps(counts), flush=True)
    # Exit now: a clean rclpy shutdown while the daemon thread still spins aborts with
    # 'terminate called without an active exception' (noise only; nothing is left to save).
    os._exit(0)


def start_subscribers(bench: NodeBench, count: int, topics: tuple = SUBSCRIBER_TOPICS) -> list:
    """``count`` subscriber processes on this process's ROS_DOMAIN_ID, each matched to all
    ``topics`` before this returns."""
    labeled = ['--labeled'] if LABELED_TOPIC in topics else []
    procs = [subprocess.Popen([sys.executable, __file__, '--as-subscriber'] + labeled,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for _ in range(count)]
    for proc in procs:
        if proc.stdout.readline().strip() != 'ready':
            raise RuntimeError('a subscriber process did not start')
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        if all(bench.peer.count_subscribers(f'/{t}') >= count for t in topics):
            return procs
        time.sleep(0.05)
    raise RuntimeError('subscriber processes not discovered within 20 s')


def stop_subscribers(procs: list) -> list:
    """Close the processes' stdin; their message counts per topic."""
    counts = []
    for proc in procs:
        out, _ = proc.communicate('', timeout=20.0)
        lines = [line for line in out.splitlines() if line.startswith('{')]
        counts.append(json.loads(lines[-1]) if lines else {})
    return counts


def last_status(bench: NodeBench, after: float):
    """The first /diagnostics status received after monotonic time ``after`` (wait <= 3 s)."""
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        with bench.lock:
            fresh = [s for t, s in bench.statuses if t > after]
        if fresh:
            return fresh[0]
        time.sleep(0.02)
    return None


LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}


def level_name(status) -> str:
    """'OK'/'WARN'/'ERROR'/'STALE' of a DiagnosticStatus (its level is a one-byte bytes)."""
    if status is None:
        return 'none'
    level = status.level
    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
    return LEVELS.get(level, str(level))


def status_dict(status) -> dict:
    return {kv.key: kv.value for kv in status.values} if status is not None else {}


# ------------------------------------------------------------------------------------ modes

def run_latency(msgs: list, duration_s: float, rate_hz: float = 10.0, warmup_s: float = 3.0,
                slot_period_s: float = 0.005, executor: str = 'single', subscribers: int = 0,
                node_process: bool = False, labeled: bool = False):
    bench = NodeBench(queue_size=1, executor=executor, node_process=node_process)
    procs = []
    topics = subscriber_topics(labeled)
    try:
        procs = start_subscribers(bench, subscribers, topics)
        load_at_start = os.getloadavg()
        sampler = Sampler(bench, slot_period_s)
        sampler.start()
        mark = {}

        def tick(_sent, elapsed):
            if 'warm' not in mark and elapsed >= warmup_s:
                mark['warm'] = bench.counts()
        pub = publish_loop(bench, msgs, rate_hz, duration_s, sampler, tick)
        drain(bench)
        t_end = time.monotonic()
        sampler.stop()
        status = last_status(bench, t_end)
        snap = bench.state(timings=True)
        subscriber_counts, procs = stop_subscribers(procs), []
        warm = mark.get('warm', (0, 0, 0, 0))
        timings = snap['timings'][warm[1]:]  # window holds every frame (window >> frames)
        stats = stage_stats(timings, LOAD_STAGES if subscribers else STAGES)
        received = snap['frames_received'] - warm[0]
        processed = snap['frames_processed'] - warm[1]
        dropped = snap['frames_dropped'] - warm[2]
        failed = snap['frames_failed'] - warm[3]
        steady_s = pub['seconds'] - warmup_s
        result = {
            'rate_hz': rate_hz, 'duration_s': pub['seconds'], 'warmup_s': warmup_s,
            'published': pub['published'], 'publisher_late': pub['publisher_late'],
            'received_total': snap['frames_received'],
            'processed_total': snap['frames_processed'],
            'dropped_total': snap['frames_dropped'], 'failed_total': snap['frames_failed'],
            'received': received, 'processed': processed, 'dropped': dropped, 'failed': failed,
            'processed_hz': processed / steady_s if steady_s > 0 else float('nan'),
            'stages': stats, 'max_slot': sampler.max_slot, 'queue_size': bench.queue_size,
            'executor': bench.executor_name, 'node_process': node_process,
            'stalls': list(sampler.stalls),
            'status_level': level_name(status),
            'status_message': status.message if status else 'no status',
            'diag': status_dict(status), 'points': msgs[0].width,
            'subscribers': subscribers, 'subscriber_counts': subscriber_counts,
            'subscriber_topics': topics,
            'load_at_start': load_at_start,
            'fastdds_profile': os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE',
                                              'none (Fast DDS defaults)'),
        }
        first = snap['timings'][0] if snap['timings'] else {}
        result['cold_ms'] = first.get('total', float('nan'))
        # steady state: after warm-up, every frame received was processed, none dropped/failed
        # (a frame in flight at the warm-up mark makes processed = received + 1 there)
        result['sustained'] = (dropped == 0 and failed == 0 and processed >= received
                               and result['processed_hz'] >= 0.95 * rate_hz)
        return result
    finally:
        for proc in procs:
            proc.kill()
        bench.close()


def run_overload(msgs: list, duration_s: float, rate_hz: float = 50.0, warmup_s: float = 10.0,
                 queue_size: int = 1, slot_period_s: float = 0.005, executor: str = 'single',
                 window: int = 100000):
    bench = NodeBench(queue_size=queue_size, executor=executor, window=window)
    try:
        w = bench.node.window
        sampler = Sampler(bench, slot_period_s)
        sampler.start()
        pub = publish_loop(bench, msgs, rate_hz, duration_s, sampler)
        t_pub_end = time.monotonic()
        snap_at_end = w.snapshot()
        drain(bench)
        sampler.stop()
        status = last_status(bench, time.monotonic())
        snap = w.snapshot()
        rss = np.array(sampler.rss, dtype=float)
        start_mb = rss[0, 1] / MB
        warm_idx = int(np.searchsorted(rss[:, 0], warmup_s))
        warm_idx = min(warm_idx, len(rss) - 1)
        warm_mb = rss[warm_idx, 1] / MB
        end_mb = rss[-1, 1] / MB
        after = rss[warm_idx:]
        slope = (float(np.polyfit(after[:, 0] / 60.0, after[:, 1] / MB, 1)[0])
                 if len(after) >= 3 else float('nan'))
        half = rss[rss[:, 0] >= rss[-1, 0] / 2.0]  # allocator plateaus slowly: the 2nd half
        slope_half = (float(np.polyfit(half[:, 0] / 60.0, half[:, 1] / MB, 1)[0])
                      if len(half) >= 3 else float('nan'))
        seconds = pub['seconds']
        with bench.lock:
            levels = sorted({level_name(s) for _, s in bench.statuses})
            outputs = bench.outputs
        diag = status_dict(status)
        return {
            'rate_hz': rate_hz, 'duration_s': seconds, 'warmup_s': warmup_s,
            'published': pub['published'], 'publisher_late': pub['publisher_late'],
            'input_hz': pub['published'] / seconds,
            'received': snap['frames_received'],
            'received_hz': snap_at_end['frames_received'] / seconds,
            'processed': snap['frames_processed'],
            'processed_hz': snap_at_end['frames_processed'] / seconds,
            'dropped': snap['frames_dropped'], 'failed': snap['frames_failed'],
            'conserved': (snap['frames_processed'] + snap['frames_dropped']
                          + snap['frames_failed'] == snap['frames_received']),
            'diag_dropped': diag.get('frames_dropped', 'n/a'),
            'diag_level': level_name(status),
            'diag_message': status.message if status else 'no status',
            'levels_seen': levels, 'ground_outputs': outputs,
            'max_slot': sampler.max_slot, 'slot_samples': sampler.slot_samples,
            'executor': bench.executor_name,
            'stalls': list(sampler.stalls),
            'queue_size': bench.queue_size, 'slot_period_ms': slot_period_s * 1e3,
            'rss_start_mb': start_mb, 'rss_warm_mb': warm_mb, 'rss_end_mb': end_mb,
            'rss_max_mb': float(rss[:, 1].max() / MB), 'rss_slope_mb_per_min': slope,
            'rss_slope_half_mb_per_min': slope_half,
            'rss_samples': len(rss), 'stages': stage_stats(snap['timings']),
            'rss_trace': [(float(t), float(b) / MB) for t, b in rss[::10]] + [
                (float(rss[-1, 0]), float(rss[-1, 1]) / MB)],
            'drain_s': time.monotonic() - t_pub_end,
        }
    finally:
        bench.close()


# ------------------------------------------------------------------------------------ output

def stalls_text(r: dict) -> str:
    st = np.asarray(r['stalls'], dtype=float)
    if st.size == 0:
        return 'no wake-up of the sampler thread was more than 20 ms late'
    return (f'the sampler thread woke more than 20 ms late {st.size} times (more than 100 ms: '
            f'{int((st > 100).sum())}; worst {st.max():.0f} ms): the whole process (GIL) or '
            'the machine stalled then')


def frames_table(r: dict, extra: dict | None = None) -> str:
    """Frame counts of a latency run (one row), plus ``extra`` column -> value."""
    extra = extra or {}
    return markdown_table(
        ['published', 'received', 'processed', 'dropped (all / after warm-up)', 'failed',
         'processed Hz (after warm-up)', 'max slot / queue_size'] + list(extra),
        [[fmt(r['published']), fmt(r['received_total']), fmt(r['processed_total']),
          f"{fmt(r['dropped_total'])} / {fmt(r['dropped'])}", fmt(r['failed_total']),
          fmt(r['processed_hz'], 2), f"{r['max_slot']} / {r['queue_size']}"]
         + list(extra.values())])


def latency_markdown(r: dict) -> str:
    rows = [[stage, fmt(r['stages'][stage][0]), fmt(r['stages'][stage][1]),
             fmt(r['stages'][stage][3]), fmt(r['stages'][stage][2])]
            for stage in STAGES if stage in r['stages']]
    cold = r['cold_ms']
    verdict = 'yes' if r['sustained'] else 'NO'
    med_total = r['stages'].get('total', (float('nan'),))[0]
    return '\n'.join([
        f"### Latency at {r['rate_hz']:g} Hz (real time), {r['duration_s']:.0f} s, "
        f"{r['points']:,}-point KITTI frames, {r['executor']}",
        '',
        f"Per-frame times from the node's ProcessingWindow (what /diagnostics summarises), "
        f"first {r['warmup_s']:g} s excluded (cold theta on the first frame). "
        '`total` = decode + segment + encode + input checks (wall time of '
        '`pipeline.process_cloud`).',
        '',
        markdown_table(['stage', 'ms median', 'ms p95', 'ms max', 'frames'], rows),
        '',
        frames_table(r, {'sustained 10 Hz, no drops (after warm-up)': verdict}),
        '',
        f"- Target: decode + segment + encode <= 35 ms median: measured "
        f"{fmt(med_total)} ms -> {'met' if med_total <= 35.0 else 'NOT met'}; sustains 10 Hz "
        f"with no drops: {verdict}.",
        f"- The first frame (cold start: theta learned with up to 40 likelihood evaluations) "
        f"took {fmt(cold)} ms; frames arriving meanwhile are dropped by the latest-wins slot "
        f"({fmt(r['dropped_total'] - r['dropped'])} dropped during warm-up).",
        f"- Stalls: {stalls_text(r)}.",
        f"- Last /diagnostics status: {r['status_level']} ({r['status_message']}).",
        transport_text(r),
    ])


def transport_text(r: dict) -> str:
    """Where the node ran, the Fast DDS profile, and the frames DDS lost before the node."""
    where = ('the node alone in a child process' if r.get('node_process')
             else 'the node in this process')
    profile = r['fastdds_profile'].replace(str(REPO) + os.sep, '')
    return (f"- {where}; FASTRTPS_DEFAULT_PROFILES_FILE: {profile}; published but "
            f"never received by the node (lost in DDS): {r['published'] - r['received_total']}.")


def load_markdown(r: dict) -> str:
    """The latency table of a run with extra subscriber processes (issue 14's load test)."""
    rows = [[stage, fmt(r['stages'][stage][0]), fmt(r['stages'][stage][1]),
             fmt(r['stages'][stage][3]), fmt(r['stages'][stage][2])]
            for stage in LOAD_STAGES if stage in r['stages']]
    nan = (float('nan'),) * 4
    around, node_total = r['stages'].get('around', nan), r['stages'].get('node_total', nan)
    topics = r.get('subscriber_topics', SUBSCRIBER_TOPICS)
    received = {t: sorted(c.get(t, 0) for c in r['subscriber_counts']) for t in topics}
    load = ', '.join(f'{v:.2f}' for v in r['load_at_start'])
    no_drops = r['dropped'] == 0 and r['failed'] == 0
    return '\n'.join([
        f"### Load: {r['rate_hz']:g} Hz for {r['duration_s']:.0f} s, {r['points']:,}-point "
        f"KITTI frames, {r['subscribers']} extra subscriber processes, {r['executor']}",
        '',
        f"Each subscriber process (rclpy, own executor) takes {', '.join(topics)} "
        f"with the node's RELIABLE output QoS; default node parameters "
        f"(publish_ground_surface on). Load average (1, 5, 15 min) when the publishing "
        f"started: {load} (other jobs may share the 2 cores). First "
        f"{r['warmup_s']:g} s excluded. Stages: handoff = slot wait (subscription callback "
        'to worker), decode, segment, encode (both subset clouds, the surface cloud and, when '
        'subscribed, the labelled cloud), surface and labeled (their parts of encode), publish '
        '(the publish calls); total = decode + '
        'segment + encode + input checks (process_cloud); around = handoff + total - segment '
        '(everything around segment() but the publish calls); around_without_surface = around - '
        'surface; node_total = handoff + total + publish; ground_published = the node\'s own '
        'callback-to-published time of ground and obstacles, which it publishes before it '
        'builds the surface cloud. Per-frame sums, then percentiles.',
        '',
        markdown_table(['stage', 'ms median', 'ms p95', 'ms max', 'frames'], rows),
        '',
        frames_table(r),
        '',
        '- Messages received by the subscriber processes (per process, sorted): '
        + '; '.join(f"{t} {', '.join(str(c) for c in received[t])}"
                    for t in topics) + '.',
        f"- Targets: no drops after warm-up: {'met' if no_drops else 'NOT met'}; "
        f"node_total p95 <= 50 ms: {fmt(node_total[1])} ms -> "
        f"{'met' if node_total[1] <= 50.0 else 'NOT met'}; around segment() <= 3 ms median: "
        f"{fmt(around[0])} ms -> {'met' if around[0] <= 3.0 else 'NOT met'}.",
        f"- Stalls: {stalls_text(r)}.",
        f"- Last /diagnostics status: {r['status_level']} ({r['status_message']}).",
        transport_text(r),
    ])


def overload_markdown(r: dict) -> str:
    rows = [[f"{r['rate_hz']:g} Hz x {r['duration_s']:.0f} s", fmt(r['input_hz'], 1),
             fmt(r['received_hz'], 1), fmt(r['processed_hz'], 1), fmt(r['published']),
             fmt(r['received']), fmt(r['processed']), fmt(r['dropped']), r['diag_dropped'],
             fmt(r['failed']), f"{r['max_slot']} / {r['queue_size']}"]]
    rss_rows = [[fmt(r['rss_start_mb']), fmt(r['rss_warm_mb']), fmt(r['rss_end_mb']),
                 fmt(r['rss_max_mb']), fmt(r['rss_slope_mb_per_min'], 2),
                 fmt(r['rss_slope_half_mb_per_min'], 2), fmt(r['rss_samples'])]]
    total = r['stages'].get('total', (float('nan'), float('nan'), 0, float('nan')))
    return '\n'.join([
        f"### Overload: {r['rate_hz'] / 10.0:g}x real time ({r['rate_hz']:g} Hz) for "
        f"{r['duration_s']:.0f} s, {r['executor']}",
        '',
        markdown_table(['publish', 'input Hz (published)', 'received Hz', 'processed Hz',
                        'published', 'received', 'processed', 'dropped (node)',
                        'dropped (/diagnostics)', 'failed', 'max slot / queue_size'], rows),
        '',
        markdown_table(['RSS start MB', f"RSS after {r['warmup_s']:g} s warm-up MB",
                        'RSS end MB', 'RSS max MB', 'RSS slope after warm-up MB/min',
                        'RSS slope, 2nd half of the run MB/min', 'samples (1/s)'], rss_rows),
        '',
        f"- processed + dropped + failed == received: {'yes' if r['conserved'] else 'NO'}; "
        f"slot occupancy sampled {r['slot_samples']:,} times (every ~{r['slot_period_ms']:g} "
        'ms and at each publish).',
        f"- /diagnostics after the run: {r['diag_level']} ({r['diag_message']}); levels seen "
        f"during the run: {', '.join(r['levels_seen']) or 'none'}.",
        f"- Stalls: {stalls_text(r)}.",
        '- RSS every 10 s (s: MB): ' + ', '.join(f'{t:.0f}: {mb:.0f}' for t, mb in r['rss_trace'])
        + '.',
        f"- The publisher fell more than one period behind its schedule {fmt(r['publisher_late'])}"
        ' times (it shares the GIL and the 2 cores with the node and DDS; its schedule then '
        'restarts, no catch-up burst): the input rate is what was actually published.',
        f"- Under overload the node's total per frame: median {fmt(total[0])} ms, p95 "
        f"{fmt(total[1])} ms over {total[2]} frames (the publisher and DDS share the 2 cores).",
        '- RSS is this whole process (node, publisher, Fast DDS, Python); it starts after the '
        'bag is loaded and the node is up; "start" is the first sample, at the first publish.',
    ])


KEYS = ('latency-single', 'latency-multi', 'latency-process', 'load-single', 'load-multi',
        'load-process', 'load-single-labeled', 'load-multi-labeled', 'load-process-labeled',
        'overload-single', 'overload-multi')


def _sub_blocks(text: str) -> dict:
    """Parse ``<!-- mode -->`` ... ``<!-- /mode -->`` sub-blocks of an existing section."""
    out = {}
    for mode in KEYS:
        b, e = f'<!-- {mode} -->', f'<!-- /{mode} -->'
        if b in text and e in text:
            out[mode] = text.split(b, 1)[1].split(e, 1)[0].strip('\n')
    return out


def write_results(blocks: dict) -> None:
    old = RESULTS.read_text() if RESULTS.exists() else ''
    begin, end = f'<!-- BEGIN {SECTION} -->', f'<!-- END {SECTION} -->'
    previous = _sub_blocks(old.split(begin, 1)[1].split(end, 1)[0]) \
        if begin in old and end in old else {}
    previous.update(blocks)
    parts = ['## The node over rclpy: latency at 10 Hz and 5x overload (`bench_node.py`)', '',
             '- Each sub-section below says when, on what and by which command it was measured '
             '(a run rewrites only the sub-sections of its modes).',
             '- One process: GroundSegmentationNode + a publisher node in a private rclpy '
             'context (Fast DDS, own ROS_DOMAIN_ID, localhost), spun in a background thread by '
             "the executor named in each heading (SingleThreadedExecutor is what the node's "
             'main() uses); the 6 KITTI 00 frames of the bag published round-robin to `points` '
             'with fresh stamps, RELIABLE writer -> the node\'s best-effort subscription; default '
             'node parameters (queue_size 1). Headings saying "node in its own process" '
             '(`--node-process`): the node alone in a child process, as `ros2 run` starts it, '
             'and this process only publishes and listens. This process and the node\'s child '
             "set glibc's malloc thresholds as the node's main() does "
             '(`core/allocator.py`).', '']
    for mode in KEYS:
        if mode in previous:
            parts += [f'<!-- {mode} -->', previous[mode], f'<!-- /{mode} -->', '']
    update_results_section(RESULTS, SECTION, '\n'.join(parts))
    print(f'wrote section {SECTION!r} of {RESULTS}')


def argument_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--latency', action='store_true', help='10 Hz latency run')
    ap.add_argument('--overload', action='store_true', help='5x real time overload run')
    ap.add_argument('--latency-s', type=float, default=30.0, help='latency run length (s)')
    ap.add_argument('--overload-s', type=float, default=60.0, help='overload run length (s)')
    ap.add_argument('--overload-hz', type=float, default=50.0, help='overload publish rate (Hz)')
    ap.add_argument('--overload-window', type=int, default=100000,
                    help="with --overload: the node's diagnostics_window (frames). The default "
                         "keeps every frame's timings for the table, and they are part of the "
                         "RSS; the node's own default, 50, shows the RSS of a deployed node")
    ap.add_argument('--slot-sample-ms', type=float, default=5.0,
                    help='slot occupancy sampling period (ms); it is also sampled at every '
                         'publish')
    ap.add_argument('--executor', choices=('single', 'multi', 'both'), default='single',
                    help="single: SingleThreadedExecutor, as the node's main() spins it; multi: "
                         'MultiThreadedExecutor(3), as the test harness does; both: one run each')
    ap.add_argument('--subscribers', type=int, default=0,
                    help='with --latency: this many extra subscriber processes on the outputs')
    ap.add_argument('--node-process', action='store_true',
                    help='with --latency: run the node alone in a child process (as ros2 run '
                         'does) instead of in this process beside the publisher')
    ap.add_argument('--labeled', action='store_true',
                    help='with --subscribers: the subscriber processes also take the labeled '
                         'cloud, which the node builds only while someone subscribes')
    ap.add_argument('--as-subscriber', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--as-node', nargs=3, help=argparse.SUPPRESS)
    ap.add_argument('--no-write', action='store_true', help='print only, keep RESULTS.md')
    return ap


def main(argv=None) -> int:
    ap = argument_parser()
    args = ap.parse_args(argv)
    if args.as_subscriber:
        return subscriber_main(subscriber_topics(args.labeled))
    if args.as_node:
        return node_process_main(*args.as_node)
    if args.subscribers < 0:
        ap.error(f'--subscribers must be >= 0, got {args.subscribers}')
    if args.node_process and (args.overload or args.executor != 'single'):
        ap.error('--node-process runs the latency mode only, with the node spun by a '
                 "SingleThreadedExecutor: drop --overload and --executor")
    args.latency |= args.node_process
    if args.node_process:
        # between processes Fast DDS's default 512 KB shared-memory segment loses most 2 MB
        # clouds (RESULTS.md); the README tells users to set this profile, and so do we, unless
        # the variable is set (set and empty: Fast DDS's defaults, to see the losses)
        if os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE') == '':
            del os.environ['FASTRTPS_DEFAULT_PROFILES_FILE']
        else:
            os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                                  str(REPO / 'config' / 'fastdds_large_shm.xml'))
    if not (args.latency or args.overload):
        args.latency = args.overload = True
    # this process holds the node (or publishes to it): malloc as the node's main() sets it
    sys.path.insert(0, str(REPO))
    from gp_ground_segmentation.core.allocator import keep_freed_memory
    keep_freed_memory()
    msgs = load_bag_messages()
    print(f'{len(msgs)} frames of {msgs[0].width:,} points ({len(msgs[0].data) / MB:.1f} MB '
          f'each); ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}', flush=True)
    blocks = {}
    measured = machine_markdown(command_line()).rstrip('\n')  # heads each sub-section
    executors = ('single', 'multi') if args.executor == 'both' else (args.executor,)
    for executor in executors:
        if args.latency:
            r = run_latency(msgs, args.latency_s, slot_period_s=args.slot_sample_ms / 1e3,
                            executor=executor, subscribers=args.subscribers,
                            node_process=args.node_process, labeled=args.labeled)
            key = (f"{'load' if args.subscribers else 'latency'}-"
                   f"{'process' if args.node_process else executor}"
                   f"{'-labeled' if args.labeled and args.subscribers else ''}")
            blocks[key] = (load_markdown(r) if args.subscribers else latency_markdown(r)) \
                .replace('\n\n', f'\n\n{measured}\n\n', 1)
            print(blocks[key] + '\n', flush=True)
        if args.overload:
            r = run_overload(msgs, args.overload_s, rate_hz=args.overload_hz,
                             slot_period_s=args.slot_sample_ms / 1e3, executor=executor,
                             window=args.overload_window)
            blocks[f'overload-{executor}'] = overload_markdown(r).replace(
                '\n\n', f'\n\n{measured}\n\n', 1)
            print(blocks[f'overload-{executor}'] + '\n', flush=True)
    if not args.no_write:
        write_results(blocks)
    return 0


if __name__ == '__main__':
    sys.exit(main())
