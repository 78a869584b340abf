"""The mock driver node on real rclpy, in-process: its timer is stepped by hand (``tick``) for determinism."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from ros_rig import Rosout, Tester
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    actions_to_joint_trajectory,
    applied_action,
    applied_action_msg,
    joint_state_arrays,
    last_step_stamp,
    names,
    stamp_to_ns,
    status_event,
)
from t42_transfer.conventions import ACTION_UNIT_RAD, CONTROL_PERIOD_NS, DROP_REASONS
from t42_transfer.data.bag import bag_info, read_bag
from t42_transfer.driver.commands import CommandRejected, check_stamp, validate_command, validate_trajectory
from t42_transfer.hand.params import NAMED_VARIANTS
from t42_transfer.nodes.mock_driver import MockDriver, MockDriverParams
from t42_transfer.nodes.recorder import Recorder
from t42_transfer.ros.qos import profile

START_NS = 1_000_000_000
MAX_AGE_NS = 500_000_000
SLOW_TIMER = 1e-3
"""rate_factor that keeps the driver's own timer (100 s period) out of hand-stepped tests."""

SOME_WALL_TIME_NS = 1_600_000_000 * 10**9
"""September 2020: a clock that starts from the wall time is past it; one that starts from 0 is not."""


class Rig(Tester):
    """A driver node and a tester node in one process; the driver is stepped by hand with :meth:`tick`."""

    def __init__(self, ros, **params) -> None:
        super().__init__(ros)
        params.setdefault("rate_factor", SLOW_TIMER)
        self.driver = ros.add(MockDriver, params)
        self.got: dict[str, list] = {
            names.OBJECT_POSE: self.listen(PoseStamped, names.OBJECT_POSE),
            names.JOINT_STATES: self.listen(JointState, names.JOINT_STATES),
            names.APPLIED_ACTION: self.listen(JointState, names.APPLIED_ACTION),
            names.HAND_STATUS: self.listen(String, names.HAND_STATUS, profile(names.EVENTS)),
        }
        self.command_pub = self.tester.create_publisher(JointState, names.HAND_COMMAND, 10)
        self.trajectory_pub = self.tester.create_publisher(JointTrajectory, names.HAND_TRAJECTORY, 10)
        self.reset_client = self.tester.create_client(Trigger, names.HAND_RESET)
        # discovery: the driver hears the tester and the tester the driver before the test starts
        assert ros.spin_until(lambda: self.command_pub.get_subscription_count() == 1
                              and self.trajectory_pub.get_subscription_count() == 1
                              and len(self.got[names.HAND_STATUS]) >= 2, 10.0)  # the first grasp's two
        assert self.wait_graph(publishers=dict.fromkeys((names.OBJECT_POSE, names.JOINT_STATES,
                                                         names.APPLIED_ACTION), 1)), "discovery"

    def clock(self) -> int:
        return self.driver.now_ns()

    def _count(self) -> int:
        return sum(len(v) for k, v in self.got.items() if k != names.HAND_STATUS)

    def tick(self, n: int = 1, stamp_ns: int | None = None) -> None:
        """``n`` control steps, each delivered to the tester before the next (one stamped ``stamp_ns`` if given)."""
        for _ in range(n):
            before, running = self._count(), self.driver.running
            self.driver.tick(stamp_ns=stamp_ns)
            if running:
                assert self.ros.spin_until(lambda before=before: self._count() > before + 1, 5.0), "step not delivered"
                self.ros.spin_for(0.02)

    def deliver(self, what: list | None = None) -> None:
        """Let published test messages reach the driver's callbacks."""
        self.ros.spin_for(0.15)

    def command(self, action, stamp_ns: int | None = None) -> None:
        self.command_pub.publish(applied_action_msg(np.asarray(action, np.float32), self._stamp(stamp_ns), RCLPY))
        self.deliver()

    def trajectory(self, msg) -> None:
        self.trajectory_pub.publish(msg)
        self.deliver()

    def _stamp(self, stamp_ns: int | None) -> int:
        return self.clock() if stamp_ns is None else stamp_ns

    def applied(self) -> np.ndarray:
        return np.array([applied_action(m) for m in self.got[names.APPLIED_ACTION]]).reshape(-1, 2)

    def statuses(self) -> list[str]:
        return [m.data for m in self.got[names.HAND_STATUS]]

    def reset(self) -> Trigger.Response:
        return self.ros.call(self.reset_client, Trigger.Request())


