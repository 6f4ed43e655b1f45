# SPDX-License-Identifier: Apache-2.0
"""Shared test set-up: an isolated DDS domain, real data location, and an rclpy test harness.

ROS_DOMAIN_ID is one no other test session on this machine holds (several developers, CI, a
helper's clone), so that concurrent sessions never see each other's topics, and discovery is kept
on localhost. Both must be set before any rclpy context is initialised, hence at import time here.
"""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from scenes.real_data import DATA_DIR


def _claim_domain_id(first: int = 1, last: int = 100):
    """A DDS domain id in first..last that no other process holding this claim uses, and the
    open lock file descriptor that holds it (kept open for the whole session; the lock goes
    with the process). A pid-derived id alone put two sessions in one domain about once in 100
    pairs. Starts at the pid-derived id; an id whose lock file cannot be opened (another user's,
    say) counts as taken; falls back to the pid-derived id when every id is taken or the
    temporary directory is unusable."""
    import fcntl
    import tempfile
    span = last - first + 1
    start = os.getpid() % span
    try:
        folder = Path(tempfile.gettempdir())
    except OSError:  # no usable temporary directory: no claims, the pid-derived id
        return first + start, None
    for k in range(span):
        domain = first + (start + k) % span
        path = folder / f'gp_ground_seg_domain_{domain}.lock'
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except PermissionError:  # another user's file: a read-only descriptor locks too
            try:
                fd = os.open(path, os.O_RDONLY)
            except OSError:
                continue
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return domain, fd
    return first + start, None


# Domain ids 1..100 are valid for every RMW; 0 (the default) is left to interactive use.
_DOMAIN_ID, _DOMAIN_LOCK = _claim_domain_id()
os.environ['ROS_DOMAIN_ID'] = str(_DOMAIN_ID)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

REPO = Path(__file__).resolve().parents[1]
DATA = DATA_DIR  # scenes/real_data.py finds ../shared/data
BAG = DATA / 'kitti00_velodyne_points'
NODE_MODULE = 'gp_ground_segmentation.ros.node'


def module_env(extra=None) -> dict:
    """Environment of a child ``python -m``: unbuffered output (lines arrive as printed) and
    this checkout first on PYTHONPATH, plus ``extra``."""
    env = dict(os.environ, PYTHONUNBUFFERED='1', **(extra or {}))
    env['PYTHONPATH'] = os.pathsep.join([str(REPO), env.get('PYTHONPATH', '')])
    return env


def start_module(module: str, *args, env_extra=None, stderr=subprocess.STDOUT, **kwargs):
    """``python -m module args`` as a text Popen (stdout piped, stderr into it by default)."""
    return subprocess.Popen([sys.executable, '-m', module, *args], stdout=subprocess.PIPE,
                            stderr=stderr, text=True, env=module_env(env_extra), **kwargs)


def lines_until(proc, stream, marker: str, timeout: float) -> list:
    """Lines of ``stream`` (one of ``proc``'s pipes) up to the first holding ``marker``. A
    process that has not printed it after ``timeout`` s is killed (its output then ends): a
    failure naming what it printed, not a hung test run."""
    lines = []
    watchdog = threading.Timer(timeout, proc.kill)
    watchdog.start()
    try:
        for line in stream:
            lines.append(line)
            if marker in line:
                return lines
    finally:
        watchdog.cancel()
    raise AssertionError(f'no {marker!r} within {timeout:.0f} s: {"".join(lines)}')


def wait_listening(proc, timeout=300.0) -> list:
    """Lines of a started node's output up to its 'listening on' line (it is up)."""
    return lines_until(proc, proc.stdout, 'listening on', timeout)


@pytest.fixture(scope='session')
def kitti_msgs():
    """The six real KITTI PointCloud2 frames of the shared bag, as rclpy messages."""
    if not BAG.is_dir():
        pytest.skip(f'real data not found: {BAG} (../shared/data beside the repo)')
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2

    msgs = []
    with AnyReader([BAG]) as reader:
        conns = [c for c in reader.connections if c.topic == '/velodyne_points']
        for _, _, raw in reader.messages(connections=conns):
            msgs.append(deserialize_message(raw, PointCloud2))
    assert msgs, 'bag holds no /velodyne_points messages'
    return msgs


