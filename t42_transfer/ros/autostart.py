"""Autostart of a lifecycle node run without a lifecycle manager (``t42 up``): configure, then activate, each tried
again every ``retry_s`` while it fails, until the node is active.

A hardware node's transition can fail for a moment (a port not there yet, a servo that missed one answer as its
torque came on); without a manager to try again, a node that gave up after one failed activate stayed inactive for
good.  A lifecycle client that got there first, or that took over (a cleanup after autostart's configure), ends
the retries.  They run on the steady clock: a retry comes in seconds, whatever the graph's time.
"""

from __future__ import annotations

from collections.abc import Callable

from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

from t42_transfer.ros.node_lifetime import lifecycle_state


class Autostart:
    """Configures, then activates ``node`` once its executor spins, retrying each step every ``retry_s``.

    ``ready()``: whether to try configure now (False: wait ``retry_s``, say why yourself; a port that does not
    exist yet)."""

    def __init__(self, node: LifecycleNode, retry_s: float, ready: Callable[[], bool] = lambda: True) -> None:
        self._node, self._ready, self._retry_ns = node, ready, round(retry_s * 1e9)
        self.configuring = False
        """Whether the configure under way is autostart's (a node may say a failure it repeats once only)."""
        self._configured = False
        self.waiting = False
        """Whether a try failed or waited (the next comes ``retry_s`` later, not at once)."""
        self._timer = node.create_timer(0.0, self._next, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _next(self) -> None:
        state = lifecycle_state(self._node)
        if state == "inactive" and self._configured:
            self._activate()
        elif state != "unconfigured" or self._configured:  # a lifecycle client got there first, or took over
            self._done()
        elif not self._ready():
            self._again()
        else:
            self.configuring = True
            try:
                self._configured = self._node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            finally:
                self.configuring = False
            self._activate() if self._configured else self._again()

    def _activate(self) -> None:
        if self._node.trigger_activate() == TransitionCallbackReturn.SUCCESS:
            self._done()
        else:  # the node says why; it is inactive
            self._again()

    def _again(self) -> None:
        self.waiting = True
        self._timer.timer_period_ns = self._retry_ns

    def _done(self) -> None:
        # Destroyed, not cancelled: a cancelled timer stays in the executor's wait set, built at every wake.
        self._node.destroy_timer(self._timer)