@pytest.fixture
def rig(ros):
    return Rig(ros)


# --------------------------------------------------------------------------- pure functions
def _command_msg(values, names=("actuator_1", "actuator_2"), stamp_ns=START_NS):
    msg = applied_action_msg(np.zeros(2, np.float32), stamp_ns)
    msg.name = list(names)
    msg.velocity = np.asarray(values, np.float64) * ACTION_UNIT_RAD / 0.1
    return msg


def test_validate_command_decodes_velocity():
    action = validate_command(_command_msg([0.5, -1.5]), START_NS, MAX_AGE_NS)
    np.testing.assert_allclose(action, [0.5, -1.5], rtol=1e-6)


@pytest.mark.parametrize("values,names,stamp,why", [
    ([np.nan, 0.0], ("actuator_1", "actuator_2"), START_NS, "non-finite"),
    ([0.0, np.inf], ("actuator_1", "actuator_2"), START_NS, "non-finite"),
    ([1.6, 0.0], ("actuator_1", "actuator_2"), START_NS, "outside"),
    ([0.1, 0.2, 0.3], ("actuator_1", "actuator_2"), START_NS, "3 values for 2"),
    ([0.1], ("actuator_1",), START_NS, r"^command lacks actuator\(s\) \[.actuator_2.\]"),
    ([0.1, 0.1], ("actuator_1", "actuator_2"), START_NS - 600_000_000, "stale"),
    ([0.1, 0.1], ("actuator_1", "actuator_2"), START_NS + 600_000_000, "future"),
    ([0.1, 0.1], ("actuator_1", "actuator_2"), 0, "unset"),
])
def test_validate_command_rejects(values, names, stamp, why):
    with pytest.raises(CommandRejected, match=why):
        validate_command(_command_msg(values, names, stamp), START_NS, MAX_AGE_NS)


def test_check_stamp_window():
    check_stamp(START_NS - MAX_AGE_NS, START_NS, MAX_AGE_NS)
    check_stamp(START_NS + MAX_AGE_NS, START_NS, MAX_AGE_NS)
    with pytest.raises(CommandRejected, match="stale"):
        check_stamp(START_NS - MAX_AGE_NS - 1, START_NS, MAX_AGE_NS)


def test_validate_trajectory_round_trip_and_rejects():
    start = np.array([0.4, 0.5])
    actions = np.array([[0.5, -0.25], [1.5, -1.5], [0.0, 1.0]], np.float32)
    msg = actions_to_joint_trajectory(actions, start, 0)  # stamp 0: start now
    np.testing.assert_allclose(validate_trajectory(msg, start, START_NS, MAX_AGE_NS), actions, atol=1e-6)
    too_big = actions_to_joint_trajectory(np.array([[2.0, 0.0]], np.float32), start, START_NS)
    with pytest.raises(CommandRejected, match="outside"):
        validate_trajectory(too_big, start, START_NS, MAX_AGE_NS)
    msg.points[1].time_from_start.nanosec += 50_000_000
    with pytest.raises(CommandRejected, match="every"):
        validate_trajectory(msg, start, START_NS, MAX_AGE_NS)
    stale = actions_to_joint_trajectory(actions, start, START_NS - 600_000_000)
    with pytest.raises(CommandRejected, match="stale"):
        validate_trajectory(stale, start, START_NS, MAX_AGE_NS)
    empty = JointTrajectory(joint_names=list(msg.joint_names))
    assert validate_trajectory(empty, start, START_NS, MAX_AGE_NS).shape == (0, 2)