@pytest.fixture(params=['compiled', 'numpy'])
def split_path(request, monkeypatch):
    """cloud.split_cloud (and so process_cloud's output clouds) through its compiled pass
    (loaded first; its numpy twin is made to fail, so a test cannot pass on the twin) or
    through the twin (the compiled pass taken away)."""
    from gp_ground_segmentation.core import compiled
    from gp_ground_segmentation.ros import cloud, pipeline
    if request.param == 'numpy':
        monkeypatch.setattr(cloud, '_split_rows_compiled', None)
        return request.param
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    pipeline.warm_up()  # queues the pass's compilation
    assert compiled.wait(300.0) and not compiled.failed(cloud._split_rows_compiled)

    def twin_must_not_run(*args):
        raise AssertionError('the numpy twin ran instead of the compiled pass')
    monkeypatch.setattr(cloud, '_split_rows', twin_must_not_run)
    return request.param


def assert_output_like_input(inp, out):
    """An output cloud keeps the input's header and field layout, as one unorganized row."""
    assert out.header.stamp == inp.header.stamp
    assert out.header.frame_id == inp.header.frame_id
    assert [(f.name, f.offset, f.datatype, f.count) for f in out.fields] == \
        [(f.name, f.offset, f.datatype, f.count) for f in inp.fields]
    assert out.point_step == inp.point_step and out.is_bigendian == inp.is_bigendian
    assert out.height == 1
    assert out.row_step == out.width * out.point_step == len(out.data)


def quaternion_of(matrix):
    """(x, y, z, w) of a rotation matrix whose trace is > -1 (rotations below 180 degrees)."""
    import math

    import numpy as np
    w = math.sqrt(1.0 + np.trace(matrix)) / 2.0
    return ((matrix[2, 1] - matrix[1, 2]) / (4 * w), (matrix[0, 2] - matrix[2, 0]) / (4 * w),
            (matrix[1, 0] - matrix[0, 1]) / (4 * w), w)


