"""The Monte Carlo planner: bounds, seeds, optimality on a linear model, every safety rejection, fast path,
chunking, CLI."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from toys import Toy

from t42_transfer.cli import main
from t42_transfer.models import CumulativeResidualModel, LatentDynamics, Normalisation, TransitionModel
from t42_transfer.models.checkpoint import save_model
from t42_transfer.planning import (
    DISCRETE_ACTIONS,
    SAMPLERS,
    Planner,
    PlannerConfig,
    PlanStopped,
    Workspace,
    sample_actions,
)
from t42_transfer.planning.fused import FusedRollout, is_paper_mlp, make_rollout
from t42_transfer.planning.planner import ANSWERS
from t42_transfer.planning.sampling import REAL_HAND_ACTIONS, colored_noise

START = np.array([0.0, 80.0, 100.0, -100.0])


pytestmark = pytest.mark.usefixtures("one_torch_thread")


BOX = Workspace.box(-50.0, 50.0, 40.0, 120.0)


def hand_norm() -> Normalisation:
    return Normalisation(
        state_mean=np.array([0.0, 80.0, 120.0, -120.0], np.float32),
        state_std=np.array([15.0, 10.0, 30.0, 30.0], np.float32),
        delta_mean=np.zeros(4, np.float32),
        delta_std=np.array([0.4, 0.4, 2.0, 2.0], np.float32),
    )


def plan(model: LatentDynamics, goal: tuple[float, float], workspace: Workspace = BOX, **config: object):
    return Planner(model, workspace, PlannerConfig(**config)).plan(START, np.array(goal))  # type: ignore[arg-type]


def executed(actions: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """Where the toy's true dynamics put the object after ``actions``."""
    return START[:2] + gain * actions.sum(0)


# ------------------------------------------------------------------------------ samplers and bounds


def test_samplers_draw_bounded_actions_of_their_kind() -> None:
    gen = torch.Generator().manual_seed(0)
    assert torch.allclose(DISCRETE_ACTIONS * 1.5, torch.tensor(REAL_HAND_ACTIONS))
    for sampler in SAMPLERS:
        actions = sample_actions(sampler, 50, 40, gen, hold_steps=(5, 12))
        assert actions.shape == (50, 40, 2) and actions.dtype == torch.float32
        assert actions.abs().max() <= 1.0
    discrete = sample_actions("discrete", 50, 40, gen).reshape(-1, 2)
    assert (torch.cdist(discrete, DISCRETE_ACTIONS).min(1).values == 0).all()
    held = sample_actions("piecewise", 50, 40, gen, hold_steps=(5, 12))
    for seq in held:
        changes = [0, *((seq[1:] != seq[:-1]).any(1).nonzero().flatten() + 1).tolist(), 40]
        runs = np.diff(changes)
        assert (runs[:-1] >= 5).all() and (runs <= 12).all()  # the last hold may be cut by the horizon


@pytest.mark.parametrize("horizon", [40, 41])
def test_colored_noise_has_unit_variance_and_smooths_with_its_colour(horizon: int) -> None:
    lag_one = []
    for beta in (0.0, 1.0, 2.0):
        noise = colored_noise(20_000, horizon, beta, torch.Generator().manual_seed(0))
        assert noise.shape == (20_000, horizon, 2) and noise.dtype == torch.float32
        assert noise.var().item() == pytest.approx(1.0, abs=0.02)  # every step, at every colour
        assert noise[:, 0].var().item() == pytest.approx(1.0, abs=0.05) and abs(noise.mean().item()) < 0.02
        lag_one.append(((noise[:, 1:] * noise[:, :-1]).mean() / noise.var()).item())
    assert abs(lag_one[0]) < 0.02 and 0.4 < lag_one[1] < lag_one[2] < 1.0  # white, pink, brown
    # white is randn itself: the planner's draws at beta 0 are what they were before the option
    assert torch.equal(colored_noise(3, horizon, 0.0, torch.Generator().manual_seed(5)),
                       torch.randn(3, horizon, 2, generator=torch.Generator().manual_seed(5)))


