# SPDX-License-Identifier: Apache-2.0
"""Ctrl-C and SIGTERM for the console scripts: stop on the first signal, ignore the rest."""

import signal

__all__ = ['QuietShutdown', 'shutdown_context']


def shutdown_context(context=None) -> None:
    """``rclpy.try_shutdown(context)``, also when rclpy's own signal handler shuts the context
    down between try_shutdown's "is it still up?" check and its shutdown call: rcl then raises
    RCLError "rcl_shutdown already called", and the context is down, which is all the caller
    wants (test_node_process's two SIGINTs to the node's process group got exit code 1 from it
    once, in a clean-clone CI run; the full runs around it passed). Any other failure, with the
    context still up, is raised."""
    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    try:
        rclpy.try_shutdown(context=context)
    except _rclpy.RCLError:
        if rclpy.ok(context=context):
            raise


class QuietShutdown:
    """SIGINT/SIGTERM: the first one raises KeyboardInterrupt (in the node after rclpy's own
    handler has shut the context down), any further one is ignored. A terminal sends SIGINT to
    the whole process group and ``ros2 launch`` forwards another one; without this the second
    signal lands inside destroy_node() as a KeyboardInterrupt traceback and the exit code is
    -2."""

    def __init__(self):
        self.signalled = False

    def install(self) -> None:
        # The node installs this before rclpy.init(), so rclpy's handlers chain to it.
        signal.signal(signal.SIGINT, self._handle)
        signal.signal(signal.SIGTERM, self._handle)

    def ignore_signals(self) -> None:
        """From now on (clean-up) every signal is ignored."""
        self.signalled = True
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)

    def _handle(self, signum, frame) -> None:
        if self.signalled:
            return
        self.signalled = True
        raise KeyboardInterrupt
