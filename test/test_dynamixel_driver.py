"""The Dynamixel driver node on the emulated servo bus, the simulated hand behind it, driven as a user would.

The lifecycle goes through the stock ``change_state`` / ``get_state`` services; the hand's tracker pose
comes from the test, as a camera node would send it.  The emulator's plant steps on its own thread at the
control rate, unsynchronised with the driver, as a real hand is.  The driver spins on rclpy's EventsExecutor,
as ``t42 node`` spins it.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter
from ros_rig import Rosout, RosRig, Tester, start_node, stop
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from msg_adapters import RCLPY, last_step_stamp, names, object_pose_msg, stamp_to_ns, status_event, status_report
from msg_adapters.wire import ACTUATOR_NAMES
from t42_transfer.conventions import ACTION_UNIT_RAD, CONTROL_PERIOD_S, LATE_STEP_NS, LOAD_UNIT_NM, MIN_STEP_NS
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.hardware import protocol
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS, Faults, PtyBus, t42_bus
from t42_transfer.hardware.hand_plant import HandPlant
from t42_transfer.nodes.dynamixel_driver import REFUSED, STATUS_NAME, DynamixelDriver
from t42_transfer.ros.qos import profile

pytestmark = pytest.mark.events_executor


class Bench:
    """The emulated hand: its bus on a pty, and a thread stepping its physics and sending tracker poses."""

    def __init__(self, tester: Any) -> None:
        self.plant = HandPlant(SimulatedHand("target"))
        self.bus = PtyBus(t42_bus(plant=self.plant))
        self.tracking = True
        self.offset_mm = np.zeros(2)
        """Added to the tracked pose: what the camera sees of an object that fell (the plant holds it on)."""
        self._pose_pub = tester.create_publisher(PoseStamped, names.TRACKER_POSE, 10)
        self._clock = tester.get_clock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(CONTROL_PERIOD_S):
            self.plant.tick()
            if self.tracking:
                stamp = self._clock.now().nanoseconds
                self._pose_pub.publish(object_pose_msg(self.plant.hand.object_xy + self.offset_mm, stamp, RCLPY))

    def torque(self) -> list[bool]:
        return [s.torque for s in self.bus.bus.servos.values()]

    def goals(self) -> list[int]:
        return [s.get(xm.GOAL_POSITION) for s in self.bus.bus.servos.values()]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.bus.close_port()


class Rig(Tester):
    def __init__(self, ros: RosRig, driver: type[DynamixelDriver] = DynamixelDriver) -> None:
        super().__init__(ros)
        self.bench = Bench(self.tester)
        self.driver = ros.add(driver, {"port": self.bench.bus.port, "latency_timer_ms": EMULATED_LATENCY_TIMER_MS})
        self.statuses = self.listen(String, names.HAND_STATUS, profile(names.EVENTS))
        self.joints = self.listen(JointState, names.JOINT_STATES)
        self.poses = self.listen(PoseStamped, names.OBJECT_POSE)
        self.actions = self.listen(JointState, names.APPLIED_ACTION)
        self.change = self.tester.create_client(ChangeState, "dynamixel_driver/change_state")
        self.get = self.tester.create_client(GetState, "dynamixel_driver/get_state")
        self.reset_client = self.tester.create_client(Trigger, names.HAND_RESET)
        self.trajectory_pub = self.tester.create_publisher(JointTrajectory, names.HAND_TRAJECTORY, 10)
        self.grasped = False
        """A reset answered success and no test has failed or let the object go since (shared rig)."""

    def transition(self, transition_id: int) -> bool:
        request = ChangeState.Request()
        request.transition.id = transition_id
        return self.ros.call(self.change, request).success

    def state(self) -> str:
        return self.ros.call(self.get, GetState.Request()).current_state.label

    def events(self) -> list[str]:
        return [status_event(s.data) for s in self.statuses]

    def reset(self) -> Any:
        answer = self.ros.call(self.reset_client, Trigger.Request(), timeout_s=60.0)
        self.grasped = bool(answer.success)
        return answer

    def forget(self) -> None:
        """Drop what was heard so far: what a test reads is what came in since it began, as on a new rig."""
        for heard in (self.statuses, self.joints, self.poses, self.actions):
            heard.clear()


@pytest.fixture
def fresh_rig(ros: RosRig) -> Iterator[Rig]:
    """A rig of the test's own, the driver unconfigured: for the tests of the lifecycle and of closing."""
    r = Rig(ros)
    yield r
    r.driver.close()  # torque off while the bus is still there
    r.bench.close()


@pytest.fixture(scope="module")
def shared_rig(module_ros_domain: int) -> Iterator[Rig]:
    """One bench and driver for the tests below that need an active driver on a grasped hand: a grasp through the
    servos is ~5.6 s at 10 Hz, and each of these tests grasped on a rig of its own before; now a test that passed
    leaves the next its grasp (see :func:`rig`)."""
    ros = RosRig(module_ros_domain, events=True)
    r = Rig(ros)
    try:
        yield r
    finally:
        r.driver.close()  # torque off while the bus is still there
        r.bench.close()
        ros.shutdown()


