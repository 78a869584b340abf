"""Dynamixel driver: a real T42's two XM430 servos behind the mock driver's topics, as a lifecycle node.

Lifecycle (``ros2 lifecycle set`` or any ``change_state`` client):

* configure: open ``port`` at ``baud`` (exclusively: a second driver or ``t42 hw`` on it is refused as in use until
  cleanup), ping both servos (an XM430-W350 each), torque off, set the
  operating mode and the position limits, read where the fingers stand (a finger more than 0.1 rad outside its
  range is refused: activate would move it);
* activate: torque on, goals where the fingers stand (nothing moves), then step every control period;
* deactivate: hold the position, stop stepping (torque stays on);
* cleanup and shutdown: torque off, close the port;
* a transition that raises (a bug: faults are answered FAILURE) is said with its reason on /rosout,
  ``hand/status`` and ``diagnostics``, and ``on_error`` turns the torque off and closes the port before the
  node goes back to unconfigured (rclpy would otherwise drop the exception unsaid and leave both as they
  were).  The process's exit (Ctrl-C, SIGTERM, an exception out of a
  callback) turns the torque off too, whatever the state, on each servo that answers.  ``autostart`` configures
  and activates at start, for a suite run without a lifecycle manager (``t42 up``), trying configure again
  every second until the port is there (a port that does not exist yet is waited for quietly for
  :data:`PORT_GRACE_S`, then it is a fault), and activate again every second while it fails (a servo that does
  not answer as the torque comes on; the torque is left off meanwhile).

Interface: that of :mod:`~t42_transfer.nodes.mock_driver` (``hand/joint_states`` with actuator angles and
loads, ``hand/object_pose``, ``hand/applied_action``, ``hand/command``, ``hand/trajectory``,
``hand/status``, ``hand/reset``), the same step convention (one sync read, publish the state and the action
applied from it with one stamp, one sync write), and the same command rules
(:mod:`t42_transfer.driver.commands`): a single-step command moves the hand for one step only, so with no
command the hand holds where it is (the watchdog is the step convention itself).  ``hand/reset`` runs the
authors' grasp: open, then close each finger until its load passes ``grasp_load``; ``hand/status`` says
``grasping`` as it begins (a tracker then takes the object's jump for a new placement), and the service answers
once the grasp closed (the steps run meanwhile).

Parameters at run time: ``load_limit``, ``grasp_load`` and ``max_angle_rad`` set while the
driver is configured take effect from the next step (a goal past a lowered limit is brought back onto it).  The
servos' own Min/Max Position Limit are EEPROM, written only with the torque off, at configure: so a limit lowered
at run time is kept by the driver (the servos keep the wider one until the next configure), and a limit raised
beyond what the servos were configured with is refused with the reason (cleanup, set it, configure).

Object pose: the newest ``tracker/object_pose`` (remappable) is published each step, stamped with the step,
unless it is older than ``max_pose_age_s``: then no pose goes out for the step, and ``hand/status`` says
``stale`` once per stale stretch (a recorder's step then lacks its pose, so the bag reader leaves it out and
splits the episode there, saying so).  A reset forgets the pose held and every pose of a frame taken before it:
the object is placed anew, so a new episode's first state is never the old grasp's, whatever ``max_pose_age_s``.
Drops: a published pose more than ``drop_jump_m`` (the paper's 8 mm) a control period, over the time between its
frame's stamp and the step before's, from the step before's ends the episode as the mock driver ends one: that
step's state goes out without an action, ``hand/status`` says ``dropped`` and the hand holds until the next reset.

Faults (a servo that stops answering, a garbled answer, a Hardware Error Status bit, the torque found off on a servo
that restarted, the port gone) are reported on ``hand/status`` (``fault: ...``, which ends the episode) and
``diagnostics`` with the servo id and the error bits decoded; so is a configure that fails (no port, a port that is
no Dynamixel bus, servos of another model: ``fault: configure failed: ...``, said again on ``hand/status`` only when
it changes, and ``recovered`` once a configure passes). A command refused or cut short (clamped at a position limit,
a finger held for its load) says ``refused`` on ``hand/status`` as on /rosout, at most once a second per kind. A
Hardware Error Status bit latches: the servo is never rebooted by the driver, the fault stays until cleanup and
configure (:mod:`t42_transfer.driver.faults`). From the others recovery is automatic: once a second the driver
reopens the port if it went, pings, turns the torque back on and holds; ``recovered`` then says the hand is back (a
reset starts the next episode). While inactive the servos are read once a second (the torque may be on, holding a
grasp), faults said as while active. Late steps are counted and reported in diagnostics, and each says ``late`` on
``hand/status`` with its stamp (a recording keeps it as data); a tick whose stamp would come less than half a period
after the last step's (a timer catching up after a late one) does not step, so two steps are never stamped closer
than the bag reader accepts. Both are judged on the stamps published, taken after the read
(:mod:`t42_transfer.driver.timing`).
Steps follow the graph's clock: with ``use_sim_time`` (the emulator's ``/clock``) they run as fast as that clock
does.  ``t42 node`` spins the driver on rclpy's EventsExecutor (its CPU per step: ``bench/bench_driver.py``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.lifecycle import State, TransitionCallbackReturn
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    applied_action_msg,
    diagnostic_array,
    grasp_detail,
    grasping_detail,
    joint_state_msg,
    names,
    object_pose_msg,
    status_message,
)
from t42_transfer.conventions import CONTROL_PERIOD_S, MM_PER_M
from t42_transfer.driver.commands import ActionQueue, accept, validate_command, validate_trajectory
from t42_transfer.driver.faults import RETRY_PERIOD_S, FaultState, latched_hint, recover
from t42_transfer.driver.pose import DropWatch, NewestPose
from t42_transfer.driver.servo_hand import Grasp, ServoHand
from t42_transfer.driver.timing import StepTiming, step_timing
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.servos import HARDWARE, PORT, HandServos, ServoFault
from t42_transfer.hardware.servos import REFUSED as REFUSED_KIND
from t42_transfer.nodes.dynamixel_params import DynamixelDriverParams
from t42_transfer.ros.autostart import Autostart
from t42_transfer.ros.deferred_service import DeferredService, Pending
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import DestroyableLifecycleNode, destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams
from t42_transfer.ros.qos import profile

STATUS_NAME = "t42_transfer: dynamixel_driver"
REFUSED = "refused"
"""``hand/status`` word of a command refused or cut short: a goal clamped at the position limits, a finger not
closed for its load over the limit, a command or trajectory rejected (NaN, wrong names, stale); at most a line a
second per kind, as on /rosout.  It neither ends nor splits an episode."""
PORT_GRACE_S = 10.0
"""How long ``autostart`` waits quietly for a port that does not exist yet (``t42 up`` starts an emulator beside the
driver; an adapter is plugged in) before a missing port is a fault."""
DIAGNOSTICS_EVERY = 10
"""Steps between two diagnostics while all is well (faults are reported at once)."""
_NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
_NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)
"""The driver's publishers and subscriptions go without rclpy's default QoS event handlers (a warning on an
incompatible QoS or type, which the peer's own handlers log as well): each handler is a waitable that the
SingleThreadedExecutor builds into its wait set again at every wake (about 6 a step: the timer, the command, the
tracker's pose, each followed by the wake its guard condition causes). Measured: a spin_once of the unconfigured
driver with nothing ready took 172 us of CPU with the 16, 132 us without (an idle node with one timer: 94-105)."""


class DynamixelDriver(DestroyableLifecycleNode):
    """A real (or emulated) T42 on the driver topics; see the module docstring."""

    params_class = DynamixelDriverParams  # the one its LiveParams declares; t42 node NAME --help lists it

    events_executor = True
    """``t42 node`` spins it on rclpy's EventsExecutor (:func:`~t42_transfer.ros.runner.make_executor`)."""

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("dynamixel_driver", **node_kwargs)
        self._servo_limits_rad: tuple[float, ...] | None = None
        """``max_angle_rad`` as written to the servos' Position Limits at configure (None: not configured)."""
        self._params = LiveParams(self, self.params_class, on_change=self._on_params, veto=self._veto_params)
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        """Warnings about single messages: a flood gives a line a second, with a count."""
        self.refusals = ThrottledLog(_LogAndStatus(self.log, lambda line: self._status(REFUSED, line)))
        """Commands refused or cut short, on /rosout and ``hand/status`` alike, throttled as :attr:`per_message`."""
        self._configure_error = ""
        """The last configure failure reported on ``hand/status`` (autostart retries say a new one only), or the fault
        held when the hand was released: the next configure that passes says ``recovered`` after it."""
        self._autostart: Autostart | None = None
        self._transition_error = ""
        """Why the transition in progress raised, for :meth:`on_error` ("" when none did)."""
        self.hand: ServoHand | None = None
        self.queue = ActionQueue()
        self.episode = -1
        self.steps = 0
        self.running = False
        self.late_steps = 0
        self.skipped_ticks = 0
        """Timer ticks that came less than half a period after a step (after a late one) and did not step."""
        self._faults = FaultState()
        self._torque_wanted = False
        """Whether the hand has its torque on (activate turned it on; deactivate keeps it): recovery restores it."""
        self._grasp: Grasp | None = None
        self._grasp_answer: Pending | None = None
        self._stepping = False
        self._last_stamp = 0
        self.pose = NewestPose()
        self.drops = DropWatch()
        self._ticks = 0
        pub, sub = {"event_callbacks": _NO_PUB_EVENTS}, {"event_callbacks": _NO_SUB_EVENTS}
        self._pose_pub = self.create_publisher(PoseStamped, names.OBJECT_POSE, 10, **pub)
        self._joints_pub = self.create_publisher(JointState, names.JOINT_STATES, 10, **pub)
        self._action_pub = self.create_publisher(JointState, names.APPLIED_ACTION, 10, **pub)
        self._status_pub = self.create_publisher(String, names.HAND_STATUS, profile(names.OFFERED[names.HAND_STATUS]),
                                                 **pub)
        self._diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10, **pub)
        # A motion-capture bridge may publish best effort (sensor data QoS), which a reliable reader never
        # matches: ``-p qos_overrides./tracker/object_pose.subscription.reliability:=best_effort`` (ROS's overrides).
        self.create_subscription(PoseStamped, names.TRACKER_POSE, self._on_pose, 10, **sub,
                                 qos_overriding_options=QoSOverridingOptions.with_default_policies())
        # Raw: a message's size is checked before it is deserialized (a huge one would stall the steps).
        self.create_subscription(JointState, names.HAND_COMMAND, self._on_command, 10, raw=True, **sub)
        self.create_subscription(JointTrajectory, names.HAND_TRAJECTORY, self._on_trajectory, 10, raw=True, **sub)
        # Answered once the grasp closed, which the next steps run: a pending answer (deferred_service says why).
        self._reset = DeferredService(self, Trigger, names.HAND_RESET, self._on_reset,
                                      qos_profile=profile(names.REQUESTS))
        self._timer = self.create_timer(CONTROL_PERIOD_S, self._on_timer)
        self._port_wait_until = time.monotonic() + PORT_GRACE_S
        self._autostart = Autostart(self, RETRY_PERIOD_S, self._port_ready) if self.params.autostart else None

    def _port_ready(self) -> bool:
        """Autostart's configure waits quietly for a port that does not exist yet (an adapter plugged in later, an
        emulator still starting), up to :data:`PORT_GRACE_S`; then a missing port is a configure fault."""
        port = self.params.port
        if os.path.exists(port) or time.monotonic() >= self._port_wait_until:
            return True
        if self._autostart is not None and not self._autostart.waiting:  # not yet a fault: say it once
            self.log.info(f"autostart: waiting for {port} to appear (up to {PORT_GRACE_S:g} s before it is a fault)")
        return False

    @property
    def params(self) -> DynamixelDriverParams:
        return self._params.value

    @property
    def fault(self) -> ServoFault | None:
        """The fault held (None: none)."""
        return self._faults.fault

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        return self._transition("configure", self._configure)

    def _transition(self, name: str, run: Callable[[], TransitionCallbackReturn]) -> TransitionCallbackReturn:
        """``run()``; an exception out of it is kept with its reason for :meth:`on_error` and answered ERROR."""
        try:
            return run()
        except Exception as err:  # rclpy would answer ERROR too, saying nothing of why
            self._transition_error = f"{name} raised {type(err).__name__}: {err}"
            self.log.error(self._transition_error)
            return TransitionCallbackReturn.ERROR

    def on_error(self, state: State) -> TransitionCallbackReturn:
        """A transition raised: the hand released (torque off, port closed) and the reason said; unconfigured
        next, from where configure starts over."""
        reason = self._transition_error or f"a transition from {state.label} failed"
        self._transition_error = ""
        message = f"{reason}: torque off, port closed; configure to start again"
        self._release()
        self.log.error(message)
        self._status(names.FAULT, message)
        self._publish_diagnostics("ERROR", message)
        return TransitionCallbackReturn.SUCCESS

    def _configure(self) -> TransitionCallbackReturn:
        p = self.params
        servos = HandServos(p.port, p.baud, p.servo_ids, p.latency_timer_ms)
        try:
            servos.open()
            models = servos.check()
            geometry = p.geometry()
            servos.configure(xm.POSITION_MODE, geometry.limits())
            hand = ServoHand(servos, geometry)
            hand.start_from_present()
            hand.check_range()  # activate would move a finger standing outside its range
        except (ServoFault, ValueError) as err:
            servos.close()
            self._configure_failed(err)
            return TransitionCallbackReturn.FAILURE
        self.hand, self._servo_limits_rad = hand, geometry.max_angle_rad
        if self._configure_error:  # said on hand/status (latched): a late joiner hears that it passed
            self._status(names.RECOVERED, f"configured {p.port} after: {self._configure_error}")
            self._publish_diagnostics("OK", f"configured after: {self._configure_error}")
        self._configure_error = ""
        self.log.info(f"configured {p.port}: servos {models} in position mode, limits {geometry.limits()}")
        return TransitionCallbackReturn.SUCCESS

    def _configure_failed(self, err: Exception) -> None:
        """On ``diagnostics`` each time, on ``hand/status`` when it differs from the last, on /rosout both then and
        at each configure a client asked for (autostart's retries say a new failure only): no port, a port that is
        no Dynamixel bus (nothing answers the pings), servos of another model, an error bit."""
        message = f"configure failed: {err}"
        fault = err if isinstance(err, ServoFault) else ServoFault(REFUSED_KIND, None, str(err))
        self._publish_diagnostics("ERROR", message, fault)
        new = message != self._configure_error
        if new or not (self._autostart is not None and self._autostart.configuring):
            self.log.error(message + ("" if fault.kind != HARDWARE else
                                      "; stop the driver, find the cause, then t42 hw reboot clears the error bit"))
        if new:
            self._configure_error = message
            self._status(names.FAULT, message)

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        return self._transition("activate", lambda: self._activate(state))

    def _activate(self, state: State) -> TransitionCallbackReturn:
        try:
            self._need_hand().start_from_present()
            self._need_hand().servos.torque(True)
            self._need_hand().hold()
        except ServoFault as err:
            self.log.error(f"activate failed: {err}")
            self._need_hand().servos.set_torque(False)  # inactive again: no servo left on
            return TransitionCallbackReturn.FAILURE
        self._stepping = self._torque_wanted = True
        self.log.info("active: torque on, holding; call hand/reset to grasp")
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        return self._transition("deactivate", lambda: self._deactivate(state))

    def _deactivate(self, state: State) -> TransitionCallbackReturn:
        self._stop_episode("deactivated")
        self._stepping = False
        try:
            self._need_hand().hold()
        except ServoFault as err:
            self.log.warning(f"could not hold on deactivate: {err}")
        else:
            self.log.info("inactive: torque on, holding where the fingers stand; activate to step again, cleanup "
                          "to turn the torque off")
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        if self._release():
            self.log.info("unconfigured: torque off, port closed")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        """Torque off and the port closed, whatever state the node is in (the process exits)."""
        self._release()

    def _release(self) -> bool:
        """Torque off and the port closed; whether every servo confirmed the torque off (False: no hand held)."""
        self._stepping = False
        self._stop_episode("the driver stopped")
        hand, self.hand = self.hand, None
        self._servo_limits_rad = None
        self._torque_wanted = False
        fault = self._faults.clear()  # a configure starts over: the next fault is the new hand's
        if fault is not None and not self._configure_error:  # the next configure that passes says recovered
            self._configure_error = f"fault: {fault}"
        if hand is None:
            return False
        failed = hand.servos.set_torque(False)  # each servo tried on its own: one silent servo leaves no other on
        if failed:
            self.log.error(f"could not turn the torque off on servo(s) {sorted(failed)}: "
                           + "; ".join(str(err) for err in failed.values()))
        hand.servos.close()
        return not failed

    # ------------------------------------------------------------------ parameters at run time
    def _veto_params(self, old: DynamixelDriverParams, new: DynamixelDriverParams) -> str | None:
        """A position limit beyond what the servos were configured with waits for the next configure: the servos'
        Min/Max Position Limit are EEPROM, written only with the torque off, and refuse goals past them."""
        configured = self._servo_limits_rad
        if configured is None or all(a <= b + 1e-9 for a, b in zip(new.max_angle_rad, configured, strict=True)):
            return None
        return (f"max_angle_rad {list(new.max_angle_rad)} goes beyond the servos' Position Limits written at configure "
                f"({list(configured)} rad; EEPROM, written only with the torque off): lower limits take effect at "
                "once, higher ones after cleanup, setting it, and configure")

    def _on_params(self, old: DynamixelDriverParams, new: DynamixelDriverParams) -> None:
        """The hand's limits and grasp load follow the parameters from the next step on."""
        hand = self.hand
        if hand is None or new.geometry() == hand.geometry:
            return
        hand.geometry = new.geometry()
        self.log.info(f"now: max_angle_rad {list(new.max_angle_rad)}, load_limit {new.load_limit:g}, grasp_load "
                      f"{new.grasp_load:g} (from the next step)")

    def _need_hand(self) -> ServoHand:
        if self.hand is None:
            raise ServoFault(PORT, None, "the driver is not configured")
        return self.hand

    # ------------------------------------------------------------------ inputs
    def _on_pose(self, msg: PoseStamped) -> None:
        if (why := self.pose.receive_msg(msg)) is not None:
            self.per_message.warning(f"rejected {names.TRACKER_POSE}: {why}")

    def _on_command(self, data: bytes) -> None:
        max_age = round(self.params.max_command_age_s * 1e9)
        action = accept(self.refusals, names.HAND_COMMAND, lambda: validate_command(data, self.now_ns(), max_age))
        if action is not None:
            self.queue.set_command(action)

    def _on_trajectory(self, data: bytes) -> None:
        hand = self.hand
        if hand is None:
            self.per_message.warning(f"rejected {names.HAND_TRAJECTORY}: the driver is not active")
            return
        max_age = round(self.params.max_command_age_s * 1e9)
        actions = accept(self.refusals, names.HAND_TRAJECTORY, lambda: validate_trajectory(
            data, hand.goal, self.now_ns(), max_age))
        if actions is not None:
            self.queue.set_plan(actions)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response | Pending:
        """Open, then close until the grasp load; answered when the grasp closed (the steps run it)."""
        if not self._stepping or self.hand is None:
            response.success, response.message = False, "the driver is not active (configure and activate it)"
            return response
        if self.fault is not None:
            response.success, response.message = False, f"the hand has a fault: {self.fault}"
            return response
        self._stop_episode("a new reset")
        self.pose.forget(before_ns=self.now_ns() + 1)  # the object is placed anew: no frame until now counts
        self._grasp, self._grasp_answer = Grasp(self.hand), self._reset.later()
        self._status(names.GRASPING, grasping_detail(self.episode + 1))
        return self._grasp_answer

    # ------------------------------------------------------------------ steps
    def _on_timer(self) -> None:
        """Active: a step each period.  Inactive (configured), a health read a second with diagnostics: the
        servos may hold a grasp with their torque on.  A fault held: a retry when due (a latched one: said again)."""
        if self.hand is None:
            return
        self._ticks += 1
        second = self._ticks % DIAGNOSTICS_EVERY == 0
        try:
            if self.fault is not None:
                if self._faults.due(time.monotonic()):  # on the wall clock, whatever the graph's
                    self._try_recover()
            elif self._stepping:
                if second:
                    stale = self.pose.stale
                    self._publish_diagnostics("WARN" if stale else "OK", "stale object pose" if stale else "stepping")
                self.step()
            elif second:
                self.hand.read()
                self._publish_diagnostics("OK", "inactive: " + ("torque on, holding" if self._torque_wanted
                                                                  else "torque off"))
        except ServoFault as err:
            self._on_fault(err)
        except Exception as err:  # a bug must not leave the hand moving
            self.log.error(f"step failed ({err!r}); holding")
            self._on_fault(ServoFault(PORT, None, repr(err)))

    def step(self) -> None:
        """One control step: read, publish the state and the action applied from it, write the goals."""
        hand = self._need_hand()
        angles, loads = hand.read()
        if self._grasp is not None:
            self._grasp_step()
            return
        if not self.running:
            hand.hold()
            return
        stamp = self.now_ns()  # the graph's clock, after the read: the stamp published is the one judged
        since = stamp - self._last_stamp if self.steps > 0 else None
        timing = step_timing(since)
        if timing is StepTiming.TOO_SOON:
            self.skipped_ticks += 1  # the goals stay until the next tick
            return
        self._last_stamp = stamp
        xy = self._publish_pose(stamp)
        self._joints_pub.publish(joint_state_msg(loads, angles, stamp, RCLPY))
        if timing is StepTiming.LATE and since is not None:  # a recording keeps the step: none is missing
            self.late_steps += 1
            self._status(names.LATE, f"{since / 1e6:.1f} ms after the step before")
        jump_mm = self.params.drop_jump_m * MM_PER_M
        drop = self.drops.moved_mm(xy, self.pose.stamp_ns or stamp, jump_mm)
        if drop is not None:  # the final state goes out without an action, as the mock driver ends an episode
            self.running = False
            self.queue.clear()
            detail = f"episode {self.episode} ended after {self.steps} steps: the object moved {drop[0]:.1f} mm " \
                     f"between frames {drop[1]:.2f} s apart (over {jump_mm:g} mm a period)"
            self.log.warning(detail)
            self._status(names.DROPPED, detail)
            hand.hold()
            return
        action, last = self.queue.next()
        if last:
            self._status(names.TRAJECTORY_DONE, f"episode {self.episode} step {self.steps + 1}")
        self._action_pub.publish(applied_action_msg(action, stamp, RCLPY))
        refused = hand.apply(action)
        self.steps += 1
        if refused:
            self.refusals.warning(f"step {self.steps}: {refused}")

    def _publish_pose(self, stamp: int) -> np.ndarray | None:
        """The step's object pose, published unless stale (None then)."""
        xy, why = self.pose.for_step(stamp, self.params.max_pose_age_s)
        if why is not None:
            self._status(names.STALE, f"no fresh object pose on {names.TRACKER_POSE} ({why}): "
                                      "steps go out without one")
        if xy is not None:
            self._pose_pub.publish(object_pose_msg(xy, stamp, RCLPY))
        return xy

    def _grasp_step(self) -> None:
        grasp = self._grasp
        assert grasp is not None
        grasp.step()
        if not (grasp.done or grasp.failed):
            return
        self._grasp = None
        if grasp.done:
            self.episode += 1
            self.running, self.steps = True, 0
            self.queue.clear()
            self.drops.start()
            message = grasp_detail(self.episode, None)
            self._status(names.RESET, message)
            self._answer(True, message)
        else:
            self._status(names.RESET_FAILED, grasp.failed)
            self._answer(False, f"grasp failed: {grasp.failed}")

    def _answer(self, ok: bool, message: str) -> None:
        answer, self._grasp_answer = self._grasp_answer, None
        if answer is not None:
            answer.answer(Trigger.Response(success=ok, message=message))

    def _stop_episode(self, why: str) -> None:
        self.queue.clear()
        self.running = False
        if self._grasp is not None:
            self._grasp = None
            self._answer(False, f"reset interrupted: {why}")
            try:  # (a grasp cut short is a failed one: a tracker waiting for the grasp's end hears it)
                self._status(names.RESET_FAILED, f"interrupted: {why}")
            except Exception:  # the process exits: the context may be gone
                pass

    # ------------------------------------------------------------------ faults
    def _on_fault(self, fault: ServoFault) -> None:
        """A fault, or a retry that failed: on /rosout and ``hand/status`` when its cause (kind and servo) differs
        from the one held (a retry failing the same way every second says so on ``diagnostics`` only).  A hardware
        error bit latches (:mod:`t42_transfer.driver.faults`): no retry until the operator acts."""
        new = self._faults.hold(fault, time.monotonic())
        self._stop_episode(str(fault))
        if new:
            then = latched_hint(self.params.port) if self._faults.latched else \
                f"retrying every {RETRY_PERIOD_S:g} s"
            self.log.error(f"{fault}; holding, {then}")
            self._status(names.FAULT, f"{fault}; {then}" if self._faults.latched else str(fault))
        self._publish_diagnostics("ERROR", str(fault))
        if self.hand is not None:
            try:
                self.hand.hold()
            except ServoFault:
                pass

    def _try_recover(self) -> None:
        fault = self.fault
        assert fault is not None
        if self._faults.latched:  # said again on diagnostics each second; the servos are left alone
            self._publish_diagnostics("ERROR", f"{fault}; {latched_hint(self.params.port)}")
            return
        recover(self._need_hand(), fault, self._torque_wanted)
        self._faults.clear()
        self.log.info(f"recovered from: {fault}")
        self._status(names.RECOVERED, f"after {fault}; the hand holds (call hand/reset for a new episode)")
        self._publish_diagnostics("OK", f"back from: {fault}")

    # ------------------------------------------------------------------ reports
    def _status(self, event: str, detail: str) -> None:
        self._status_pub.publish(String(data=status_message(event, detail, self._last_stamp or None)))

    def _publish_diagnostics(self, level: str, message: str, fault: ServoFault | None = None) -> None:
        fault = fault or self.fault
        values: dict[str, object] = {"late_steps": self.late_steps, "skipped_ticks": self.skipped_ticks,
                                     "episode": self.episode, "steps": self.steps, "pose_stale": self.pose.stale}
        if fault is not None:
            values.update(fault_kind=fault.kind, servo_id="" if fault.servo_id is None else fault.servo_id)
            if fault.kind == HARDWARE:
                values["hardware_errors"] = fault.detail
        self._diagnostics.publish(diagnostic_array(STATUS_NAME, level, message, values, self.now_ns(),
                                                   hardware_id=self.params.port, kit=RCLPY))


class _LogAndStatus:
    """A logger for :class:`ThrottledLog` whose warnings go to /rosout and ``hand/status`` both."""

    def __init__(self, log: Any, status: Any) -> None:
        self._log, self._status = log, status

    def warning(self, line: str) -> None:
        self._log.warning(line)
        self._status(line)

    def error(self, line: str) -> None:
        self._log.error(line)
        self._status(line)
