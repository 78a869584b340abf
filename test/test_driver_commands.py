"""driver.commands' queue and driver.servo_hand's geometry: what a step applies, and no goal past a limit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from t42_transfer.driver.commands import ActionQueue, CommandRejected, validate_trajectory
from t42_transfer.driver.servo_hand import HandGeometry
from t42_transfer.hardware import xm430 as xm


def test_a_command_holds_one_step_a_trajectory_runs_out_and_says_its_last_point() -> None:
    queue = ActionQueue()
    assert queue.next()[0].tolist() == [0.0, 0.0]
    queue.set_command(np.array([0.5, -0.5]))
    assert queue.next()[0].tolist() == [0.5, -0.5] and queue.next()[0].tolist() == [0.0, 0.0]
    assert queue.set_plan(np.array([[1.0, 0.0], [0.0, 1.0]])) == 0
    first, second = queue.next(), queue.next()
    assert (first[1], second[1]) == (False, True) and second[0].tolist() == [0.0, 1.0]
    queue.set_plan(np.ones((3, 2)))
    assert queue.set_command(np.zeros(2)) == 3 and queue.pending == 0  # a command cancels a trajectory
    queue.set_plan(np.ones((3, 2)))
    assert queue.set_plan(np.zeros((0, 2))) == 3 and queue.pending == 0  # an empty trajectory just cancels


def test_an_action_goes_out_as_float32_values() -> None:
    queue = ActionQueue()
    queue.set_command(np.array([0.1, 0.2]))
    action, _ = queue.next()
    assert action.tolist() == np.float32([0.1, 0.2]).astype(np.float64).tolist()


@settings(max_examples=60, deadline=None)
@given(angles=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=2, max_size=2),
       mirrored=st.booleans())
def test_no_goal_leaves_the_limits_whatever_the_angles(angles: list[float], mirrored: bool) -> None:
    g = HandGeometry(servo_ids=(2, 1) if mirrored else (1, 2), open_ticks=(3000, 1000) if mirrored else (1000, 1000),
                     directions=(-1, 1) if mirrored else (1, 1))
    limits = g.limits()
    for servo, tick in g.ticks(np.array(angles)).items():
        low, high = limits[servo]
        assert low <= tick <= high and 0 <= tick <= xm.MAX_TICK


def test_angles_and_ticks_round_trip_and_the_geometry_checks_itself() -> None:
    g = HandGeometry(open_ticks=(1000, 3000), directions=(1, -1))
    angles = np.array([0.5, 1.25])
    assert np.allclose(g.angles(g.ticks(angles)), angles, atol=xm.RAD_PER_TICK)
    with pytest.raises(ValueError, match="leaves the servo's range"):
        HandGeometry(open_ticks=(3500, 2048))
    with pytest.raises(ValueError, match="two different servos"):
        HandGeometry(servo_ids=(1, 1))
    with pytest.raises(ValueError, match="directions must be"):
        HandGeometry(directions=(1, 0))


def test_a_trajectory_longer_than_any_plan_is_refused() -> None:
    from msg_adapters import RCLPY, actions_to_joint_trajectory
    from t42_transfer.conventions import MAX_PLAN_HORIZON

    long = actions_to_joint_trajectory(np.zeros((MAX_PLAN_HORIZON + 1, 2), np.float32), np.zeros(2), 0, RCLPY)
    with pytest.raises(CommandRejected, match=f"no plan is longer than {MAX_PLAN_HORIZON}"):
        validate_trajectory(long, np.zeros(2), 0, 10**9)
    longest = actions_to_joint_trajectory(np.zeros((MAX_PLAN_HORIZON, 2), np.float32), np.zeros(2), 0, RCLPY)
    assert validate_trajectory(longest, np.zeros(2), 0, 10**9).shape == (MAX_PLAN_HORIZON, 2)
