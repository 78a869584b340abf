"""Dropout members: each one the model in training mode with fixed masks; the members' choice among a plan's
best sequences, and the planner's ``rerank`` step that makes it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_planner import START, hand_norm
from toys import Toy

from t42_transfer.models import TransitionModel
from t42_transfer.planning import Planner, PlannerConfig, Workspace
from t42_transfer.planning.members import (
    ALPHA_DROPOUT_ALPHA,
    MembersRollout,
    can_rerank,
    dropout_masks,
    robust_choice,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")
WIDE = Workspace.box(-200.0, 200.0, -100.0, 300.0, load_limit=1e6)


def train_mode_with_masks(model: TransitionModel, kept_1: torch.Tensor, kept_2: torch.Tensor, x0: torch.Tensor,
                          actions: torch.Tensor) -> torch.Tensor:
    """``[B, T + 1, 4]``: the network's own layers, with torch's AlphaDropout and Dropout arithmetic on the given
    masks instead of fresh ones."""
    net, p = model.net, model.dropout
    a = 1.0 / math.sqrt((ALPHA_DROPOUT_ALPHA**2 * p + 1.0) * (1.0 - p))
    x, out = x0, [x0]
    with torch.no_grad():
        for t in range(actions.shape[1]):
            hidden = net[1](net[0](model.features(x, actions[:, t], x0 if model.grasp_input else None)))
            hidden = hidden * (a * kept_1) + a * ALPHA_DROPOUT_ALPHA * (kept_1 - 1.0 + p)
            hidden = net[4](net[3](hidden)) * kept_2 / (1.0 - p)
            x = x + net[6](hidden) * model.delta_std + model.delta_mean
            out.append(x)
    return torch.stack(out, 1)


def test_torchs_alpha_dropout_gives_the_two_values_the_members_fold_in() -> None:
    p = 0.1
    a = 1.0 / math.sqrt((ALPHA_DROPOUT_ALPHA**2 * p + 1.0) * (1.0 - p))
    values = torch.nn.functional.alpha_dropout(torch.ones(4000), p, True).unique()
    dropped, kept = a * ALPHA_DROPOUT_ALPHA * (p - 1.0), a + a * ALPHA_DROPOUT_ALPHA * p
    torch.testing.assert_close(values, torch.tensor([dropped, kept]))


@pytest.mark.parametrize("grasp_input", [False, True])
def test_each_member_is_the_model_in_training_mode_with_its_masks(grasp_input: bool) -> None:
    torch.manual_seed(4)
    model = TransitionModel(hand_norm(), grasp_input=grasp_input, dropout=0.2)
    x0 = torch.tensor(START, dtype=torch.float32) + torch.randn(16, 4) * torch.tensor([5.0, 5.0, 10.0, 10.0])
    actions = torch.rand(16, 30, 2) * 2 - 1
    states = MembersRollout(model, 5, seed=3)(x0, actions)
    assert states.shape == (31, 5, 16, 4)
    kept_1, kept_2 = dropout_masks(model, 5, seed=3)
    for m in range(5):
        expected = train_mode_with_masks(model, kept_1[m], kept_2[m], x0, actions)
        torch.testing.assert_close(states[:, m].transpose(0, 1), expected, rtol=1e-4, atol=1e-3)
    assert (states[-1, 0] - states[-1, 1]).abs().max() > 0.01  # members differ


def test_masks_are_seeded_and_keep_about_one_minus_p() -> None:
    model = TransitionModel(hand_norm(), dropout=0.25)
    first, again, other = (dropout_masks(model, 50, seed) for seed in (1, 1, 2))
    assert all(torch.equal(x, y) for x, y in zip(first, again, strict=True))
    assert not torch.equal(first[0], other[0])
    assert 0.7 < float(first[0].mean()) < 0.8 and 0.7 < float(first[1].mean()) < 0.8


def test_only_the_papers_mlp_with_dropout_has_members() -> None:
    assert can_rerank(TransitionModel(hand_norm(), dropout=0.1))
    assert not can_rerank(TransitionModel(hand_norm(), dropout=0.0))
    assert not can_rerank(Toy())


def test_the_choice_is_the_lowest_mean_plus_risk_std_and_never_one_a_member_takes_outside() -> None:
    torch.manual_seed(5)
    model = TransitionModel(hand_norm(), dropout=0.3)
    rollout = MembersRollout(model, 6, seed=0)
    x0, goal = torch.tensor(START, dtype=torch.float32), torch.tensor([3.0, 82.0])
    candidates = torch.rand(12, 20, 2) * 2 - 1
    final = rollout(x0.expand(12, 4), candidates)[-1, :, :, :2] - goal  # [M, K, 2]
    distance = final.norm(dim=-1)
    for risk in (0.0, 1.0, 3.0):
        score = distance.mean(0) + risk * distance.std(0)
        assert robust_choice(rollout, WIDE, x0, goal, candidates, risk) == int(score.argmin())
    # a workspace that one member's prediction of the favourite leaves: the favourite is passed over
    favourite = int((distance.mean(0) + distance.std(0)).argmin())
    states = rollout(x0.expand(12, 4), candidates)
    reach = states[1:, :, favourite, 0].max()
    others = states[1:, :, torch.arange(12) != favourite, 0].amax((0, 1))
    assert bool((others < reach).any())  # some sequence stays short of the favourite's furthest x
    narrow = Workspace.box(-200.0, float(reach) - 1e-3, -100.0, 300.0, load_limit=1e6)
    assert robust_choice(rollout, narrow, x0, goal, candidates, 1.0) not in (favourite, None)
    nowhere = Workspace.box(-200.0, float(states[1:, :, :, 0].min()) - 1.0, -100.0, 300.0, load_limit=1e6)
    assert robust_choice(rollout, nowhere, x0, goal, candidates, 1.0) is None


def rerank_plan(model: TransitionModel, goal: tuple[float, float], seed: int, tolerance_mm: float = 1.0,
                **config: object):
    cfg = PlannerConfig(samples=30, horizon=25, tolerance_mm=tolerance_mm, **config)  # type: ignore[arg-type]
    return Planner(model, WIDE, cfg).plan(START, np.array(goal), seed=seed)


def reachable_goal(model: TransitionModel, seed: int) -> tuple[float, float]:
    """Where the model puts the object after a random sequence of half-size actions: a goal some plan reaches."""
    gen = torch.Generator().manual_seed(seed)
    x0 = torch.tensor(START, dtype=torch.float32)[None]
    end = model.rollout(x0, (torch.rand(1, 25, 2, generator=gen) * 2 - 1) * 0.5)[0, -1, :2]
    return float(end[0]), float(end[1])


def test_a_reranked_plan_keeps_the_contract_is_seeded_and_lists_each_candidate_once() -> None:
    torch.manual_seed(6)
    model = TransitionModel(hand_norm(), dropout=0.2)
    changed = 0
    for seed in range(4):
        goal = reachable_goal(model, seed)
        plain = rerank_plan(model, goal, seed, tolerance_mm=3.0, refine_iterations=1)
        ranked, again = (rerank_plan(model, goal, seed, tolerance_mm=3.0, rerank=30, candidates=50, refine_iterations=1)
                         for _ in range(2))
        assert np.array_equal(ranked.actions, again.actions)
        assert ranked.actions.shape == (25, 2) and np.abs(ranked.actions).max() <= 1.0
        assert np.isfinite(ranked.predicted).all() and ranked.ok
        moved = not np.array_equal(ranked.actions, plain.actions)
        assert ranked.evaluated == plain.evaluated + 30 * 8 + moved
        paths = np.stack(ranked.candidates)  # the answer's rollout adds no second copy of a path (to rounding)
        gaps = np.abs(paths[:, None] - paths[None]).max((2, 3)) + np.eye(len(paths))
        assert len(paths) == 50 and gaps.min() > 1e-4  # (57 sequences evaluated: nearly all are candidates)
        changed += moved
    assert changed  # the members did choose


def test_rerank_changes_nothing_where_there_are_no_members() -> None:
    torch.manual_seed(7)
    model = TransitionModel(hand_norm(), dropout=0.0)
    plain = rerank_plan(model, (4.0, 84.0), 0)
    ranked = rerank_plan(model, (4.0, 84.0), 0, rerank=30)
    assert np.array_equal(plain.actions, ranked.actions) and ranked.evaluated == plain.evaluated


@pytest.mark.parametrize("other", [{"answer": "elite_mean"}, {"polish_steps": 3}, {"horizon_search": True},
                                   {"perturbations": 3}, {"uncertainty": "dropout", "members": 2},
                                   {"rerank_members": 1000}])
def test_rerank_is_refused_where_something_else_chooses_the_answer_or_the_batch_is_too_big(other: dict) -> None:
    with pytest.raises(ValueError, match="rerank chooses the answer"):
        PlannerConfig(rerank=30, **other)  # type: ignore[arg-type]
    PlannerConfig(rerank=0, **other)  # type: ignore[arg-type]


def test_rerank_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="rerank"):
        PlannerConfig(rerank=-1)
    with pytest.raises(ValueError, match="rerank_members"):
        PlannerConfig(rerank_members=0)


def test_a_plan_predicted_to_reach_is_never_traded_for_one_that_is_not() -> None:
    """Goals a sequence is known to reach, a tight tolerance: the search reaches them, and among its best the
    members would often prefer one that ends a little further off."""
    torch.manual_seed(6)
    model = TransitionModel(hand_norm(), dropout=0.2)
    changed = 0
    for seed in range(6):
        goal = reachable_goal(model, seed)
        plain = rerank_plan(model, goal, seed, tolerance_mm=0.05)
        ranked = rerank_plan(model, goal, seed, tolerance_mm=0.05, rerank=30)
        assert plain.ok and ranked.ok and ranked.error_mm <= 0.05, (seed, plain.error_mm, ranked.error_mm)
        changed += not np.array_equal(plain.actions, ranked.actions)
    assert changed  # the members chose among the reaching ones