@pytest.mark.parametrize("kwargs", [{"rate_factor": 0.0}, {"rate_factor": float("nan")},
                                    {"max_command_age_s": -1.0}, {"seed": -3}])
def test_params_validated(kwargs):
    with pytest.raises(ValueError):
        MockDriverParams(**kwargs)


# --------------------------------------------------------------------------- the node
def test_publishes_state_and_action_per_step_with_one_stamp(rig):
    assert rig.statuses() == ["grasping: episode 0: the hand opens, then closes on the object [last step 0 ns]",
                              "reset: episode 0 grasped (seed 0) [last step 0 ns]"]
    grasped = rig.driver.hand.state
    rig.tick(5)
    stamps = {topic: [stamp_to_ns(m.header.stamp) for m in rig.got[topic]]
              for topic in (names.OBJECT_POSE, names.JOINT_STATES, names.APPLIED_ACTION)}
    assert len(stamps[names.JOINT_STATES]) == 5
    assert stamps[names.OBJECT_POSE] == stamps[names.JOINT_STATES] == stamps[names.APPLIED_ACTION]
    loads, angles = joint_state_arrays(rig.got[names.JOINT_STATES][0])
    np.testing.assert_array_equal(loads, grasped[2:].astype(np.float32))  # state k at stamp k
    assert angles is not None and loads[0] > 0 > loads[1]
    np.testing.assert_array_equal(rig.applied(), np.zeros((5, 2)))  # no command: the hand holds
    assert rig.driver.steps == 5


def test_timer_runs_at_rate_factor_and_rate_changes_at_run_time(ros):
    driver = ros.add(MockDriver, {"rate_factor": 10.0, "sim_time": True})  # a step every 10 ms
    ros.spin_for(1.0)
    fast = driver.steps
    assert 40 <= fast <= 110, fast  # shared machine: generous bounds around 100
    setter = ros.node("setter").create_client(SetParameters, "mock_driver/set_parameters")
    result = ros.call(setter,
                      SetParameters.Request(parameters=[Parameter("rate_factor", value=1.0).to_parameter_msg()]))
    assert result.results[0].successful
    ros.spin_for(0.05)
    before = driver.steps
    ros.spin_for(1.0)
    assert 5 <= driver.steps - before <= 12, driver.steps - before  # 10 Hz now


def test_a_rate_factor_on_the_wall_clock_is_warned_about_at_start(ros):
    """Steps 20 ms apart on the wall clock: a bag of them reads as no episode, which the user learns at start."""
    ros.add(MockDriver, {"rate_factor": 5.0})
    warned = Rosout(ros, "mock_driver").wait_warnings()
    assert any("20 ms apart" in w and "sim_time" in w for w in warned), warned


def test_on_wall_clock_stamps_a_run_time_rate_change_is_refused_with_the_reason(ros):
    """It put the steps of the bag being recorded 17 ms apart, and the bag reader refused all of it."""
    driver = ros.add(MockDriver, {"rate_factor": 1.0})
    setter = ros.node("setter").create_client(SetParameters, "mock_driver/set_parameters")
    (result,) = ros.call(setter, SetParameters.Request(
        parameters=[Parameter("rate_factor", value=6.0).to_parameter_msg()])).results
    assert not result.successful and "only with sim_time" in result.reason
    assert driver.params.rate_factor == 1.0 and driver.get_parameter("rate_factor").value == 1.0