@pytest.mark.parametrize("beta", [1.0, 2.5])
def test_coloured_plans_are_bounded_seeded_and_reach_a_linear_models_goal(beta: float) -> None:
    goal = (START[0] + 12.0, START[1] - 9.0)
    config = PlannerConfig(horizon=40, noise_beta=beta)
    first = Planner(Toy(), BOX, config).plan(START, np.array(goal))
    again = Planner(Toy(), BOX, config).plan(START, np.array(goal))
    white = Planner(Toy(), BOX, PlannerConfig(horizon=40)).plan(START, np.array(goal))
    assert np.array_equal(first.actions, again.actions) and not np.array_equal(first.actions, white.actions)
    assert np.isfinite(first.actions).all() and np.abs(first.actions).max() <= 1.0
    assert first.ok and np.linalg.norm(executed(first.actions) - goal) <= config.tolerance_mm + 1e-4
    with pytest.raises(ValueError, match="noise_beta"):
        PlannerConfig(noise_beta=-1.0)


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_plans_are_bounded_finite_and_seeded(sampler: str) -> None:
    torch.manual_seed(0)
    model = TransitionModel(hand_norm())
    config = {"samples": 300, "horizon": 15, "sampler": sampler, "refine_iterations": 2, "horizon_search": True}
    workspace = Workspace.box(-60, 60, 30, 130)
    first = Planner(model, workspace, PlannerConfig(**config)).plan(START, (3.0, 78.0))  # type: ignore[arg-type]
    again = Planner(model, workspace, PlannerConfig(**config)).plan(START, (3.0, 78.0))  # type: ignore[arg-type]
    other = Planner(model, workspace, PlannerConfig(**config)).plan(START, (3.0, 78.0), seed=1)  # type: ignore[arg-type]
    assert len(first.actions) > 0 and first.predicted.shape == (len(first.actions) + 1, 4)
    assert (
        np.abs(first.actions).max() <= 1.0 and np.isfinite(first.actions).all() and np.isfinite(first.predicted).all()
    )
    assert np.array_equal(first.actions, again.actions) and first.error_mm == again.error_mm
    assert first.actions.shape != other.actions.shape or not np.array_equal(first.actions, other.actions)
    assert first.evaluated == 300 + 2 * (300 - 30)  # refinement keeps the 10 % elites and redraws the rest


@settings(max_examples=25, deadline=None)
@given(
    sampler=st.sampled_from(SAMPLERS),
    seed=st.integers(0, 2**31 - 1),
    refine=st.integers(0, 2),
    search=st.booleans(),
    gain=st.floats(0.1, 20.0),
    goal=st.tuples(st.floats(-45.0, 45.0), st.floats(45.0, 115.0)),
    answer=st.sampled_from(ANSWERS),
)
def test_any_plan_is_bounded_and_keeps_its_prediction_safe(
    sampler: str, seed: int, refine: int, search: bool, gain: float, goal: tuple[float, float], answer: str
) -> None:
    config = PlannerConfig(
        samples=64, horizon=8, sampler=sampler, refine_iterations=refine, horizon_search=search, seed=seed,
        answer=answer,
    )
    result = Planner(Toy(gain=gain), BOX, config).plan(START, goal)
    assert np.isfinite(result.actions).all() and (np.abs(result.actions) <= 1.0).all()
    assert np.isfinite(result.predicted).all() and result.predicted.shape == (len(result.actions) + 1, 4)
    assert BOX.allows(torch.as_tensor(result.predicted)).all()
    assert result.ok == (result.error_mm <= config.tolerance_mm) and (result.status == "ok") == result.ok


# --------------------------------------------------------------------- optimality on a linear model


def test_finds_the_known_optimum_of_a_linear_model() -> None:
    goal = (START[0] + 4.0, START[1] - 2.0)  # reachable in 10 steps, e.g. a = (0.4, -0.2) throughout
    result = plan(Toy(), goal, samples=500, horizon=10, sampler="uniform", refine_iterations=6, tolerance_mm=0.2)
    assert result.ok and result.status == "ok" and result.error_mm <= 0.2
    assert np.linalg.norm(executed(result.actions) - goal) <= 0.2 + 1e-5
    assert np.allclose(result.predicted[-1, 2:], START[2:])


