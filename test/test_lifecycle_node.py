# SPDX-License-Identifier: Apache-2.0
"""The managed node (ros/lifecycle.py) through every transition, over real rclpy services.

A peer node drives ``GroundSegmentationLifecycleNode`` with lifecycle_msgs ChangeState and
GetState (what ``ros2 lifecycle set`` and Nav2's lifecycle manager call), publishes real KITTI
clouds and listens to the outputs: unconfigured has no topics; configure reads and validates
the parameters (a cross-field error fails it and leaves the node unconfigured until fixed) and
creates them; only active publishes; deactivate keeps the subscription, the learned theta and
the counts; cleanup and shutdown release everything; the console script starts unconfigured.
"""

import signal
import threading

import pytest
from conftest import start_module, wait_for

from gp_ground_segmentation import SegmenterParams
from gp_ground_segmentation.ros.node import OUTPUT_QOS

LIFECYCLE_MODULE = 'gp_ground_segmentation.ros.lifecycle'


class LifecycleHarness:
    """The managed node and a peer (ChangeState/GetState clients, a 'points' publisher,
    ground and obstacles subscribers) in a private context, spun in a background thread."""

    def __init__(self, parameter_overrides=(), **node_kwargs):
        import rclpy
        from lifecycle_msgs.srv import ChangeState, GetState
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.parameter import Parameter
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        from gp_ground_segmentation.ros.lifecycle import GroundSegmentationLifecycleNode
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        overrides = [Parameter('diagnostics_period_s', value=0.2)] + list(parameter_overrides)
        self.node = GroundSegmentationLifecycleNode(context=self.context,
                                                    parameter_overrides=overrides, **node_kwargs)
        self.peer = rclpy.create_node('gp_lifecycle_peer', context=self.context)
        self.lock = threading.Lock()
        self.ground, self.obstacles = [], []
        for topic, bucket in (('ground', self.ground), ('obstacles', self.obstacles)):
            self.peer.create_subscription(PointCloud2, topic, self._collect(bucket),
                                          QoSProfile(depth=100,
                                                     reliability=OUTPUT_QOS.reliability))
        self.pub = self.peer.create_publisher(
            PointCloud2, 'points', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.change = self.peer.create_client(ChangeState, '/ground_segmentation/change_state')
        self.get = self.peer.create_client(GetState, '/ground_segmentation/get_state')
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        assert self.change.wait_for_service(timeout_sec=10.0)
        assert self.get.wait_for_service(timeout_sec=10.0)

    def _collect(self, bucket):
        def cb(msg):
            with self.lock:
                bucket.append(msg)
        return cb

    def _spin(self):
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def _call(self, client, request):
        future = client.call_async(request)
        assert wait_for(future.done, 60.0), 'lifecycle service call timed out'
        return future.result()

    def transition(self, label: str) -> bool:
        """ChangeState by the transition's label ('configure', 'activate', ...): success."""
        from lifecycle_msgs.srv import ChangeState
        request = ChangeState.Request()
        request.transition.label = label
        return self._call(self.change, request).success

    def state(self) -> str:
        from lifecycle_msgs.srv import GetState
        return self._call(self.get, GetState.Request()).current_state.label

    def outputs_for(self, stamp):
        with self.lock:
            return (any(m.header.stamp == stamp for m in self.ground)
                    and any(m.header.stamp == stamp for m in self.obstacles))

    def publish_until_counted(self, msg, counter, timeout=30.0):
        """Publish ``msg`` (again, best effort) until ``counter()`` grows."""
        before = counter()
        for _ in range(3):
            self.pub.publish(msg)
            if wait_for(lambda: counter() > before, timeout / 3):
                return True
        return False

    def ours(self, entities):
        """Topic names of the node's own publishers or subscriptions (not rosout, params)."""
        return sorted(e.topic_name for e in entities
                      if e.topic_name not in ('/rosout', '/parameter_events'))

    def close(self):
        import rclpy
        self._stop.set()
        self.executor.wake()
        self.thread.join(5.0)
        self.executor.shutdown(timeout_sec=5.0)
        self.node.destroy_node()
        self.peer.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def lifecycle():
    made = []

    def make(**kwargs):
        made.append(LifecycleHarness(**kwargs))
        return made[-1]
    yield make
    for h in made:
        h.close()


def _stamped(msg, sec):
    """``msg`` with header stamp ``sec`` s (the frames are told apart by it)."""
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, 0
    return msg


def test_every_transition_through_the_services(kitti_msgs, lifecycle):
    h = lifecycle()
    node = h.node
    assert h.state() == 'unconfigured'
    assert h.ours(node.publishers) == [] and h.ours(node.subscriptions) == []
    assert node.get_parameter('ground_threshold_m').value == SegmenterParams().ground_threshold_m

    assert h.transition('configure') and h.state() == 'inactive'
    assert h.ours(node.publishers) == ['/diagnostics', '/ground', '/ground_surface',
                                       '/labeled', '/obstacles']
    assert h.ours(node.subscriptions) == ['/points']
    assert node.warmed_up.wait(300.0)
    assert wait_for(lambda: h.pub.get_subscription_count() == 1, 10.0)
    # inactive: clouds are counted, not processed; nothing is published
    msg = _stamped(kitti_msgs[0], 10)
    assert h.publish_until_counted(msg, lambda: node.frames_while_inactive)
    assert node.window.frames_received == 0 and not h.outputs_for(msg.header.stamp)

    assert h.transition('activate') and h.state() == 'active'
    assert h.publish_until_counted(_stamped(kitti_msgs[1], 11),
                                   lambda: node.window.frames_processed)
    assert wait_for(lambda: h.outputs_for(kitti_msgs[1].header.stamp), 10.0)
    segmenter, theta = node.segmenter, node.segmenter.hyperparameters
    subscription = [s for s in node.subscriptions if s.topic_name == '/points'][0]

    # deactivate: output stops, the subscription and the learned state stay
    assert h.transition('deactivate') and h.state() == 'inactive'
    inactive_before = node.frames_while_inactive
    msg = _stamped(kitti_msgs[2], 12)
    assert h.publish_until_counted(msg, lambda: node.frames_while_inactive)
    assert node.frames_while_inactive > inactive_before
    assert not wait_for(lambda: h.outputs_for(msg.header.stamp), 1.0)
    assert node.segmenter is segmenter and node.segmenter.hyperparameters == theta
    assert [s for s in node.subscriptions if s.topic_name == '/points'] == [subscription]
    assert h.pub.get_subscription_count() == 1  # still matched: no rediscovery on activate
    assert node.window.frames_processed == 1

    assert h.transition('activate') and h.state() == 'active'
    assert h.publish_until_counted(_stamped(kitti_msgs[3], 13),
                                   lambda: node.window.frames_processed)
    assert node.window.frames_processed == 2  # the counts went on
    assert wait_for(lambda: h.outputs_for(kitti_msgs[3].header.stamp), 10.0)

    assert not h.transition('cleanup')  # not from active
    assert h.transition('deactivate') and h.transition('cleanup')
    assert h.state() == 'unconfigured'
    assert h.ours(node.publishers) == [] and h.ours(node.subscriptions) == []
    assert node._worker is None  # noqa: SLF001 - the worker thread was joined
    assert wait_for(lambda: h.pub.get_subscription_count() == 0, 10.0)

    # configured again from scratch, then shut down from active
    assert h.transition('configure') and h.transition('activate')
    assert node.segmenter is not segmenter and node.window.frames_processed == 0
    assert h.transition('shutdown') and h.state() == 'finalized'
    assert h.ours(node.publishers) == [] and h.ours(node.subscriptions) == []


def test_configure_validates_and_a_failure_leaves_it_unconfigured(lifecycle):
    from rclpy.parameter import Parameter
    # each value is in range, together they break a cross-field rule
    h = lifecycle(parameter_overrides=[Parameter('ground_threshold_m', value=0.35)])
    node = h.node
    assert not h.transition('configure') and h.state() == 'unconfigured'
    assert h.ours(node.publishers) == [] and node.declared_params is None
    # a value that breaks the rule on its own is refused while unconfigured too
    assert not node.set_parameters([Parameter('max_threshold_m', value=0.3)])[0].successful
    assert node.set_parameters([Parameter('max_threshold_m', value=0.4)])[0].successful
    assert h.transition('configure') and h.state() == 'inactive'
    assert node.declared_params.ground_threshold_m == 0.35
    assert node.segmenter_params.max_threshold_m == 0.4


def test_trigger_methods_and_shutdown_from_unconfigured(lifecycle):
    from rclpy.lifecycle import TransitionCallbackReturn
    h = lifecycle()
    node = h.node
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS and node.accepting
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert not node.accepting
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
    assert h.state() == 'finalized' and h.ours(node.subscriptions) == []


def test_console_script_starts_unconfigured_and_stops_on_sigint():
    proc = start_module(LIFECYCLE_MODULE, '--ros-args', '-r', 'points:=/gp_lc_points',
                        start_new_session=True)
    try:
        from conftest import lines_until
        lines = lines_until(proc, proc.stdout, 'unconfigured', 120.0)
        assert "'/ground_segmentation/change_state'" in lines[-1], lines
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and 'Traceback' not in out, out


def test_console_script_help_says_it_is_managed():
    proc = start_module(LIFECYCLE_MODULE, '--help')
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert out.startswith('usage: ground_segmentation_lifecycle_node') and 'configure' in out


def test_a_configure_that_raises_fails_cleanly(lifecycle):
    made = []

    def broken_factory(params):
        made.append(params)
        raise RuntimeError('no segmenter today')
    h = lifecycle(segmenter_factory=broken_factory)
    assert not h.transition('configure') and h.state() == 'unconfigured'
    assert made and h.ours(h.node.publishers) == [] and h.ours(h.node.subscriptions) == []
    assert h.transition('shutdown') and h.state() == 'finalized'
