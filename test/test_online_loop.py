"""The online loop's yardstick: executed plans cut at their first command, and models scored on them."""

from __future__ import annotations

import numpy as np
import pytest

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.online_loop import commanded, executed_plan_scores, idle_share
from t42_transfer.models.baselines import HoldStill


def goal_episode(settle: int, plan: int, hold: int, step_mm: float = 1.0) -> Trajectory:
    """Held still for ``settle`` steps, moved +x ``step_mm`` a step for ``plan`` commanded steps, held again."""
    actions = np.zeros((settle + plan + hold, 2), np.float32)
    actions[settle:settle + plan] = 0.5
    x = np.concatenate([[0.0], np.cumsum(np.abs(actions[:, 0]) > 0) * step_mm])
    states = np.stack([x, np.full_like(x, 80.0), np.zeros_like(x), np.zeros_like(x)], axis=1)
    return Trajectory(states, actions, end_reason="length", hand="target")


def test_commanded_cuts_the_settling_and_optionally_the_hold_and_drops_what_is_too_short() -> None:
    data = TrajectorySet([goal_episode(80, 20, 30), goal_episode(80, 10, 0), goal_episode(50, 0, 0)], hand="target")
    assert idle_share(data) == pytest.approx(1 - 30 / (130 + 90 + 50))
    from_command = commanded(data)
    assert [len(t) for t in from_command] == [50]  # 20 + 30; the 10-step plan is too short; no command at all: out
    assert np.all(np.abs(from_command[0].actions[0]) > 0) and from_command[0].states[0, 0] == 0.0
    stretches = commanded(data, to_last_command=True)
    assert [len(t) for t in stretches] == [20] and idle_share(stretches) == 0.0
    assert stretches[0].states[-1, 0] == pytest.approx(20.0)  # the state after the last commanded step
    assert [len(t) for t in commanded(data, to_last_command=True, min_steps=10)] == [20, 10]


def test_holding_still_diverges_once_a_plan_has_moved_the_object_4_mm() -> None:
    data = TrajectorySet([goal_episode(80, 20, 30, step_mm=1.0)], hand="target")
    plans, scores = executed_plan_scores({"hold_still": HoldStill()}, data)
    assert plans == 1
    assert scores["hold_still"]["divergence_steps"] == pytest.approx(4, abs=1)  # 4 mm off after about 4 steps
    assert scores["hold_still"]["position_mse_mm2"] > 100.0
    with pytest.raises(ValueError, match="first command"):
        executed_plan_scores({"hold_still": HoldStill()}, TrajectorySet([goal_episode(80, 5, 5)], hand="target"))


def test_an_episode_that_mostly_holds_still_is_a_plan() -> None:
    from t42_transfer.evaluation.online_loop import episode_kind

    assert episode_kind(goal_episode(80, 20, 30)) == "plan"  # 110 of 130 steps idle
    assert episode_kind(goal_episode(5, 60, 0)) == "exploration"
    explored = Trajectory(np.zeros((41, 4)), np.random.default_rng(0).uniform(-1, 1, (40, 2)), hand="target")
    assert episode_kind(explored) == "exploration"