def test_the_default_planner_reaches_a_linear_models_optimum_over_its_whole_horizon() -> None:
    """The defaults (only the horizon set): a goal reachable in 40 steps is reached at the plan's last step, so
    nothing is left to drift through while the hand holds after it; the executed end is the predicted one."""
    goal = (START[0] + 12.0, START[1] - 9.0)  # |a| <= 1 per step: reachable in 40 steps, not in 12
    result = Planner(Toy(), BOX, PlannerConfig(horizon=40)).plan(START, np.array(goal))
    defaults = PlannerConfig()
    assert result.ok and result.error_mm <= defaults.tolerance_mm
    assert len(result.actions) == 40 and np.abs(result.actions).max() <= 1.0
    end = executed(result.actions)
    assert np.linalg.norm(end - goal) <= defaults.tolerance_mm + 1e-4
    assert np.allclose(end, result.predicted[-1, :2], atol=1e-4)
    assert result.evaluated <= defaults.samples * (1 + defaults.refine_iterations)


def test_stop_ends_a_plan_before_its_next_chunk_and_a_stop_never_asked_changes_nothing() -> None:
    planner = Planner(Toy(), BOX, PlannerConfig(horizon=20, samples=300, chunk=100, refine_iterations=2))
    goal = np.array([START[0] + 5.0, START[1] - 3.0])
    asked = []

    def stop_at_third() -> bool:
        asked.append(True)
        return len(asked) == 3

    with pytest.raises(PlanStopped, match="after 200 of the samples"):
        planner.plan(START, goal, stop=stop_at_third)
    assert len(asked) == 3  # asked before each chunk, and none after it said stop
    with pytest.raises(PlanStopped):
        planner.plan(START, goal, stop=lambda: True)
    plain, unstopped = planner.plan(START, goal), planner.plan(START, goal, stop=lambda: False)
    assert np.array_equal(plain.actions, unstopped.actions) and plain.evaluated == unstopped.evaluated


def test_the_elite_mean_answer_reaches_a_linear_models_goal_for_one_more_rollout() -> None:
    goal = np.array([START[0] + 12.0, START[1] - 9.0])
    config = PlannerConfig(horizon=40, answer="elite_mean")
    mean = Planner(Toy(), BOX, config).plan(START, goal)
    best = Planner(Toy(), BOX, PlannerConfig(horizon=40)).plan(START, goal)
    assert mean.ok and np.linalg.norm(executed(mean.actions) - goal) <= config.tolerance_mm + 1e-4
    assert not np.array_equal(mean.actions, best.actions) and np.abs(mean.actions).max() <= 1.0
    assert mean.evaluated == best.evaluated + 1
    with pytest.raises(ValueError, match="answer"):
        PlannerConfig(answer="median")


def test_the_polish_takes_a_rough_plan_to_a_linear_models_goal() -> None:
    """Ten random sequences and no refinement miss a 40-step goal; gradient steps on the best one reach it."""
    goal = np.array([START[0] + 12.0, START[1] - 9.0])
    rough = PlannerConfig(horizon=40, samples=10, refine_iterations=0)
    before = Planner(Toy(), BOX, rough).plan(START, goal)
    after = Planner(Toy(), BOX, replace(rough, polish_steps=100, polish_lr=0.05)).plan(START, goal)
    assert not before.ok and after.ok and after.error_mm < 0.5 * before.error_mm
    assert len(after.actions) == 40 and np.abs(after.actions).max() <= 1.0
    assert np.allclose(executed(after.actions), after.predicted[-1, :2], atol=1e-4)
    assert after.evaluated == before.evaluated + 1


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**16), steps=st.integers(1, 5), lr=st.floats(0.01, 2.0))
def test_a_polished_plan_is_never_predicted_worse_and_stays_in_the_box(seed: int, steps: int, lr: float) -> None:
    torch.manual_seed(seed)
    model = TransitionModel(hand_norm())
    goal = np.array([START[0] + 5.0, START[1] - 5.0])
    config = PlannerConfig(horizon=12, samples=20, refine_iterations=1, seed=seed)
    plain = Planner(model, BOX, config).plan(START, goal)
    polished = Planner(model, BOX, replace(config, polish_steps=steps, polish_lr=lr)).plan(START, goal)
    assert polished.error_mm <= plain.error_mm
    assert np.isfinite(polished.actions).all() and np.abs(polished.actions).max() <= 1.0
    assert all(p.requires_grad and p.grad is None for p in model.parameters())  # the model is not trained


