"""Uncertainty-aware planning (ensembles, dropout samples, risk-averse cost) and closed-loop execution (MPC)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_planner import BOX, START, hand_norm
from toys import Toy, ToyHand

from t42_transfer.models import TransitionModel
from t42_transfer.planning import Planner, PlannerConfig
from t42_transfer.planning.execution import execute

pytestmark = pytest.mark.usefixtures("one_torch_thread")

GOAL = np.array([START[0] + 8.0, START[1]])
"""8 mm across the palm: 10 steps of a = (0.8, 0) for a gain-1 toy."""


def fixed(**overrides: object) -> PlannerConfig:
    settings = dict(samples=400, horizon=10, sampler="uniform", refine_iterations=5, tolerance_mm=0.2)
    return PlannerConfig(**{**settings, **overrides})  # type: ignore[arg-type]


def test_an_ensemble_of_one_model_repeated_plans_as_that_model_at_equal_rollouts() -> None:
    single = Planner(Toy(), BOX, fixed(samples=200)).plan(START, GOAL, seed=3)
    triple = Planner([Toy(), Toy(), Toy()], BOX, fixed(samples=600, uncertainty="ensemble")).plan(START, GOAL, seed=3)
    assert np.array_equal(single.actions, triple.actions)
    assert single.evaluated == triple.evaluated  # sequences: 600 rollouts // 3 members


class Mapped(Toy):
    """``(x, y) += move(a)`` for a given function of the action."""

    kind = "test_toy_mapped"

    def __init__(self, move) -> None:
        super().__init__()
        self.move = move

    def latent_step(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return z + torch.cat([self.move(action), torch.zeros_like(action)], -1)


def test_risk_averse_cost_prefers_sequences_the_members_agree_on() -> None:
    # One step of the real hand's moves.  Member A: (x, y) += 2a; member B: x -= 2 a_x.  Towards a goal
    # 2 mm along x, a = (1, 0) is perfect for A and 4 mm off for B: the best mean, the largest spread.
    a = Mapped(lambda act: 2.0 * act)
    b = Mapped(lambda act: torch.stack([-2.0 * act[:, 0], torch.zeros_like(act[:, 0])], -1))
    goal = np.array([START[0] + 2.0, START[1]])
    cfg = PlannerConfig(samples=400, horizon=1, sampler="discrete", uncertainty="ensemble")

    def errors(actions: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(START, dtype=torch.float32)[None]
        moves = torch.as_tensor(actions, dtype=torch.float32)
        return np.array([float(torch.linalg.vector_norm(m.rollout(x, moves[None])[0, -1, :2] - torch.as_tensor(goal)))
                         for m in (a, b)])

    neutral = Planner([a, b], BOX, replace(cfg, risk=0.0)).plan(START, goal, seed=0)
    averse = Planner([a, b], BOX, replace(cfg, risk=1.0)).plan(START, goal, seed=0)
    assert np.allclose(neutral.actions, [[1.0, 0.0]])
    assert np.ptp(errors(averse.actions)) < np.ptp(errors(neutral.actions)) - 1.0
    assert errors(averse.actions).mean() > errors(neutral.actions).mean()  # it pays in mean for certainty


def test_dropout_samples_are_seeded_and_differ_from_the_deterministic_plan() -> None:
    torch.manual_seed(0)
    model = TransitionModel(hand_norm(), dropout=0.3).eval()
    cfg = PlannerConfig(samples=300, horizon=8, uncertainty="dropout", members=5, refine_iterations=0)
    first = Planner(model, BOX, cfg).plan(START, GOAL, seed=11)
    again = Planner(model, BOX, cfg).plan(START, GOAL, seed=11)
    assert np.array_equal(first.actions, again.actions) and first.evaluated == 300 // 5
    plain = Planner(model, BOX, PlannerConfig(samples=60, horizon=8)).plan(START, GOAL, seed=11)
    assert first.actions.shape == plain.actions.shape == (8, 2)
    deterministic = model.rollout(torch.as_tensor(START, dtype=torch.float32)[None],
                                  torch.as_tensor(first.actions)[None])
    assert not np.allclose(first.predicted, deterministic[0].numpy(), atol=1e-4)  # the members' mean, not eval mode
    assert not model.training  # dropout is on only inside the planner's rollouts


@pytest.mark.parametrize(
    ("config", "models", "message"),
    [
        (dict(uncertainty="dropout", horizon_search=True), 1, "fixed-length"),
        (dict(uncertainty="ensemble"), 1, "several models"),
        (dict(), 2, "several models"),
        (dict(uncertainty="bogus"), 1, "uncertainty must be"),
        (dict(members=0), 1, "members"),
    ],
)
def test_uncertainty_settings_are_checked(config: dict, models: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Planner([Toy()] * models if models > 1 else Toy(), BOX, PlannerConfig(**config))  # type: ignore[arg-type]


NEAR = np.array([START[0] + 6.0, START[1]])
"""6 mm: a = 0.6 for the model, leaving the replanner room below the action bound."""


def _run(model_gain: float, true_gain: float, replan_every: int) -> float:
    planner = Planner(Toy(gain=model_gain), BOX, fixed())
    hand = ToyHand(true_gain, START.copy())
    run = execute(hand, lambda state, left: planner.plan(state, NEAR, seed=1, horizon=left), 10, replan_every)
    assert run.completed and len(run.actions) == 10
    assert len(run.plans) == (1 if replan_every == 0 else -(-10 // replan_every))
    return float(np.linalg.norm(run.states[-1, :2] - NEAR))


def test_open_loop_on_an_exact_model_reaches_the_known_optimum() -> None:
    assert _run(1.0, 1.0, 0) <= 0.2 + 1e-5


def test_replanning_corrects_a_biased_model_that_open_loop_cannot() -> None:
    open_loop = _run(1.0, 0.8, 0)  # the model's optimum a = 0.6 moves the true hand 4.8 mm: ~1.2 mm short
    assert open_loop > 1.0
    every_two = _run(1.0, 0.8, 2)
    every_step = _run(1.0, 0.8, 1)
    assert every_two < 0.5 * open_loop
    assert every_step <= every_two + 0.1 and every_step < 0.4


def test_a_refused_replan_keeps_the_rest_of_the_previous_plan() -> None:
    planner = Planner(Toy(), BOX, fixed())
    calls = []

    def plan_at(state: np.ndarray, left: int):
        calls.append(left)
        plan = planner.plan(state, GOAL, seed=1, horizon=left)
        if len(calls) > 1:  # every replan refused: zero actions
            return type(plan)(False, "no_safe_sequence", "test", np.zeros((0, 2), np.float32), plan.predicted[:1],
                              float("inf"), plan.goal)
        return plan

    run = execute(ToyHand(1.0, START.copy()), plan_at, 10, 3)
    assert calls == [10, 7, 4, 1] and run.completed
    assert np.linalg.norm(run.states[-1, :2] - GOAL) <= 0.2 + 1e-5