def _holding(r: Rig) -> bool:
    """The driver steps an episode without a fault, the fingers loaded on the object (as a reset leaves them)."""
    return (r.driver.running and r.driver.fault is None
            and bool(np.all(np.abs(r.bench.plant.hand.loads) > 80)))


@pytest.fixture
def active_rig(shared_rig: Rig, request: pytest.FixtureRequest) -> Iterator[Rig]:
    """The shared rig, active, faults cleared and the tracker on; its message lists hold only what came in since
    the test began.  Afterwards it counts as grasped only if the test passed and the hand still holds."""
    r = shared_rig
    r.bench.bus.bus.faults = Faults()  # a count a test left set would fire in the next
    r.bench.tracking = True
    if r.state() != "active":
        assert r.transition(Transition.TRANSITION_CONFIGURE) and r.transition(Transition.TRANSITION_ACTIVATE)
    r.ros.spin_for(0.3)  # the steps the driver owes after the pause between tests go out before the test starts
    # A bus answer late on a busy machine (seen at the first reads after activation in a fast-suite run) is a
    # fault the driver retries each second: the test starts once it has recovered, as its reset would refuse.
    assert r.ros.spin_until(lambda: r.driver.fault is None, 5.0), r.driver.fault
    r.forget()
    yield r
    passed = getattr(request.node, "report_call", None) is not None and request.node.report_call.passed
    r.grasped = r.grasped and passed and _holding(r)


@contextlib.contextmanager
def drops_unjudged(rig: Rig) -> Iterator[None]:
    """The driver's drop rule off: for a test of limits that may let the object go (a fall would end the episode
    and, with it, the steps the test checks)."""
    assert rig.driver.set_parameters([Parameter("drop_jump_m", value=0.0)])[0].successful
    try:
        yield
    finally:
        assert rig.driver.set_parameters([Parameter("drop_jump_m", value=0.008)])[0].successful


@pytest.fixture
def rig(active_rig: Rig) -> Rig:
    """:func:`active_rig` with the hand grasped: reset here unless the test before left it grasped."""
    r = active_rig
    if not (r.grasped and _holding(r)):  # (the first test, or the one before failed or let go)
        assert r.reset().success  # (any fault recovered first: see active_rig)
        r.ros.spin_for(0.3)
        r.forget()
    return r


def test_the_lifecycle_drives_the_torque(fresh_rig: Rig) -> None:
    """Each transition says on /rosout what it left the hand in."""
    rig = fresh_rig
    log = Rosout(rig.ros, "dynamixel_driver")
    assert rig.state() == "unconfigured"
    assert rig.transition(Transition.TRANSITION_CONFIGURE) and rig.state() == "inactive"
    assert rig.bench.torque() == [False, False]
    assert rig.transition(Transition.TRANSITION_ACTIVATE) and rig.state() == "active"
    assert rig.bench.torque() == [True, True]
    assert rig.transition(Transition.TRANSITION_DEACTIVATE) and rig.bench.torque() == [True, True]  # holds
    assert rig.transition(Transition.TRANSITION_CLEANUP) and rig.state() == "unconfigured"
    assert rig.bench.torque() == [False, False]
    said = ("configured", "active: torque on", "inactive: torque on", "unconfigured: torque off")
    assert rig.ros.spin_until(lambda: all(any(m.msg.startswith(w) for m in log.lines) for w in said), 5.0), \
        [m.msg for m in log.lines]


@pytest.mark.parametrize("port, kind", [("file", "port"), ("silent pty", "timeout")],
                         ids=["not a serial port", "a serial port that is no Dynamixel bus"])
def test_configure_fails_on_a_port_without_servos_and_says_so(ros: RosRig, tmp_path, port: str, kind: str,
                                                             capfd: pytest.CaptureFixture[str]) -> None:
    """The failure goes to hand/status and diagnostics, not only to the log; a configure asked for twice is told
    twice in the log (autostart's retries are not: a new failure only)."""
    if port == "file":
        bogus = tmp_path / "no_bus"
        bogus.write_text("")
        path = str(bogus)
    else:  # a terminal where nothing answers: a modem, an Arduino, another adapter
        master, slave = os.openpty()
        path = os.ttyname(slave)
    try:
        driver = ros.add(DynamixelDriver, {"port": path})
        tester = Tester(ros, "probe")
        statuses = tester.listen(String, names.HAND_STATUS, profile(names.EVENTS))
        diagnostics = tester.listen(DiagnosticArray, names.DIAGNOSTICS)
        change = tester.tester.create_client(ChangeState, "dynamixel_driver/change_state")
        request = ChangeState.Request()
        request.transition.id = Transition.TRANSITION_CONFIGURE
        assert not ros.call(change, request).success
        assert driver.hand is None
        assert ros.spin_until(lambda: statuses and diagnostics, 2.0)

        assert status_event(statuses[-1].data) == names.FAULT and "configure failed" in statuses[-1].data
        report = status_report(diagnostics[-1], STATUS_NAME)
        assert report.level == "ERROR" and report.values["fault_kind"] == kind, report
        assert "configure failed" in report.message
        assert not ros.call(change, request).success  # the same failure again: on diagnostics, not on hand/status
        assert ros.spin_until(lambda: len(diagnostics) >= 2, 2.0)
        ros.spin_for(0.2)
        assert len(statuses) == 1
        errors = [line for line in capfd.readouterr().err.splitlines() if "[dynamixel_driver]" in line]
        assert len(errors) == 2 and all("[ERROR]" in e and "configure failed" in e for e in errors), errors  # asked
    finally:
        if port != "file":
            os.close(master)
            os.close(slave)


