"""msg_adapters: SI units on the wire, bit-exact round trips, clear refusals of bad messages."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import msg_adapters as ma
from msg_adapters import wire

F32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
PAIRS = arrays(np.float32, 2, elements=F32)
STAMPS = st.integers(0, 2**31 * 10**9 - 1)


def through_cdr(msg):
    """The message as a subscriber gets it: serialised to CDR and back."""
    return ma.TYPESTORE.deserialize_cdr(ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype == np.float32 and np.array_equal(a.view(np.uint32), b.view(np.uint32))


@given(xy=PAIRS, stamp=STAMPS)
def test_object_pose_round_trip_is_bit_exact(xy, stamp):
    msg = through_cdr(ma.object_pose_msg(xy, stamp))
    assert same_bits(ma.object_xy_mm(msg), xy)
    assert ma.stamp_to_ns(msg.header.stamp) == stamp


@given(loads=PAIRS, angles=st.none() | PAIRS, stamp=STAMPS)
def test_joint_state_round_trip_is_bit_exact(loads, angles, stamp):
    msg = through_cdr(ma.joint_state_msg(loads, angles, stamp))
    got_loads, got_angles = ma.joint_state_arrays(msg)
    assert same_bits(got_loads, loads)
    assert got_angles is None if angles is None else same_bits(got_angles, angles)
    assert ma.stamp_to_ns(msg.header.stamp) == stamp


@given(action=PAIRS, stamp=STAMPS)
def test_applied_action_round_trip_is_bit_exact(action, stamp):
    msg = through_cdr(ma.applied_action_msg(action, stamp))
    assert same_bits(ma.applied_action(msg), action)
    assert ma.stamp_to_ns(msg.header.stamp) == stamp


def test_messages_carry_si_units_and_the_hand_layout():
    pose = ma.object_pose_msg([12.5, -40.0], 3_000_000_123)
    assert pose.header.frame_id == wire.FRAME_ID
    assert (pose.header.stamp.sec, pose.header.stamp.nanosec) == (3, 123)
    p, q = pose.pose.position, pose.pose.orientation
    assert (p.x, p.y, p.z) == pytest.approx((0.0125, -0.040, 0.0))
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)

    joints = ma.joint_state_msg([100.0, -120.0], [0.5, 0.25], 0)
    assert joints.name == list(wire.ACTUATOR_NAMES)
    assert joints.effort == pytest.approx([100.0 * wire.LOAD_UNIT_NM, -120.0 * wire.LOAD_UNIT_NM])
    assert list(joints.position) == [0.5, 0.25] and len(joints.velocity) == 0
    assert len(ma.joint_state_msg([1.0, 1.0], None, 0).position) == 0

    action = ma.applied_action_msg([1.0, -1.5], 0)
    assert action.name == list(wire.ACTUATOR_NAMES)
    rate = wire.ACTION_UNIT_RAD / wire.CONTROL_PERIOD_S
    assert action.velocity == pytest.approx([rate, -1.5 * rate])
    assert len(action.position) == 0 and len(action.effort) == 0


def test_readers_follow_joint_names_not_positions():
    msg = ma.joint_state_msg([1.0, 2.0], [0.1, 0.2], 0)
    msg.name = ["gripper", "actuator_2", "actuator_1"]
    msg.effort = np.array([9.0, 2.0, 1.0]) * wire.LOAD_UNIT_NM
    msg.position = np.array([7.0, 0.2, 0.1])
    loads, angles = ma.joint_state_arrays(msg)
    assert loads.tolist() == [1.0, 2.0]
    assert angles == pytest.approx([0.1, 0.2])


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda m: setattr(m, "name", ["actuator_1"]), "lacks actuator"),
        (lambda m: setattr(m, "effort", np.array([1.0])), "effort has 1 values for 2"),
        (lambda m: setattr(m, "position", np.array([1.0, 2.0, 3.0])), "position has 3 values"),
        (lambda m: setattr(m, "effort", np.array([np.nan, 1.0])), "non-finite"),
        (lambda m: setattr(m, "position", np.array([np.inf, 1.0])), "non-finite"),
        (lambda m: setattr(m, "effort", np.array([1e300, 1.0])), "outside float32 range"),
    ],
)
def test_bad_joint_states_are_refused(change, match):
    msg = ma.joint_state_msg([1.0, 2.0], [0.0, 0.0], 0)
    change(msg)
    with pytest.raises(ValueError, match=match):
        ma.joint_state_arrays(msg)


def test_bad_poses_and_actions_are_refused():
    pose = ma.object_pose_msg([1.0, 2.0], 0)
    pose.header.frame_id = "world"
    with pytest.raises(ValueError, match="frame 'world'"):
        ma.object_xy_mm(pose)
    pose = ma.object_pose_msg([1.0, 2.0], 0)
    pose.pose.position.x = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        ma.object_xy_mm(pose)
    action = ma.applied_action_msg([1.0, 1.0], 0)
    action.velocity = np.array([])
    with pytest.raises(ValueError, match="velocity has 0 values"):
        ma.applied_action(action)
    with pytest.raises(ValueError, match="non-finite"):
        ma.applied_action_msg([np.nan, 0.0], 0)
    with pytest.raises(ValueError, match="shape"):
        ma.object_pose_msg([1.0, 2.0, 3.0], 0)


@pytest.mark.parametrize("stamp", [-1, 2**31 * 10**9])
def test_stamps_outside_builtin_time_are_refused(stamp):
    with pytest.raises(ValueError, match="outside builtin_interfaces/Time"):
        ma.ns_to_stamp(stamp)


# ------------------------------------------------------------------ JointTrajectory

ACTIONS = st.integers(0, 40).flatmap(
    lambda n: arrays(np.float32, (n, 2), elements=st.floats(-1.5, 1.5, width=32))
)
ANGLES = arrays(np.float32, 2, elements=st.floats(-3.0, 3.0, width=32))


@settings(max_examples=50)
@given(actions=ACTIONS, start=ANGLES, stamp=STAMPS)
def test_joint_trajectory_round_trip(actions, start, stamp):
    msg = through_cdr(ma.actions_to_joint_trajectory(actions, start, stamp))
    assert ma.stamp_to_ns(msg.header.stamp) == stamp
    back = ma.joint_trajectory_to_actions(msg, start)
    assert back.dtype == np.float32 and back.shape == actions.shape
    np.testing.assert_allclose(back, actions, rtol=0, atol=1e-6)


def test_joint_trajectory_holds_angle_targets_every_period():
    actions = np.array([[1.0, -1.0], [0.5, 0.0], [-1.5, 1.5]], np.float32)
    msg = ma.actions_to_joint_trajectory(actions, [0.25, 0.5], 7)
    assert msg.joint_names == list(wire.ACTUATOR_NAMES)
    assert [ma.stamp_to_ns(p.time_from_start) for p in msg.points] == [
        wire.CONTROL_PERIOD_NS,
        2 * wire.CONTROL_PERIOD_NS,
        3 * wire.CONTROL_PERIOD_NS,
    ]
    expected = np.array([0.25, 0.5]) + wire.ACTION_UNIT_RAD * np.cumsum(actions, axis=0)
    np.testing.assert_allclose([p.positions for p in msg.points], expected, atol=1e-12)
    assert all(len(p.velocities) == len(p.accelerations) == len(p.effort) == 0 for p in msg.points)


def _trajectory():
    return ma.actions_to_joint_trajectory(np.ones((3, 2), np.float32), [0.0, 0.0], 0)


def _set_point(index, **fields):
    def change(msg):
        for name, value in fields.items():
            setattr(msg.points[index], name, value)

    return change


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda m: setattr(m, "joint_names", ["actuator_1", "wrist"]), "lacks actuator"),
        (_set_point(1, time_from_start=ma.ns_to_stamp(3 * wire.CONTROL_PERIOD_NS)), "point 1 is at 300000000 ns"),
        (lambda m: m.points.pop(0), "point 0 is at 200000000 ns"),
        (_set_point(2, positions=np.array([0.1])), "point 2 positions has 1 values"),
        (_set_point(0, positions=np.array([np.nan, 0.0])), "point 0 has a non-finite position"),
    ],
)
def test_bad_joint_trajectories_are_refused(change, match):
    msg = _trajectory()
    change(msg)
    with pytest.raises(ValueError, match=match):
        ma.joint_trajectory_to_actions(msg, [0.0, 0.0])


def test_joint_trajectory_rejects_bad_inputs():
    with pytest.raises(ValueError, match=r"shape \[T, 2\]"):
        ma.actions_to_joint_trajectory(np.zeros((3, 3), np.float32), [0.0, 0.0], 0)
    with pytest.raises(ValueError, match="non-finite"):
        ma.actions_to_joint_trajectory(np.array([[np.nan, 0.0]], np.float32), [0.0, 0.0], 0)
    with pytest.raises(ValueError, match="start angles"):
        ma.joint_trajectory_to_actions(_trajectory(), [0.0])
    assert ma.joint_trajectory_to_actions(
        ma.actions_to_joint_trajectory(np.zeros((0, 2), np.float32), [0.0, 0.0], 0), [0.0, 0.0]
    ).shape == (0, 2)


def test_a_reset_names_its_grasp_seed_in_one_format() -> None:
    from msg_adapters import grasp_detail, grasp_seed, status_message

    assert grasp_seed(grasp_detail(3, 17)) == 17
    assert grasp_seed(status_message("reset", grasp_detail(3, 0), 100)) == 0
    assert grasp_seed(grasp_detail(3, None)) is None and grasp_seed("episode 3 grasped") is None


def test_a_status_names_its_last_step_stamp_only_where_a_header_stamp_could_hold_it() -> None:
    """A damaged text (a stamp past int64, thousands of digits) names no step instead of breaking a reader."""
    assert ma.last_step_stamp(ma.status_message("dropped", "x", 2**63 - 1)) == 2**63 - 1
    for stamp in ("9223372036854775808", "99999999999999999999", "9" * 5000):
        assert ma.last_step_stamp(f"dropped: x [last step {stamp} ns]") is None
    assert ma.event_stamps([f"reset: x [last step {'9' * 30} ns]", ma.status_message("reset", "y", 5)], "reset") == {5}


def test_message_fields_gives_plain_data_of_nested_messages_arrays_and_bytes() -> None:
    import json

    from sensor_msgs.msg import Image, JointState

    from msg_adapters import message_fields

    state = JointState(name=["a", "b"], position=[0.5, -1.0])
    state.header.stamp.sec, state.header.frame_id = 7, "t42_base"
    got = message_fields(state)
    assert got == {"header": {"stamp": {"sec": 7, "nanosec": 0}, "frame_id": "t42_base"}, "name": ["a", "b"],
                   "position": [0.5, -1.0], "velocity": [], "effort": []}
    image = message_fields(Image(height=1, width=2, encoding="mono8", step=2, data=bytes([0, 255])))
    assert image["data"] == [0, 255] and image["encoding"] == "mono8"
    json.dumps([got, image])  # plain data all through


def test_message_from_fields_is_message_fields_backwards_and_names_a_bad_field() -> None:
    from nav_msgs.msg import Path as PathMsg
    from sensor_msgs.msg import CameraInfo

    from msg_adapters import message_fields, message_from_fields

    data = {"header": {"stamp": {"sec": 3, "nanosec": 5}, "frame_id": "t42_base"},
            "poses": [{"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
                       "pose": {"position": {"x": 0.01, "y": 0.07, "z": 0.0},
                                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]}
    assert message_fields(message_from_fields(PathMsg, data)) == data
    info = message_fields(message_from_fields(CameraInfo, {"k": [1, 0, 2, 0, 1, 2, 0, 0, 1], "height": 480}))
    assert info["k"] == [1.0, 0.0, 2.0, 0.0, 1.0, 2.0, 0.0, 0.0, 1.0] and info["height"] == 480  # ints as doubles
    for bad, problem in (({"poses": [{"pose": {"position": {"x": "a"}}}]}, "poses[0].pose.position.x: 'a' is no "),
                         ({"header": {"frame": "x"}}, "header.frame: no such field"),
                         ({"poses": {"pose": {}}}, "poses: expected a list"),
                         ({"header": {"stamp": {"sec": 2 ** 31}}}, "header.stamp.sec: 2147483648 is out of range "
                                                                      "for int32 [-2147483648, 2147483647]"),
                         ({"header": {"stamp": {"nanosec": -1}}}, "header.stamp.nanosec: -1 is out of range for "
                                                                  "uint32")):
        with pytest.raises(ValueError, match=re.escape(problem)):
            message_from_fields(PathMsg, bad)
    edges = message_from_fields(CameraInfo, {"height": 2 ** 32 - 1, "d": [float("nan")]})  # a double has no range
    assert edges.height == 2 ** 32 - 1 and math.isnan(edges.d[0])


def test_the_authors_unit_is_their_drivers_step_and_units_are_checked() -> None:
    # 0.065 % of the normalised range a step, over 0.95 of a 4096-tick turn: 2.53 ticks
    assert wire.AUTHORS_ACTION_UNIT_RAD / (2 * np.pi / 4096) == pytest.approx(0.00065 * 0.95 * 4096)
    assert wire.checked_action_unit(np.float32(0.025)) == pytest.approx(0.025)
    for bad in (0, -0.025, 0.2, float("nan"), float("inf"), True, "0.025", None):
        with pytest.raises(ValueError, match=r"an action unit must be a number of rad in \(0, 0\.1\]"):
            wire.checked_action_unit(bad)
        with pytest.raises(ValueError, match="an action unit must be"):
            ma.applied_action_msg([0.5, -0.5], 1, unit_rad=bad)


@settings(max_examples=50, deadline=None)
@given(arrays(np.float32, (7, 2), elements=st.floats(-1.5, 1.5, width=32)))
def test_actions_in_any_unit_are_the_same_actuator_steps_and_come_back_bit_for_bit(actions: np.ndarray) -> None:
    unit = wire.AUTHORS_ACTION_UNIT_RAD
    for a in actions:
        msg = ma.applied_action_msg(a, 5, unit_rad=unit)
        np.testing.assert_array_equal(ma.applied_action(msg, unit_rad=unit), a)
        np.testing.assert_allclose(np.asarray(msg.velocity) * wire.CONTROL_PERIOD_S, a.astype(np.float64) * unit)
    start = np.array([0.3, 0.4])
    traj = ma.actions_to_joint_trajectory(actions, start, 5, unit_rad=unit)
    np.testing.assert_allclose(traj.points[-1].positions, start + unit * actions.astype(np.float64).sum(axis=0))
    back = ma.joint_trajectory_to_actions(traj, start, unit_rad=unit)
    np.testing.assert_allclose(back, actions, atol=1e-5)
    np.testing.assert_allclose(ma.joint_trajectory_to_actions(traj, start), actions * (unit / wire.ACTION_UNIT_RAD),
                               atol=1e-5)  # the same steps in the suite's unit
