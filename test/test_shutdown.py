# SPDX-License-Identifier: Apache-2.0
"""ros/shutdown.shutdown_context: rclpy's signal handler may shut the context down between
try_shutdown's check and its own shutdown call (a race seen once with two SIGINTs)."""

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402

from gp_ground_segmentation.ros.shutdown import shutdown_context  # noqa: E402


def _context():
    from rclpy.signals import SignalHandlerOptions
    context = rclpy.Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    return context


def test_shuts_a_context_down():
    context = _context()
    shutdown_context(context)
    assert not rclpy.ok(context=context)
    shutdown_context(context)  # a second call does nothing


def test_a_shutdown_that_races_the_signal_handler_is_not_an_error(monkeypatch):
    context = _context()

    def racing_try_shutdown(context=None):
        context.shutdown()  # the signal handler got there first ...
        context._Context__context.shutdown()  # ... and rcl refuses the second shutdown
    monkeypatch.setattr(rclpy, 'try_shutdown', racing_try_shutdown)
    with pytest.raises(_rclpy.RCLError):  # what the node saw without shutdown_context
        racing_try_shutdown(context=_context())
    shutdown_context(context)
    assert not rclpy.ok(context=context)


def test_other_rcl_failures_are_raised(monkeypatch):
    context = _context()

    def failing_try_shutdown(context=None):
        raise _rclpy.RCLError('something else')
    monkeypatch.setattr(rclpy, 'try_shutdown', failing_try_shutdown)
    with pytest.raises(_rclpy.RCLError):
        shutdown_context(context)
    context.shutdown()