def wait_for(predicate, timeout=20.0, period=0.01):
    """Poll ``predicate`` until true or ``timeout`` (s); return its last value."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > deadline:
            return value
        time.sleep(period)


class RosHarness:
    """A GroundSegmentationNode plus a peer node (publisher of 'points', subscriber of the
    outputs and /diagnostics), spun by a MultiThreadedExecutor in a background thread, all in a
    private rclpy Context. ``labeled``: the peer also subscribes to 'labeled' (the node builds
    that cloud only while someone does); ``imu_topic``: the peer gets a sensor_msgs/Imu
    publisher there (``imu_pub``), matched to the node's subscription when the node has one."""

    def __init__(self, node_kwargs=None, context_args=None, labeled=False, imu_topic=None):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Imu, PointCloud2

        from gp_ground_segmentation.ros.node import OUTPUT_QOS, GroundSegmentationNode

        self.context = rclpy.Context()
        rclpy.init(args=context_args, context=self.context)
        self.node = None
        self.peer = None
        self.executor = None
        self.thread = None
        self._stop_spinning = threading.Event()
        try:
            self.node = GroundSegmentationNode(context=self.context, **(node_kwargs or {}))
            self.peer = rclpy.create_node('gp_test_peer', context=self.context)
            self.lock = threading.Lock()
            self.ground, self.obstacles, self.diagnostics = [], [], []
            self.surface, self.labeled = [], []
            # The node's reliable output matched with a deep reader: a loaded machine that
            # runs the peer's callbacks late must not lose an output in the peer's own history.
            deep_reader = QoSProfile(depth=100, reliability=OUTPUT_QOS.reliability,
                                     durability=OUTPUT_QOS.durability)
            self.peer.create_subscription(PointCloud2, 'ground', self._collect(self.ground),
                                          deep_reader)
            self.peer.create_subscription(PointCloud2, 'obstacles',
                                          self._collect(self.obstacles), deep_reader)
            self.peer.create_subscription(PointCloud2, 'ground_surface',
                                          self._collect(self.surface), deep_reader)
            self.peer.create_subscription(DiagnosticArray, '/diagnostics',
                                          self._collect(self.diagnostics), 10)
            if labeled:
                self.peer.create_subscription(PointCloud2, 'labeled',
                                              self._collect(self.labeled), deep_reader)
            self.imu_pub = None if imu_topic is None else self.peer.create_publisher(
                Imu, imu_topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
            # A RELIABLE writer matches the best-effort subscription (effective: best effort).
            self.pub = self.peer.create_publisher(
                PointCloud2, 'points', QoSProfile(depth=10,
                                                  reliability=ReliabilityPolicy.RELIABLE))
            self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
            self.executor.add_node(self.node)
            self.executor.add_node(self.peer)
            self.thread = threading.Thread(target=self._spin, daemon=True)
            self.thread.start()
            assert wait_for(lambda: self.pub.get_subscription_count() > 0, 10.0), \
                'node subscription not discovered'
            # resolved names: context_args may remap or namespace the outputs
            ends = ('/ground', '/obstacles') + (('/labeled',) if labeled else ())
            outputs = [p.topic_name for p in self.node.publishers if p.topic_name.endswith(ends)]
            assert wait_for(lambda: all(self.node.count_subscribers(t) > 0 for t in outputs),
                            10.0)
            if self.imu_pub is not None and self.node.get_parameter('imu_topic').value:
                assert wait_for(lambda: self.imu_pub.get_subscription_count() > 0, 10.0), \
                    'node IMU subscription not discovered'
            # the worker's warm-up done (seconds with an empty numba cache), so that a test
            # that patches the GP or numpy next patches the frames', not the warm-up's calls
            assert self.node.warmed_up.wait(300.0), 'node warm-up did not finish'
        except BaseException:
            self.close()
            raise

    def _collect(self, bucket):
        def cb(msg):
            with self.lock:
                bucket.append(msg)
        return cb

    def outputs_for(self, stamp):
        """(ground, obstacles) messages whose header stamp equals ``stamp``, or None."""
        with self.lock:
            g = [m for m in self.ground if m.header.stamp == stamp]
            o = [m for m in self.obstacles if m.header.stamp == stamp]
        return (g[-1], o[-1]) if g and o else None

    def surface_for(self, stamp):
        """The ground_surface message whose header stamp equals ``stamp``, or None."""
        return self._last_with_stamp(self.surface, stamp)

    def labeled_for(self, stamp):
        """The labeled message whose header stamp equals ``stamp``, or None."""
        return self._last_with_stamp(self.labeled, stamp)

    def _last_with_stamp(self, bucket, stamp):
        with self.lock:
            found = [m for m in bucket if m.header.stamp == stamp]
        return found[-1] if found else None

    def publish_and_wait(self, msg, timeout=30.0):
        """Publish ``msg`` and wait for both outputs with its stamp (one re-publish if the
        best-effort link lost it), then for the node to have recorded the frame: it publishes
        ground and obstacles before it builds the surface cloud and counts the frame, so a
        caller reading the node's counts right after the outputs could miss this frame."""
        self.pub.publish(msg)
        out = wait_for(lambda: self.outputs_for(msg.header.stamp), timeout / 2)
        if out is None and self.node.window.frames_received == 0:
            self.pub.publish(msg)
            out = wait_for(lambda: self.outputs_for(msg.header.stamp), timeout / 2)
        assert out is not None, 'no ground/obstacles output received for the frame'
        assert wait_for(self.node_settled, timeout / 2), 'the node never recorded the frame'
        return out

    def node_settled(self) -> bool:
        """Every frame the node received is recorded (processed, dropped or failed) and none
        waits in its slot."""
        w = self.node.window
        return (w.frames_processed + w.frames_dropped + w.frames_failed >= w.frames_received
                and not self.node._slot)  # noqa: SLF001 - read-only peek at the slot

    def steady_counts(self, timeout=20.0, quiet_s=1.0):
        """The node's counts (a window snapshot) once two of them taken ``quiet_s`` apart are
        equal, with processed + dropped + failed == received and nothing in the slot; None
        after ``timeout``.

        After a burst, DDS may still hand the node a frame it queued earlier: one settled
        snapshot then read ``frames_received`` one ahead of the recorded fates (seen once in
        CI, a 42nd frame arriving after the 41st was recorded). A frame lost or counted twice
        never gives such counts; a late one only defers them."""
        keys = ('frames_received', 'frames_processed', 'frames_dropped', 'frames_failed')
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            first = self.node.window.snapshot()
            time.sleep(quiet_s)
            counts = self.node.window.snapshot()
            fates = counts['frames_processed'] + counts['frames_dropped'] \
                + counts['frames_failed']
            if (all(first[k] == counts[k] for k in keys) and fates == counts['frames_received']
                    and not self.node._slot):  # noqa: SLF001 - read-only peek at the slot
                return counts
        return None

    def statuses(self):
        with self.lock:
            return [s for arr in self.diagnostics for s in arr.status
                    if s.name == 'ground_segmentation: processing']

    def wait_status(self, predicate, timeout=20.0):
        """The first diagnostics status (received from now on) for which predicate holds."""
        start = len(self.statuses())

        def find():
            for s in self.statuses()[start:]:
                if predicate(s):
                    return s
            return None
        return wait_for(find, timeout)

    def _spin(self):
        """Executor.spin, stopped by close() between two spin_once calls. Executor.shutdown
        from another thread while spin() runs can drop the executor's guard condition under a
        spin_once that is building its wait set ('NoneType' object has no attribute 'handle'
        in the spin thread, seen under load): close() stops this loop first."""
        while not self._stop_spinning.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        import gc

        import rclpy
        self._stop_spinning.set()
        if self.executor is not None:
            self.executor.wake()  # end the spin_once waiting now
        if self.thread is not None:
            self.thread.join(timeout=5.0)
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=5.0)
        if self.node is not None:
            self.node.destroy_node()
        if self.peer is not None:
            self.peer.destroy_node()
        rclpy.try_shutdown(context=self.context)
        # rclpy's MultiThreadedExecutor leaves the tasks of callbacks cut short by the shutdown
        # (InvalidHandle: 'cannot use Destroyable because destruction was requested') with
        # their exception unfetched; rclpy.task.Future.__del__ then prints 'The following
        # exception was never retrieved' to stderr whenever the collector reaches them, which
        # was inside a later test that counts its stderr lines (seen under load). Collect them
        # here, in the teardown of the test that made them.
        self.executor = self.thread = None
        gc.collect()


