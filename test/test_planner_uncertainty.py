"""Uncertainty-aware planning (ensembles, dropout samples, risk-averse cost, perturbed copies) and closed-loop
execution (MPC)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_planner import BOX, START, hand_norm
from torch import Tensor
from toys import StateIsLatent, Toy, ToyHand

from t42_transfer.models import TransitionModel
from t42_transfer.planning import Planner, PlannerConfig, Workspace
from t42_transfer.planning.execution import execute
from t42_transfer.planning.planner import _perturbations, _shifted

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
    run = execute(hand, lambda state, left, _: planner.plan(state, NEAR, seed=1, horizon=left), 10, replan_every)
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
    calls, handed = [], []

    def plan_at(state: np.ndarray, left: int, previous: np.ndarray):
        calls.append(left)
        handed.append(previous.copy())
        plan = planner.plan(state, GOAL, seed=1, horizon=left)
        if len(calls) > 1:  # every replan refused: zero actions
            return type(plan)(False, "no_safe_sequence", "test", np.zeros((0, 2), np.float32), plan.predicted[:1],
                              float("inf"), plan.goal)
        return plan

    run = execute(ToyHand(1.0, START.copy()), plan_at, 10, 3)
    assert calls == [10, 7, 4, 1] and run.completed
    for sent, rest in zip((3, 6, 9), handed[1:], strict=True):  # each replan is handed the first plan's rest
        np.testing.assert_array_equal(rest, run.plans[0].actions[sent:])
    assert np.linalg.norm(run.states[-1, :2] - GOAL) <= 0.2 + 1e-5


def test_receding_horizon_hands_each_replan_the_rest_of_the_plan_it_replaces() -> None:
    planner = Planner(Toy(), BOX, fixed())
    given: list[np.ndarray] = []
    made = []

    def plan_at(state: np.ndarray, left: int, previous: np.ndarray):
        given.append(previous.copy())
        made.append(planner.plan(state, GOAL, seed=1, horizon=left))
        return made[-1]

    run = execute(ToyHand(1.0, START.copy()), plan_at, 10, 3)
    assert run.completed and [len(p) for p in given] == [0, 7, 4, 1]
    for before, rest in zip(made[:-1], given[1:], strict=True):
        np.testing.assert_array_equal(rest, before.actions[3:])


# --------------------------------------------------------------------- warm starts


def _warm(**overrides: object) -> Planner:
    """A search too weak to find the goal alone: one or a few sequences, no refinement."""
    return Planner(Toy(), BOX, fixed(**{"samples": 3, "refine_iterations": 0, "sampler": "gaussian", **overrides}))


EXACT = np.tile([0.8, 0.0], (10, 1)).astype(np.float32)
"""Ten steps of a = (0.8, 0): the toy's exact way from START to GOAL."""


def test_a_warm_replan_is_never_predicted_worse_than_the_rest_it_was_given() -> None:
    cold = _warm().plan(START, GOAL, seed=1, previous=EXACT)
    warm = _warm(warm_start=True).plan(START, GOAL, seed=1, previous=EXACT)
    assert cold.error_mm > 1.0  # the weak search alone misses ...
    assert warm.ok and warm.error_mm <= 1e-5  # ... and starting from the exact rest it keeps it
    np.testing.assert_allclose(warm.actions, EXACT)
    for seed in range(5):  # whatever the draw around it, never worse than the rest itself
        rough = np.clip(EXACT + np.random.default_rng(seed).normal(0, 0.2, EXACT.shape), -1, 1).astype(np.float32)
        start_error = float(np.linalg.norm(START[:2] + rough.sum(0) - GOAL))
        assert _warm(warm_start=True).plan(START, GOAL, seed=seed, previous=rough).error_mm <= start_error + 1e-4


def test_the_rest_is_cut_or_padded_with_holds_to_the_horizon() -> None:
    one = _warm(samples=1, warm_start=True)
    short = one.plan(START, GOAL, seed=1, previous=EXACT[:4])
    np.testing.assert_allclose(short.actions, np.concatenate([EXACT[:4], np.zeros((6, 2))]))
    long = one.plan(START, GOAL, seed=1, previous=np.concatenate([EXACT, EXACT]), horizon=7)
    np.testing.assert_allclose(long.actions, EXACT[:7])
    wild = one.plan(START, GOAL, seed=1, previous=np.full((10, 2), 5.0))
    assert np.abs(wild.actions).max() <= 1.0  # projected into the box like any draw


def test_without_warm_start_or_without_a_rest_the_draw_is_the_cold_one() -> None:
    alone = _warm().plan(START, GOAL, seed=2)
    np.testing.assert_array_equal(_warm().plan(START, GOAL, seed=2, previous=EXACT).actions, alone.actions)
    empty = _warm(warm_start=True).plan(START, GOAL, seed=2, previous=np.zeros((0, 2)))
    np.testing.assert_array_equal(empty.actions, alone.actions)


@pytest.mark.parametrize("previous", [np.zeros(10), np.zeros((10, 3)), np.full((10, 2), np.nan)])
def test_a_malformed_rest_is_a_value_error(previous: np.ndarray) -> None:
    with pytest.raises(ValueError, match="previous must be"):
        _warm(warm_start=True).plan(START, GOAL, seed=1, previous=previous)