def test_a_configure_that_failed_then_passes_says_recovered(fresh_rig: Rig) -> None:
    rig = fresh_rig
    rig.bench.bus.bus.faults.dead.update({1, 2})  # the servos' power off: the port answers nothing
    assert not rig.transition(Transition.TRANSITION_CONFIGURE)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.0), rig.events()
    assert "configure failed: timeout on servo 1" in rig.statuses[-1].data
    rig.bench.bus.bus.faults.dead.clear()
    assert rig.transition(Transition.TRANSITION_CONFIGURE)
    assert rig.ros.spin_until(lambda: rig.events()[-1:] == [names.RECOVERED], 2.0), rig.events()


def test_a_wrong_port_is_fixed_by_setting_it_while_unconfigured_not_by_a_restart(fresh_rig: Rig, tmp_path) -> None:
    rig, bus = fresh_rig, fresh_rig.bench.bus.port
    (tmp_path / "no_bus").write_text("")
    assert rig.driver.set_parameters([Parameter("port", value=str(tmp_path / "no_bus"))])[0].successful
    assert not rig.transition(Transition.TRANSITION_CONFIGURE) and rig.state() == "unconfigured"
    assert rig.driver.set_parameters([Parameter("port", value=bus)])[0].successful
    assert rig.transition(Transition.TRANSITION_CONFIGURE) and rig.driver.hand is not None
    refused = rig.driver.set_parameters([Parameter("baud", value=57_600)])[0]  # the bus is open at 1 Mbaud
    assert not refused.successful and "baud is read at configure" in refused.reason, refused.reason
    assert rig.transition(Transition.TRANSITION_CLEANUP) and rig.driver.hand is None
    assert rig.driver.set_parameters([Parameter("baud", value=57_600)])[0].successful


# The tests on the shared rig run one after the other (its driver steps only while a test spins it); the one that
# may open the hand comes last.


def test_reset_grasps_then_steps_publish_the_hand_at_the_control_rate(active_rig: Rig) -> None:
    """Also: the tracker loses the object while the hand opens; with a pose age limit longer than the grasp the
    new episode's first steps still go out without the old grasp's pose (the object was placed anew)."""
    rig = active_rig  # (active, not grasped by the fixture: the reset here is the one under test)
    rig.ros.spin_for(0.3)  # a tracker pose of the old grasp is held
    rig.bench.tracking = False
    assert rig.driver.set_parameters([Parameter("max_pose_age_s", value=10.0)])[0].successful
    try:
        cut_short = rig.reset_client.call_async(Trigger.Request())
        rig.ros.spin_for(0.5)  # the hand opens ...
        answer = rig.reset()  # ... and a new reset cuts that grasp short: it failed, and says so
        assert answer.success, answer.message
        assert cut_short.done() and not cut_short.result().success, cut_short.result()
        assert cut_short.result().message == "reset interrupted: a new reset"
        assert rig.ros.spin_until(lambda: names.RESET in rig.events(), 2.0)
        grasp_events = [e for e in rig.events() if e in names.GRASP_EVENTS]
        assert grasp_events == [names.GRASPING, names.RESET_FAILED, names.GRASPING, names.RESET], rig.events()
        loads = np.abs(rig.bench.plant.hand.loads)
        assert np.all(loads > 80), loads  # the fingers closed on the object
        said = len(rig.statuses)
        first = len(rig.joints)
        assert rig.ros.spin_until(lambda: len(rig.joints) >= first + 3, 2.0)
        episode_start = stamp_to_ns(rig.joints[first].header.stamp)
        assert [p for p in rig.poses if stamp_to_ns(p.header.stamp) >= episode_start] == []
        assert rig.ros.spin_until(lambda: names.STALE in [status_event(s.data) for s in rig.statuses[said:]], 2.0)
    finally:
        rig.bench.tracking = True
        rig.driver.set_parameters([Parameter("max_pose_age_s", value=0.3)])
    assert rig.ros.spin_until(lambda: stamp_to_ns(rig.poses[-1].header.stamp) > episode_start if rig.poses
                              else False, 2.0)
    start = len(rig.joints)
    rig.ros.spin_for(2.0)
    joints, poses = rig.joints[start:], rig.poses
    assert 15 <= len(joints) <= 25  # 10 Hz
    stamps = [j.header.stamp.sec * 10**9 + j.header.stamp.nanosec for j in joints]
    assert all(0.05e9 < b - a < 0.2e9 for a, b in zip(stamps, stamps[1:], strict=False))
    by_stamp = {p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in poses}
    assert sum(s in by_stamp for s in stamps) >= len(stamps) - 1  # state k's pose shares its stamp
    assert all(np.all(np.abs(j.effort) > 50 * LOAD_UNIT_NM) for j in joints[-3:])  # effort in N m