@pytest.fixture
def ros_harness():
    """Factory: ``ros_harness(node_kwargs=..., context_args=...)``; closed after the test."""
    made = []

    def make(**kwargs):
        h = RosHarness(**kwargs)
        made.append(h)
        return h
    yield make
    for h in made:
        h.close()


def status_values(status):
    """DiagnosticStatus KeyValues as a dict (values stay strings)."""
    return {kv.key: kv.value for kv in status.values}


def check_warm_up_in_fresh_cache(script: str, cache_dir) -> str:
    """Run ``script`` (an ``if True:`` block, body indented 8 spaces, that warms up, sets
    ``queued = set(compiled._queued)``, then runs frames) in a fresh interpreter with an empty
    NUMBA_CACHE_DIR (``cache_dir``), followed by a report; assert that the frames queued no
    signature the warm-up had not (a missed one compiles only once a frame needs it) and that
    every queued kernel compiled (numba does not rebuild a cached kernel when a kernel of
    another module that it calls changes, so only an empty cache shows a mismatch between
    them). Returns the script's stdout."""
    report = """
        for kernel, signature in set(compiled._queued) - queued:
            print('MISSING', kernel.py_func.__name__, signature)
        print('WAITED', compiled.wait(240.0))
        for kernel in compiled._failed:
            print('FAILED', kernel.py_func.__name__)
        """
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    out = subprocess.run([sys.executable, '-c', script.rstrip() + report], cwd=REPO,
                         capture_output=True, text=True, timeout=400, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert 'MISSING' not in out.stdout, out.stdout
    assert 'WAITED True' in out.stdout and 'FAILED' not in out.stdout, out.stdout
    return out.stdout


def compiled_ready(function, *args, **kwargs):
    """Call ``function`` once, then wait until the kernels it queued are compiled (core/
    compiled.py compiles in the background and meanwhile runs the numpy reference)."""
    from gp_ground_segmentation.core import compiled
    function(*args, **kwargs)
    assert compiled.wait(300.0), 'background compilation did not finish'


def compiled_and_reference(function, *args, **kwargs):
    """(function(..., compiled=True) once its kernel is compiled, function(..., compiled=False));
    skips without numba."""
    from gp_ground_segmentation.core import compiled
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    compiled_ready(function, *args, compiled=True, **kwargs)
    out = (function(*args, compiled=True, **kwargs), function(*args, compiled=False, **kwargs))
    # a kernel that failed to compile runs its reference: the comparison would prove nothing
    # (test_compiled.py breaks kernels of its own on purpose)
    failed = [k for k in compiled._failed
              if getattr(k, 'py_func', k).__module__.startswith('gp_ground_segmentation')]
    assert not failed, f'kernels that did not compile: {failed}'
    return out


def candidate_grid(source: str):
    """(RadialGrid at the default M x N, SegmenterParams()) of a scan under DATA (a .pcd or
    KITTI .bin path relative to it) or of the synthetic scene ``source``; skips when the file
    is missing."""
    import numpy as np
    from gp_ground_segmentation.core.grid import build_grid
    from gp_ground_segmentation.core.params import SegmenterParams
    from gp_ground_segmentation.tools.io import read_points_file
    if '.' in source:
        if not (DATA / source).exists():
            pytest.skip(f'{DATA / source} not found')
        arr = read_points_file(DATA / source)
        xyz = np.stack([arr['x'], arr['y'], arr['z']], axis=1).astype(np.float64)
    else:
        from scenes import synthetic
        xyz = np.asarray(synthetic.scan_scene(source).points, dtype=np.float64)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1) & (np.abs(xyz).sum(axis=1) > 0)]
    params = SegmenterParams()
    grid = build_grid(*(np.ascontiguousarray(xyz[:, i]) for i in range(3)),
                      params.num_segments, params.num_bins)
    return grid, params
