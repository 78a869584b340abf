"""Mock hand driver: a :class:`~t42_transfer.hand.sim.SimulatedHand` behind the real driver's topics.

Wiring (relative names: remap them with ``--ros-args -r``, or run under a namespace):

* ``hand/object_pose`` (geometry_msgs/msg/PoseStamped): published each step;
* ``hand/joint_states`` (sensor_msgs/msg/JointState): published each step,
  position = actuator angles, effort = loads;
* ``hand/applied_action`` (sensor_msgs/msg/JointState): published each step the hand moves;
* ``hand/command`` (sensor_msgs/msg/JointState): subscribed, one single-step
  action as velocity = action * ACTION_UNIT_RAD / CONTROL_PERIOD_S;
* ``hand/trajectory`` (trajectory_msgs/msg/JointTrajectory): subscribed, a whole
  open-loop sequence of actuator-angle targets, one point per control period;
* ``hand/reset`` (std_srvs/srv/Trigger): served, re-open, re-grasp, start an episode;
* ``hand/status`` (std_msgs/msg/String, latched): episode ends, resets, and
  ``trajectory_done`` when a trajectory's last point is being applied.

Camera (``camera_rate_hz`` above 0, :mod:`t42_transfer.ros.sim_camera`): the hand is rendered with its
markers and published on ``camera/image_raw`` + ``camera/camera_info`` (true intrinsics), with the true pose on
``sim/object_pose``.  A frame is rendered at the end of a step, so it shows the state the next step publishes,
and carries that step's stamp on sim time (the simulated clock jumps one period per tick, and that state holds
from then); on wall-clock time it is stamped when rendered.  ``pose_source: topic`` makes the driver publish,
as ``hand/object_pose``, the newest ``tracker/object_pose`` instead of the simulator's, by the real driver's
rule (:mod:`t42_transfer.driver.pose`: never one older than ``max_pose_age_s``; ``stale`` on ``hand/status``).
On sim time the driver runs in lockstep with the tracker: a tick waits (``tracker_wait_s`` of wall time at
most) until the tracker's pose of the last frame came, so a slow tracker slows the graph's clock instead of
leaving steps without a pose, and each step's pose is its own frame's, with the frame's stamp.  A reset renders
the new grasp at once (on sim time the re-grasp takes one period of the graph's clock, so its frame is stamped
after every frame of the old grasp), and a pose of a frame before it, which a busy tracker sends late, is left
out: the first step of an episode never goes out with the old grasp's pose.  Every reset says ``grasping`` on
``hand/status`` before it re-grasps, as the Dynamixel driver does (the tracker's cue that the object moves on
purpose).  ``seed`` and
``pose_source`` may change at run time: a seed set applies from the next reset (a grasp made again).

Timing.  A timer every ``CONTROL_PERIOD_S / rate_factor`` seconds runs one step.
A step stamped ``t`` (ROS time) publishes the current state (pose and
joint states) and, if the episode is still running, the action applied from that
state, all with stamp ``t`` (the bag convention of :mod:`t42_transfer.data.bag`:
state ``k`` and action ``k`` share a stamp), then steps the hand with that action.
When a step ends the episode (drop, lost contact, overload) the next timer tick
publishes the final state without an action, publishes ``hand/status`` and stops
stepping until ``hand/reset``.  With ``rate_factor != 1`` and wall-clock stamps
they would be ``0.1 / rate_factor`` s apart, which is not a T42 recording; so
``sim_time`` makes the driver the clock of the graph, as a simulator is in ROS: it
publishes ``/clock`` (rosgraph_msgs/msg/Clock) every tick, advancing one
control period per tick from the wall time it started at (a reset with the camera
on adds one: see "Camera"), and stamps everything with it.  Nodes run with
``use_sim_time:=true`` then read ROS time from ``/clock``, so stamps, staleness
checks and recorded times agree at any rate.

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
the node's logger and leaves the pending command as it was.  No
callback raises.  The checks and the queue are :mod:`t42_transfer.driver.commands`, shared with the
real hand's driver.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    applied_action_msg,
    grasp_detail,
    grasping_detail,
    joint_state_msg,
    names,
    ns_to_stamp,
    object_pose_msg,
    status_message,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS, CONTROL_PERIOD_S
from t42_transfer.driver.commands import ActionQueue, accept, validate_command, validate_trajectory
from t42_transfer.driver.pose import NewestPose
from t42_transfer.driver.timing import StepTiming, step_timing
from t42_transfer.hand.params import NAMED_VARIANTS
from t42_transfer.hand.sim import GraspFailed, SimulatedHand
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.qos import profile
from t42_transfer.ros.sim_camera import SimCamera, SimCameraParams

POSE_SOURCES = ("sim", "topic")


@dataclass(frozen=True)
class MockDriverParams(SimCameraParams):
    """The mock driver's ROS parameters (and its camera's)."""

    hand: str = param("target", f"simulated hand variant: {', '.join(NAMED_VARIANTS)} or family-<seed>", read_only=True)
    rate_factor: float = param(1.0, "steps run this many times faster than real time (timer 0.1 s / rate_factor)",
                               min=1e-3, max=1000.0)
    seed: int = param(0, "seed of the first grasp; each reset after uses the next (-1: unseeded, a new grasp each "
                         "reset); a change applies from the next reset, which grasps with the new seed", min=-1)
    max_command_age_s: float = param(0.5, "commands stamped further than this from now (past or future) are refused",
                                     min=1e-3, max=3600.0)
    sim_time: bool = param(False, "be the graph's clock: publish /clock, one control period per tick, and stamp "
                                  "with it (other nodes then run with use_sim_time:=true)", read_only=True)
    pose_source: str = param("sim", "where hand/object_pose comes from: sim (the simulator) or topic (the newest "
                                    "tracker/object_pose, as on a real hand)", constraints="sim or topic")
    max_pose_age_s: float = param(0.3, "with pose_source topic: a tracker pose older than this is never "
                                       "published as current", min=0.01, max=10.0)
    tracker_wait_s: float = param(0.5, "on sim time with the camera and pose_source topic: a step waits up to this "
                                       "long (wall seconds) for the tracker's pose of its frame (0: never waits)",
                                  min=0.0, max=60.0)

    def __post_init__(self) -> None:
        self.check_camera()
        if self.pose_source not in POSE_SOURCES:
            raise ValueError(f"pose_source must be one of {', '.join(POSE_SOURCES)}, got {self.pose_source!r}")
        if not (math.isfinite(self.tracker_wait_s) and self.tracker_wait_s >= 0):
            raise ValueError(f"tracker_wait_s must be a finite number >= 0, got {self.tracker_wait_s!r}")
        if not (math.isfinite(self.max_pose_age_s) and self.max_pose_age_s > 0):
            raise ValueError(f"max_pose_age_s must be positive and finite, got {self.max_pose_age_s!r}")
        rate = self.rate_factor
        if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate_factor must be a positive finite number, got {self.rate_factor!r}")
        if not (math.isfinite(self.max_command_age_s) and self.max_command_age_s > 0):
            raise ValueError(f"max_command_age_s must be positive and finite, got {self.max_command_age_s!r}")
        if not isinstance(self.seed, int) or self.seed < -1:
            raise ValueError(f"seed must be a non-negative int or -1 (unseeded), got {self.seed!r}")

    @property
    def period_s(self) -> float:
        return CONTROL_PERIOD_S / self.rate_factor

    @property
    def max_command_age_ns(self) -> int:
        return round(self.max_command_age_s * 1e9)


# --------------------------------------------------------------------------- the node
class MockDriver(Node):
    """The simulated hand on the driver's topics; see the module docstring for behaviour."""

    params_class = MockDriverParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("mock_driver", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params, self._veto)
        p = self.params
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        """Warnings about single messages: a flood gives a line a second, with a count."""
        self.hand = SimulatedHand(p.hand)
        self.episode = -1
        """Index of the current episode (resets so far - 1)."""
        self.steps = 0
        """Steps taken in the current episode."""
        self.running = False
        """Whether the timer steps the hand (False after an episode end until a reset)."""
        self.queue = ActionQueue()
        self._closed = False
        self._last_stamp = 0
        """Stamp of the last step published (0 before the first: every step comes after it)."""
        self.late_steps = 0
        """Steps that came more than 1.5 periods after the one before (wall-clock stamps only)."""
        self.skipped_ticks = 0
        """Timer ticks less than half a period after a step (catching up after a late one) that did not step."""

        self._pose_pub = self.create_publisher(PoseStamped, names.OBJECT_POSE, 10)
        self._joints_pub = self.create_publisher(JointState, names.JOINT_STATES, 10)
        self._action_pub = self.create_publisher(JointState, names.APPLIED_ACTION, 10)
        self._status_pub = self.create_publisher(String, names.HAND_STATUS, profile(names.OFFERED[names.HAND_STATUS]))
        self._sim_ns = time.time_ns()  # the wall time: with use_sim_time on itself, ROS time is 0 until its /clock
        self._clock_pub = self.create_publisher(Clock, names.CLOCK, 10) if p.sim_time else None
        if p.rate_factor > 1.0 and not p.sim_time:  # (the hand-stepped tests slow the timer to a halt instead)
            self.log.warning(f"rate_factor {p.rate_factor:g} on the wall clock stamps steps {p.period_s * 1e3:g} ms "
                             "apart: a bag of them is no 10 Hz recording and reads as no episode (set sim_time)")
        self.pose = NewestPose()
        """The tracker's newest pose (``pose_source: topic``)."""
        self._tracker_sub: Any = None
        self._listen_to_the_tracker(p)
        self._seeded_from = 0
        """The episode that grasps with ``params.seed`` itself (the first after the seed was last set)."""
        self._frame_ns: int | None = None
        """The stamp of the last frame rendered, which the next step publishes."""
        self._waiting_since: float | None = None
        """Wall time the tick began to wait for the tracker's pose of the last frame."""
        self.add_post_set_parameters_callback(self._on_seed_set)
        self.camera = SimCamera(self, self.hand.params, p) if p.camera_rate_hz > 0 else None
        # Raw: a message's size is checked before it is deserialized (a huge one would stall the steps).
        self.create_subscription(JointState, names.HAND_COMMAND, self._on_command, 10, raw=True)
        self.create_subscription(JointTrajectory, names.HAND_TRAJECTORY, self._on_trajectory, 10, raw=True)
        self.create_service(Trigger, names.HAND_RESET, self._on_reset, qos_profile=profile(names.REQUESTS))
        ok, why = self.reset()
        if not ok:
            self.log.warning(f"initial grasp failed: {why}; "
                             f"call {self.resolve_service_name(names.HAND_RESET)} to retry")
        # The graph's clock ticks on the machine's: on ROS time (use_sim_time) it would wait for itself.
        self._timer = self.create_timer(p.period_s, self._on_timer,
                                       clock=RosClock(clock_type=ClockType.STEADY_TIME) if p.sim_time else None)

    # ------------------------------------------------------------------ state
    @property
    def params(self) -> MockDriverParams:
        return self._params.value

    @property
    def pending_actions(self) -> int:
        """Trajectory points still to execute."""
        return self.queue.pending

    def reset(self) -> tuple[bool, str]:
        """Re-open the hand, re-grasp (seed ``params.seed + episode``) and start stepping; (success, message)."""
        self.queue.clear()
        self.episode += 1
        self._publish_status(status_message(names.GRASPING, grasping_detail(self.episode), self._last_stamp))
        seed = None if self.params.seed < 0 else self.params.seed + self.episode - self._seeded_from
        try:
            self.hand.reset(seed)
        except GraspFailed as err:
            self.running = False
            self._publish_status(status_message(names.RESET_FAILED, str(err), self._last_stamp))
            return False, f"grasp failed: {err}"
        self.running, self.steps = True, 0
        self.pose.forget()  # the object was placed anew: no pose of the old grasp is current
        self._waiting_since = None  # a new episode's first step waits its whole tracker_wait_s
        if self.camera is not None:
            if self._clock_pub is not None:  # the re-grasp takes a period: its frame is stamped after the old ones
                self._sim_ns += CONTROL_PERIOD_NS
            self._frame_ns = None  # (a failed capture leaves no old frame to wait for)
            self.camera.restart()
            self._capture()
            # the old grasp's frames, tracked late, are left out (all of them, should the capture have failed)
            self.pose.forget(before_ns=self._frame_ns or self.now_ns() + 1)
        message = grasp_detail(self.episode, seed)
        self._publish_status(status_message(names.RESET, message, self._last_stamp))
        return True, message

    def now_ns(self) -> int:
        """The driver's time: the simulated clock with ``sim_time``, else the node's ROS time."""
        return self._sim_ns if self._clock_pub is not None else self.get_clock().now().nanoseconds

    def close(self) -> None:
        """Stop stepping (the owner destroys the node)."""
        self._closed = True
        if self.camera is not None:
            self.camera.close()

    # ------------------------------------------------------------------ callbacks
    @staticmethod
    def _veto(old: MockDriverParams, new: MockDriverParams) -> str | None:
        """On wall-clock stamps a new rate puts steps 0.1 / rate_factor s apart: the bag being recorded would no
        longer read as T42 steps.  On sim time each step is one control period of the graph's clock, at any rate."""
        if new.rate_factor != old.rate_factor and not new.sim_time:
            return ("rate_factor changes at run time only with sim_time (the driver as the graph's clock): on "
                    "wall-clock stamps the steps would come 0.1 / rate_factor s apart and the recording turn "
                    "unreadable; restart with sim_time:=true, or with the new rate")
        return None

    def _listen_to_the_tracker(self, p: MockDriverParams) -> None:
        if p.pose_source == "topic" and self._tracker_sub is None:
            # best effort by ROS's QoS override, as the Dynamixel driver's reader (a motion-capture bridge)
            self._tracker_sub = self.create_subscription(PoseStamped, names.TRACKER_POSE, self._on_tracker_pose, 10,
                                                         qos_overriding_options=QoSOverridingOptions.with_default_policies())

    def _on_seed_set(self, parameters: list[Any]) -> None:
        """A seed set, even to the value it had, applies from the next reset (a grasp made again)."""
        seed = next((p for p in parameters if p.name == "seed"), None)
        if seed is not None:  # (its value from the set itself: this may run before the params dataclass is updated)
            self._seeded_from = self.episode + 1
            self.log.info(f"the next reset grasps with seed {seed.value}" if seed.value >= 0
                          else "the next resets grasp unseeded")

    def _on_params(self, old: MockDriverParams, new: MockDriverParams) -> None:
        if new.pose_source != old.pose_source:
            self._listen_to_the_tracker(new)
            self.pose.forget()  # a pose heard before the switch may be old: the next fresh one counts
            self.log.info(f"pose_source {old.pose_source} -> {new.pose_source}")
        if new.rate_factor != old.rate_factor:
            self._timer.timer_period_ns = round(new.period_s * 1e9)
            self.log.info(f"rate_factor {old.rate_factor} -> {new.rate_factor}: a step every {new.period_s:.4f} s")

    def _on_command(self, data: bytes) -> None:
        action = accept(self.per_message, names.HAND_COMMAND, lambda: validate_command(
            data, self.now_ns(), self.params.max_command_age_ns))
        if action is None:
            return
        cancelled = self.queue.set_command(action)
        if cancelled:
            self.log.info(f"single-step command cancels a trajectory with {cancelled} points left")

    def _on_tracker_pose(self, msg: PoseStamped) -> None:
        if (why := self.pose.receive_msg(msg)) is not None:
            self.per_message.warning(f"rejected {names.TRACKER_POSE}: {why}")

    def _on_trajectory(self, data: bytes) -> None:
        actions = accept(self.per_message, names.HAND_TRAJECTORY, lambda: validate_trajectory(
            data, self.hand.actuator_angles, self.now_ns(), self.params.max_command_age_ns))
        if actions is None:
            return
        pre_empted = self.queue.set_plan(actions)
        if pre_empted:
            self.log.info(f"trajectory with {len(actions)} points pre-empts one with {pre_empted} points left")

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            ok, message = self.reset()
        except Exception as err:  # a service handler must answer, not raise
            self.log.error(f"reset failed: {err!r}")
            self.running = False
            ok, message = False, f"reset failed: {err}"
            self._publish_status(status_message(names.RESET_FAILED, repr(err), self._last_stamp))
        response.success, response.message = ok, message
        return response

    def _waits_for_the_tracker(self) -> bool:
        """On sim time, whether this tick waits for the tracker's pose of the frame the step publishes: in
        lockstep with the tracker a slow one (a busy machine, a large frame) slows the graph's clock instead
        of leaving steps without a pose.  The wait is ``tracker_wait_s`` at most (a frame without the object
        gives no pose at all)."""
        p = self.params
        frame, held = self._frame_ns, self.pose.stamp_ns
        if (self._clock_pub is None or p.pose_source != "topic" or not self.running or frame is None
                or p.tracker_wait_s <= 0 or (held is not None and held >= frame)):
            self._waiting_since = None
            return False
        now = time.monotonic()
        if self._waiting_since is None:
            self._waiting_since = now
        if now - self._waiting_since < p.tracker_wait_s:
            return True
        self._waiting_since = None
        return False

    def _on_timer(self) -> None:
        if self._closed or self._waits_for_the_tracker():
            return
        try:
            if self._clock_pub is not None:
                self._sim_ns += CONTROL_PERIOD_NS
                self._clock_pub.publish(Clock(clock=ns_to_stamp(self._sim_ns, RCLPY)))
            self._timed_tick()
        except Exception as err:
            self.log.error(f"step failed ({err!r}); the hand stops until {names.HAND_RESET} is called")
            self.running = False
            self.queue.clear()

    # ------------------------------------------------------------------ one step
    def _next_action(self) -> np.ndarray:
        """The action of this step, as float32 values (what the applied-action topic can carry exactly)."""
        action, last = self.queue.next()
        if last:
            self._publish_status(status_message(names.TRAJECTORY_DONE, f"episode {self.episode} step {self.steps + 1}",
                                                self._last_stamp))
        return action

    def _timed_tick(self) -> None:
        """The timer's step.  On wall-clock stamps a tick can come late (a stalled process, a busy machine): the
        step is taken and ``late`` says so on ``hand/status`` with its stamp, so a recording keeps it.  A tick
        less than half a period after the last step (the timer catching up) does not step: two stamps that close
        would not be two steps."""
        if not (self.running and self.steps > 0 and self._clock_pub is None):
            self.tick()
            return
        stamp = self.now_ns()  # judged and published alike: no clock reading between the two
        since = stamp - self._last_stamp
        timing = step_timing(since, self.params.rate_factor)
        if timing is StepTiming.TOO_SOON:
            self.skipped_ticks += 1
            return
        late = timing is StepTiming.LATE
        self.late_steps += late
        self.tick(late_by_ns=since if late else None, stamp_ns=stamp)

    def tick(self, late_by_ns: int | None = None, stamp_ns: int | None = None) -> None:
        """One control step: publish the state (and the action applied from it), then step the hand.

        ``late_by_ns``: the step comes that long after the one before, which ``hand/status`` says (``late``);
        ``stamp_ns``: the step's stamp (now when None)."""
        if not self.running:
            return
        stamp = self.now_ns() if stamp_ns is None else stamp_ns
        state = self.hand.state
        self._last_stamp = stamp
        self._publish_pose(state[:2], stamp)
        self._joints_pub.publish(joint_state_msg(state[2:], self.hand.actuator_angles, stamp, RCLPY))
        if late_by_ns is not None:
            self._publish_status(status_message(names.LATE, f"{late_by_ns / 1e6:.1f} ms after the step before", stamp))
        if self.hand.done:
            self.running = False
            self.queue.clear()
            reason = self.hand.end_reason
            self.log.warning(f"episode {self.episode} ended after {self.steps} steps: {reason}")
            self._publish_status(status_message(reason, f"episode {self.episode} ended after {self.steps} steps",
                                                stamp))
            return
        action = self._next_action()
        self._action_pub.publish(applied_action_msg(action, stamp, RCLPY))
        info = self.hand.step_info(action)
        self.steps += 1
        self._capture()
        if info.refused:
            # Throttled: a command held against a limit is refused at every step (20 lines a second at 2x).
            self.per_message.info(f"step {self.steps}: a servo move was refused (travel limit or load guard)")

    def _publish_pose(self, simulated_xy: np.ndarray, stamp: int) -> None:
        """The step's object pose: the simulator's, or the tracker's newest fresh one (``pose_source: topic``)."""
        if self.params.pose_source == "sim":
            self._pose_pub.publish(object_pose_msg(simulated_xy, stamp, RCLPY))
            return
        xy, why = self.pose.for_step(stamp, self.params.max_pose_age_s)
        if why is not None:
            self._publish_status(status_message(names.STALE, f"no fresh object pose on {names.TRACKER_POSE} "
                                                             f"({why}): steps go out without one", stamp))
        if xy is not None:
            self._pose_pub.publish(object_pose_msg(xy, stamp, RCLPY))

    def _capture(self) -> None:
        """A camera frame of the hand as the next step will publish it (see the module docstring)."""
        if self.camera is None:
            return
        stamp = self._sim_ns + CONTROL_PERIOD_NS if self._clock_pub is not None else self.now_ns()
        try:
            if self.camera.capture(self.hand, stamp):
                self._frame_ns = stamp
        except Exception as err:  # the hand steps on without its camera
            self.per_message.error(f"camera frame failed: {err!r}")

    def _publish_status(self, text: str) -> None:
        self._status_pub.publish(String(data=text))