def test_a_polish_into_nan_keeps_the_searched_plan() -> None:
    """The Toy predicts NaN once x passes 4 mm to the right: the goal lies beyond, the polish runs into it."""
    goal = np.array([START[0] + 6.0, START[1]])
    config = PlannerConfig(horizon=10, samples=50, refine_iterations=2)
    toy = Toy(nan_beyond=START[0] + 4.0)
    plain = Planner(toy, BOX, config).plan(START, goal)
    polished = Planner(toy, BOX, replace(config, polish_steps=50, polish_lr=0.5)).plan(START, goal)
    assert np.array_equal(polished.actions, plain.actions) and polished.error_mm == plain.error_mm
    assert polished.rejected["nan"] == plain.rejected["nan"] + 1


def test_the_polish_is_refused_where_it_has_no_gradient_to_follow() -> None:
    for settings_ in ({"horizon_search": True}, {"perturbations": 3}, {"uncertainty": "dropout", "members": 2}):
        with pytest.raises(ValueError, match="polish refines a fixed-length plan"):
            PlannerConfig(polish_steps=5, **settings_)  # type: ignore[arg-type]
    for bad in ({"polish_steps": -1}, {"polish_steps": 1001}, {"polish_lr": 0.0}, {"polish_lr": math.nan}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            PlannerConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="differentiable rollout"):
        Planner(_unsafe_between, BOX, PlannerConfig(polish_steps=1))