def test_an_object_that_jumps_ends_the_episode_as_dropped_and_a_reset_starts_the_next(rig: Rig) -> None:
    """The tracker sees the object 60 mm away from one frame to the next (over the paper's 8 mm a period, even
    across a stall of half a second): that step's state goes out without an action, ``dropped`` names it, and the
    hand holds; the next grasp's first pose, 60 mm from the dropped one, is no drop."""
    rig.ros.spin_for(0.3)  # (on a grasped hand: see the rig fixture)
    assert names.DROPPED not in rig.events()
    rig.bench.offset_mm = np.array([60.0, 0.0])
    try:
        assert rig.ros.spin_until(lambda: names.DROPPED in rig.events(), 2.0), rig.events()
        dropped = next(s.data for s in rig.statuses if status_event(s.data) == names.DROPPED)
        moved = re.search(r"the object moved ([0-9.]+) mm between frames ([0-9.]+) s apart \(over 8 mm", dropped)
        assert moved and abs(float(moved.group(1)) - 60.0) < 3.0, dropped
        rig.ros.spin_for(0.5)
        goals = rig.bench.goals()
        final = stamp_to_ns(rig.joints[-1].header.stamp)
        assert last_step_stamp(dropped) == final  # the last state published is the drop's ...
        assert stamp_to_ns(rig.actions[-1].header.stamp) < final  # ... and no action went out from it
        rig.ros.spin_for(0.3)
        assert not rig.driver.running and rig.bench.goals() == goals  # the hand holds
    finally:
        rig.bench.offset_mm = np.zeros(2)  # the object placed anew, 60 mm from where it was last seen
    answer = rig.reset()
    assert answer.success, answer.message
    actions = len(rig.actions)
    rig.ros.spin_for(0.6)
    assert len(rig.actions) >= actions + 4 and rig.events().count(names.DROPPED) == 1, rig.events()


def test_a_stalled_step_is_taken_late_and_said_so_with_its_stamp(rig: Rig) -> None:
    rig.ros.spin_for(0.5)  # (on a grasped hand: see the rig fixture)
    start, late_before = len(rig.joints), rig.driver.late_steps
    time.sleep(0.4)  # the executor stalls: the driver's next timer tick comes ~0.4 s late
    rig.ros.spin_for(1.0)
    stamps = [stamp_to_ns(j.header.stamp) for j in rig.joints[start - 1:]]
    gaps = np.diff(stamps)
    assert gaps.min() >= MIN_STEP_NS and gaps.max() > 300_000_000, gaps  # late, and no catch-up burst after
    late_stamp = stamps[int(np.argmax(gaps)) + 1]
    assert rig.ros.spin_until(lambda: any(last_step_stamp(s.data) == late_stamp for s in rig.statuses
                                          if status_event(s.data) == names.LATE), 2.0), [s.data for s in rig.statuses]
    assert rig.driver.late_steps >= late_before + 1


def test_a_slow_read_is_judged_on_the_stamps_published(rig: Rig) -> None:
    """A read held up (a busy host, a buffering adapter) makes the step late by its stamp, not by its tick: it
    says so, and the tick after it, on time but now too close to that stamp, does not step (under the parallel
    suite a driver once published stamps 152 and then 46 ms apart, and the bag reader split the episode)."""
    rig.ros.spin_for(0.5)  # (on a grasped hand: see the rig fixture)
    start = len(rig.joints)
    faults = rig.bench.bus.bus.faults
    # One step's sync read answers 120 ms late: its stamp comes 100 + 120 ms after the step before, less that
    # step's own lateness (late by 150 ms needs that under 70 ms; at 80 ms, a step before 30 ms late on a busy
    # machine left the slow one 149.8 ms after it), and the answer still 80 ms inside the driver's ~202 ms timeout.
    faults.reply_delay_s, faults.slow_replies = 0.12, 1
    rig.ros.spin_for(1.0)
    assert faults.slow_replies == 0
    stamps = [stamp_to_ns(j.header.stamp) for j in rig.joints[start - 1:]]
    gaps = np.diff(stamps)
    assert gaps.min() >= MIN_STEP_NS, gaps  # no two steps closer than the reader accepts
    late = [b for a, b in zip(stamps, stamps[1:], strict=False) if b - a > LATE_STEP_NS]
    assert late, gaps  # the slow read made a step late ...

    def said() -> set[int | None]:
        return {last_step_stamp(s.data) for s in rig.statuses if status_event(s.data) == names.LATE}

    assert rig.ros.spin_until(lambda: set(late) <= said(), 2.0), (late, said())  # ... and each one says so


def test_with_the_tracker_stopped_no_fresh_looking_pose_goes_out(rig: Rig) -> None:
    rig.ros.spin_for(0.5)  # (on a grasped hand: see the rig fixture, which turns the tracker on again after)
    rig.bench.tracking = False
    rig.ros.spin_for(0.6)
    poses, joints = len(rig.poses), len(rig.joints)
    rig.ros.spin_for(1.0)
    assert len(rig.joints) >= joints + 7 and len(rig.poses) == poses  # steps go on, poses do not
    assert names.STALE in rig.events()


