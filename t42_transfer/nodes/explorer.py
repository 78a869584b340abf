"""Explorer node: collects random-action episodes from a hand through its driver's topics.

This is how target-hand data is gathered for a transfer.  Wiring (relative names,
the driver's: remap them with ``--ros-args -r``, or run under a namespace):

* ``hand/reset`` (std_srvs/srv/Trigger): called to start each episode;
* ``hand/joint_states`` (sensor_msgs/msg/JointState): the actuator angles a
  trajectory starts from;
* ``hand/trajectory`` (trajectory_msgs/msg/JointTrajectory): one per episode;
* ``hand/applied_action`` (sensor_msgs/msg/JointState): counted against the sent actions;
* ``hand/status`` (std_msgs/msg/String, latched): ``trajectory_done`` or an
  episode end (drop, lost contact, overload) ends the episode.

For each episode it calls the reset service, waits for a joint state of the new
grasp, sends one ``JointTrajectory`` of ``steps`` random piecewise-constant actions
(the sampler of :class:`~t42_transfer.hand.collect.RandomPolicy`, seeded
``seed + episode - 1``, in ``action_unit_rad``: the unit of the model the data are
for) and counts the applied actions the driver reports.  An episode ends when the
driver reports ``trajectory_done`` (and the last applied action arrived, or a short
grace passed: the two topics are not ordered) or an end, or after a wall-clock
timeout; then the next one starts.  The start angles come from a joint state
stamped ``SETTLE_PERIODS`` control periods after the newest one seen when the reset
answered, so a state still in flight from before the reset is not mistaken for the
new grasp, and only once discovery has matched the trajectory, applied-action and
status topics with the driver.  A recorder in ``episode`` mode splits its bags on
the driver's ``reset`` status, so each episode becomes one bag.

One whole trajectory per episode (not a command per step) keeps the actions
exactly as sampled whatever the latency: the driver executes it open loop, one
point per control period, at its own rate.  After ``episodes`` episodes
:attr:`Explorer.finished` is true (``t42 node explorer`` then exits).

With ``record_start_service`` / ``record_stop_service`` set (a recorder's
``recorder/start`` and ``recorder/stop``, resolved in the node's namespace), the
explorer starts the recording right after its first reset and stops it after its
last episode (and only then finishes), so the bags hold its episodes and nothing
of the idle hand before or after them.  A recorder that is absent or does not
answer within ``SERVICE_TIMEOUT_S`` is logged and exploring goes on.

Nothing waits inside a callback: a timer advances the episode state machine and
polls the service calls' futures, so the node shares any executor.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from rclpy.client import Client
from rclpy.exceptions import InvalidServiceNameException
from rclpy.expand_topic_name import expand_topic_name
from rclpy.node import Node
from rclpy.task import Future
from rclpy.validate_full_topic_name import validate_full_topic_name
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import RCLPY, actions_to_joint_trajectory, applied_action, joint_state_arrays, names, stamp_to_ns
from t42_transfer.conventions import (
    ACTION_LIMIT,
    ACTION_UNIT_RAD,
    CONTROL_PERIOD_NS,
    CONTROL_PERIOD_S,
    MAX_ACTION_UNIT_RAD,
    MAX_PLAN_HORIZON,
    MAX_STEP_RAD,
    RANDOM_POLICY_LIMIT,
    checked_action_unit,
)
from t42_transfer.hand.collect import RandomPolicy
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.qos import profile


def _check_service_name(field: str, name: str) -> None:
    """ValueError unless ``name`` is empty or a valid (relative or absolute) service name."""
    if not name:
        return
    try:
        validate_full_topic_name(expand_topic_name(name, "explorer", "/"), is_service=True)
    except (InvalidServiceNameException, ValueError) as err:
        why = str(err).splitlines()[0].split(", at ")[0].rstrip(":")  # rcl appends its source location
        raise ValueError(f"{field}: {name!r} is not a valid service name ({why})") from None


@dataclass(frozen=True)
class ExplorerParams:
    """The explorer's ROS parameters; all but the recorder services take effect with the next episode."""

    episodes: int = param(5, "episodes to run; the node finishes after the last", min=1, max=1_000_000)
    steps: int = param(100, "random actions per episode, sent as one trajectory (the episode may end earlier; "
                       "at most the longest trajectory a driver takes)", min=1, max=MAX_PLAN_HORIZON)
    hold_max: int = param(5, "each random action is held 1..hold_max steps", min=1, max=1_000_000)
    limit: float = param(RANDOM_POLICY_LIMIT, "random actions are uniform in [-limit, limit] per actuator",
                         min=0.0, max=ACTION_LIMIT, constraints="> 0")
    seed: int = param(0, "episode k (from 1) samples its actions with seed + k - 1", min=0)
    action_unit_rad: float = param(ACTION_UNIT_RAD, "actuator step (rad) of an action of 1: the unit of the model "
                                   "the data are for (the suite's 0.025; the paper authors' models 0.00388)",
                                   min=0.0, max=MAX_ACTION_UNIT_RAD, constraints="> 0")
    rate_factor: float = param(1.0, "the driver's rate factor: episode timeouts shrink with it", min=1e-3, max=1000.0)
    timeout_margin_s: float = param(5.0, "an episode gives up this long (wall time) after its last action was due",
                                    min=0.0, max=3600.0)
    record_start_service: str = param("", "recorder Trigger service called after the first reset, e.g. "
                                          "recorder/start (empty: none)", read_only=True)
    record_stop_service: str = param("", "recorder Trigger service called after the last episode, e.g. "
                                         "recorder/stop (empty: none)", read_only=True)

    def __post_init__(self) -> None:
        for name in ("episodes", "steps", "hold_max"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {self.seed!r}")
        if not (math.isfinite(self.limit) and 0 < self.limit <= ACTION_LIMIT):
            raise ValueError(f"limit must be in (0, {ACTION_LIMIT}], got {self.limit!r}")
        try:
            checked_action_unit(self.action_unit_rad)
        except ValueError as err:
            raise ValueError(f"action_unit_rad: {err}") from None
        if (step := self.limit * self.action_unit_rad) > MAX_STEP_RAD * (1 + 1e-9):
            raise ValueError(f"limit x action_unit_rad is {step:.4g} rad a step, more than a driver takes "
                             f"({MAX_STEP_RAD:g} rad)")
        if not (math.isfinite(self.rate_factor) and self.rate_factor > 0):
            raise ValueError(f"rate_factor must be positive and finite, got {self.rate_factor!r}")
        if not (math.isfinite(self.timeout_margin_s) and self.timeout_margin_s >= 0):
            raise ValueError(f"timeout_margin_s must be >= 0 and finite, got {self.timeout_margin_s!r}")
        _check_service_name("record_start_service", self.record_start_service)
        _check_service_name("record_stop_service", self.record_stop_service)


WAITING_NOTE_S = 5.0
"""While a service awaited with no deadline (``hand/reset``) is not there, a line this often says so."""


class _Call:
    """One Trigger call polled by a timer: waits for the service, sends the request, waits for the answer."""

    def __init__(self, client: Client, wait_s: float | None, answer_s: float,
                 note: Callable[[str], None] | None = None) -> None:
        self.client = client
        self._answer_s = answer_s
        self._deadline = None if wait_s is None else time.monotonic() + wait_s
        self._future: Future | None = None
        self._note, self._since = note, time.monotonic()
        self._noted = self._since

    def poll(self) -> Trigger.Response | str | None:
        """The response once answered, the reason (str) when it failed, None while pending."""
        name = self.client.srv_name
        if self._future is None:
            if self.client.service_is_ready():
                self._future = self.client.call_async(Trigger.Request())
                self._deadline = time.monotonic() + self._answer_s
            elif self._deadline is not None and time.monotonic() > self._deadline:
                return f"{name} is not available"
            elif self._note is not None and time.monotonic() - self._noted >= WAITING_NOTE_S:
                self._noted = time.monotonic()
                self._note(f"waiting {self._noted - self._since:.0f} s for {self.client.service_name} (is the hand's "
                           "driver running, in this namespace?)")
            return None
        if self._future.done():
            err = self._future.exception()
            return self._future.result() if err is None else f"{name} failed: {err}"
        if self._deadline is not None and time.monotonic() > self._deadline:
            self.cancel()
            return f"no answer from {name} within {self._answer_s:g} s"
        return None

    def cancel(self) -> None:
        if self._future is not None and not self._future.done():
            self.client.remove_pending_request(self._future)


class Explorer(Node):
    """Runs the episodes; see the module docstring."""

    params_class = ExplorerParams  # the one its LiveParams declares; t42 node NAME --help lists it

    POLL_S = 0.02
    """Period of the timer that advances the episodes."""
    SETTLE_PERIODS = 3
    SERVICE_TIMEOUT_S = 10.0
    """How long a recorder service may take to appear, and any service to answer."""
    DONE_GRACE_S = 1.0
    """After ``trajectory_done``, how long (wall) the last applied actions may take to arrive."""

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("explorer", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        p = self.params
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        """Warnings about single messages: a flood gives a line a second, with a count."""
        self.episode = 0
        """Episodes started so far."""
        self.completed: list[dict[str, Any]] = []
        """One summary per finished episode: ``episode``, ``applied`` actions, ``end`` (how it ended)."""
        self._phase = "between_episodes"
        self._call: _Call | None = None
        self._reset_ns = 0
        self._angles: np.ndarray | None = None
        self._angles_ns = -1
        self._applied_ns = -1
        """Stamp of the latest applied action heard in any phase: proof the driver's writer reaches us."""
        self._actions = np.zeros((0, 2))
        self._unit_rad = ACTION_UNIT_RAD
        """The unit the running episode's actions were sent in."""
        self._applied = 0
        self._mismatched = 0
        self._ended: str | None = None
        self._done_at = 0.0
        self._deadline = 0.0
        self._closed = False

        self._trajectory_pub = self.create_publisher(JointTrajectory, names.HAND_TRAJECTORY, 10)
        self._reset = self.create_client(Trigger, names.HAND_RESET)
        self._record_start = self.create_client(Trigger, p.record_start_service) if p.record_start_service else None
        self._record_stop = self.create_client(Trigger, p.record_stop_service) if p.record_stop_service else None
        self.create_subscription(JointState, names.JOINT_STATES, self._on_joint_state, 10)
        self._applied_sub = self.create_subscription(JointState, names.APPLIED_ACTION, self._on_applied,
                                                     profile(names.EVERY_STEP))
        self._status_sub = self.create_subscription(String, names.HAND_STATUS, self._on_status,
                                                    profile(names.EVENT_READER))
        self._timer = self.create_timer(self.POLL_S, self._on_timer)

    @property
    def params(self) -> ExplorerParams:
        return self._params.value

    @property
    def finished(self) -> bool:
        """True once every episode ran (and the recorder was told to stop): the process may exit."""
        return self._phase == "finished"

    def close(self) -> None:
        """Stop advancing and drop a pending service call (the owner destroys the node)."""
        if self._closed:
            return
        self._closed = True  # the timer callback returns at once from now on (cancelling it here would race
        # a tick the executor already took: "timer is canceled")
        if self._call is not None:
            self._call.cancel()

    # ------------------------------------------------------------------ callbacks
    def _on_params(self, old: ExplorerParams, new: ExplorerParams) -> None:
        changed = [f"{f.name} {getattr(old, f.name)} -> {getattr(new, f.name)}" for f in dataclasses.fields(new)
                   if getattr(old, f.name) != getattr(new, f.name)]
        self.log.info(f"{', '.join(changed)}: takes effect with the next episode")

    def _on_joint_state(self, msg: JointState) -> None:
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            _, angles = joint_state_arrays(msg)
        except Exception as err:  # never raise from a callback
            self.per_message.warning(f"ignored a joint state: {err}")
            return
        if angles is not None and stamp >= self._angles_ns:
            self._angles, self._angles_ns = angles, stamp

    def _on_applied(self, msg: JointState) -> None:
        self._applied_ns = max(self._applied_ns, stamp_to_ns(msg.header.stamp))
        if self._phase != "running":
            return
        try:
            action = applied_action(msg, unit_rad=self._unit_rad)
        except Exception as err:
            self.per_message.warning(f"ignored an applied action: {err}")
            return
        # Count the trajectory's own steps (a rejected trajectory, which the driver logs, applies none).
        if self._applied < len(self._actions) and np.allclose(action, self._actions[self._applied], atol=1e-3):
            self._applied += 1
        else:
            self._mismatched += 1

    def _on_status(self, msg: String) -> None:
        words = msg.data.split()
        event = words[0].rstrip(":") if words else ""
        if (self._phase == "running" and self._ended is None
                and (event in names.END_EVENTS or event == names.TRAJECTORY_DONE)):
            self._ended = event
            self._done_at = time.monotonic()

    def _on_timer(self) -> None:
        if self._closed:
            return
        try:
            self._advance()
        except Exception as err:  # never raise from a callback: give the episode up, go on
            self.log.error(f"episode {self.episode} failed: {err!r}")
            if self._call is not None:
                self._call.cancel()
                self._call = None
            self._finish_episode("error")

    # ------------------------------------------------------------------ the episode loop
    def _advance(self) -> None:
        p = self.params
        if self._phase == "between_episodes":
            if self.episode >= p.episodes:
                self._phase = "stopping"
                if self._record_stop is not None:
                    self._call = _Call(self._record_stop, self.SERVICE_TIMEOUT_S, self.SERVICE_TIMEOUT_S)
            else:
                self._phase = "resetting"
                self._call = _Call(self._reset, None, self.SERVICE_TIMEOUT_S, note=self.log.info)
        if self._phase == "resetting":
            self._on_reset_answer(self._call.poll())
        elif self._phase == "starting_recorder":
            if self._recorder_answered(self._call.poll()):
                self._call, self._phase = None, "grasped"
        elif self._phase == "grasped":
            settled = self._angles is not None and self._angles_ns > self._reset_ns
            # An applied action heard since the reset: the driver's writer has matched our reader too
            # (discovery matches each side on its own), so none of the episode's actions can be missed.
            heard = self._applied_ns > self._reset_ns
            if settled and heard and self._matched():
                self._send_trajectory()
        elif self._phase == "running":
            self._check_episode_end()
        elif self._phase == "stopping":
            if self._call is None or self._recorder_answered(self._call.poll()):
                self._call = None
                self._phase = "finished"
                self.log.info(f"explored {len(self.completed)} episodes")

    def _matched(self) -> bool:
        """Whether discovery matched the trajectory, applied-action and status topics with the driver.

        A trajectory sent before would be lost, and applied actions or statuses
        missed would end the episode as a mismatch or a timeout.
        """
        return (self._trajectory_pub.get_subscription_count() > 0 and self._applied_sub.get_publisher_count() > 0
                and self._status_sub.get_publisher_count() > 0)

    def _on_reset_answer(self, answer: Trigger.Response | str | None) -> None:
        if answer is None:
            return
        self.episode += 1
        self._call = None
        ok = not isinstance(answer, str) and answer.success
        if not ok:
            why = answer if isinstance(answer, str) else answer.message
            self.log.warning(f"reset failed ({why}); episode {self.episode} skipped")
            self.completed.append({"episode": self.episode, "applied": 0, "end": names.RESET_FAILED})
            self._phase = "between_episodes"
            return
        newest = max(self.get_clock().now().nanoseconds, self._angles_ns)
        self._reset_ns = newest + self.SETTLE_PERIODS * CONTROL_PERIOD_NS
        if self.episode == 1 and self._record_start is not None:
            self._call = _Call(self._record_start, self.SERVICE_TIMEOUT_S, self.SERVICE_TIMEOUT_S)
            self._phase = "starting_recorder"
        else:
            self._phase = "grasped"

    def _recorder_answered(self, answer: Trigger.Response | str | None) -> bool:
        """Log a recorder call's outcome (a failure does not stop exploring); False while pending."""
        if answer is None:
            return False
        name = self._call.client.srv_name
        if isinstance(answer, str):
            self.log.warning(f"{answer}; exploring goes on")
        elif answer.success:
            self.log.info(f"{name}: {answer.message}")
        else:
            self.log.warning(f"{name} refused: {answer.message}; exploring goes on")
        return True

    def _send_trajectory(self) -> None:
        p = self.params
        rng = np.random.default_rng(p.seed + self.episode - 1)
        actions = RandomPolicy(hold_max=p.hold_max, limit=p.limit).sample(rng, p.steps)
        self._actions, self._applied, self._mismatched, self._ended = actions, 0, 0, None
        self._unit_rad = p.action_unit_rad  # the episode's, should the parameter change during it
        now = self.get_clock().now().nanoseconds
        self._trajectory_pub.publish(actions_to_joint_trajectory(actions, self._angles, now, RCLPY, p.action_unit_rad))
        # Wall time: under use_sim_time ROS time runs rate_factor times faster.
        self._deadline = time.monotonic() + p.steps * CONTROL_PERIOD_S / p.rate_factor + p.timeout_margin_s
        self._phase = "running"

    def _check_episode_end(self) -> None:
        if self._ended == names.TRAJECTORY_DONE:
            if self._applied == len(self._actions):
                self._finish_episode("complete")
            elif time.monotonic() > self._done_at + self.DONE_GRACE_S:
                self._finish_episode("mismatch")
        elif self._ended is not None:
            self._finish_episode(self._ended)
        elif time.monotonic() > self._deadline:
            self._finish_episode("timeout")

    def _finish_episode(self, end: str) -> None:
        self.completed.append({"episode": self.episode, "applied": self._applied, "end": end})
        other = f" ({self._mismatched} other steps)" if self._mismatched else ""
        self.log.info(f"episode {self.episode}/{self.params.episodes}: {self._applied} actions applied{other}, {end}")
        self._phase = "between_episodes"
