"""The demo's own rclpy node: it watches the hand and the suite's outputs, calls services and sends action goals
(``t42/reach``, ``t42/transfer``), and hears the recorder's ``recorder/bag_closed`` events.

Imported only once the demo runs (``t42 demo --help`` needs no ROS); spun by a background executor while
the story waits on what it has seen.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.srv import GetState
from rcl_interfaces.srv import SetParameters
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger
from t42_interfaces.msg import BagClosed, ModelUpdated, PlanResult

from msg_adapters import names, object_xy_mm, stamp_to_ns, status_report
from msg_adapters.events import BagClosedEvent, bag_closed_event
from msg_adapters.plan_result import PlanResult as PlanRecord
from msg_adapters.plan_result import plan_result
from msg_adapters.reach import reach_type
from msg_adapters.transfer import ModelAnnouncement, model_announcement, transfer_type
from t42_transfer.demo.settings import SERVICES, TRANSFER_STATUS
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
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

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("t42_demo", parameter_overrides=[Parameter("use_sim_time", value=True)], **node_kwargs)
        self.spin_lock = threading.Lock()
        """Held by each ``spin_once`` of :meth:`spin` and while an action request is sent."""
        self.poses: list[tuple[int, np.ndarray]] = []
        self.truths: list[tuple[int, np.ndarray]] = []
        """The simulated hand's true object pose (``sim/object_pose``), where a node publishes it."""
        self.statuses: list[str] = []
        self.results: list[tuple[float, PlanRecord]] = []
        """Every ``t42/plan_result`` with its arrival (``time.perf_counter()``), in order."""
        self.models: list[ModelAnnouncement] = []
        """Every model the transfer server announced on ``t42/model_updated``, in order."""
        self.bags_closed: list[BagClosedEvent] = []
        """Every bag the recorder announced on ``recorder/bag_closed`` (closed and final), in order."""
        self.diagnostic: dict[str, str] = {}
        self.create_subscription(PoseStamped, names.OBJECT_POSE, self._on_pose, 100)
        self.create_subscription(PoseStamped, names.SIM_POSE, self._on_truth, 100)
        self.create_subscription(String, names.HAND_STATUS, lambda m: self.statuses.append(m.data),
                                 profile(names.EVENTS))
        self.create_subscription(PlanResult, names.PLAN_RESULT,
                                 lambda m: self.results.append((time.perf_counter(), plan_result(m))),
                                 profile(names.RESULTS))
        self.create_subscription(ModelUpdated, names.MODEL_UPDATED,
                                 lambda m: self.models.append(model_announcement(m)), profile(names.LATCHED))
        self.create_subscription(BagClosed, names.BAG_CLOSED, lambda m: self.bags_closed.append(bag_closed_event(m)),
                                 profile(names.EVENTS))
        self.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_diagnostics, 10)
        self.reach_client = ActionClient(self, reach_type(), names.REACH)
        self.transfer_client = ActionClient(self, transfer_type(), names.TRANSFER)
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

    def spin(self, executor: Any, stop: threading.Event) -> None:
        """Spin ``executor`` (single-threaded: each callback runs inside ``spin_once``) until ``stop``, each
        ``spin_once`` under :attr:`spin_lock`.  rclpy 7.1.6's ActionClient files a request's future only after
        sending it, with no lock: an executor thread that takes the answer in between drops it ("Ignoring
        unexpected goal response", seen in 1 of 2 quick demos here, which then waited in vain).  Requests are
        sent under the same lock, so no answer is taken while one is being sent."""
        while not stop.is_set():
            with self.spin_lock:
                executor.spin_once(timeout_sec=0.02)

    def ready(self) -> bool:
        return all(c.service_is_ready() for c in self.trigger_clients.values()) \
            and self.reach_client.server_is_ready() and self.transfer_client.server_is_ready()

    wait_until = staticmethod(wait_until)

    def call(self, service: str, timeout_s: float, alive: Callable[[], None] | None = None,
             progress: Callable[[], None] | None = None) -> Any:
        """Call a Trigger service and wait for its answer (showing progress meanwhile)."""
        future = self.trigger_clients[service].call_async(Trigger.Request())
        self.wait_until(future.done, timeout_s, f"the answer of {service}", alive, progress)
        if future.exception() is not None:
            raise RuntimeError(f"{service}: {future.exception()}")
        return future.result()

    def send_goal(self, client: ActionClient, name: str, goal: Any, timeout_s: float,
                  alive: Callable[[], None] | None = None, feedback: Callable[[Any], None] | None = None) -> Any:
        """Send a goal to action ``name`` (``feedback`` gets each ``Feedback``); its goal handle once accepted."""
        self.wait_until(client.server_is_ready, timeout_s, f"the {name} action server", alive)
        with self.spin_lock:  # see spin(): the answer must not be taken before the client expects it
            sent = client.send_goal_async(goal, feedback_callback=None if feedback is None else
                                          (lambda message: feedback(message.feedback)))
        self.wait_until(sent.done, timeout_s, f"{name} to take the goal", alive)
        handle = sent.result()
        if not handle.accepted:
            raise RuntimeError(f"{name} rejected the goal")
        return handle

    def goal_result(self, handle: Any, timeout_s: float, what: str, alive: Callable[[], None] | None = None,
                    progress: Callable[[], None] | None = None) -> Any:
        """Wait for an action goal's end (showing progress meanwhile); its ``Result``."""
        with self.spin_lock:
            future = handle.get_result_async()
        self.wait_until(future.done, timeout_s, what, alive, progress)
        return future.result().result

    def plan_result_for(self, goal_stamp_ns: int) -> tuple[float, PlanRecord] | None:
        """The first ``t42/plan_result`` answering the goal stamped ``goal_stamp_ns`` (with its arrival), if any."""
        return next(((at, r) for at, r in self.results if r.goal_stamp_ns == goal_stamp_ns), None)

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
