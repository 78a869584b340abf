"""Mock hand driver: a :class:`~t42_transfer.hand.sim.SimulatedHand` behind the real driver's topics.

Wiring (defaults; every name is a :class:`MockDriverParams` field):

* ``/hand/object_pose`` (geometry_msgs/msg/PoseStamped): published each step;
* ``/hand/joint_states`` (sensor_msgs/msg/JointState): published each step,
  position = actuator angles, effort = loads;
* ``/hand/applied_action`` (sensor_msgs/msg/JointState): published each step the hand moves;
* ``/hand/command`` (sensor_msgs/msg/JointState): subscribed, one single-step
  action as velocity = action * ACTION_UNIT_RAD / CONTROL_PERIOD_S;
* ``/hand/trajectory`` (trajectory_msgs/msg/JointTrajectory): subscribed, a whole
  open-loop sequence of actuator-angle targets, one point per control period;
* ``/hand/reset`` (std_srvs/srv/Trigger): served, re-open, re-grasp, start an episode;
* ``/hand/status`` (std_msgs/msg/String, latched): episode ends, resets, and
  ``trajectory_done`` when a trajectory's last point is being applied.

Timing.  A timer every ``CONTROL_PERIOD_S / rate_factor`` seconds runs one step.
A step stamped ``t = transport.now_ns()`` publishes the current state (pose and
joint states) and, if the episode is still running, the action applied from that
state, all with stamp ``t`` (the bag convention of :mod:`t42_transfer.data.bag_io`:
state ``k`` and action ``k`` share a stamp), then steps the hand with that action.
When a step ends the episode (drop, lost contact, overload) the next timer tick
publishes the final state without an action, publishes ``/hand/status`` and stops
stepping until ``/hand/reset``.  With ``rate_factor != 1`` and wall-clock stamps
they would be ``0.1 / rate_factor`` s apart, which is not a T42 recording; so
``sim_time`` makes the driver the clock of the graph, as a simulator is in ROS: it
publishes ``/clock`` (rosgraph_msgs/msg/Clock) every tick, advancing exactly one
control period per tick from the wall time it started at, and stamps everything
with it.  Nodes run with ``use_sim_time:=true`` then read ROS time from ``/clock``,
so stamps, staleness checks and recorded times agree at any rate.

Which action a step applies:

* a running trajectory's next point (one point per step, open loop);
* else the last single-step command received since the previous step, held for
  ONE step only; with no new command the step applies ``(0, 0)`` (the hand holds).

A new single-step command cancels a running trajectory; a new trajectory
pre-empts a running one (and drops a pending single-step command); an empty
trajectory just cancels (ROS's "stop" convention).  Of several commands arriving
within one period the latest wins.

Bad input (NaN/inf, ``|a| > ACTION_LIMIT``, missing actuators or value counts
that do not match the names, trajectory points not one period apart, unset,
stale or future stamps) is rejected: the callback logs the reason with
``transport.logger.warning`` and leaves the pending command as it was.  No
callback raises.  The checks are the pure functions :func:`validate_command`,
:func:`validate_trajectory` and :func:`check_stamp`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from msg_adapters import (
    APPLIED_ACTION_TOPIC,
    JOINT_STATE,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY,
    OBJECT_POSE_TOPIC,
    POSE_STAMPED,
    TYPESTORE,
    applied_action,
    applied_action_msg,
    joint_state_msg,
    joint_trajectory_to_actions,
    ns_to_stamp,
    object_pose_msg,
    stamp_to_ns,
)
from t42_transfer.conventions import ACTION_DIM, ACTION_LIMIT, CONTROL_PERIOD_NS, CONTROL_PERIOD_S
from t42_transfer.hand.sim import GraspFailed, SimulatedHand
from t42_transfer.ros import qos
from t42_transfer.ros.naming import validate_name
from t42_transfer.ros.transport import Transport, service_classes

STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"

CLOCK = "rosgraph_msgs/msg/Clock"
CLOCK_TOPIC = "/clock"
COMMAND_TOPIC = "/hand/command"
TRAJECTORY_TOPIC = "/hand/trajectory"
RESET_SERVICE = "/hand/reset"
STATUS_TOPIC = "/hand/status"

_LIMIT_SLACK = 1e-6
"""Relative slack on ACTION_LIMIT: wire round trips may land a hair past +-1.5."""

_String = TYPESTORE.types[STRING]
_Clock = TYPESTORE.types[CLOCK]


class CommandRejected(ValueError):
    """An input message the driver will not execute; the message says why."""


@dataclass(frozen=True)
class MockDriverParams:
    """Parameters of :class:`MockDriver` (the node's ROS parameters)."""

    hand: str = "target"
    """Hand variant for :class:`SimulatedHand` ("source", "target" or "family-<seed>")."""
    rate_factor: float = 1.0
    """Steps run ``rate_factor`` times faster than real time (timer period 0.1 s / rate_factor)."""
    seed: int | None = 0
    """Seed of the first grasp; reset ``k`` (counting from 0) uses ``seed + k`` (None: unseeded)."""
    max_command_age_s: float = 0.5
    """Commands (and stamped trajectories) older, or further in the future, than this are stale."""
    sim_time: bool = False
    """Publish the simulated time on ``clock_topic`` and stamp with it (see the module docstring)."""
    clock_topic: str = CLOCK_TOPIC
    object_pose_topic: str = OBJECT_POSE_TOPIC
    joint_states_topic: str = JOINT_STATES_TOPIC
    applied_action_topic: str = APPLIED_ACTION_TOPIC
    command_topic: str = COMMAND_TOPIC
    trajectory_topic: str = TRAJECTORY_TOPIC
    reset_service: str = RESET_SERVICE
    status_topic: str = STATUS_TOPIC

    def __post_init__(self) -> None:
        rate = self.rate_factor
        if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate_factor must be a positive finite number, got {self.rate_factor!r}")
        if not (math.isfinite(self.max_command_age_s) and self.max_command_age_s > 0):
            raise ValueError(f"max_command_age_s must be positive and finite, got {self.max_command_age_s!r}")
        if self.seed is not None and not isinstance(self.seed, int):
            raise ValueError(f"seed must be an int or None, got {self.seed!r}")
        for field in ("object_pose_topic", "joint_states_topic", "applied_action_topic", "command_topic",
                      "trajectory_topic", "status_topic", "clock_topic"):
            validate_name(getattr(self, field))
        validate_name(self.reset_service, "service")

    @property
    def period_s(self) -> float:
        return CONTROL_PERIOD_S / self.rate_factor

    @property
    def max_command_age_ns(self) -> int:
        return round(self.max_command_age_s * 1e9)


# --------------------------------------------------------------------------- pure checks
def check_stamp(stamp_ns: int, now_ns: int, max_age_ns: int, what: str = "command") -> None:
    """Refuse an unset (zero), stale (older than ``max_age_ns``) or future (beyond ``max_age_ns``) stamp."""
    if stamp_ns == 0:
        raise CommandRejected(f"{what} header stamp is unset (0)")
    age = now_ns - stamp_ns
    if age > max_age_ns:
        raise CommandRejected(f"{what} is stale: stamped {age / 1e9:.3f} s ago, limit {max_age_ns / 1e9:.3f} s")
    if -age > max_age_ns:
        raise CommandRejected(
            f"{what} is stamped {-age / 1e9:.3f} s in the future, limit {max_age_ns / 1e9:.3f} s"
        )


def check_actions(actions: np.ndarray, what: str = "action") -> np.ndarray:
    """``actions`` ([..., 2]) clipped onto the limit if within slack; CommandRejected if non-finite or too large."""
    acts = np.asarray(actions, dtype=np.float64)
    if acts.shape[-1:] != (ACTION_DIM,):
        raise CommandRejected(f"{what} must have {ACTION_DIM} components, got shape {acts.shape}")
    if not np.all(np.isfinite(acts)):
        raise CommandRejected(f"{what} has a non-finite value: {acts.tolist()}")
    too_big = np.abs(acts) > ACTION_LIMIT * (1.0 + _LIMIT_SLACK)
    if np.any(too_big):
        where = np.argwhere(too_big)[0].tolist()
        raise CommandRejected(
            f"{what} {acts[tuple(where)]:.6g} at index {where} is outside [-{ACTION_LIMIT}, {ACTION_LIMIT}]"
        )
    return np.clip(acts, -ACTION_LIMIT, ACTION_LIMIT)


def validate_command(msg: Any, now_ns: int, max_age_ns: int) -> np.ndarray:
    """The single-step action (float64 [2]) of a command ``JointState``, or CommandRejected saying why.

    The action is decoded from ``velocity`` by :func:`msg_adapters.applied_action`
    (velocity = action * ACTION_UNIT_RAD / CONTROL_PERIOD_S per actuator).
    """
    check_stamp(stamp_to_ns(msg.header.stamp), now_ns, max_age_ns, "command")
    try:
        action = applied_action(msg)
    except ValueError as err:
        raise CommandRejected(f"command: {err}") from None
    return check_actions(action, "command action")


def validate_trajectory(msg: Any, start_angles: np.ndarray | Sequence[float], now_ns: int,
                        max_age_ns: int) -> np.ndarray:
    """Actions ``[T, 2]`` (float64) of a ``JointTrajectory`` started from ``start_angles``, or CommandRejected.

    Decoded by :func:`msg_adapters.joint_trajectory_to_actions` (points every
    control period, actuator-angle targets).  A zero header stamp means "start
    now" (ROS convention); any other stamp must be fresh as for commands.  An
    empty trajectory is valid and gives ``T = 0``.
    """
    stamp = stamp_to_ns(msg.header.stamp)
    if stamp != 0:
        check_stamp(stamp, now_ns, max_age_ns, "trajectory")
    try:
        actions = joint_trajectory_to_actions(msg, start_angles)
    except ValueError as err:
        raise CommandRejected(f"trajectory: {err}") from None
    return check_actions(actions.reshape(-1, ACTION_DIM), "trajectory action")


def status_message(event: str, detail: str = "") -> str:
    """Text of a ``/hand/status`` message: the event word first (``dropped``, ``overload``, ``reset``...)."""
    return f"{event}: {detail}" if detail else event


# --------------------------------------------------------------------------- the node
class MockDriver:
    """The simulated hand on the driver's topics; see the module docstring for behaviour."""

    def __init__(self, transport: Transport, params: MockDriverParams | None = None) -> None:
        self.transport = transport
        self.params = params if params is not None else MockDriverParams()
        p = self.params
        self.log = transport.logger
        self.hand = SimulatedHand(p.hand)
        self.episode = -1
        """Index of the current episode (resets so far - 1)."""
        self.steps = 0
        """Steps taken in the current episode."""
        self.running = False
        """Whether the timer steps the hand (False after an episode end until a reset)."""
        self._command: np.ndarray | None = None
        self._plan: list[np.ndarray] = []

        self._pose_pub = transport.publisher(p.object_pose_topic, POSE_STAMPED, qos.DEFAULT)
        self._joints_pub = transport.publisher(p.joint_states_topic, JOINT_STATE, qos.DEFAULT)
        self._action_pub = transport.publisher(p.applied_action_topic, JOINT_STATE, qos.DEFAULT)
        self._status_pub = transport.publisher(p.status_topic, STRING, qos.TRANSIENT_LOCAL)
        self._sim_ns = transport.now_ns()
        self._clock_pub = transport.publisher(p.clock_topic, CLOCK, qos.CLOCK) if p.sim_time else None
        _, self._Response = service_classes(TRIGGER)
        transport.subscribe(p.command_topic, JOINT_STATE, qos.DEFAULT, self._on_command)
        transport.subscribe(p.trajectory_topic, JOINT_TRAJECTORY, qos.DEFAULT, self._on_trajectory)
        transport.service(p.reset_service, TRIGGER, self._on_reset)
        ok, why = self.reset()
        if not ok:
            self.log.warning("initial grasp failed: %s; call %s to retry", why, p.reset_service)
        self._timer = transport.timer(p.period_s, self._on_timer)

    # ------------------------------------------------------------------ state
    @property
    def pending_actions(self) -> int:
        """Trajectory points still to execute."""
        return len(self._plan)

    def reset(self) -> tuple[bool, str]:
        """Re-open the hand, re-grasp (seed ``params.seed + episode``) and start stepping; (success, message)."""
        self._command, self._plan = None, []
        self.episode += 1
        seed = None if self.params.seed is None else self.params.seed + self.episode
        try:
            self.hand.reset(seed)
        except GraspFailed as err:
            self.running = False
            self._publish_status(status_message("reset_failed", str(err)))
            return False, f"grasp failed: {err}"
        self.running, self.steps = True, 0
        message = f"episode {self.episode} grasped (seed {seed})"
        self._publish_status(status_message("reset", message))
        return True, message

    def now_ns(self) -> int:
        """The driver's time: the simulated clock with ``sim_time``, else the transport's."""
        return self._sim_ns if self._clock_pub is not None else self.transport.now_ns()

    def close(self) -> None:
        """Stop the timer (the transport's owner closes the transport)."""
        self._timer.cancel()

    # ------------------------------------------------------------------ callbacks
    def _on_command(self, msg: Any) -> None:
        try:
            action = validate_command(msg, self.now_ns(), self.params.max_command_age_ns)
        except CommandRejected as err:
            self.log.warning("rejected %s: %s; keeping the last safe command", self.params.command_topic, err)
            return
        except Exception:  # never raise from a callback
            self.log.exception("rejected %s: could not read the message", self.params.command_topic)
            return
        if self._plan:
            self.log.info("single-step command cancels a trajectory with %d points left", len(self._plan))
        self._plan = []
        self._command = action

    def _on_trajectory(self, msg: Any) -> None:
        try:
            actions = validate_trajectory(
                msg, self.hand.actuator_angles, self.now_ns(), self.params.max_command_age_ns
            )
        except CommandRejected as err:
            self.log.warning("rejected %s: %s; keeping the last safe command", self.params.trajectory_topic, err)
            return
        except Exception:
            self.log.exception("rejected %s: could not read the message", self.params.trajectory_topic)
            return
        if self._plan:
            self.log.info("trajectory with %d points pre-empts one with %d points left", len(actions), len(self._plan))
        self._plan = list(actions)
        self._command = None

    def _on_reset(self, request: Any) -> Any:
        try:
            ok, message = self.reset()
        except Exception as err:  # a service handler must answer, not raise
            self.log.exception("reset failed")
            self.running = False
            ok, message = False, f"reset failed: {err}"
        return self._Response(success=ok, message=message)

    def _on_timer(self) -> None:
        try:
            if self._clock_pub is not None:
                self._sim_ns += CONTROL_PERIOD_NS
                self._clock_pub.publish(_Clock(clock=ns_to_stamp(self._sim_ns)))
            self._tick()
        except Exception:
            self.log.exception("step failed; the hand stops until %s", self.params.reset_service)
            self.running, self._command, self._plan = False, None, []

    # ------------------------------------------------------------------ one step
    def _next_action(self) -> np.ndarray:
        """The action of this step, as float32 values (what the applied-action topic can carry exactly)."""
        if self._plan:
            action = self._plan.pop(0)
            if not self._plan:
                self._publish_status(status_message("trajectory_done", f"episode {self.episode} step {self.steps + 1}"))
        else:
            action = self._command if self._command is not None else np.zeros(ACTION_DIM)
            self._command = None  # a single-step command is held for one step only
        return np.asarray(action, np.float32).astype(np.float64)

    def _tick(self) -> None:
        if not self.running:
            return
        stamp = self.now_ns()
        state = self.hand.state
        self._pose_pub.publish(object_pose_msg(state[:2], stamp))
        self._joints_pub.publish(joint_state_msg(state[2:], self.hand.actuator_angles, stamp))
        if self.hand.done:
            self.running = False
            self._command, self._plan = None, []
            reason = self.hand.end_reason
            self.log.warning("episode %d ended after %d steps: %s", self.episode, self.steps, reason)
            self._publish_status(status_message(reason, f"episode {self.episode} ended after {self.steps} steps"))
            return
        action = self._next_action()
        self._action_pub.publish(applied_action_msg(action, stamp))
        info = self.hand.step_info(action)
        self.steps += 1
        if info.refused:
            self.log.info("step %d: a servo move was refused (travel limit or load guard)", self.steps)

    def _publish_status(self, text: str) -> None:
        self._status_pub.publish(_String(data=text))
