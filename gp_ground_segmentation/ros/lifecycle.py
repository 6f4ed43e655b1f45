# SPDX-License-Identifier: Apache-2.0
"""The managed (lifecycle) variant of the node, for Nav2-style bring-up.

Same topics, parameters, processing and diagnostics as ``node.GroundSegmentationNode`` (the
code is ``node.SegmentationNodeBase``); only when they exist differs:

* constructed (unconfigured): the parameters are declared, checked against the parameter file
  (an unknown key, a wrong type or an out-of-range value fails here, and main() refuses a
  file whose values break a cross-field rule, as for the plain node) and settable; no topic
  exists yet;
* configure: reads the parameters and validates them together (the cross-field rules, for
  values from ``-p`` or set since start-up: a failure logs one line and leaves the node
  unconfigured, so that a corrected value can be set and configure tried again), creates the
  publishers (lifecycle publishers), the subscriptions (points, and imu_topic when set), the
  diagnostics timer and the worker thread (which warms the segmenter up);
* activate: clouds are processed and the outputs and /diagnostics published;
* deactivate: clouds are no longer processed (counted as ``frames_while_inactive``) and nothing
  is published; the subscriptions stay matched, the segmenter keeps its learned theta, the
  diagnostics window its counts and the IMU buffer its samples, so activate resumes at once.
  Frames waiting in the slot are dropped and counted;
* cleanup (from inactive) and shutdown (from any state) release everything configure created;
  the parameters stay declared.
"""

from __future__ import annotations

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from .config import NODE_NAME, ParameterConfigError
from .entry import one_line, run_node
from .node import SegmentationNodeBase
from ..core.segmenter import GroundSegmenter

__all__ = ['GroundSegmentationLifecycleNode', 'main']


class GroundSegmentationLifecycleNode(SegmentationNodeBase, LifecycleNode):
    """Ground/obstacle split of LiDAR clouds, as a managed node (module docstring)."""

    LIFECYCLE = True  # run_node: the help of the managed node

    def __init__(self, segmenter_factory=GroundSegmenter, announce: bool = True, **node_kwargs):
        """As GroundSegmentationNode's; ``announce``: log that the node is up, unconfigured."""
        LifecycleNode.__init__(self, NODE_NAME, **node_kwargs)
        self._init_state(segmenter_factory)
        try:
            self._declare_parameters()
        except BaseException:
            LifecycleNode.destroy_node(self)
            raise
        if announce:
            self.log_started()

    def log_started(self) -> None:
        self.get_logger().info(
            f"managed node up, unconfigured: configure and activate it through "
            f"'{self.resolve_service_name('~/change_state')}' (lifecycle_msgs/ChangeState)")

    def _make_publisher(self, msg_type, topic, qos, **kwargs):
        """Lifecycle publishers: they publish only while the node is active."""
        return self._keep('publisher', self.create_lifecycle_publisher(msg_type, topic, qos,
                                                                       **kwargs))

    def _drop_publisher(self, publisher) -> None:
        self.destroy_lifecycle_publisher(publisher)

    def _diagnostics_extra(self) -> dict:
        return dict(super()._diagnostics_extra(),
                    frames_while_inactive=self.frames_while_inactive)

    # --- transitions -------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Read and validate the parameters, create the endpoints and the worker."""
        try:
            self._configure()
        except ParameterConfigError as exc:
            self.get_logger().error(f'configure failed, invalid parameters: {one_line(exc)}')
            return TransitionCallbackReturn.FAILURE
        except Exception as exc:  # rclpy would turn it into ERROR without a word
            self.get_logger().error(f'configure failed: {one_line(exc)}')
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info('configured (inactive)')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Enable the publishers, then take clouds."""
        result = super().on_activate(state)  # the lifecycle publishers
        if result == TransitionCallbackReturn.SUCCESS:
            self.accepting = True
            self.announce()
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop taking clouds, drop those waiting, then disable the publishers."""
        self.accepting = False
        dropped = self.discard_waiting_frames()
        self.get_logger().info('deactivated: output stopped'
                               + (f', {dropped} waiting frame(s) dropped' if dropped else ''))
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.get_logger().info('cleaned up (unconfigured)')
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.get_logger().info(f'shut down from {state.label}')
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised: release everything, back to unconfigured."""
        self._release()
        self.get_logger().error(f'error in {state.label}: released, unconfigured')
        return TransitionCallbackReturn.SUCCESS


def main(args=None):
    """Entry point of ``ros2 run gp_ground_segmentation ground_segmentation_lifecycle_node``."""
    run_node(GroundSegmentationLifecycleNode, 'ground_segmentation_lifecycle_node', args)


if __name__ == '__main__':
    main()