def _unsafe_between(x0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """A time-major rollout, ``x += a``, whose safe sequences are not convex: NaN when the first action's
    x is within 0.3 of zero, so the mean of safe sequences on both sides is unsafe."""
    steps = x0[:, None, :2] + actions.cumsum(1)
    states = torch.cat([x0[:, None], torch.cat([steps, x0[:, None, 2:].expand(-1, actions.shape[1], 2)], -1)], 1)
    unsafe = actions[:, 0, 0].abs() < 0.3
    states[unsafe, 1:] = math.nan
    return states.transpose(0, 1)


def test_an_unsafe_elite_mean_falls_back_to_the_best_sequence() -> None:
    goal = np.array([START[0], START[1]])  # (+a, -a) and (-a, +a) both reach it; their mean (0, 0) is unsafe
    config = PlannerConfig(samples=400, horizon=2, refine_iterations=0, answer="elite_mean", tolerance_mm=0.5)
    mean = Planner(_unsafe_between, BOX, config).plan(START, goal)
    best = Planner(_unsafe_between, BOX, replace(config, answer="best")).plan(START, goal)
    assert abs(mean.actions[0, 0]) >= 0.3 and np.array_equal(mean.actions, best.actions)
    assert mean.rejected["nan"] == best.rejected["nan"] + 1 and mean.ok


def test_discrete_sampler_finds_the_exact_sequence() -> None:
    result = plan(Toy(), (START[0] + 2.0, START[1]), samples=200, horizon=2, sampler="discrete")
    assert result.ok and result.error_mm < 1e-5
    assert np.array_equal(result.actions, [[1.0, 0.0], [1.0, 0.0]])


def test_piecewise_sequences_reach_far_goals_that_iid_actions_do_not() -> None:
    goal = (START[0] + 25.0, START[1] + 5.0)
    draw = {"samples": 1000, "horizon": 30, "tolerance_mm": 3.0, "refine_iterations": 0}  # the samplers alone
    far = plan(Toy(), goal, sampler="piecewise", hold_steps=(10, 30), **draw)
    iid = plan(Toy(), goal, sampler="uniform", **draw)
    assert far.ok and np.linalg.norm(executed(far.actions) - goal) <= 3.0 + 1e-5
    assert not iid.ok and iid.error_mm > far.error_mm


def test_horizon_search_returns_the_shortest_reaching_prefix() -> None:
    goal = (START[0] + 5.0, START[1])
    result = plan(Toy(), goal, samples=1000, horizon=30, horizon_search=True, tolerance_mm=1.0)
    assert result.ok and 5 <= len(result.actions) < 30  # |a| <= 1: at least 4 steps to come within 1 mm, 5 to pass 4 mm
    dist = np.linalg.norm(result.predicted[1:, :2] - goal, axis=1)
    assert dist[-1] <= 1.0 and (dist[:-1] > 1.0).all()
    assert np.linalg.norm(executed(result.actions) - goal) <= 1.0 + 1e-5
    assert len(plan(Toy(), goal, samples=1000, horizon=30, tolerance_mm=1.0).actions) == 30


# ------------------------------------------------------------------------------ safety rejections


def test_nan_predictions_are_rejected() -> None:
    partial = plan(
        Toy(nan_beyond=START[0] + 3.0), (START[0] + 2.5, START[1]), samples=400, horizon=10, tolerance_mm=1.0
    )
    assert partial.ok and partial.rejected["nan"] > 0 and np.isfinite(partial.predicted).all()
    everywhere = plan(Toy(nan_beyond=-math.inf), (START[0] + 2.0, START[1]), samples=100, horizon=10)
    assert not everywhere.ok and everywhere.status == "no_safe_sequence"
    assert (
        everywhere.rejected == {"nan": 100, "load": 0, "workspace": 0} and "100 predicted NaN/inf" in everywhere.reason
    )
    assert everywhere.actions.shape == (0, 2) and math.isinf(everywhere.error_mm)


def test_leaving_the_workspace_is_rejected() -> None:
    edge = Workspace.box(-50.0, START[0] + 3.0, 40.0, 120.0)
    near_edge = plan(Toy(), (START[0] + 2.5, START[1]), edge, samples=400, horizon=10, tolerance_mm=1.0)
    assert near_edge.ok and near_edge.rejected["workspace"] > 0
    assert near_edge.predicted[:, 0].max() <= START[0] + 3.0
    drifting = plan(Toy(drift=(5.0, 0.0)), (START[0] + 2.0, START[1]), edge, samples=100, horizon=10)
    assert drifting.status == "no_safe_sequence" and drifting.rejected == {"nan": 0, "load": 0, "workspace": 100}


def test_exceeding_the_load_limit_is_rejected() -> None:
    result = plan(Toy(load_rate=30.0), (START[0] + 2.0, START[1]), samples=100, horizon=10)  # 100 + 30 t > 280 at t = 7
    assert result.status == "no_safe_sequence" and result.rejected == {"nan": 0, "load": 100, "workspace": 0}
    assert "100 over the load limit" in result.reason
    short = plan(Toy(load_rate=30.0), (START[0] + 2.0, START[1]), samples=100, horizon=6, tolerance_mm=1.0)
    assert short.ok and np.abs(short.predicted[:, 2:]).max() <= 280.0
    strict = Workspace(BOX.lower, BOX.upper, load_limit=150.0)
    assert plan(Toy(load_rate=30.0), (START[0] + 2.0, START[1]), strict, samples=100, horizon=6).rejected["load"] == 100


def test_unreachable_goal_is_reported_with_its_predicted_error() -> None:
    result = plan(Toy(), (START[0] + 40.0, START[1]), samples=500, horizon=10, sampler="piecewise")
    assert not result.ok and result.status == "unreachable"
    assert 30.0 <= result.error_mm < 32.0  # at most 10 mm of travel towards a goal 40 mm away
    assert f"{result.error_mm:.2f} mm" in result.reason
    assert result.actions.shape == (10, 2)  # the best safe attempt is still returned


def test_start_or_goal_outside_the_workspace_and_bad_input() -> None:
    outside = plan(Toy(), (START[0] + 60.0, START[1]), samples=10, horizon=5)
    assert outside.status == "goal_outside_workspace" and outside.evaluated == 0
    tight = Workspace.box(10.0, 20.0, 40.0, 120.0)
    assert plan(Toy(), (15.0, 80.0), tight, samples=10, horizon=5).status == "start_outside_workspace"
    with pytest.raises(ValueError, match="goal must be 2 finite"):
        plan(Toy(), (math.nan, 80.0), samples=10, horizon=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # finite in float64 but not in float32: refused, not cast to inf with a warning
        with pytest.raises(ValueError, match="goal must be 2 finite"):
            plan(Toy(), (1e300, 80.0), samples=10, horizon=5)
    with pytest.raises(ValueError, match="state must be 4"):
        Planner(Toy(), BOX).plan(START[:3], (0.0, 80.0))
    with pytest.raises(ValueError, match="sampler"):
        PlannerConfig(sampler="brownian")


# ------------------------------------------------------------------------------ fast path, chunking


@pytest.mark.parametrize("grasp_input", [False, True])
def test_fused_rollout_equals_the_generic_rollout(grasp_input: bool) -> None:
    torch.manual_seed(1)
    model = TransitionModel(hand_norm(), grasp_input=grasp_input)
    x0 = torch.tensor(START, dtype=torch.float32) + torch.randn(64, 4) * torch.tensor([10.0, 10.0, 20.0, 20.0])
    actions = torch.rand(64, 50, 2) * 2 - 1
    torch.testing.assert_close(FusedRollout(model)(x0, actions), model.rollout(x0, actions), rtol=1e-4, atol=1e-4)
    residual = CumulativeResidualModel(model, TransitionModel(hand_norm()), 0.3, 0.99)
    assert is_paper_mlp(model) and not is_paper_mlp(residual)
    generic = make_rollout(residual)(x0, actions)
    assert torch.equal(generic.transpose(0, 1), residual.rollout(x0, actions))


@pytest.mark.parametrize(("batch", "horizon"), [(1, 7), (3, 1), (5, 0)])
def test_fused_rollout_at_small_shapes(batch: int, horizon: int) -> None:
    torch.manual_seed(3)
    model = TransitionModel(hand_norm(), grasp_input=True)
    x0 = torch.tensor(START, dtype=torch.float32) + torch.randn(batch, 4)
    actions = torch.rand(batch, horizon, 2) * 2 - 1
    states = FusedRollout(model)(x0, actions)
    assert states.shape == (batch, horizon + 1, 4)
    torch.testing.assert_close(states, model.rollout(x0, actions), rtol=1e-4, atol=1e-4)


def test_fast_and_generic_paths_choose_the_same_plan() -> None:
    torch.manual_seed(2)
    model = TransitionModel(hand_norm())
    workspace = Workspace.box(-60, 60, 30, 130)
    fast, slow = (
        Planner(model, workspace, PlannerConfig(samples=300, horizon=20, fast_path=f)).plan(START, (2.0, 79.0))
        for f in (True, False)
    )
    assert np.array_equal(fast.actions, slow.actions)
    assert fast.error_mm == pytest.approx(slow.error_mm, abs=1e-4)


@pytest.mark.parametrize("kind", ["toy", "transition"])
def test_chunking_gives_the_same_plan_as_one_batch(kind: str) -> None:
    torch.manual_seed(3)
    model = Toy(load_rate=8.0) if kind == "toy" else TransitionModel(hand_norm())
    config = {"samples": 200, "horizon": 20, "horizon_search": True, "refine_iterations": 1, "tolerance_mm": 0.5}
    whole, chunked = (
        Planner(model, Workspace.box(-60, 60, 30, 130), PlannerConfig(chunk=c, **config)).plan(START, (3.0, 77.0))  # type: ignore[arg-type]
        for c in (200, 7)
    )
    assert np.array_equal(whole.actions, chunked.actions) and whole.status == chunked.status
    assert whole.error_mm == pytest.approx(chunked.error_mm, abs=1e-5)
    assert whole.rejected == chunked.rejected and whole.evaluated == chunked.evaluated == 200 + (200 - 20)


def test_candidates_are_the_lowest_cost_paths_best_first_and_the_plan_unchanged() -> None:
    goal = (START[0] + 4.0, START[1] - 2.0)
    config = {"samples": 300, "horizon": 10, "sampler": "uniform", "refine_iterations": 2, "tolerance_mm": 0.5}
    none = plan(Toy(), goal, **config)
    kept = plan(Toy(), goal, candidates=5, **config)
    assert none.candidates == () and len(kept.candidates) == 5
    assert np.array_equal(kept.actions, none.actions)  # keeping them changes nothing planned
    assert np.array_equal(kept.candidates[0], kept.predicted[:, :2])  # the best is the plan's own path
    ends = [float(np.linalg.norm(c[-1] - goal)) for c in kept.candidates]
    assert ends == sorted(ends) and ends[-1] > ends[0]  # distinct sequences, lowest cost (final distance) first
    assert all(np.array_equal(c[0], START[:2]) and c.shape == (11, 2) for c in kept.candidates)
    assert kept.to_dict()["candidates"][1] == kept.candidates[1].tolist()
    refused = plan(Toy(), (START[0] + 500.0, START[1]), candidates=5, **config)  # goal outside the box
    assert not refused.ok and refused.candidates == ()
    with pytest.raises(ValueError, match="candidates"):
        PlannerConfig(candidates=-1)


# ------------------------------------------------------------------------------------ workspace


def test_workspace_contains_its_states_and_round_trips() -> None:
    rng = np.random.default_rng(0)
    states = np.column_stack([rng.normal(0, 10, 500), rng.normal(80, 8, 500), rng.normal(100, 20, (500, 2))])
    ws = Workspace.from_states(states, margin_mm=2.0)
    assert ws.contains_xy(torch.as_tensor(states[:, :2])).all()
    x_min, x_max, y_min, y_max = ws.bounds()
    assert x_min == pytest.approx(states[:, 0].min() - 2.0) and y_max == pytest.approx(states[:, 1].max() + 2.0)
    corner = torch.tensor([[x_max - 0.1, y_max - 0.1]], dtype=torch.float64)  # inside the box, outside the hull
    assert not ws.contains_xy(corner).any() and Workspace.box(x_min, x_max, y_min, y_max).contains_xy(corner).all()
    assert not ws.contains_xy(torch.tensor([[math.nan, 80.0], [math.inf, 80.0]])).any()
    again = Workspace.from_metadata({"extra": {"workspace": json.loads(json.dumps(ws.to_dict()))}})
    assert again is not None and np.array_equal(again.lower, ws.lower) and again.load_limit == ws.load_limit
    assert Workspace.from_metadata({"extra": {}}) is None
    with pytest.raises(ValueError, match="even number"):
        Workspace(np.zeros(3), np.ones(3))


# ------------------------------------------------------------------------------------------ CLI


def test_cli_plan_writes_json_csv_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    torch.manual_seed(4)
    workspace = Workspace.box(-60, 60, 30, 130)
    path = save_model(
        TransitionModel(hand_norm()),
        tmp_path / "m.safetensors",
        method="new_model",
        extra={"workspace": workspace.to_dict()},
    )

    def argv(goal_y: str, tolerance: str, out: str) -> list[str]:
        return [
            "plan",
            str(path),
            "--start",
            *map(str, START),
            "--goal",
            "1",
            goal_y,
            "--horizon",
            "10",
            "--samples",
            "200",
            "--sampler",
            "uniform",
            "--tolerance",
            tolerance,
            "--out",
            str(tmp_path / out),
        ]

    assert main(argv("79", "50", "out")) == 0
    record = json.loads((tmp_path / "out" / "plan.json").read_text())
    assert record["plan"]["ok"] and len(record["plan"]["actions"]) == 10 and record["config"]["samples"] == 200
    rows = (tmp_path / "out" / "plan.csv").read_text().splitlines()
    assert rows[0].startswith("step,action1,action2,predicted_x_mm") and len(rows) == 12
    assert (tmp_path / "out" / "plan.png").stat().st_size > 0
    assert main(argv("125", "1", "far")) == 1  # a random model does not travel 45 mm in 10 steps
    assert "unreachable" in capsys.readouterr().err
    assert json.loads((tmp_path / "far" / "plan.json").read_text())["plan"]["status"] == "unreachable"
    bare = save_model(TransitionModel(hand_norm()), tmp_path / "bare.safetensors", method="new_model")
    assert (
        main(["plan", str(bare), "--start", *map(str, START), "--goal", "1", "79", "--out", str(tmp_path / "x")]) == 2
    )
    assert "--workspace" in capsys.readouterr().err


@pytest.mark.parametrize("stored", [
    [1, 2], {"lower": "abc", "upper": [1.0, 2.0]}, {"lower": [0.0, 0.0], "upper": [1.0]},
    {"lower": [0.0, True], "upper": [1.0, 1.0]}, {"lower": [0.0] * 1000, "upper": [1.0] * 1000},
    {"lower": [0.0, 0.0], "upper": [1.0, 1.0], "load_limit": "x"}, {"lower": [1.0, 1.0], "upper": [0.0, 0.0]},
    {"lower": [[0.0, 0.0]], "upper": [[1.0, 1.0]]},
])
def test_a_malformed_stored_workspace_is_a_one_line_value_error(stored):
    with pytest.raises(ValueError) as err:
        Workspace.from_metadata({"extra": {"workspace": stored}})
    assert "\n" not in str(err.value)
    assert Workspace.from_metadata({"extra": []}) is None
