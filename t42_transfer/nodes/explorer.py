"""Explorer node: collects random-action episodes from a hand through its driver's topics.

This is how target-hand data is gathered for a transfer: for each episode it calls
the driver's reset service (``/hand/reset``), waits for the first joint state of
the new grasp, sends one ``JointTrajectory`` of ``steps`` random piecewise-constant
actions (the sampler of :class:`~t42_transfer.hand.collect.RandomPolicy`, seeded
``seed + episode``) on ``/hand/trajectory``, and counts the applied actions the
driver reports on ``/hand/applied_action``.  An episode ends when the driver's
``/hand/status`` reports ``trajectory_done`` or an end (drop, lost contact,
overload), or after a timeout; then the next one starts.  The start angles are
taken from a joint state stamped ``SETTLE_PERIODS`` control periods after the
newest one seen when the reset answered, so a state still in flight from before the
reset is not mistaken for the new grasp.  A recorder in ``episode`` mode splits
its bags on the driver's ``reset`` status, so each episode becomes one bag.

One whole trajectory per episode (not a command per step) keeps the actions
exactly as sampled whatever the transport latency: the driver executes it open
loop, one point per control period, at its own rate.  After ``episodes`` episodes
:attr:`Explorer.finished` is true and the node idles (``t42 node`` exits).

With ``record_start_service`` / ``record_stop_service`` set (a recorder's
``/recorder/start`` and ``/recorder/stop``), the explorer starts the recording right
after its first reset and stops it after its last episode, so the bags hold its
episodes and nothing of the idle hand before or after them.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters import (
    APPLIED_ACTION_TOPIC,
    JOINT_STATE,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY,
    actions_to_joint_trajectory,
    applied_action,
    joint_state_arrays,
    stamp_to_ns,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS, CONTROL_PERIOD_S
from t42_transfer.hand.collect import RANDOM_POLICY_LIMIT, RandomPolicy
from t42_transfer.nodes.mock_driver import RESET_SERVICE, STATUS_TOPIC, STRING, TRAJECTORY_TOPIC, TRIGGER
from t42_transfer.nodes.recorder import END_EVENTS
from t42_transfer.ros import qos
from t42_transfer.ros.naming import validate_name
from t42_transfer.ros.transport import Transport, deserialize


@dataclass(frozen=True)
class ExplorerParams:
    """Parameters of :class:`Explorer` (the node's ROS parameters)."""

    episodes: int = 5
    steps: int = 100
    """Random actions per episode (the episode may end earlier)."""
    hold_max: int = 5
    """Each random action is held 1..hold_max steps."""
    limit: float = RANDOM_POLICY_LIMIT
    seed: int = 0
    rate_factor: float = 1.0
    """The driver's rate factor: episode timeouts shrink with it."""
    timeout_margin_s: float = 5.0
    """An episode gives up this long (wall) after its last action was due."""
    record_start_service: str = ""
    """Trigger service called after the first reset (empty: none)."""
    record_stop_service: str = ""
    """Trigger service called after the last episode (empty: none)."""
    reset_service: str = RESET_SERVICE
    trajectory_topic: str = TRAJECTORY_TOPIC
    joint_states_topic: str = JOINT_STATES_TOPIC
    applied_action_topic: str = APPLIED_ACTION_TOPIC
    status_topic: str = STATUS_TOPIC

    def __post_init__(self) -> None:
        for name in ("episodes", "steps", "hold_max"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not (math.isfinite(self.limit) and 0 < self.limit <= 1.5):
            raise ValueError(f"limit must be in (0, 1.5], got {self.limit!r}")
        if not (math.isfinite(self.rate_factor) and self.rate_factor > 0):
            raise ValueError(f"rate_factor must be positive, got {self.rate_factor!r}")
        for name in ("trajectory_topic", "joint_states_topic", "applied_action_topic", "status_topic",
                     "reset_service", "record_start_service", "record_stop_service"):
            if name.startswith("record_") and not getattr(self, name):
                continue
            try:
                validate_name(getattr(self, name), "service" if name.endswith("_service") else "topic")
            except ValueError as err:
                raise ValueError(f"{name}: {err}") from None


class Explorer:
    """Runs the episodes; see the module docstring.  Driven by a timer of the node."""

    POLL_S = 0.02
    SETTLE_PERIODS = 3

    def __init__(self, transport: Transport, params: ExplorerParams | None = None) -> None:
        self.transport = transport
        self.params = p = params if params is not None else ExplorerParams()
        self.log = transport.logger
        self.policy = RandomPolicy(hold_max=p.hold_max, limit=p.limit)
        self.episode = 0
        """Episodes started so far."""
        self.completed: list[dict[str, Any]] = []
        """One summary per finished episode: applied actions, how it ended."""
        self._phase = "reset"
        self._reset_ns = 0
        self._angles: np.ndarray | None = None
        self._angles_ns = -1
        self._actions = np.zeros((0, 2))
        self._mismatched = 0
        self._applied = 0
        self._ended: str | None = None
        self._deadline = 0.0
        self._trajectory_pub = transport.publisher(p.trajectory_topic, JOINT_TRAJECTORY, qos.DEFAULT)
        self._reset = transport.client(p.reset_service, TRIGGER)
        self._record_start = transport.client(p.record_start_service, TRIGGER) if p.record_start_service else None
        self._record_stop = transport.client(p.record_stop_service, TRIGGER) if p.record_stop_service else None
        transport.subscribe(p.joint_states_topic, JOINT_STATE, qos.DEFAULT, self._on_joint_state)
        transport.subscribe(p.applied_action_topic, JOINT_STATE, qos.DEFAULT, self._on_applied, raw=True)
        transport.subscribe(p.status_topic, STRING, qos.TRANSIENT_LOCAL, self._on_status)
        self._timer = transport.timer(self.POLL_S, self._on_timer)

    @property
    def finished(self) -> bool:
        return self._phase == "finished"

    def close(self) -> None:
        self._timer.cancel()

    # ------------------------------------------------------------------ callbacks
    def _on_joint_state(self, msg: Any) -> None:
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            _, angles = joint_state_arrays(msg)
            if angles is not None and stamp >= self._angles_ns:
                self._angles, self._angles_ns = angles, stamp
        except Exception as err:  # never raise from a callback
            self.log.warning("ignored a joint state: %s", err)

    def _on_applied(self, data: Any) -> None:
        if self._phase != "running":
            return
        try:
            action = applied_action(deserialize(JOINT_STATE, data))
        except Exception as err:
            self.log.warning("ignored an applied action: %s", err)
            return
        # Count the trajectory's own steps (a rejected trajectory, which the driver logs, applies none).
        if self._applied < len(self._actions) and np.allclose(action, self._actions[self._applied], atol=1e-3):
            self._applied += 1
        else:
            self._mismatched += 1

    def _on_status(self, msg: Any) -> None:
        words = str(msg.data).split()
        event = words[0].rstrip(":") if words else ""
        if self._phase == "running" and (event in END_EVENTS or event == "trajectory_done"):
            self._ended = event

    def _on_timer(self) -> None:
        try:
            self._advance()
        except Exception:  # never raise from a callback: give the episode up, go on
            self.log.exception("episode %d failed", self.episode)
            self._finish_episode("error")

    # ------------------------------------------------------------------ the episode loop
    def _advance(self) -> None:
        p, now = self.params, self.transport.now_ns()
        if self._phase == "reset":
            if self.episode >= p.episodes:
                self._trigger(self._record_stop)
                self._phase = "finished"
                self.log.info("explored %d episodes", len(self.completed))
                return
            if not self._reset.service_is_ready():
                return
            response = self._reset.call(self._reset.Request(structure_needs_at_least_one_member=0), timeout_s=10.0)
            self.episode += 1
            if not response.success:
                self.log.warning("reset failed (%s); episode %d skipped", response.message, self.episode)
                self.completed.append({"episode": self.episode, "applied": 0, "end": "reset_failed"})
                return
            self._reset_ns = max(self.transport.now_ns(), self._angles_ns) + self.SETTLE_PERIODS * CONTROL_PERIOD_NS
            self._phase = "grasped"
            if self.episode == 1:
                self._trigger(self._record_start)
        elif self._phase == "grasped":
            if self._angles is None or self._angles_ns <= self._reset_ns:
                return
            self._send_trajectory(now)
        elif self._phase == "running":
            if self._ended == "trajectory_done":
                self._finish_episode("complete" if self._applied == p.steps else "mismatch")
            elif self._ended is not None:
                self._finish_episode(self._ended)
            elif time.monotonic() > self._deadline:
                self._finish_episode("timeout")

    def _trigger(self, client: Any) -> None:
        """Call a recorder's Trigger service; a failure is logged, exploring goes on."""
        if client is None:
            return
        try:
            response = client.call(client.Request(structure_needs_at_least_one_member=0), timeout_s=10.0)
            (self.log.info if response.success else self.log.warning)("%s: %s", client.name, response.message)
        except Exception as err:
            self.log.warning("%s failed: %s", client.name, err)

    def _send_trajectory(self, now: int) -> None:
        p = self.params
        rng = np.random.default_rng(p.seed + self.episode - 1)
        actions = self.policy.sample(rng, p.steps)
        self._actions, self._applied, self._mismatched, self._ended = actions, 0, 0, None
        self._trajectory_pub.publish(actions_to_joint_trajectory(actions, self._angles, now))
        # Wall time: under use_sim_time ROS time runs rate_factor times faster.
        self._deadline = time.monotonic() + p.steps * CONTROL_PERIOD_S / p.rate_factor + p.timeout_margin_s
        self._phase = "running"

    def _finish_episode(self, end: str) -> None:
        self.completed.append({"episode": self.episode, "applied": self._applied, "end": end})
        other = f" ({self._mismatched} other steps)" if self._mismatched else ""
        self.log.info("episode %d/%d: %d actions applied%s, %s", self.episode, self.params.episodes,
                      self._applied, other, end)
        self._phase = "reset"