def test_with_no_command_the_hand_holds_a_single_command_moves_it_one_step(rig: Rig) -> None:
    """The watchdog is the step convention: a command is applied for one step, then the hand holds."""
    publisher = rig.tester.create_publisher(JointState, names.HAND_COMMAND, 10)  # (grasped: see the rig fixture)
    try:
        assert rig.ros.spin_until(lambda: publisher.get_subscription_count() >= 1, 5.0)
        rig.ros.spin_for(0.3)
        before = np.array(rig.driver.hand.goal)
        command = JointState(name=list(ACTUATOR_NAMES), velocity=[0.0, -0.25 * 0.025 / CONTROL_PERIOD_S])
        command.header.stamp = rig.tester.get_clock().now().to_msg()
        publisher.publish(command)
        rig.ros.spin_for(1.5)  # many steps after it, no other command
        moved = np.array(rig.driver.hand.goal) - before
        assert np.allclose(moved, [0.0, -0.25 * 0.025], atol=1e-6), moved  # one step of it, then holding
    finally:
        rig.tester.destroy_publisher(publisher)


def test_parameters_are_declared_and_bad_ones_refused(shared_rig: Rig) -> None:
    driver = shared_rig.driver  # (the shared rig's driver; what the test changes is set back)
    assert driver.get_parameter("load_limit").value == 280.0
    try:
        refused = driver.set_parameters([Parameter("grasp_load", value=500.0)])[0]  # above the load limit
        assert not refused.successful and "grasp_load must be below load_limit" in refused.reason
        for value in ([1.0], [1.0, 1.0, 1.0]):  # one limit for two servos raised IndexError out of the service
            refused = driver.set_parameters([Parameter("max_angle_rad", value=value)])[0]
            assert not refused.successful and "2 values, one per actuator" in refused.reason, refused
        assert driver.set_parameters([Parameter("load_limit", value=250.0)])[0].successful
    finally:
        assert driver.set_parameters([Parameter("load_limit", value=280.0)])[0].successful


@pytest.mark.parametrize("inject", [  # each ~7 s; test_hw_emulator_node covers every fault again (an error bit
    # latches: test_hw_emulator_node's test of it)
    pytest.param(lambda bus: setattr(bus.bus.faults, "drop_replies", 3), marks=pytest.mark.slow, id="dropped replies"),
    pytest.param(lambda bus: setattr(bus.bus.faults, "corrupt_replies", 2), id="corruption"),
    pytest.param(lambda bus: bus.bus.servos[2].reboot(), marks=pytest.mark.slow, id="servo restarted"),
])
def test_a_fault_is_reported_then_the_driver_recovers(rig: Rig, inject) -> None:
    inject(rig.bench.bus)  # (on a grasped hand: see the rig fixture)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 1.5), rig.events()
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 5.0), rig.events()
    assert rig.state() == "active" and rig.bench.torque() == [True, True]
    assert rig.reset().success  # and a new episode steps
    count = len(rig.joints)
    rig.ros.spin_for(0.5)
    assert len(rig.joints) > count


def test_a_trajectory_moves_the_servos_and_bad_commands_keep_the_goals_inside_the_limits(rig: Rig) -> None:
    with drops_unjudged(rig):  # (on a grasped hand: see the rig fixture; opening a finger may let the object go)
        _trajectory_and_bad_commands(rig)


def _trajectory_and_bad_commands(rig: Rig) -> None:
    rig.ros.spin_for(0.5)
    written = rig.bench.bus.bus.goals_written
    written.clear()  # every goal the driver sends from here, as sent (the servos refuse those past their limits)
    start = np.array(rig.driver.hand.goal)
    msg = JointTrajectory(joint_names=list(ACTUATOR_NAMES))
    targets = [start + np.array([0.0, -0.02]) * (k + 1) for k in range(10)]  # open finger 2 a little
    for k, t in enumerate(targets):
        point = JointTrajectoryPoint(positions=[float(v) for v in t])
        point.time_from_start.nanosec = int((k + 1) * CONTROL_PERIOD_S * 1e9)
        msg.points.append(point)
    rig.trajectory_pub.publish(msg)
    assert rig.ros.spin_until(lambda: names.TRAJECTORY_DONE in rig.events(), 5.0), rig.events()
    rig.ros.spin_for(0.3)
    assert np.allclose(rig.driver.hand.goal, targets[-1], atol=2 * xm.RAD_PER_TICK)
    commander = rig.tester.create_publisher(JointState, names.HAND_COMMAND, 10)
    assert rig.ros.spin_until(lambda: commander.get_subscription_count() >= 1, 5.0)
    for bad in ([float("nan"), 0.0], [0.0, 1e9], [-1e9, 0.0]):
        command = JointState(name=list(ACTUATOR_NAMES), velocity=bad)
        command.header.stamp = rig.tester.get_clock().now().to_msg()
        commander.publish(command)
    wrong = JointTrajectory(joint_names=["elbow", "wrist"], points=[JointTrajectoryPoint(positions=[9.0, 9.0])])
    rig.trajectory_pub.publish(wrong)
    rig.ros.spin_for(0.5)
    refusals = [s.data for s in rig.statuses if status_event(s.data) == REFUSED]
    assert any(names.HAND_COMMAND in r for r in refusals) and any(names.HAND_TRAJECTORY in r for r in refusals)
    # a good command that would pass a limit: finger 1 may close 0.01 rad more, the command asks 0.025
    limit = [float(rig.driver.hand.goal[0]) + 0.01, 3.0]
    assert rig.driver.set_parameters([Parameter("max_angle_rad", value=limit)])[0].successful
    try:
        command = JointState(name=list(ACTUATOR_NAMES), velocity=[ACTION_UNIT_RAD / CONTROL_PERIOD_S, 0.0])
        command.header.stamp = rig.tester.get_clock().now().to_msg()
        commander.publish(command)
        assert rig.ros.spin_until(lambda: rig.driver.hand.goal[0] >= limit[0] - 1e-9, 2.0), rig.driver.hand.goal
        rig.ros.spin_for(0.3)  # steps after it (the bus takes each write in its own time)
        limits = rig.driver.hand.geometry.limits()
    finally:
        assert rig.driver.set_parameters([Parameter("max_angle_rad", value=[3.0, 3.0])])[0].successful
        rig.tester.destroy_publisher(commander)
    low, high = zip(*limits.values(), strict=True)
    assert all(lo <= g <= hi for g, lo, hi in zip(rig.bench.goals(), low, high, strict=True)), rig.bench.goals()
    assert len(written) >= 15  # a goal each step, through the trajectory and the bad commands
    outside = [goals for goals in written if not all(limits[i][0] <= g <= limits[i][1] for i, g in goals.items())]
    assert not outside, outside


