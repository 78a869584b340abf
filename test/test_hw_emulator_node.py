"""The emulated hardware node with the Dynamixel driver on its port: the suite's hand without a hand."""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.srv import GetState
from rclpy.parameter import Parameter
from ros_rig import Rosout, RosRig, Tester
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from msg_adapters import last_step_stamp, names, stamp_to_ns, status_event, status_report
from t42_transfer.conventions import CONTROL_PERIOD_NS, MIN_EPISODE_STEPS
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS
from t42_transfer.nodes.dynamixel_driver import RETRY_PERIOD_S, STATUS_NAME, DynamixelDriver
from t42_transfer.nodes.hw_emulator import HwEmulator
from t42_transfer.ros.qos import profile


class Rig(Tester):
    def __init__(self, ros: RosRig, link: Path, emulator: dict | None = None, driver: dict | None = None) -> None:
        super().__init__(ros)
        self.emulator = ros.add(HwEmulator, {"link": str(link), **(emulator or {})})
        self.driver = ros.add(DynamixelDriver, {"port": str(link), "autostart": True,
                                                "latency_timer_ms": EMULATED_LATENCY_TIMER_MS, **(driver or {})})
        self.statuses = self.listen(String, names.HAND_STATUS, profile(names.EVENTS))
        self.tracker = self.listen(PoseStamped, names.TRACKER_POSE)
        self.poses = self.listen(PoseStamped, names.OBJECT_POSE)
        self.joints = self.listen(JointState, names.JOINT_STATES)
        self.diagnostics = self.listen(DiagnosticArray, names.DIAGNOSTICS)
        self.get = self.tester.create_client(GetState, "dynamixel_driver/get_state")
        self.reset_client = self.tester.create_client(Trigger, names.HAND_RESET)
        self.grasped = False
        """A reset answered success and no test has failed or seen the episode end since (shared rig)."""

    def reports(self, level: str) -> list[Any]:
        """The driver's diagnostics at ``level`` so far."""
        found = []
        for array in self.diagnostics:
            try:
                report = status_report(array, STATUS_NAME)
            except KeyError:
                continue
            if report.level == level:
                found.append(report)
        return found

    def events(self) -> list[str]:
        return [status_event(s.data) for s in self.statuses]

    def active(self) -> bool:
        return self.ros.call(self.get, GetState.Request()).current_state.label == "active"

    def reset(self, within_s: float = 20.0) -> bool:
        """Reset the hand.  A reset refused or cut short by a fault is asked again after the driver's retry period
        until ``within_s``: a busy machine can hold the emulator's answers past the driver's timeout (one such
        timeout, mid-grasp after a port fault, failed a fast suite on 3 workers), and the driver recovering and
        then grasping is what the callers check."""
        deadline = time.monotonic() + within_s
        while True:
            answer = self.ros.call(self.reset_client, Trigger.Request(), timeout_s=60.0)
            self.grasped = bool(answer.success)
            by_fault = answer.message.startswith(("the hand has a fault", "reset interrupted"))
            if answer.success or not by_fault or time.monotonic() > deadline:
                return self.grasped
            self.ros.spin_for(RETRY_PERIOD_S)

    def forget(self) -> None:
        """Drop what was heard so far: what a test reads is what came in since it began, as on a new rig."""
        for heard in (self.statuses, self.tracker, self.poses, self.joints, self.diagnostics):
            heard.clear()

    def inject(self, **faults: object) -> None:
        result = self.emulator.set_parameters([Parameter(k, value=v) for k, v in faults.items()])
        assert all(r.successful for r in result), result


HEALTHY = {"drop_replies": 0, "corrupt_replies": 0, "slow_replies": 0, "error_bits": [0, 0], "dead_servos": [0],
           "port_closed": False, "pose_dropout": 0.0}
"""The emulator's fault parameters with no fault injected."""