def test_bad_parameter_values_are_refused_and_the_old_kept(ros):
    driver = ros.add(MockDriver, {"rate_factor": SLOW_TIMER})
    setter = ros.node("setter").create_client(SetParameters, "mock_driver/set_parameters")
    cases = [Parameter("rate_factor", value=-1.0), Parameter("rate_factor", value="fast"),
             Parameter("max_command_age_s", value=0.0), Parameter("hand", value="source"),
             Parameter("seed", value=-2)]
    for p in cases:
        result = ros.call(setter, SetParameters.Request(parameters=[p.to_parameter_msg()]))
        assert not result.results[0].successful and result.results[0].reason, p.name
    assert driver.params == MockDriverParams(rate_factor=SLOW_TIMER)
    ok = ros.call(setter,
                  SetParameters.Request(parameters=[Parameter("max_command_age_s", value=2.0).to_parameter_msg()]))
    assert ok.results[0].successful and driver.params.max_command_age_s == 2.0
    log = Rosout(ros, "mock_driver")
    for seed in (5, 7, -1):  # (-1: unseeded; ROS has no null for a parameter)
        ros.call(setter, SetParameters.Request(parameters=[Parameter("seed", value=seed).to_parameter_msg()]))
    assert ros.spin_until(lambda: any("unseeded" in m.msg for m in log.lines), 3.0)
    said = [m.msg for m in log.lines if "next reset" in m.msg]
    assert said[-3:] == ["the next reset grasps with seed 5", "the next reset grasps with seed 7",
                         "the next resets grasp unseeded"], said
    assert driver.params.seed == -1
    ok, said_reset = driver.reset()
    assert ok and said_reset.endswith("grasped") and "seed" not in said_reset, said_reset  # no seed to tell
    described = driver.describe_parameter("rate_factor")
    assert described.type == ParameterType.PARAMETER_DOUBLE and described.description
    assert described.floating_point_range[0].from_value > 0 and driver.describe_parameter("hand").read_only
    hand = driver.describe_parameter("hand").description
    assert "target_abrupt" in hand and "family-<seed>" in hand  # every variant hand.params names
    assert all(name in hand for name in NAMED_VARIANTS)


def test_bad_startup_parameters_are_one_line_errors(ros):
    with pytest.raises(ValueError, match="rate_factor"):
        ros.add(MockDriver, {"rate_factor": 0.0})


def test_single_step_command_moves_angles_once(rig):
    before = rig.driver.hand.actuator_angles
    rig.command([0.8, -0.4])
    rig.tick()
    np.testing.assert_allclose(rig.driver.hand.actuator_angles - before,
                               np.array([0.8, -0.4], np.float32) * ACTION_UNIT_RAD, atol=1e-9)
    rig.tick()  # held for one step only
    np.testing.assert_allclose(rig.applied(), [[0.8, -0.4], [0.0, 0.0]], atol=1e-7)
    # the published joint state at the second stamp shows the moved angles
    _, angles = joint_state_arrays(rig.got[names.JOINT_STATES][1])
    np.testing.assert_allclose(angles, before + np.array([0.8, -0.4]) * ACTION_UNIT_RAD, atol=1e-6)


def test_trajectory_runs_point_by_point_and_is_preempted(rig):
    first = np.array([[0.2, 0.1], [0.3, -0.2], [-0.1, 0.2], [0.4, 0.4], [0.1, 0.1]], np.float32)
    rig.trajectory(actions_to_joint_trajectory(first, rig.driver.hand.actuator_angles, rig.clock(), RCLPY))
    targets = []
    for _ in range(2):
        rig.tick()
        targets.append(rig.driver.hand.actuator_angles)
    assert rig.driver.pending_actions == 3
    second = np.array([[-0.5, -0.5], [0.0, -0.3]], np.float32)
    start = rig.driver.hand.actuator_angles
    rig.trajectory(actions_to_joint_trajectory(second, start, rig.clock(), RCLPY))
    rig.tick(3)
    np.testing.assert_allclose(rig.applied(), np.vstack([first[:2], second, [[0.0, 0.0]]]), atol=1e-6)
    np.testing.assert_allclose(rig.driver.hand.actuator_angles,
                               start + ACTION_UNIT_RAD * second.astype(np.float64).sum(axis=0), atol=1e-9)
    np.testing.assert_allclose(targets[1] - targets[0], ACTION_UNIT_RAD * first[1].astype(np.float64), atol=1e-9)
    assert rig.driver.pending_actions == 0
    assert any(s.startswith("trajectory_done") for s in rig.statuses())