def test_limits_set_at_run_time_take_effect_at_once(rig: Rig) -> None:
    """What ros2 param set accepts on a configured driver is what the next steps obey (it may let the object go)."""
    with drops_unjudged(rig):
        _limits_at_run_time(rig)


def _limits_at_run_time(rig: Rig) -> None:
    driver = rig.driver  # (on a grasped hand: see the rig fixture)
    publisher = rig.tester.create_publisher(JointState, names.HAND_COMMAND, 10)

    def command(action: list[float]) -> np.ndarray:
        """The goal's move over the steps that one command and the holding after it make."""
        before = np.array(driver.hand.goal)
        msg = JointState(name=list(ACTUATOR_NAMES), velocity=[a * ACTION_UNIT_RAD / CONTROL_PERIOD_S for a in action])
        msg.header.stamp = rig.tester.get_clock().now().to_msg()
        publisher.publish(msg)
        rig.ros.spin_for(0.5)
        return np.array(driver.hand.goal) - before

    def set_param(name: str, value: Any) -> Any:
        return driver.set_parameters([Parameter(name, value=value)])[0]

    def refused(why: str) -> bool:  # on hand/status, with the reason
        return any(status_event(s.data) == REFUSED and why in s.data for s in rig.statuses)

    try:
        assert rig.ros.spin_until(lambda: publisher.get_subscription_count() >= 1, 5.0)
        rig.ros.spin_for(0.3)
        # the radians the command asks for are the radians the servos move (the wire's action unit)
        assert np.allclose(command([0.0, -0.5]), [0.0, -0.5 * ACTION_UNIT_RAD], atol=1e-9)
        assert np.all(np.abs(driver.hand.loads) > 60)  # (the grasp holds the object)
        assert set_param("grasp_load", 30.0).successful and set_param("load_limit", 60.0).successful
        assert np.allclose(command([1.0, 1.0]), 0.0), "a finger closed with its load over the new limit"
        assert rig.ros.spin_until(lambda: refused("load over 60"), 1.0), [s.data for s in rig.statuses]
        limit = np.array(driver.hand.goal) - 0.1  # short of where the fingers stand now
        assert set_param("max_angle_rad", [float(a) for a in limit]).successful
        rig.ros.spin_for(0.5)
        assert np.all(np.array(driver.hand.goal) <= limit + 1e-9), (driver.hand.goal, limit)
        assert rig.ros.spin_until(lambda: refused("position limit"), 1.0), [s.data for s in rig.statuses]
        low, high = zip(*driver.hand.geometry.limits().values(), strict=True)
        assert all(lo <= g <= hi for g, lo, hi in zip(rig.bench.goals(), low, high, strict=True))  # on the servos
        refused = set_param("max_angle_rad", [3.1, 3.1])  # past the servos' EEPROM limits: needs a configure
        assert not refused.successful and "Position Limits" in refused.reason, refused
    finally:
        for name, value in (("max_angle_rad", [3.0, 3.0]), ("load_limit", 280.0), ("grasp_load", 100.0)):
            assert set_param(name, value).successful
        rig.tester.destroy_publisher(publisher)


# Rigs of their own.


def test_cleanup_and_close_turn_the_torque_off(fresh_rig: Rig) -> None:
    rig = fresh_rig
    assert rig.transition(Transition.TRANSITION_CONFIGURE) and rig.transition(Transition.TRANSITION_ACTIVATE)
    assert rig.bench.torque() == [True, True]
    rig.driver.close()  # what the runner calls on SIGINT / SIGTERM
    assert rig.bench.torque() == [False, False]
    time.sleep(0.1)


