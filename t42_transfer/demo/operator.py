"""The demo's own rclpy node: it watches the hand and the suite's outputs, calls services and sends goals.

Imported only once the demo runs (``t42 demo --help`` needs no ROS); spun by a background executor while
the story waits on what it has seen.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseStamped
from lifecycle_msgs.srv import GetState
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger
from t42_interfaces.msg import ModelUpdated, PlanResult

from msg_adapters import names, object_xy_mm, path_xy_mm, stamp_to_ns, status_report
from msg_adapters.plan_result import plan_result
from msg_adapters.transfer import model_announcement
from t42_transfer.demo.settings import SERVICES, TRANSFER_STATUS
from t42_transfer.ros.qos import profile

MAX_POSES = 2000
"""Poses kept: enough for the longest plan and its settling."""


def wait_until(cond: Callable[[], Any], timeout_s: float, what: str, alive: Callable[[], None] | None = None,
               progress: Callable[[], None] | None = None) -> None:
    """Wait (an executor thread spins) until ``cond()``; ``alive()`` raises if a node died."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        if alive is not None:
            alive()
        if progress is not None:
            progress()
        time.sleep(0.05)


class Operator(Node):
    """What a user at the keyboard does: watch, call, send goals; every topic and service from :mod:`names`."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("t42_demo", parameter_overrides=[Parameter("use_sim_time", value=True)], **node_kwargs)
        self.poses: list[tuple[int, np.ndarray]] = []
        self.truths: list[tuple[int, np.ndarray]] = []
        """The simulated hand's true object pose (``sim/object_pose``), where a node publishes it."""
        self.statuses: list[str] = []
        self.results: list[dict[str, Any]] = []
        self.paths: list[np.ndarray] = []
        self.models: list[str] = []
        """Every model path the transfer server announced on ``t42/model_updated``, in order."""
        self.diagnostic: dict[str, str] = {}
        self.create_subscription(PoseStamped, names.OBJECT_POSE, self._on_pose, 100)
        self.create_subscription(PoseStamped, names.SIM_POSE, self._on_truth, 100)
        self.create_subscription(String, names.HAND_STATUS, lambda m: self.statuses.append(m.data),
                                 profile(names.EVENTS))
        self.create_subscription(PlanResult, names.PLAN_RESULT, lambda m: self.results.append(asdict(plan_result(m))),
                                 10)
        self.create_subscription(PathMsg, names.PLANNED_PATH, lambda m: self.paths.append(path_xy_mm(m)), 10)
        self.create_subscription(ModelUpdated, names.MODEL_UPDATED,
                                 lambda m: self.models.append(model_announcement(m).path), profile(names.LATCHED))
        self.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_diagnostics, 10)
        self.goal_pub = self.create_publisher(PointStamped, names.GOAL, 10)
        self.trigger_clients = {name: self.create_client(Trigger, name) for name in SERVICES}
        self.lifecycle_clients: dict[str, Any] = {}
        self.parameter_clients: dict[str, Any] = {}

    def _on_pose(self, msg: Any) -> None:
        self.poses.append((stamp_to_ns(msg.header.stamp), object_xy_mm(msg).astype(np.float64)))
        del self.poses[:-MAX_POSES]

    def _on_truth(self, msg: Any) -> None:
        self.truths.append((stamp_to_ns(msg.header.stamp), object_xy_mm(msg).astype(np.float64)))
        del self.truths[:-MAX_POSES]

    def _on_diagnostics(self, msg: Any) -> None:
        try:
            report = status_report(msg, TRANSFER_STATUS)
        except KeyError:
            return
        self.diagnostic = {"message": report.message, **report.values}

    def ready(self) -> bool:
        return all(c.service_is_ready() for c in self.trigger_clients.values())

    wait_until = staticmethod(wait_until)

    def call(self, service: str, timeout_s: float, alive: Callable[[], None] | None = None,
             progress: Callable[[], None] | None = None) -> Any:
        """Call a Trigger service and wait for its answer (showing progress meanwhile)."""
        future = self.trigger_clients[service].call_async(Trigger.Request())
        self.wait_until(future.done, timeout_s, f"the answer of {service}", alive, progress)
        if future.exception() is not None:
            raise RuntimeError(f"{service}: {future.exception()}")
        return future.result()

    def lifecycle_state(self, node: str, timeout_s: float, alive: Callable[[], None] | None = None) -> str:
        """The label of lifecycle ``node``'s state ("active", ...), as any lifecycle client asks for it."""
        client = self.lifecycle_clients.get(node)
        if client is None:
            client = self.lifecycle_clients[node] = self.create_client(GetState,
                                                                       names.private_of(node, names.GET_STATE))
        self.wait_until(client.service_is_ready, timeout_s, f"{node}'s lifecycle services", alive)
        future = client.call_async(GetState.Request())
        self.wait_until(future.done, timeout_s, f"the state of {node}", alive)
        return future.result().current_state.label

    def set_parameters(self, node: str, values: dict[str, Any], timeout_s: float,
                       alive: Callable[[], None] | None = None) -> None:
        """Set ``node``'s parameters as ``ros2 param set`` does; RuntimeError with the node's reason if refused."""
        client = self.parameter_clients.get(node)
        if client is None:
            client = self.parameter_clients[node] = self.create_client(
                SetParameters, names.private_of(node, "~/set_parameters"))
        self.wait_until(client.service_is_ready, timeout_s, f"{node}'s parameter services", alive)
        request = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
        future = client.call_async(request)
        self.wait_until(future.done, timeout_s, f"{node} to take {values}", alive)
        refused = [r.reason for r in future.result().results if not r.successful]
        if refused:
            raise RuntimeError(f"{node} refused {values}: {'; '.join(refused)}")

    def latest_truth(self) -> np.ndarray | None:
        """The newest true object position, where the hand's simulator publishes it (None: it does not)."""
        return self.truths[-1][1] if self.truths else None

    def latest_pose(self) -> tuple[int, np.ndarray]:
        return self.poses[-1] if self.poses else (-1, np.full(2, np.nan))

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds
