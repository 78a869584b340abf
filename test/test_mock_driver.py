"""The mock driver node on the in-process transport with a fake clock."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from msg_adapters import (
    APPLIED_ACTION_TOPIC,
    JOINT_STATE,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY,
    OBJECT_POSE_TOPIC,
    POSE_STAMPED,
    TYPESTORE,
    actions_to_joint_trajectory,
    applied_action,
    applied_action_msg,
    joint_state_arrays,
    ns_to_stamp,
    stamp_to_ns,
)
from t42_transfer.conventions import ACTION_UNIT_RAD, CONTROL_PERIOD_NS
from t42_transfer.nodes.mock_driver import (
    COMMAND_TOPIC,
    RESET_SERVICE,
    STATUS_TOPIC,
    STRING,
    TRAJECTORY_TOPIC,
    TRIGGER,
    CommandRejected,
    MockDriver,
    MockDriverParams,
    check_stamp,
    validate_command,
    validate_trajectory,
)
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport

START_NS = 1_000_000_000
MAX_AGE_NS = 500_000_000


class Rig:
    """A driver node and a tester node on one bus, stepped by hand."""

    def __init__(self, params: MockDriverParams | None = None) -> None:
        self.clock = FakeClock(START_NS)
        self.bus = InProcessBus(clock=self.clock)
        self.driver_node = InProcessTransport(self.bus, "mock_driver")
        self.tester = InProcessTransport(self.bus, "tester")
        self.got: dict[str, list] = {t: [] for t in (OBJECT_POSE_TOPIC, JOINT_STATES_TOPIC, APPLIED_ACTION_TOPIC,
                                                      STATUS_TOPIC)}
        for topic, msgtype in ((OBJECT_POSE_TOPIC, POSE_STAMPED), (JOINT_STATES_TOPIC, JOINT_STATE),
                               (APPLIED_ACTION_TOPIC, JOINT_STATE)):
            self.tester.subscribe(topic, msgtype, qos.DEFAULT, self.got[topic].append)
        self.tester.subscribe(STATUS_TOPIC, STRING, qos.TRANSIENT_LOCAL, self.got[STATUS_TOPIC].append)
        self.driver = MockDriver(self.driver_node, params or MockDriverParams())
        self.period_s = self.driver.params.period_s
        self.command_pub = self.tester.publisher(COMMAND_TOPIC, JOINT_STATE)
        self.trajectory_pub = self.tester.publisher(TRAJECTORY_TOPIC, JOINT_TRAJECTORY)
        self.reset_client = self.tester.client(RESET_SERVICE, TRIGGER)

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.clock.advance(self.period_s)
            self.driver_node.spin_once()
            self.tester.spin_once()

    def deliver(self) -> None:
        """Run the driver's message callbacks without a timer tick."""
        self.driver_node.spin_once()

    def command(self, action, stamp_ns: int | None = None) -> None:
        self.command_pub.publish(applied_action_msg(np.asarray(action, np.float32), self._stamp(stamp_ns)))

    def _stamp(self, stamp_ns: int | None) -> int:
        return self.clock() if stamp_ns is None else stamp_ns

    def applied(self) -> np.ndarray:
        return np.array([applied_action(m) for m in self.got[APPLIED_ACTION_TOPIC]]).reshape(-1, 2)

    def statuses(self) -> list[str]:
        return [m.data for m in self.got[STATUS_TOPIC]]

    def close(self) -> None:
        self.driver.close()
        self.driver_node.close()
        self.tester.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and r.name.endswith("mock_driver")]


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
    ([0.1], ("actuator_1",), START_NS, "lacks actuator"),
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
    empty = TYPESTORE.types[JOINT_TRAJECTORY](header=msg.header, joint_names=msg.joint_names, points=[])
    assert validate_trajectory(empty, start, START_NS, MAX_AGE_NS).shape == (0, 2)


@pytest.mark.parametrize("kwargs", [{"rate_factor": 0.0}, {"rate_factor": float("nan")},
                                    {"max_command_age_s": -1.0}, {"command_topic": "hand/command"}])
def test_params_validated(kwargs):
    with pytest.raises(ValueError):
        MockDriverParams(**kwargs)


# --------------------------------------------------------------------------- the node
def test_publishes_at_10_hz_with_stamps(rig):
    rig.tester.spin_once()
    assert rig.statuses() == ["reset: episode 0 grasped (seed 0)"]
    grasped = rig.driver.hand.state
    rig.tick(5)
    for topic in (OBJECT_POSE_TOPIC, JOINT_STATES_TOPIC, APPLIED_ACTION_TOPIC):
        stamps = [stamp_to_ns(m.header.stamp) for m in rig.got[topic]]
        assert stamps == [START_NS + (k + 1) * CONTROL_PERIOD_NS for k in range(5)], topic
    loads, angles = joint_state_arrays(rig.got[JOINT_STATES_TOPIC][0])
    np.testing.assert_array_equal(loads, grasped[2:].astype(np.float32))  # state k at stamp k
    assert angles is not None and loads[0] > 0 > loads[1]
    np.testing.assert_array_equal(rig.applied(), np.zeros((5, 2)))  # no command: the hand holds
    assert rig.driver.steps == 5


def test_rate_factor_speeds_up_the_timer():
    r = Rig(MockDriverParams(rate_factor=10.0))
    try:
        r.tick(5)  # half a real period: five steps
        assert r.driver.steps == 5
        stamps = [stamp_to_ns(m.header.stamp) for m in r.got[JOINT_STATES_TOPIC]]
        assert np.all(np.diff(stamps) == CONTROL_PERIOD_NS // 10)
    finally:
        r.close()


def test_single_step_command_moves_angles_once(rig):
    before = rig.driver.hand.actuator_angles
    rig.command([0.8, -0.4])
    rig.tick()
    np.testing.assert_allclose(rig.driver.hand.actuator_angles - before,
                               np.array([0.8, -0.4], np.float32) * ACTION_UNIT_RAD, atol=1e-9)
    rig.tick()  # held for one step only
    np.testing.assert_allclose(rig.applied(), [[0.8, -0.4], [0.0, 0.0]], atol=1e-7)
    # the published joint state at the second stamp shows the moved angles
    _, angles = joint_state_arrays(rig.got[JOINT_STATES_TOPIC][1])
    np.testing.assert_allclose(angles, before + np.array([0.8, -0.4]) * ACTION_UNIT_RAD, atol=1e-6)


def test_trajectory_runs_point_by_point_and_is_preempted(rig):
    first = np.array([[0.2, 0.1], [0.3, -0.2], [-0.1, 0.2], [0.4, 0.4], [0.1, 0.1]], np.float32)
    rig.trajectory_pub.publish(actions_to_joint_trajectory(first, rig.driver.hand.actuator_angles, rig.clock()))
    targets = []
    for _ in range(2):
        rig.tick()
        targets.append(rig.driver.hand.actuator_angles)
    assert rig.driver.pending_actions == 3
    second = np.array([[-0.5, -0.5], [0.0, -0.3]], np.float32)
    start = rig.driver.hand.actuator_angles
    rig.trajectory_pub.publish(actions_to_joint_trajectory(second, start, rig.clock()))
    rig.tick(3)
    np.testing.assert_allclose(rig.applied(), np.vstack([first[:2], second, [[0.0, 0.0]]]), atol=1e-6)
    np.testing.assert_allclose(rig.driver.hand.actuator_angles,
                               start + ACTION_UNIT_RAD * second.astype(np.float64).sum(axis=0), atol=1e-9)
    np.testing.assert_allclose(targets[1] - targets[0], ACTION_UNIT_RAD * first[1].astype(np.float64), atol=1e-9)
    assert rig.driver.pending_actions == 0


def test_empty_trajectory_and_command_cancel_a_running_one(rig):
    acts = np.full((5, 2), 0.1, np.float32)
    rig.trajectory_pub.publish(actions_to_joint_trajectory(acts, rig.driver.hand.actuator_angles, 0))
    rig.tick()
    empty = TYPESTORE.types[JOINT_TRAJECTORY](header=rig.got[JOINT_STATES_TOPIC][0].header,
                                              joint_names=["actuator_1", "actuator_2"], points=[])
    empty.header.stamp = ns_to_stamp(0)
    rig.trajectory_pub.publish(empty)
    rig.tick()
    rig.trajectory_pub.publish(actions_to_joint_trajectory(acts, rig.driver.hand.actuator_angles, 0))
    rig.deliver()
    assert rig.driver.pending_actions == 5
    rig.command([-0.3, 0.0])
    rig.tick(2)
    np.testing.assert_allclose(rig.applied(), [[0.1, 0.1], [0, 0], [-0.3, 0.0], [0, 0]], atol=1e-6)


def test_reset_service_regrasps(rig):
    rig.command([1.0, 1.0])
    rig.tick(3)
    response = rig.reset_client.call(rig.reset_client.Request())
    assert response.success and "episode 1" in response.message
    assert rig.driver.steps == 0 and rig.driver.running and rig.driver.episode == 1
    rig.tester.spin_once()
    assert rig.statuses()[-1].startswith("reset")


def _bad_inputs(r: Rig):
    good = applied_action_msg(np.array([0.1, 0.1], np.float32), r.clock())
    nan = _command_msg([np.nan, 0.0], stamp_ns=r.clock())
    inf = _command_msg([0.0, -np.inf], stamp_ns=r.clock())
    big = _command_msg([1.6, 0.0], stamp_ns=r.clock())
    names = _command_msg([0.1], names=("actuator_1",), stamp_ns=r.clock())
    values = _command_msg([0.1, 0.1, 0.1], stamp_ns=r.clock())
    stale = applied_action_msg(np.array([0.1, 0.1], np.float32), r.clock() - 10**9)
    spacing = actions_to_joint_trajectory(np.full((3, 2), 0.1, np.float32), r.driver.hand.actuator_angles, 0)
    spacing.points[2].time_from_start.sec += 1
    positions = actions_to_joint_trajectory(np.full((2, 2), 0.1, np.float32), r.driver.hand.actuator_angles, 0)
    positions.points[0].positions = np.array([0.1])
    nan_traj = actions_to_joint_trajectory(np.full((2, 2), 0.1, np.float32), r.driver.hand.actuator_angles, 0)
    nan_traj.points[1].positions = np.array([np.nan, 0.2])
    return good, [("NaN", nan, "non-finite"), ("inf", inf, "non-finite"), ("|a|>1.5", big, "outside"),
                  ("names", names, "lacks actuator"), ("values", values, "3 values for 2"),
                  ("stale", stale, "stale"), ("spacing", spacing, "every"),
                  ("positions", positions, "1 values for 2"), ("nan trajectory", nan_traj, "non-finite")]


def test_bad_inputs_are_rejected_and_the_last_safe_command_kept(rig, caplog):
    caplog.set_level(logging.WARNING)
    rig.tick()
    good, bad = _bad_inputs(rig)
    rig.command_pub.publish(good)
    for name, msg, why in bad:
        pub = rig.trajectory_pub if msg.__msgtype__ == JOINT_TRAJECTORY else rig.command_pub
        caplog.clear()
        pub.publish(msg)
        rig.deliver()  # no exception escapes the callback
        warnings = _warnings(caplog)
        assert len(warnings) == 1 and why in warnings[0] and "rejected" in warnings[0], (name, warnings)
    rig.tick(2)
    np.testing.assert_allclose(rig.applied(), [[0, 0], [0.1, 0.1], [0, 0]], atol=1e-6)
    assert rig.driver.running


def test_drop_publishes_status_and_stops_until_reset(rig, caplog):
    caplog.set_level(logging.WARNING)
    for _ in range(60):
        rig.command([-1.0, -1.0])
        rig.tick()
        if not rig.driver.running:
            break
    assert not rig.driver.running
    status = rig.statuses()[-1]
    assert status.split(":")[0] in ("dropped", "lost_contact"), status
    assert any("ended" in w for w in _warnings(caplog))
    n_actions, n_states = len(rig.got[APPLIED_ACTION_TOPIC]), len(rig.got[JOINT_STATES_TOPIC])
    assert n_states == n_actions + 1  # the final state has no action
    rig.command([-1.0, -1.0])
    rig.tick(3)  # no stepping (nor crash) until reset
    assert len(rig.got[JOINT_STATES_TOPIC]) == n_states
    assert rig.reset_client.call(rig.reset_client.Request()).success
    rig.tick()
    assert len(rig.got[JOINT_STATES_TOPIC]) == n_states + 1 and rig.driver.running


def test_sim_time_publishes_clock_and_stamps_one_period_per_tick_at_any_rate():
    r = Rig(MockDriverParams(rate_factor=10.0, sim_time=True))
    clocks: list = []
    r.tester.subscribe("/clock", "rosgraph_msgs/msg/Clock", qos.CLOCK, clocks.append)
    r.tick(5)
    r.tester.spin_once()
    stamps = [stamp_to_ns(m.header.stamp) for m in r.got[JOINT_STATES_TOPIC]]
    assert len(stamps) == 5 and np.all(np.diff(stamps) == CONTROL_PERIOD_NS)  # while wall moved 10 ms a tick
    assert [stamp_to_ns(c.clock) for c in clocks] == stamps
    assert stamps[0] == START_NS + CONTROL_PERIOD_NS
    # commands are judged against the simulated clock: one stamped at sim time is fresh
    r.command([0.5, 0.5], stamp_ns=stamps[-1])
    r.tick()
    np.testing.assert_allclose(r.applied()[-1], [0.5, 0.5], rtol=1e-6)
    r.close()