@pytest.mark.parametrize("inject, off", [
    (lambda bus: setattr(bus.bus.faults, "drop_replies", 1), [True, True]),
    (lambda bus: bus.bus.faults.dead.add(1), [False, True]),
], ids=["one reply dropped", "servo 1 dead"])
def test_close_turns_the_torque_off_on_every_servo_that_answers(fresh_rig: Rig, inject, off: list) -> None:
    """One lost reply used to leave servo 2 on after close(); a dead servo 1 left both on."""
    rig = fresh_rig
    assert rig.transition(Transition.TRANSITION_CONFIGURE) and rig.transition(Transition.TRANSITION_ACTIVATE)
    assert rig.bench.torque() == [True, True]
    inject(rig.bench.bus)
    rig.driver.close()
    assert [not on for on in rig.bench.torque()] == off


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_the_driver_process_turns_the_torque_off_when_stopped(ros: RosRig, sig: int, tmp_path: Path) -> None:
    """``t42 node dynamixel_driver`` with autostart on the emulated bus; the signal ends it, the torque goes off."""
    bus = PtyBus(t42_bus())
    log = tmp_path / "driver.log"
    proc = start_node("dynamixel_driver", "-p", f"port:={bus.port}", "-p", "autostart:=true", log=log)
    try:
        deadline = time.monotonic() + 30.0
        while [s.torque for s in bus.bus.servos.values()] != [True, True]:
            assert time.monotonic() < deadline and proc.poll() is None, \
                f"the driver never turned the torque on ({bus.bus.handled} packets handled):\n{log.read_text()[-3000:]}"
            time.sleep(0.05)
        handled, deadline = bus.bus.handled, time.monotonic() + 5.0
        while bus.bus.handled <= handled + 5:  # it steps: one sync read and one sync write each period
            assert time.monotonic() < deadline and proc.poll() is None, f"the driver does not step:\n{log.read_text()}"
            time.sleep(0.05)  # (0.5 s once held only one step, under the parallel suite)
        assert stop([proc], timeout_s=10.0, sig=sig) == [0], log.read_text()[-3000:]
        assert [s.torque for s in bus.bus.servos.values()] == [False, False]
    finally:
        stop([proc])
        bus.close_port()


def test_autostart_tries_activate_again_when_it_fails(ros: RosRig) -> None:
    """The servos' answer to activate's read of where the fingers stand is lost: activate fails and leaves the
    torque off.  Autostart tries it again a second later, as it does configure, until the hand is active (it once
    stayed inactive for good, the torque never on)."""
    with PtyBus(t42_bus()) as bus:
        handle, sync_reads = bus.bus.handle, []

        def second_read_lost(ins):  # noqa: ANN001, ANN202 (configure reads once, then activate does)
            answer = handle(ins)
            if ins.instruction == protocol.SYNC_READ:
                sync_reads.append(answer)
                if len(sync_reads) == 2:
                    return b""
            return answer

        bus.bus.handle = second_read_lost
        driver = ros.add(DynamixelDriver, {"port": bus.port, "autostart": True,
                                           "latency_timer_ms": EMULATED_LATENCY_TIMER_MS})
        assert ros.spin_until(lambda: len(sync_reads) >= 2, 10.0), len(sync_reads)
        assert ros.spin_until(lambda: driver.state == "inactive", 5.0), driver.state  # activate failed
        assert [s.torque for s in bus.bus.servos.values()] == [False, False]
        assert ros.spin_until(lambda: driver.state == "active", 5.0), driver.state
        assert [s.torque for s in bus.bus.servos.values()] == [True, True]
        driver.close()
        assert [s.torque for s in bus.bus.servos.values()] == [False, False]


class RaisingDriver(DynamixelDriver):
    """The driver with a bug: a callback that raises once the hand is active (torque on)."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(**node_kwargs)
        self.create_timer(0.05, self._bug)

    def _bug(self) -> None:
        if self._stepping:
            raise RuntimeError("a bug in a callback")


def test_an_exception_out_of_a_callback_still_turns_the_torque_off(ros_domain: int,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The runner's spin loop ends on the exception; the node's close() runs before it propagates."""
    from t42_transfer.nodes.registry import NODES, NodeSpec
    from t42_transfer.ros.runner import run_node

    monkeypatch.setitem(NODES, "raising_driver", NodeSpec(f"{__name__}:RaisingDriver", "a driver with a bug"))
    with PtyBus(t42_bus()) as bus:
        turned_on = []
        handle = bus.bus.handle

        def watch(ins):  # noqa: ANN001, ANN202 (the torque was on before the bug struck)
            answer = handle(ins)
            turned_on.append(all(s.torque for s in bus.bus.servos.values()))
            return answer

        bus.bus.handle = watch
        with pytest.raises(RuntimeError, match="a bug in a callback"):
            run_node("raising_driver", ["--ros-args", "-p", f"port:={bus.port}", "-p", "autostart:=true",
                                        "-p", f"latency_timer_ms:={EMULATED_LATENCY_TIMER_MS}"])
        assert any(turned_on)
        assert [s.torque for s in bus.bus.servos.values()] == [False, False]


