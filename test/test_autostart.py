"""Autostart (t42_transfer/ros/autostart.py) on a plain lifecycle node: retries of configure and of activate, and
a lifecycle client that takes over."""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn

from t42_transfer.ros.autostart import Autostart
from t42_transfer.ros.node_lifetime import lifecycle_state

RETRY_S = 0.2


class Flaky(LifecycleNode):
    """Fails its first ``configure_fails`` configures and ``activate_fails`` activates; counts every try."""

    def __init__(self, configure_fails: int = 0, activate_fails: int = 0, ready_after: int = 0,
                 **kwargs: Any) -> None:
        super().__init__("flaky", **kwargs)
        self.fails = {"configure": configure_fails, "activate": activate_fails}
        self.tries = {"configure": 0, "activate": 0, "ready": 0}
        self.ready_after = ready_after
        self.autostart = Autostart(self, RETRY_S, self._ready)

    def _ready(self) -> bool:
        self.tries["ready"] += 1
        return self.tries["ready"] > self.ready_after

    def _try(self, name: str) -> TransitionCallbackReturn:
        self.tries[name] += 1
        return TransitionCallbackReturn.FAILURE if self.tries[name] <= self.fails[name] else \
            TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        assert self.autostart.configuring
        return self._try("configure")

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        return self._try("activate")


def test_configure_and_activate_are_each_tried_again_until_the_node_is_active(ros: Any) -> None:
    node = ros.add(Flaky, ready_after=1, configure_fails=2, activate_fails=2)
    assert ros.spin_until(lambda: lifecycle_state(node) == "active", 10 * RETRY_S + 5.0), (node.tries, node.fails)
    assert node.tries == {"ready": 4, "configure": 3, "activate": 3}
    assert not node.autostart.configuring
    ros.spin_for(3 * RETRY_S)  # nothing more once active
    assert node.tries == {"ready": 4, "configure": 3, "activate": 3}


def test_a_node_whose_transitions_pass_is_tried_once(ros: Any) -> None:
    node = ros.add(Flaky)
    assert ros.spin_until(lambda: lifecycle_state(node) == "active", 5.0), node.tries
    ros.spin_for(3 * RETRY_S)
    assert node.tries == {"ready": 1, "configure": 1, "activate": 1} and not node.autostart.waiting


def test_a_lifecycle_client_that_takes_over_ends_the_retries(ros: Any) -> None:
    node = ros.add(Flaky, activate_fails=1000)
    assert ros.spin_until(lambda: node.tries["activate"] >= 2, 5.0), node.tries
    assert lifecycle_state(node) == "inactive"
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS  # a client took over
    tries = dict(node.tries)
    ros.spin_for(3 * RETRY_S)
    assert node.tries == tries and lifecycle_state(node) == "unconfigured"