@pytest.mark.parametrize("warm_start", [True, False])
def test_a_one_sequence_warm_search_replans_its_own_rest(warm_start: bool) -> None:
    """With one sequence and no refinement a warm replan can only return the rest it was handed: the loop then
    executes its first plan whole.  Cold, each replan is a fresh draw."""
    planner = Planner(Toy(), BOX, fixed(samples=1, refine_iterations=0, warm_start=warm_start))
    done = execute(ToyHand(1.0, START.copy()), lambda state, left, previous: planner.plan(
        state, GOAL, seed=len(previous), horizon=left, previous=previous), 10, 3)
    assert done.completed and len(done.plans) == 4
    assert np.array_equal(done.actions, done.plans[0].actions) == warm_start


@pytest.mark.parametrize("config", [dict(samples=1, noise_beta=1.0), dict(samples=8, perturbations=8, noise_beta=2.0),
                                    dict(samples=1, sampler="discrete")])
def test_a_warm_start_of_one_sequence_plans_in_every_mode(config: dict) -> None:
    plan = _warm(warm_start=True, **config).plan(START, GOAL, seed=1, previous=EXACT)
    assert plan.evaluated == 1 and len(plan.actions) == 10 and np.abs(plan.actions).max() <= 1.0


# --------------------------------------------------------------------- perturbed copies (the robust cost)


class Sensitive(StateIsLatent):
    """``x += a_x (1 + 4 a_y^2)``: every ``a_y`` reaches the same ``x`` with its own ``a_x``, but the end moves with
    ``a_y`` except near ``a_y = 0``, which the robust cost should find."""

    kind = "test_sensitive"

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        dx = action[:, :1] * (1.0 + 4.0 * action[:, 1:] ** 2)
        return z + torch.cat([dx, torch.zeros_like(z[:, 1:])], -1)


def _end_spread(model: StateIsLatent, actions: np.ndarray, std: float, draws: int = 200) -> float:
    """Std of the predicted end x over random N(0, std) perturbations of ``actions`` (clipped)."""
    gen = torch.Generator().manual_seed(99)
    seq = torch.as_tensor(actions, dtype=torch.float32)
    shaken = (seq + std * torch.randn(draws, *seq.shape, generator=gen)).clamp(-1.0, 1.0)
    ends = model.rollout(torch.as_tensor(START, dtype=torch.float32).expand(draws, 4), shaken)[:, -1, 0]
    return float(ends.std())


def test_perturbed_copies_with_zero_std_plan_exactly_as_the_sequences_alone_at_equal_sequences() -> None:
    alone = Planner(Toy(), BOX, fixed(samples=200)).plan(START, GOAL, seed=4)
    copies = Planner(Toy(), BOX, fixed(samples=600, perturbations=3, perturbation_std=0.0)).plan(START, GOAL, seed=4)
    assert np.array_equal(alone.actions, copies.actions) and alone.error_mm == copies.error_mm
    assert copies.evaluated == alone.evaluated  # sequences drawn; each rolled out three times


def test_the_robust_cost_prefers_a_sequence_whose_end_does_not_depend_on_its_exact_actions() -> None:
    goal = np.array([START[0] + 4.0, START[1]])
    config = fixed(samples=1200, refine_iterations=15, tolerance_mm=0.5)
    plain = Planner(Sensitive(), BOX, config).plan(START, goal, seed=0)
    robust = Planner(Sensitive(), BOX, replace(config, perturbations=6, perturbation_std=0.1)).plan(START, goal, seed=0)
    assert plain.ok and robust.ok, (plain.reason, robust.reason)
    assert np.abs(robust.actions[:, 1]).mean() < np.abs(plain.actions[:, 1]).mean()
    assert _end_spread(Sensitive(), robust.actions, 0.2) < 0.8 * _end_spread(Sensitive(), plain.actions, 0.2)
    assert np.allclose(robust.predicted, Sensitive().rollout(torch.as_tensor(START, dtype=torch.float32)[None],
                                                             torch.as_tensor(robust.actions)[None])[0], atol=1e-5)


def test_every_perturbed_copy_of_the_plan_keeps_the_safety_rules() -> None:
    """Goals near the edge of the workspace: the plan is unusable if any copy leaves it, so the plan keeps a margin."""
    edge = Workspace.box(-50.0, START[0] + 6.0, 40.0, 120.0)
    config = fixed(samples=400, perturbations=4, perturbation_std=0.3)
    for seed in range(5):
        plan = Planner(Toy(), edge, config).plan(START, (START[0] + 5.5, START[1]), seed=seed)
        assert len(plan.actions) == 10 and np.abs(plan.actions).max() <= 1.0 and np.isfinite(plan.actions).all()
        shifts = _perturbations(config, 10, seed)
        copies = _shifted(torch.as_tensor(plan.actions)[None], shifts)
        states = Toy().rollout(torch.as_tensor(START, dtype=torch.float32).expand(len(copies), 4), copies)
        assert edge.allows(states[:, 1:]).all()
        assert edge.allows(torch.as_tensor(plan.predicted[1:])).all()


@pytest.mark.parametrize(
    ("config", "message"),
    [
        (dict(perturbations=0), "perturbations"),
        (dict(perturbations=2, horizon_search=True), "fixed-length"),
        (dict(perturbations=2, uncertainty="dropout", members=2), "fixed-length"),
        (dict(perturbation_std=-0.1), "perturbation_std"),
        (dict(perturbation_std=float("nan")), "perturbation_std"),
    ],
)
def test_perturbation_settings_are_checked(config: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PlannerConfig(**config)  # type: ignore[arg-type]
