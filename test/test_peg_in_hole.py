"""Peg-in-hole: goals made on the true target hand, plans executed open loop, success rate per distance."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from t42_transfer.data.bag_io import read_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.training import TrainConfig, train_transition_model
from t42_transfer.planning import PlannerConfig, Workspace
from t42_transfer.planning.peg_in_hole import (
    Goal,
    PegInHoleConfig,
    Trial,
    evaluate,
    main,
    make_goals,
    markdown_table,
    plot_success,
    summarise,
)

BAGS = Path(__file__).resolve().parents[1] / "bags"
TINY = PegInHoleConfig(
    distances=(5, 15), trials=2, planner=PlannerConfig(samples=200, horizon=20, horizon_search=True, tolerance_mm=3.0)
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def target_data() -> TrajectorySet:
    return read_bag(BAGS / "target_small")


@pytest.fixture(scope="module")
def target_model(target_data: TrajectorySet) -> TransitionModel:
    """The paper's MLP after a few epochs on the small target fixture bag: crude, but a real hand model."""
    return train_transition_model(target_data, TrainConfig(epochs=5, patience=None))[0]


@pytest.fixture(scope="module")
def goals() -> list[Goal]:
    return make_goals(TINY)


def test_goals_are_made_on_the_true_hand_deterministically(goals: list[Goal], target_data: TrajectorySet) -> None:
    assert [g.steps for g in goals] == [5, 5, 15, 15]
    tight = Workspace.from_trajectories(target_data, margin_mm=0.0)
    assert all(tight.contains_xy(torch.as_tensor(g.position)) for g in make_goals(TINY, tight))
    assert all(np.array_equal(a.position, b.position) for a, b in zip(goals, make_goals(TINY)))
    hand = SimulatedHand("target")
    # The plan starts from the goal's own grasp (trajectories hold float32).
    assert np.array_equal(hand.reset(goals[0].seed).astype(np.float32), goals[0].grasp.astype(np.float32))
    assert all(g.distance_mm > 0 for g in goals)


def test_peg_in_hole_runs_end_to_end(
    goals: list[Goal], target_data: TrajectorySet, target_model: TransitionModel
) -> None:
    still = TransitionModel(Normalisation.identity())  # zero output layer: predicts the hand never moves
    torch.nn.init.zeros_(still.net[6].weight)
    torch.nn.init.zeros_(still.net[6].bias)
    workspace = Workspace.from_trajectories(target_data)
    rows, trials = evaluate({"trained": target_model, "still": still}, workspace, TINY, goals=goals, progress=False)
    assert [(r.model, r.steps) for r in rows] == [("trained", 5), ("trained", 15), ("still", 5), ("still", 15)]
    assert all(0.0 <= r.success_rate <= 1.0 and r.trials == 2 for r in rows)
    assert len(trials) == 8 and all(
        t.success == (t.final_error_mm is not None and t.final_error_mm <= 10.0 and t.end_reason == "length")
        for t in trials
    )
    assert all(t.plan_steps <= 20 for t in trials)
    # A model that predicts no motion cannot plan towards goals farther than the planning tolerance.
    assert all(t.status != "ok" for t in trials if t.model == "still" and t.goal_distance_mm > 3.0)


def test_peg_in_hole_runs_on_model_files(tmp_path: Path, target_model: TransitionModel) -> None:
    path = save_model(target_model, tmp_path / "target.safetensors", method="new_model")
    argv = [
        f"few_epochs={path}",
        "--workspace",
        str(BAGS / "target_small"),
        "--out",
        str(tmp_path / "out"),
        "--distances",
        "5",
        "15",
        "--trials",
        "2",
        "--samples",
        "200",
        "--horizon",
        "20",
        "--quiet",
    ]
    assert main(argv) == 0
    report = json.loads((tmp_path / "out" / "peg_in_hole.json").read_text())
    assert [(r["model"], r["steps"]) for r in report["rows"]] == [("few_epochs", 5), ("few_epochs", 15)]
    assert all(0.0 <= r["success_rate"] <= 1.0 for r in report["rows"])
    assert "| few_epochs | 5 |" in (tmp_path / "out" / "peg_in_hole.md").read_text()
    assert (tmp_path / "out" / "peg_in_hole.png").stat().st_size > 0


def test_summary_table_and_figure(tmp_path: Path) -> None:
    def trial(model: str, steps: int, error: float | None, end: str = "length") -> Trial:
        status = "ok" if error is not None else "no_safe_sequence"
        return Trial(
            model, steps, error is not None and error <= 10.0 and end == "length", status, end, 20.0, error, 1.0, 5
        )

    trials = [
        trial("a", 10, 2.0),
        trial("a", 10, 12.0),
        trial("a", 10, 3.0, "dropped"),
        trial("a", 20, None, "not_executed"),
        trial("b", 10, 1.0),
    ]
    rows = summarise(trials)
    assert [(r.model, r.steps, r.successes, r.trials) for r in rows] == [
        ("a", 10, 1, 3),
        ("a", 20, 0, 1),
        ("b", 10, 1, 1),
    ]
    assert rows[0].success_rate == pytest.approx(1 / 3) and rows[0].final_error_mm == 3.0
    assert rows[1].refused == 1 and rows[1].final_error_mm is None
    table = markdown_table(rows)
    assert "| a | 10 | 20.0 | 3 | 33% | 3.0 | 3 | 0 |" in table and "| a | 20 | 20.0 | 1 | 0% | - | 0 | 1 |" in table
    assert plot_success(rows, tmp_path / "fig.png", 10.0).stat().st_size > 0