def test_empty_trajectory_and_command_cancel_a_running_one(rig):
    acts = np.full((5, 2), 0.1, np.float32)
    rig.trajectory(actions_to_joint_trajectory(acts, rig.driver.hand.actuator_angles, 0, RCLPY))
    rig.tick()
    rig.trajectory(JointTrajectory(joint_names=["actuator_1", "actuator_2"]))  # stamp 0, no points: stop
    rig.tick()
    rig.trajectory(actions_to_joint_trajectory(acts, rig.driver.hand.actuator_angles, 0, RCLPY))
    assert rig.driver.pending_actions == 5
    rig.command([-0.3, 0.0])
    rig.tick(2)
    np.testing.assert_allclose(rig.applied(), [[0.1, 0.1], [0, 0], [-0.3, 0.0], [0, 0]], atol=1e-6)


def test_reset_service_regrasps(rig):
    rig.command([1.0, 1.0])
    rig.tick(3)
    response = rig.reset()
    assert response.success and "episode 1" in response.message
    assert rig.driver.steps == 0 and rig.driver.running and rig.driver.episode == 1
    assert rig.ros.spin_until(lambda: rig.statuses()[-1].startswith("reset: episode 1"), 5.0)


def _command_rclpy(values, names=("actuator_1", "actuator_2"), stamp_ns=START_NS):
    msg = applied_action_msg(np.zeros(2, np.float32), stamp_ns, RCLPY)
    msg.name = list(names)
    msg.velocity = [float(v) * ACTION_UNIT_RAD / 0.1 for v in values]
    return msg


def _bad_inputs(r: Rig):
    now = r.clock()
    good = applied_action_msg(np.array([0.1, 0.1], np.float32), now, RCLPY)
    start = r.driver.hand.actuator_angles
    spacing = actions_to_joint_trajectory(np.full((3, 2), 0.1, np.float32), start, 0, RCLPY)
    spacing.points[2].time_from_start.sec += 1
    positions = actions_to_joint_trajectory(np.full((2, 2), 0.1, np.float32), start, 0, RCLPY)
    positions.points[0].positions = [0.1]
    nan_traj = actions_to_joint_trajectory(np.full((2, 2), 0.1, np.float32), start, 0, RCLPY)
    nan_traj.points[1].positions = [float("nan"), 0.2]
    return good, [("NaN", _command_rclpy([np.nan, 0.0], stamp_ns=now), "non-finite"),
                  ("inf", _command_rclpy([0.0, -np.inf], stamp_ns=now), "non-finite"),
                  ("|a|>1.5", _command_rclpy([1.6, 0.0], stamp_ns=now), "outside"),
                  ("names", _command_rclpy([0.1], names=("actuator_1",), stamp_ns=now), "lacks actuator"),
                  ("values", _command_rclpy([0.1, 0.1, 0.1], stamp_ns=now), "3 values for 2"),
                  ("stale", applied_action_msg(np.array([0.1, 0.1], np.float32), now - 60 * 10**9, RCLPY), "stale"),
                  ("spacing", spacing, "every"),
                  ("positions", positions, "1 values for 2"), ("nan trajectory", nan_traj, "non-finite")]


