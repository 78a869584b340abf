"""msg_adapters.plan_result: the planner's t42/plan_result as a typed message, metres in t42_base on the wire,
bit-exact mm positions, missing values as flags and NaN, any goal stamp, and the same CDR for rclpy and rosbags."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_msg_adapters import PAIRS, STAMPS, same_bits, through_cdr

from msg_adapters import RCLPY, ROSBAGS, stamp_to_ns
from msg_adapters.plan_result import PLAN_RESULT_MSG, PlanResult, plan_result, plan_result_msg

ACCEPTED = PlanResult(True, "ok", "", [12.5, -80.0], 1_500_000_000, start_mm=[10.0, -75.25],
                      predicted_error_mm=2.5, horizon=30, samples_evaluated=400, planning_time_s=0.25,
                      model="/m/transferred_001.safetensors", method="l2_finetune", replan_every=5)


@given(goal=PAIRS, start=PAIRS, stamp=STAMPS)
def test_positions_round_trip_bit_exact_through_cdr(goal, start, stamp):
    sent = PlanResult(True, "ok", "", goal.tolist(), stamp, start_mm=start.tolist(), predicted_error_mm=1.0)
    msg = through_cdr(plan_result_msg(sent, stamp, kit=ROSBAGS))
    got = plan_result(msg)
    assert same_bits(np.asarray(got.goal_mm, np.float32), goal)
    assert same_bits(np.asarray(got.start_mm, np.float32), start)
    assert got.goal_stamp_ns == stamp and stamp_to_ns(msg.header.stamp) == stamp


def test_the_wire_is_si_metres_in_t42_base_and_every_field_comes_back() -> None:
    msg = plan_result_msg(ACCEPTED, 7, kit=RCLPY)
    assert type(msg).__module__.startswith("t42_interfaces.msg")
    assert msg.header.frame_id == "t42_base" and stamp_to_ns(msg.header.stamp) == 7
    assert (msg.goal.x, msg.goal.y, msg.goal.z) == (0.0125, -0.08, 0.0) and msg.has_goal and msg.has_start
    assert msg.predicted_error_m == 0.0025 and (msg.goal_stamp.sec, msg.goal_stamp.nanosec) == (1, 500_000_000)
    assert plan_result(msg) == ACCEPTED


def test_missing_values_travel_as_flags_and_nan() -> None:
    refused = PlanResult(False, "bad_goal", "goal is in frame 'map'", None, 5)
    msg = plan_result_msg(refused, 9, kit=RCLPY)
    assert not msg.has_goal and not msg.has_start and math.isnan(msg.predicted_error_m)
    assert plan_result(msg) == refused
    unreachable = PlanResult(False, "unreachable", "far", [1.0, 2.0], 5, predicted_error_mm=math.inf)
    assert plan_result(plan_result_msg(unreachable, 9)).predicted_error_mm is None  # no finite prediction


@pytest.mark.parametrize("stamp_ns, back", [(-1_500_000_000, -1_500_000_000), (-(2**40) * 10**9, -(2**31) * 10**9),
                                             (2**40 * 10**9, 2**31 * 10**9 - 1)])
def test_any_goal_stamp_is_sent_negative_ones_too_and_out_of_range_ones_clamped(stamp_ns: int, back: int) -> None:
    """A refused goal's result names the goal by its stamp, whatever its header held (a negative second too)."""
    msg = through_cdr(plan_result_msg(PlanResult(False, "bad_goal", "stamp", [0.0, 0.0], stamp_ns), 1, kit=ROSBAGS))
    assert plan_result(msg).goal_stamp_ns == back


def test_counts_are_clamped_to_uint32_and_another_frame_is_refused() -> None:
    msg = plan_result_msg(PlanResult(True, "ok", "", [0.0, 0.0], 0, horizon=-3, samples_evaluated=2**40), 0)
    assert (msg.horizon, msg.samples_evaluated) == (0, 2**32 - 1)
    msg.header.frame_id = "map"
    with pytest.raises(ValueError, match="frame 'map'"):
        plan_result(msg)


@given(stamp=st.integers(0, 2**31 * 10**9 - 1))
def test_rclpys_cdr_is_what_rosbags_reads(stamp: int) -> None:
    """An independent reader (rosbags, the recorder's) decodes the node's bytes to the same result."""
    from rclpy.serialization import serialize_message

    from msg_adapters import TYPESTORE

    decoded = TYPESTORE.deserialize_cdr(serialize_message(plan_result_msg(ACCEPTED, stamp, kit=RCLPY)),
                                        PLAN_RESULT_MSG)
    assert plan_result(decoded) == ACCEPTED and stamp_to_ns(decoded.header.stamp) == stamp