def test_a_fault_that_changes_while_held_is_said_again(fresh_rig: Rig) -> None:
    """Servo 1 dies; while the driver retries, servo 1 comes back and servo 2 dies: the new cause goes to
    hand/status (and /rosout), not to diagnostics alone; the same cause again each second does not."""
    rig = fresh_rig
    assert rig.transition(Transition.TRANSITION_CONFIGURE) and rig.transition(Transition.TRANSITION_ACTIVATE)
    rig.forget()
    faults = rig.bench.bus.bus.faults
    faults.dead.add(1)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.0), rig.events()
    assert "servo 1" in rig.statuses[-1].data
    rig.ros.spin_for(1.5)  # a retry (each second) failing the same way
    assert rig.events().count(names.FAULT) == 1, [s.data for s in rig.statuses]
    faults.dead.clear()
    faults.dead.add(2)
    assert rig.ros.spin_until(lambda: rig.events().count(names.FAULT) == 2, 3.0), [s.data for s in rig.statuses]
    assert "servo 2" in rig.statuses[-1].data
    faults.dead.clear()
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 3.0), rig.events()


class ActivateWithABug(DynamixelDriver):
    """The driver with a bug in activate, after the torque came on."""

    def _activate(self, state: Any) -> Any:
        super()._activate(state)
        raise RuntimeError("a bug in activate")


def test_a_transition_that_raises_releases_the_hand_and_says_why(ros: RosRig) -> None:
    """rclpy answers ERROR and goes to on_error, dropping the exception; the driver says it and lets go."""
    rig = Rig(ros, ActivateWithABug)
    diagnostics = rig.listen(DiagnosticArray, names.DIAGNOSTICS)
    try:
        assert rig.transition(Transition.TRANSITION_CONFIGURE)
        assert not rig.transition(Transition.TRANSITION_ACTIVATE)
        assert rig.state() == "unconfigured" and rig.driver.hand is None
        assert rig.bench.torque() == [False, False]
        assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.0), rig.events()
        said = "activate raised RuntimeError: a bug in activate: torque off, port closed"
        assert said in rig.statuses[-1].data
        assert rig.ros.spin_until(lambda: any(said in status_report(d, STATUS_NAME).message for d in diagnostics),
                                  2.0)
        assert rig.transition(Transition.TRANSITION_CONFIGURE)  # the port was closed: it opens again
    finally:
        rig.driver.close()
        rig.bench.close()


@pytest.mark.parametrize("config", ["hardware_real.yaml", "hardware_emulated.yaml"])
def test_the_shipped_hardware_configs_are_valid_driver_settings(config: str) -> None:
    import yaml
    from ros_rig import REPO

    from t42_transfer.nodes.dynamixel_params import DynamixelDriverParams

    sections = yaml.safe_load((REPO / "configs" / config).read_text())

    def values(node: str) -> dict:
        section = sections[f"/**/{node}"]["ros__parameters"]
        return {k: tuple(v) if isinstance(v, list) else v for k, v in section.items()}

    params = DynamixelDriverParams(**values("dynamixel_driver"))
    assert params.geometry().limits()  # the geometry checks itself: servo range, grasp below the load limit
    if config == "hardware_real.yaml":  # the pose source a real hand has: a camera and the marker tracker
        from t42_transfer.nodes.camera import CameraParams
        from t42_transfer.nodes.object_tracker import ObjectTrackerParams

        camera = CameraParams(**values("camera"))
        assert camera.fps >= 10.0 and str(camera.calibration_file).endswith(".yaml")
        tracker = ObjectTrackerParams(**values("object_tracker"))
        assert len(tracker.base_poses) == 6 * len(tracker.base_ids) == 6 * len(tracker.base_sizes_m)


@pytest.mark.parametrize("override", [False, True], ids=["reliable reader", "best effort by qos_overrides"])
def test_a_best_effort_tracker_is_heard_once_the_reader_is_overridden_to_best_effort(ros: RosRig,
                                                                                    override: bool) -> None:
    """A motion-capture bridge publishing best effort (sensor data QoS) never matches the default reliable
    reader; ROS's QoS override parameter makes the reader best effort, and then its poses come in."""
    from rclpy.qos import qos_profile_sensor_data

    params = {"port": "/nonexistent"}
    if override:
        params[f"qos_overrides./{names.TRACKER_POSE}.subscription.reliability"] = "best_effort"
    driver = ros.add(DynamixelDriver, params)
    tester = Tester(ros)
    bridge = tester.tester.create_publisher(PoseStamped, names.TRACKER_POSE, qos_profile_sensor_data)
    ros.spin_for(1.0)  # discovery (a reader that cannot match never shows as matched)
    assert bridge.get_subscription_count() == (1 if override else 0)
    stamp = tester.tester.get_clock().now().nanoseconds
    for _ in range(5):
        bridge.publish(object_pose_msg(np.array([3.0, 95.0]), stamp, RCLPY))
        ros.spin_for(0.05)
    assert (driver.pose.stamp_ns == stamp) == override