def test_bad_inputs_are_rejected_on_rosout_and_the_last_safe_command_kept(ros):
    rig = Rig(ros, max_command_age_s=30.0)  # wall time passes between making and delivering a message
    log = Rosout(rig.ros, "mock_driver")
    rig.tick()
    good, bad = _bad_inputs(rig)
    rig.command_pub.publish(good)
    rig.deliver()
    for name, msg, why in bad:
        log.clear()
        (rig.trajectory_pub if isinstance(msg, JointTrajectory) else rig.command_pub).publish(msg)
        rig.deliver()  # no exception escapes the callback
        warnings = log.wait_warnings()
        assert len(warnings) == 1 and why in warnings[0] and "rejected" in warnings[0], (name, warnings)
        assert warnings[0].endswith("ignored (the hand goes on as before: holding, or the trajectory it runs)")
    rig.tick(2)
    np.testing.assert_allclose(rig.applied(), [[0, 0], [0.1, 0.1], [0, 0]], atol=1e-6)
    assert rig.driver.running


def test_a_flood_of_bad_commands_is_a_log_line_a_second_that_counts_the_rest(ros):
    """500 NaN commands once made 500 /rosout lines; now a line a second goes out, each counting those held back."""
    import re
    import time

    rig = Rig(ros, max_command_age_s=30.0)
    log = Rosout(rig.ros, "mock_driver")
    rig.tick()
    log.clear()
    started = time.monotonic()
    for k in range(500):
        rig.command_pub.publish(_command_rclpy([np.nan, k / 1000], stamp_ns=rig.clock()))
        rig.ros.executor.spin_once(timeout_sec=0.0)  # delivered as they come, not collapsed by the queue's depth
    rig.ros.spin_for(0.2)
    flood_s = time.monotonic() - started
    rig.ros.spin_for(1.1)  # past the period: the next one of the kind goes out with the count
    rig.command_pub.publish(_command_rclpy([np.nan, 0.0], stamp_ns=rig.clock()))
    rig.ros.spin_for(0.3)
    warnings = log.wait_warnings()
    assert all("non-finite" in w for w in warnings)
    assert 2 <= len(warnings) <= int(flood_s) + 2, (flood_s, warnings)  # a line a second of the flood, then one
    held = [int(m.group(1)) for w in warnings if (m := re.search(r"\((\d+) more like it", w))]
    assert len(held) == len(warnings) - 1 and len(warnings) + sum(held) >= 100, warnings  # every one is counted
    rig.tick(2)
    assert rig.driver.running


def test_moves_refused_step_after_step_are_a_log_line_a_second(ros):
    """A command held against a travel limit is refused at every step: once a /rosout line a step (20 a second
    at twice real time), now a line a second counting the rest."""
    import time

    rig = Rig(ros, max_command_age_s=30.0)
    log = Rosout(rig.ros, "mock_driver")
    rig.tick()
    log.clear()
    started = time.monotonic()
    rig.trajectory(actions_to_joint_trajectory(np.full((30, 2), 1.5, np.float32), rig.driver.hand.actuator_angles,
                                               rig.clock(), RCLPY))
    rig.tick(30)
    took = time.monotonic() - started
    rig.ros.spin_for(0.3)
    refused = [m.msg for m in log.lines if "servo move was refused" in m.msg]
    assert rig.driver.running and refused, "no refused move to log"
    assert len(refused) <= int(took) + 1, (took, refused)


def test_drop_publishes_status_and_stops_until_reset(rig):
    log = Rosout(rig.ros, "mock_driver")
    for _ in range(60):
        rig.command([-1.0, -1.0])
        rig.tick()
        if not rig.driver.running:
            break
    assert not rig.driver.running
    assert rig.ros.spin_until(lambda: rig.statuses()[-1].split(":")[0] in ("dropped", "lost_contact"), 5.0), \
        rig.statuses()
    assert any("ended" in w for w in log.wait_warnings())
    rig.ros.spin_for(0.1)
    n_actions, n_states = len(rig.got[names.APPLIED_ACTION]), len(rig.got[names.JOINT_STATES])
    assert n_states == n_actions + 1  # the final state has no action
    rig.command([-1.0, -1.0])
    rig.driver.tick()  # no stepping (nor crash) until reset
    rig.ros.spin_for(0.1)
    assert len(rig.got[names.JOINT_STATES]) == n_states
    assert rig.reset().success
    rig.tick()
    assert len(rig.got[names.JOINT_STATES]) == n_states + 1 and rig.driver.running