@pytest.fixture(scope="module")
def shared_rig(module_ros_domain: int, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    """One emulator and driver for the tests below that run on wall time: a grasp through the servos takes ~5.6 s
    at 10 Hz, and each of these tests found the hand grasped by its own reset before; now a test that passed
    leaves the next its grasp (each fault test ends with a reset, the proof that the driver came back)."""
    ros = RosRig(module_ros_domain)
    r = Rig(ros, tmp_path_factory.mktemp("hw") / "ttyT42")
    try:
        yield r
    finally:
        r.driver.close()
        r.emulator.close()
        ros.shutdown()


@pytest.fixture
def rig(shared_rig: Rig, request: pytest.FixtureRequest) -> Iterator[Rig]:
    """The shared rig, active, the hand grasped (reset here unless the test before left it grasped) and holding;
    its message lists hold only what comes in from the test's start."""
    r = shared_rig
    r.inject(**HEALTHY)  # every fault parameter: a test that failed may have left one injected
    assert r.ros.spin_until(r.active, 10.0)
    if not r.grasped:  # (the first test, or the one before failed or saw the episode end)
        assert r.reset()
    r.ros.spin_for(0.3)  # the steps the driver owes after the pause between tests go out before the test starts
    r.forget()
    yield r
    passed = getattr(request.node, "report_call", None) is not None and request.node.report_call.passed
    r.grasped = r.grasped and passed and not any(e in names.END_EVENTS for e in r.events())


@pytest.mark.parametrize("everyone_on_sim_time", [False, True])
def test_on_sim_time_the_driver_steps_in_lockstep_with_the_emulators_clock_faster_than_real_time(
        ros: RosRig, tmp_path: Path, everyone_on_sim_time: bool) -> None:
    """With ``everyone_on_sim_time`` the emulator, the clock's source, also has ``use_sim_time`` (a params file
    that sets it for every node): its ticks run on the machine's clock, not on the /clock it publishes."""
    emulator = {"sim_time": True, "rate_factor": 4.0, **({"use_sim_time": True} if everyone_on_sim_time else {})}
    rig = Rig(ros, tmp_path / "ttyT42", emulator=emulator, driver={"use_sim_time": True, "max_command_age_s": 2.0})
    try:
        assert rig.ros.spin_until(rig.active, 10.0) and rig.reset()
        start = len(rig.joints)
        rig.ros.spin_for(2.0)
        stamps = [stamp_to_ns(j.header.stamp) for j in rig.joints[start:]]
        assert len(stamps) >= 50, len(stamps)  # 2 s: 20 steps at 1x, 80 at 4x (slack for load)
        gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
        assert set(gaps) == {CONTROL_PERIOD_NS}, gaps  # a step each period: in lockstep, a busy machine skips none
        assert stamps[0] > 1_600_000_000 * 10**9, stamps[0]  # the clock starts from the wall time, not from 0
        assert rig.reports("OK") and rig.reports("OK")[-1].values["skipped_ticks"] == "0"
    finally:
        rig.driver.close()
        rig.emulator.close()


def test_a_fault_is_injected_once_per_change_and_a_spent_count_goes_back_to_zero(ros: RosRig) -> None:
    """A count the bus used up is 0 in the parameters too, so the same count can be set again; a change of
    another parameter injects nothing again (it once re-armed every fault)."""
    from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler

    from t42_transfer.hardware.servos import _Port

    emulator = ros.add(HwEmulator, {})
    # dynamixel-sdk's own packets, on its port with the emulated bus's latency timer as every other client of it
    # in the suite: the SDK's 16 ms gives an answer ~34 ms, which a busy machine can hold the bus's thread past.
    # (A guess at why this test failed under the parallel suite and passed alone: that output was not kept.)
    port, packets = _Port(emulator.port, EMULATED_LATENCY_TIMER_MS), PacketHandler(2.0)
    assert port.openPort() and port.setBaudRate(1_000_000)

    def inject(**faults: object) -> None:
        assert all(r.successful for r in emulator.set_parameters([Parameter(k, value=v) for k, v in faults.items()]))

    def pings() -> list[int]:
        return [packets.ping(port, 1)[1] for _ in range(3)]

    try:
        inject(drop_replies=2)
        assert pings() == [COMM_RX_TIMEOUT, COMM_RX_TIMEOUT, COMM_SUCCESS]
        assert ros.spin_until(lambda: emulator.get_parameter("drop_replies").value == 0, 5.0)  # (at the next tick)
        inject(pose_dropout=0.5)
        assert pings() == [COMM_SUCCESS] * 3
        inject(drop_replies=2)
        assert pings() == [COMM_RX_TIMEOUT, COMM_RX_TIMEOUT, COMM_SUCCESS]
        inject(error_bits=[0, 32])
        assert packets.read1ByteTxRx(port, 2, xm.HARDWARE_ERROR_STATUS.address)[0] == 32
        assert packets.reboot(port, 2)[0] == COMM_SUCCESS  # clears it
        inject(pose_dropout=0.0)
        assert packets.read1ByteTxRx(port, 2, xm.HARDWARE_ERROR_STATUS.address)[0] == 0
    finally:
        port.closePort()
        emulator.close()


def test_autostart_waits_for_a_port_that_appears_later(ros: RosRig, tmp_path: Path) -> None:
    """``t42 up`` starts emulator and driver at once: a driver that looks first keeps trying, and says so once at
    info level (no fault on ``hand/status``, no error on /rosout, for a port not there yet)."""
    link = tmp_path / "ttyT42"
    tester = Tester(ros)
    log = Rosout(ros, "dynamixel_driver")
    statuses = tester.listen(String, names.HAND_STATUS, profile(names.EVENTS))
    get = tester.tester.create_client(GetState, "dynamixel_driver/get_state")
    driver = ros.add(DynamixelDriver, {"port": str(link), "autostart": True,
                                       "latency_timer_ms": EMULATED_LATENCY_TIMER_MS})
    emulator = None
    try:
        ros.spin_for(2.5)
        assert ros.call(get, GetState.Request()).current_state.label == "unconfigured"
        emulator = ros.add(HwEmulator, {"link": str(link)})
        assert ros.spin_until(lambda: ros.call(get, GetState.Request()).current_state.label == "active", 10.0)
        lines = [(m.level, m.msg) for m in log.lines if m.name.endswith("dynamixel_driver")]
        assert [msg for _, msg in lines if msg.startswith("autostart: waiting for")] == [
            f"autostart: waiting for {link} to appear (up to 10 s before it is a fault)"], lines
        assert not [msg for level, msg in lines if level >= Rosout.WARN], lines
        assert not [s.data for s in statuses if s.data.startswith(names.FAULT)], [s.data for s in statuses]
    finally:
        driver.close()
        if emulator is not None:
            emulator.close()


def test_autostart_gives_way_to_a_lifecycle_client_that_configures_first(ros: RosRig, tmp_path: Path) -> None:
    """The retry once raised in the timer (configure from 'inactive') and the driver process died."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    link = tmp_path / "ttyT42"
    tester = Tester(ros)
    get = tester.tester.create_client(GetState, "dynamixel_driver/get_state")
    change = tester.tester.create_client(ChangeState, "dynamixel_driver/change_state")
    driver = ros.add(DynamixelDriver, {"port": str(link), "autostart": True,
                                       "latency_timer_ms": EMULATED_LATENCY_TIMER_MS})
    emulator = None
    try:
        ros.spin_for(0.3)  # the first try failed: no port yet
        emulator = ros.add(HwEmulator, {"link": str(link)})
        configure = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE))
        assert ros.call(change, configure).success
        ros.spin_for(1.5)  # the retry comes due
        assert ros.call(get, GetState.Request()).current_state.label == "inactive"
        activate = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_ACTIVATE))
        for _ in range(3):  # a busy machine may delay the emulator's answer past a read's timeout: still inactive
            if ros.call(change, activate).success:
                break
            assert ros.call(get, GetState.Request()).current_state.label == "inactive"
        assert ros.call(get, GetState.Request()).current_state.label == "active"
    finally:
        driver.close()
        if emulator is not None:
            emulator.close()


# The tests on the shared rig run one after the other (its driver steps only while a test spins it).


def test_the_driver_runs_the_emulated_hand_with_the_trackers_rate(rig: Rig) -> None:
    start_joints, start_tracker = len(rig.joints), len(rig.tracker)
    rig.ros.spin_for(3.0)
    steps, frames = len(rig.joints) - start_joints, len(rig.tracker) - start_tracker
    assert 25 <= steps <= 35
    assert 0.3 <= 1 - frames / steps <= 0.6, (frames, steps)  # steps without a new frame: 34-53 % on the real hands
    joint_stamps = {stamp_to_ns(j.header.stamp) for j in rig.joints[start_joints:]}
    pose_stamps = [stamp_to_ns(p.header.stamp) for p in rig.poses]
    assert sum(s in joint_stamps for s in pose_stamps) >= steps - 2  # one pose per step, stamped with it


SLOW = pytest.mark.slow  # each case is ~15 s of a running driver: two stay in the default run


@pytest.mark.parametrize("fault, clear", [
    pytest.param({"drop_replies": 4}, {}, marks=SLOW, id="dropped replies"),
    pytest.param({"corrupt_replies": 3}, {}, marks=SLOW, id="corruption"),
    pytest.param({"dead_servos": [2]}, {"dead_servos": [0]}, marks=SLOW, id="dead servo"),
    pytest.param({"port_closed": True}, {"port_closed": False}, id="port closed"),
])
def test_each_injected_fault_shows_within_a_second_and_the_driver_comes_back(rig: Rig, fault: dict,
                                                                              clear: dict) -> None:
    rig.inject(**fault)  # (on a grasped hand: see the rig fixture)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events() and rig.reports("ERROR"), 1.0), rig.events()
    values = rig.reports("ERROR")[0].values
    assert values["fault_kind"] in ("timeout", "corrupt", "port")
    assert rig.driver.get_parameter("port").value and rig.active()  # alive and still active
    servos = rig.emulator.bus.servos.values()
    goals = [s.get(xm.GOAL_POSITION) for s in servos]
    rig.ros.spin_for(0.3)
    assert all(not s.torque or s.get(xm.GOAL_POSITION) == g for s, g in zip(servos, goals, strict=True)), \
        "a servo moved during the fault"  # each held, or its torque off
    if clear:
        rig.inject(**clear)
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 5.0), rig.events()
    assert rig.reset()
    count = len(rig.joints)
    rig.ros.spin_for(0.5)
    assert len(rig.joints) > count


def test_an_error_bit_latches_until_cleanup_t42_hw_reboot_and_configure(rig: Rig) -> None:
    """A servo overloaded (it may still be): the driver used to reboot it and torque it again every second without
    end.  Now the fault stays, said again on diagnostics each second, the servo left alone, until the operator
    cleans up (the port is free then), reboots the servo with ``t42 hw reboot`` and configures again."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    from t42_transfer.cli import main

    rig.inject(error_bits=[0, 32])
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events() and rig.reports("ERROR"), 1.0), rig.events()
    values = rig.reports("ERROR")[0].values
    assert values["fault_kind"] == "hardware" and values["servo_id"] == "2", values
    assert "overload error" in values["hardware_errors"]
    said = [s.data for s in rig.statuses if status_event(s.data) == names.FAULT]
    assert "latched" in said[0] and "t42 hw reboot" in said[0], said
    rig.ros.spin_for(2.5)
    assert names.RECOVERED not in rig.events() and rig.active(), rig.events()
    assert rig.emulator.bus.servos[2].get(xm.HARDWARE_ERROR_STATUS) == 32  # never rebooted by the driver
    assert len(rig.reports("ERROR")) >= 3  # said again each second
    change = rig.tester.create_client(ChangeState, "dynamixel_driver/change_state")

    def transition(transition_id: int) -> bool:
        return rig.ros.call(change, ChangeState.Request(transition=Transition(id=transition_id))).success

    assert transition(Transition.TRANSITION_DEACTIVATE) and transition(Transition.TRANSITION_CLEANUP)
    port = rig.driver.get_parameter("port").value
    assert main(["hw", "reboot", "--port", port, "--ids", "2", "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]) == 0
    assert transition(Transition.TRANSITION_CONFIGURE) and transition(Transition.TRANSITION_ACTIVATE)
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 2.0), rig.events()
    assert rig.reset()


def test_steps_without_a_fresh_pose_are_left_out_of_the_recorded_episode_with_a_warning(rig: Rig,
                                                                                          tmp_path: Path) -> None:
    from t42_transfer.data.bag import read_bag
    from t42_transfer.nodes.recorder import Recorder

    ros = rig.ros  # (the grasped hand: see the rig fixture)
    recorder = ros.add(Recorder, {"out_dir": str(tmp_path / "bags")})
    try:
        rig.ros.spin_for(2.5)
        rig.inject(pose_dropout=1.0)  # the camera loses the object for a second
        assert rig.ros.spin_until(lambda: names.STALE in rig.events(), 2.0)
        rig.ros.spin_for(1.0)
        rig.inject(pose_dropout=0.0)
        rig.ros.spin_for(2.5)
        (bag,) = [recorder.current_bag]
    finally:
        recorder.close()
        ros.executor.remove_node(recorder)
        ros.nodes.remove(recorder)
        recorder.destroy_node()
    with pytest.warns(UserWarning, match="dropped|left out|missing"):
        data = read_bag(bag)
    assert len(data) == 2  # split where the poses went stale
    stale = [stamp_to_ns(j.header.stamp) for j in rig.joints if stamp_to_ns(j.header.stamp) not in
             {stamp_to_ns(p.header.stamp) for p in rig.poses}]
    assert len(stale) >= 5  # steps went out without a pose ...
    kept = {t.start_ns + k * CONTROL_PERIOD_NS for t in data for k in range(len(t) + 1)}
    assert not kept & set(stale)  # ... and none of them is in the recorded episodes


def whole_runs(rig: Rig, after_ns: int, until_ns: int | None = None) -> list[list[int]]:
    """Stamps of the runs of consecutive whole steps (a joint state and its pose) heard in ``(after_ns,
    until_ns]``: what a bag reader keeps as episodes (a stale step, without its pose, ends a run)."""
    posed = {stamp_to_ns(p.header.stamp) for p in rig.poses}
    runs: list[list[int]] = [[]]
    for stamp in sorted(stamp_to_ns(j.header.stamp) for j in rig.joints):
        if stamp <= after_ns or (until_ns is not None and stamp > until_ns):
            continue
        if stamp in posed:
            runs[-1].append(stamp)
        elif runs[-1]:
            runs.append([])
    return [run for run in runs if run]


LONG_RUN = MIN_EPISODE_STEPS + 6
"""States in a run the fault test waits for: an episode of MIN_EPISODE_STEPS transitions, and some to spare."""


def test_a_fault_mid_episode_loses_nothing_already_recorded_and_splits_the_episode(rig: Rig, tmp_path: Path) -> None:
    """The port goes away mid-episode and comes back: the bags hold every step of an episode published before
    the fault, the fault ends the episode there (a split event: the next episode, after the reset, is another
    bag).  Episodes are runs of whole steps: on a loaded machine a pose can come too late for its step, which
    then splits the run (the reader keeps runs of MIN_EPISODE_STEPS transitions and more), so the test waits
    for runs rather than for a time."""
    import numpy as np

    from t42_transfer.data.bag import read_bag
    from t42_transfer.nodes.recorder import Recorder

    ros, out = rig.ros, tmp_path / "bags"  # (the grasped hand: see the rig fixture)
    recorder = ros.add(Recorder, {"out_dir": str(out), "mode": "episode"})
    try:
        ros.spin_for(1.0)  # the recorder's subscriptions match
        # a loaded machine can delay the first step past that second (a bus timeout, recovered): wait for one
        assert ros.spin_until(lambda: rig.joints, 10.0), "the driver published no joint state"
        began_ns = max(stamp_to_ns(j.header.stamp) for j in rig.joints)
        assert ros.spin_until(lambda: whole_runs(rig, began_ns)[-1:] and len(whole_runs(rig, began_ns)[-1])
                              >= LONG_RUN, 20.0), [len(r) for r in whole_runs(rig, began_ns)]
        rig.inject(port_closed=True)
        assert ros.spin_until(lambda: names.FAULT in rig.events(), 1.0), rig.events()
        (fault,) = [s.data for s in rig.statuses if status_event(s.data) == names.FAULT]
        fault_ns = last_step_stamp(fault)
        assert fault_ns is not None, fault
        rig.inject(port_closed=False)
        assert ros.spin_until(lambda: names.RECOVERED in rig.events(), 5.0), rig.events()
        assert rig.reset()  # the next episode (and the next test's grasp)
        reset_ns, heard = max(stamp_to_ns(j.header.stamp) for j in rig.joints), len(rig.statuses)
        # late steps on a loaded machine break runs (a 4-worker suite once saw only 13 whole steps in 20 s): the
        # wait is long, the run asked for the same.  (A 2-worker suite once saw one run of 6 in 45 s: the message
        # says whether steps stopped, lost their poses, or an end status came.)
        assert ros.spin_until(lambda: any(len(r) >= LONG_RUN for r in whole_runs(rig, reset_ns)), 45.0), (
            [len(r) for r in whole_runs(rig, reset_ns)],
            f"{sum(stamp_to_ns(j.header.stamp) > reset_ns for j in rig.joints)} joint states and "
            f"{sum(stamp_to_ns(p.header.stamp) > reset_ns for p in rig.poses)} poses since the reset",
            [s.data for s in rig.statuses[heard:]][-10:])
        ros.spin_for(0.5)  # the recorder takes the last of them
    finally:
        recorder.close()
        ros.executor.remove_node(recorder)
        ros.nodes.remove(recorder)
        recorder.destroy_node()
    heard = {stamp_to_ns(j.header.stamp): np.array(j.position, np.float32) for j in rig.joints}
    bags = sorted(out.iterdir())
    with warnings.catch_warnings(record=True) as caught:  # why a step was left out, should one be missing
        warnings.simplefilter("always")
        episodes = [read_bag(bag) for bag in bags]
    said = [str(w.message) for w in caught]
    assert len(bags) == 2, (bags, said)  # split at the fault
    recorded: dict[int, np.ndarray] = {}
    for k, data in enumerate(episodes):
        for t in data:
            steps = t.step_ns if t.step_ns is not None else np.full(len(t), CONTROL_PERIOD_NS)  # (exact stamps)
            for stamp, angles in zip(t.start_ns + np.concatenate([[0], np.cumsum(steps)]), t.actuator_angles,
                                     strict=True):
                recorded[int(stamp)] = angles
                assert (stamp <= fault_ns) == (k == 0), (k, stamp, fault_ns)  # the fault splits there
    assert recorded, bags
    assert min(recorded) - began_ns < 1_500_000_000  # the recorder began with the test (subscriptions matched)
    kept = [run for run in whole_runs(rig, began_ns, fault_ns) if len(run) > MIN_EPISODE_STEPS]
    assert kept and kept[-1][-1] == fault_ns, ([len(r) for r in whole_runs(rig, began_ns, fault_ns)], fault_ns)
    before = [stamp for run in kept for stamp in run]  # the episode ran to the fault
    missing = [s for s in before if s not in recorded or not np.array_equal(heard[s], recorded[s])]
    assert not missing, f"{len(missing)} of {len(before)} steps published before the fault are not in the bags: {said}"
    assert len(episodes[1]) >= 1, f"the episode after the reset is not in the second bag: {said}"


def test_a_dead_servo_is_named_on_diagnostics_and_the_hand_holds_until_it_answers(rig: Rig) -> None:
    """The fast dead-servo case (the full one, with a reset after, is slow): the fault names servo 2, the other
    servo keeps its torque and its goal while the driver retries, and the hand is back once servo 2 answers."""
    bus = rig.emulator.bus  # (on a grasped hand: see the rig fixture; last here, as the episode ends)
    rig.grasped = False  # the fault ends the episode: a test after this one grasps again
    rig.inject(dead_servos=[2])
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events() and rig.reports("ERROR"), 1.0), rig.events()
    values = rig.reports("ERROR")[0].values
    assert (values["servo_id"], values["fault_kind"]) == ("2", "timeout"), values
    held = bus.servos[1].get(xm.GOAL_POSITION)
    rig.ros.spin_for(1.2)  # a retry comes and fails meanwhile
    servo = bus.servos[1]
    assert servo.torque and servo.get(xm.GOAL_POSITION) == held  # held where it stood, not slack, not moving
    assert abs(servo.get(xm.PRESENT_POSITION) - held) <= 20, (servo.get(xm.PRESENT_POSITION), held)
    assert rig.reports("ERROR")[-1].values["servo_id"] == "2" and rig.active()
    rig.inject(dead_servos=[0])
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 3.0), rig.events()
    assert [s.torque for s in bus.servos.values()] == [True, True]