def test_a_recorded_drop_reads_as_the_simulated_collection_ends_the_episode(ros, tmp_path):
    """The recorder keeps what the driver published, the state the object fell into too; the reader leaves that
    state out and gives the episode the driver's end reason, as ``hand.collect`` ends a simulated episode."""
    recorder = ros.add(Recorder, params={"out_dir": str(tmp_path), "mode": "episode", "step_hold_s": 1.0})
    rig = Rig(ros)
    start = rig.clock()  # steps stamped a control period apart, as the driver's timer stamps them
    rig.tick(stamp_ns=start)
    assert ros.spin_until(lambda: recorder.current_count >= 3, 5.0), recorder.current_count  # it hears the hand
    for k in range(1, 20):  # held long enough to make an episode before it opens
        rig.tick(stamp_ns=start + k * CONTROL_PERIOD_NS)
    for k in range(20, 80):
        rig.command([-1.0, -1.0])
        rig.tick(stamp_ns=start + k * CONTROL_PERIOD_NS)
        if not rig.driver.running:
            break
    assert not rig.driver.running
    end = rig.statuses()[-1]
    assert status_event(end) in DROP_REASONS, rig.statuses()
    assert ros.spin_until(lambda: len(recorder.bags) == 1, 10.0), recorder.bags  # closed at the end status
    states = [joint_state_arrays(m)[0] for m in rig.got[names.JOINT_STATES]]
    recorded = bag_info(recorder.bags[0])["topics"][f"/{names.JOINT_STATES}"]["count"]
    (episode,) = read_bag(recorder.bags[0])
    assert episode.end_reason == status_event(end) and len(episode.states) == recorded - 1
    np.testing.assert_allclose(episode.states[-1, 2:], states[-2], rtol=1e-6)  # the last state before the fall
    assert last_step_stamp(end) == stamp_to_ns(rig.got[names.JOINT_STATES][-1].header.stamp)


def test_sim_time_publishes_clock_and_stamps_one_period_per_tick_at_any_rate(ros):
    r = Rig(ros, sim_time=True)
    clocks: list = []
    r.tester.create_subscription(Clock, "/clock", clocks.append, 10)
    ros.spin_for(0.3)
    start = r.clock()
    for k in range(1, 6):
        r.driver._on_timer()  # the timer callback: /clock first, then the step
        assert ros.spin_until(lambda k=k: len(r.got[names.JOINT_STATES]) == len(clocks) == k, 5.0)
    stamps = [stamp_to_ns(m.header.stamp) for m in r.got[names.JOINT_STATES]]
    assert len(stamps) == 5 and np.all(np.diff(stamps) == CONTROL_PERIOD_NS)
    assert [stamp_to_ns(c.clock) for c in clocks] == stamps and stamps[0] == start + CONTROL_PERIOD_NS
    # commands are judged against the simulated clock: one stamped at sim time is fresh
    r.command([0.5, 0.5], stamp_ns=stamps[-1])
    r.driver._on_timer()
    assert ros.spin_until(lambda: len(r.applied()) == 6, 5.0)
    np.testing.assert_allclose(r.applied()[-1], [0.5, 0.5], rtol=1e-6)


def test_the_clock_source_on_sim_time_itself_still_ticks(ros):
    """A params file that sets ``use_sim_time`` for every node, this one included: its ticks run on the machine's
    clock, not on the /clock it publishes (on which it would wait for itself)."""
    ros.add(MockDriver, {"rate_factor": 10.0, "sim_time": True, "use_sim_time": True})
    clocks: list = []
    ros.node("clock_listener").create_subscription(Clock, "/clock", clocks.append, 10)
    assert ros.spin_until(lambda: len(clocks) >= 5, 10.0), len(clocks)
    stamps = [stamp_to_ns(c.clock) for c in clocks]
    assert np.all(np.diff(stamps) == CONTROL_PERIOD_NS)
    assert stamps[0] > SOME_WALL_TIME_NS, stamps[0]  # from the wall time it started at, not from 0 (its ROS time)


def test_works_under_a_namespace_with_remapped_names(ros):
    driver = ros.add(MockDriver, {"rate_factor": SLOW_TIMER}, namespace="/left",
                     cli_args=["--ros-args", "-r", "hand/object_pose:=pose_remapped"])
    tester = ros.node("ns_tester")
    poses, joints = [], []
    tester.create_subscription(PoseStamped, "/left/pose_remapped", poses.append, 10)
    tester.create_subscription(JointState, "/left/hand/joint_states", joints.append, 10)
    reset = tester.create_client(Trigger, "/left/hand/reset")
    assert ros.spin_until(lambda: tester.count_publishers("/left/pose_remapped") == 1
                          and tester.count_publishers("/left/hand/joint_states") == 1, 10.0)
    driver.tick()
    assert ros.spin_until(lambda: poses and joints, 5.0)
    assert ros.call(reset, Trigger.Request()).success


def test_statuses_are_events_kept_deep_enough_not_to_be_replaced(rig):
    """A reliable KEEP_LAST 1 writer replaces a status a slow reader has not acknowledged: under load the
    recorder missed a reset and merged two episodes. Statuses use a deep, latched history instead."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    qos = rig.driver._status_pub.qos_profile  # the depth is not in the graph's endpoint info
    assert qos.depth >= 50 and qos.reliability == ReliabilityPolicy.RELIABLE
    assert qos.durability == DurabilityPolicy.TRANSIENT_LOCAL  # a late joiner still hears the last reset
    for k in range(50):
        rig.driver._publish_status(f"trajectory_done: burst {k}")
    assert rig.ros.spin_until(lambda: sum("burst" in s for s in rig.statuses()) == 50, 10.0)
    assert [s for s in rig.statuses() if "burst" in s] == [f"trajectory_done: burst {k}" for k in range(50)]


def test_a_burst_of_resets_from_separate_clients_is_answered_in_full(rig):
    """50 callers at once: each gets its answer (10 of 50 did, the service's queue held 10)."""
    clients = [rig.tester.create_client(Trigger, names.HAND_RESET) for _ in range(50)]
    assert rig.ros.spin_until(lambda: all(c.service_is_ready() for c in clients), 10.0)
    futures = [c.call_async(Trigger.Request()) for c in clients]
    assert rig.ros.spin_until(lambda: all(f.done() for f in futures), 60.0), sum(f.done() for f in futures)
    answers = [f.result() for f in futures]
    assert all(a.success and "grasped" in a.message for a in answers), [a.message for a in answers if not a.success]


def test_a_trajectory_longer_than_any_plan_is_refused_unread_and_the_steps_go_on(ros):
    """Its size is read before its points: deserializing a million points once held the driver for 15 s."""
    rig = Rig(ros, max_command_age_s=30.0)
    log = Rosout(rig.ros, "mock_driver")
    rig.tick()
    huge = actions_to_joint_trajectory(np.zeros((60_000, 2), np.float32), rig.driver.hand.actuator_angles, 0, RCLPY)
    rig.trajectory_pub.publish(huge)
    warnings = log.wait_warnings(timeout_s=10.0)
    assert len(warnings) == 1 and "refused unread" in warnings[0] and "trajectory" in warnings[0], warnings
    rig.tick(2)
    np.testing.assert_allclose(rig.applied()[-2:], 0.0)  # nothing of it was queued
