"""Peg-in-hole: goals made on the true target hand, plans executed open loop, success rate per distance."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from t42_transfer.cli import main as t42
from t42_transfer.data.bag import read_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.peg_in_hole import (
    Contender,
    Goal,
    PegInHoleConfig,
    Trial,
    contenders_for,
    evaluate,
    make_goals,
    progress_towards,
    summarise,
    verdict,
)
from t42_transfer.evaluation.peg_in_hole_report import markdown_table, paired, paired_table, plot_success
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.checkpoint import save_model
from t42_transfer.models.training import TrainConfig, train_transition_model
from t42_transfer.planning import PlannerConfig, Workspace

BAGS = Path(__file__).resolve().parents[1] / "bags"
TINY = PegInHoleConfig(distances=(10, 20), trials=3, tolerances_mm=(10.0, 4.0), min_distance_factor=1.2,
                       planner=PlannerConfig(samples=40, tolerance_mm=3.0, refine_iterations=2))
"""Goals at least 12 mm away (factor 1.2 keeps the tiny runs quick; the default is 2).  Two refinement rounds, not
nine: the oracle plans on the simulated hand itself, a MuJoCo run per sample and round (with nine, the fixture and
the CLI run below took 37 of the module's 42 s; with two, 14 s)."""


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


@pytest.fixture(scope="module")
def workspace(target_data: TrajectorySet) -> Workspace:
    return Workspace.from_trajectories(target_data)


@pytest.fixture(scope="module")
def evaluated(goals: list[Goal], workspace: Workspace, target_model: TransitionModel) -> tuple[list, list[Trial]]:
    still = TransitionModel(Normalisation.identity())  # zero output layer: predicts the hand never moves
    torch.nn.init.zeros_(still.net[6].weight)
    torch.nn.init.zeros_(still.net[6].bias)
    return evaluate({"trained": target_model, "still": still}, workspace, TINY, goals=goals, progress=False)


def test_goals_are_made_on_the_true_hand_deterministically_and_far_enough(
    goals: list[Goal], target_data: TrajectorySet
) -> None:
    assert [g.steps for g in goals] == [10, 10, 10, 20, 20, 20]
    assert TINY.min_distance_mm == pytest.approx(12.0)
    assert all(g.distance_mm >= TINY.min_distance_mm and g.still_distance_mm >= TINY.min_distance_mm for g in goals)
    assert PegInHoleConfig().min_distance_mm == 20.0  # twice the paper's 10 mm tolerance
    tight = Workspace.from_trajectories(target_data, margin_mm=0.0)
    assert all(tight.contains_xy(torch.as_tensor(g.position)) for g in make_goals(TINY, tight))
    assert all(np.array_equal(a.position, b.position) for a, b in zip(goals, make_goals(TINY), strict=True))
    hand = SimulatedHand("target")
    # The plan starts from the goal's own grasp (trajectories hold float32).
    assert np.array_equal(hand.reset(goals[0].seed).astype(np.float32), goals[0].grasp.astype(np.float32))


@pytest.mark.parametrize(
    ("distance", "error", "progress", "completed", "expected"),
    [
        (20.0, 3.0, 18.0, True, "hit"),
        (20.0, 10.5, 15.0, True, "miss"),  # a near miss at 10 mm
        (20.0, 10.0, 15.0, True, "hit"),  # on the border
        (5.0, 5.0, 0.0, True, "no_progress"),  # within 10 mm of a near goal without moving
        (20.0, 9.0, 9.0, True, "no_progress"),  # within tolerance sideways, but less than half way
        (20.0, 1.0, 19.0, False, "incomplete"),  # dropped on the way, however close
        (20.0, None, None, True, "incomplete"),  # nothing executed
    ],
)
def test_the_success_rule_on_hand_made_cases(distance, error, progress, completed, expected) -> None:
    assert verdict(distance, error, progress, completed, 10.0) == expected


def test_holding_still_is_simulated_once_per_grasp_and_the_goals_stay_the_same(monkeypatch) -> None:
    """A driver's grasp seed fixes the grasp for every attempt: holding still from it is simulated once (then
    kept, for any hand of the same model), and the goal is bit for bit the one of a hold simulated each time."""
    from t42_transfer.evaluation import peg_in_hole

    holds = []
    simulate = peg_in_hole.run_episode

    def counted(hand, actions, seed):
        holds.append(not np.any(actions))
        return simulate(hand, actions, seed)

    class Forgetful(dict):
        def __setitem__(self, key, value) -> None:  # the uncached path: every attempt simulates its hold
            pass

    monkeypatch.setattr(peg_in_hole, "run_episode", counted)

    def goal(kept: dict) -> tuple[Goal, int, int]:
        monkeypatch.setattr(peg_in_hole, "_held_still", kept)
        holds.clear()
        made = peg_in_hole.reachable_goal(SimulatedHand("target"), 8, (5, 40), iter(range(30)), grasp_seed=3,
                                          settle_steps=2, min_distance_mm=8.0)
        return made, sum(holds), len(holds) - sum(holds)

    uncached, uncached_holds, attempts = goal(Forgetful())
    cold, cold_holds, cold_attempts = goal({})
    warm, warm_holds, _ = goal(peg_in_hole._held_still)  # a new hand, the hold kept from the call before
    assert uncached_holds >= 3 and cold_attempts == attempts  # (several attempts got as far as the hold)
    assert (cold_holds, warm_holds) == (1, 0)
    for made in (cold, warm):
        assert (made.steps, made.trial, made.seed) == (uncached.steps, uncached.trial, uncached.seed) == (8, 0, 3)
        for field in ("grasp", "position", "still"):
            assert np.array_equal(getattr(made, field), getattr(uncached, field)), field


def test_progress_is_the_displacement_along_the_start_goal_line() -> None:
    start, goal = np.array([0.0, 80.0]), np.array([20.0, 80.0])
    assert progress_towards(start, goal, np.array([10.0, 85.0])) == pytest.approx(10.0)
    assert progress_towards(start, goal, np.array([-3.0, 80.0])) == pytest.approx(-3.0)
    assert progress_towards(start, start, start) == 0.0


def test_doing_nothing_scores_zero_and_the_oracle_beats_every_learned_model(evaluated) -> None:
    rows, trials = evaluated
    by = {(r.model, r.steps, r.tolerance_mm): r for r in rows}
    assert [m for m in dict.fromkeys(r.model for r in rows)] == ["do_nothing", "oracle", "trained", "still"]
    for steps in TINY.distances:
        for tol in TINY.tolerances_mm:
            assert by["do_nothing", steps, tol].successes == 0
            oracle = by["oracle", steps, tol]
            for model in ("trained", "still"):
                assert oracle.successes >= by[model, steps, tol].successes
        assert by["oracle", steps, 10.0].final_error_mm < min(by[m, steps, 10.0].final_error_mm
                                                              for m in ("trained", "still"))
    still = [t for t in trials if t.model == "do_nothing"]
    assert all(t.completed and t.plan_steps == t.steps and t.verdict(10.0) != "hit" for t in still)
    # Same samples, exact predictions: the oracle's pick is the truly best of them, never worse than a model's.
    oracle = {(t.steps, t.trial): t for t in trials if t.model == "oracle"}
    better = [oracle[t.steps, t.trial].final_error_mm <= t.final_error_mm + 1e-6
              for t in trials if t.model == "trained" and t.final_error_mm is not None]
    assert sum(better) >= len(better) - 1
    assert all(t.predicted_error_mm == pytest.approx(t.final_error_mm, abs=1e-3) for t in oracle.values())


def test_fixed_plans_have_exactly_n_steps_and_rows_carry_wilson_intervals(evaluated) -> None:
    rows, trials = evaluated
    assert all(t.plan_steps == t.steps for t in trials if t.completed)
    for r in rows:
        assert r.trials == 3 and 0.0 <= r.ci_low <= r.success_rate <= r.ci_high <= 1.0
        assert sum(r.verdicts.values()) == r.trials and r.verdicts["hit"] == r.successes
    zero = next(r for r in rows if r.model == "do_nothing")
    assert zero.ci_low == 0.0 and 0.4 < zero.ci_high < 0.6  # Wilson 95 % of 0/3: [0, 0.56]
    assert all(r.relative_error is not None and r.relative_error > 0.5 for r in rows if r.model == "do_nothing")


def test_closed_loop_contenders_replan_on_the_same_goals(goals: list[Goal], workspace: Workspace,
                                                        target_model: TransitionModel) -> None:
    contenders = contenders_for({"trained": target_model}, TINY.planner, mpc=5)
    assert [c.name for c in contenders] == ["trained", "trained+mpc5"]
    rows, trials = evaluate(contenders, workspace, TINY, goals=goals[:2], progress=False, baselines=())
    closed = [t for t in trials if t.model == "trained+mpc5"]
    assert all(t.plans == 2 for t in closed if t.completed)  # 10 steps, a plan every 5
    assert all(t.plans == 1 for t in trials if t.model == "trained")


def test_a_warm_closed_loop_of_one_sequence_executes_its_first_plan(goals: list[Goal], workspace: Workspace,
                                                                    target_model: TransitionModel) -> None:
    """Each warm replan of a one-sequence search can only return the rest it is handed, so the closed loop ends
    where the open loop ends, goal by goal; cold replans draw afresh and end elsewhere."""
    one = replace(TINY.planner, samples=1, refine_iterations=0)

    def ends(planner: PlannerConfig) -> list[bool]:
        """Per goal both loops ran (the planner refuses goals outside this workspace): the same end?"""
        contenders = [Contender("open", (target_model,), planner=one),
                      Contender("closed", (target_model,), planner=planner, replan_every=3)]
        _, trials = evaluate(contenders, workspace, TINY, goals=goals, progress=False, baselines=())
        open_, closed = trials[: len(goals)], trials[len(goals):]
        ran = [(a, b) for a, b in zip(open_, closed, strict=True) if a.final_error_mm is not None]
        assert len(ran) >= 2 and all(b.plans > 1 for _, b in ran)
        return [a.final_error_mm == b.final_error_mm for a, b in ran]

    assert all(ends(replace(one, warm_start=True)))
    assert not any(ends(one))


def test_peg_in_hole_runs_on_model_files(tmp_path: Path, target_model: TransitionModel) -> None:
    path = save_model(target_model, tmp_path / "target.safetensors", method="new_model")
    other = save_model(target_model, tmp_path / "again.safetensors", method="new_model")
    argv = [
        f"few_epochs={path}", f"again={other}",
        "--workspace", str(BAGS / "target_small"),
        "--out", str(tmp_path / "out"),
        "--distances", "25", "--trials", "2", "--samples", "60", "--tolerances", "10", "4",
        "--ensemble", "few_epochs", "again", "--dropout", "3", "--variants-of", "few_epochs",
        "--warm-start", "--refine", "2", "--quiet",
    ]
    assert t42(["peg-in-hole", *argv]) == 0
    report = json.loads((tmp_path / "out" / "peg_in_hole.json").read_text())
    assert report["config"]["planner"]["warm_start"] is True and report["config"]["planner"]["refine_iterations"] == 2
    names = list(dict.fromkeys(r["model"] for r in report["rows"]))
    assert names == ["do_nothing", "oracle", "few_epochs", "again", "few_epochs+dropout3", "ensemble2"]
    assert {(r["model"], r["tolerance_mm"]) for r in report["rows"]} >= {("oracle", 10.0), ("oracle", 4.0)}
    assert all(0.0 <= r["success_rate"] <= 1.0 for r in report["rows"])
    assert "| do_nothing | 25 |" in (tmp_path / "out" / "peg_in_hole.md").read_text()
    assert (tmp_path / "out" / "peg_in_hole.png").stat().st_size > 0


def test_summary_table_and_figure(tmp_path: Path) -> None:
    def trial(model: str, steps: int, error: float | None, end: str = "length", progress: float = 15.0) -> Trial:
        return Trial(model, steps, 0, "ok", end, 20.0, error, None if error is None else progress, 1.0, steps, 1, 0.1)

    trials = [
        trial("a", 10, 2.0),
        trial("a", 10, 12.0),
        trial("a", 10, 3.0, "dropped"),
        trial("a", 20, None, "refused"),
        trial("b", 10, 1.0),
    ]
    rows = summarise(trials, (10.0, 4.0))
    assert [(r.model, r.steps, r.tolerance_mm, r.successes, r.trials) for r in rows] == [
        ("a", 10, 10.0, 1, 3), ("a", 10, 4.0, 1, 3), ("a", 20, 10.0, 0, 1), ("a", 20, 4.0, 0, 1),
        ("b", 10, 10.0, 1, 1), ("b", 10, 4.0, 1, 1),
    ]
    assert rows[0].success_rate == pytest.approx(1 / 3) and rows[0].final_error_mm == 3.0
    assert rows[0].verdicts == {"hit": 1, "miss": 1, "no_progress": 0, "incomplete": 1}
    assert rows[2].verdicts["incomplete"] == 1 and rows[2].final_error_mm is None
    table = markdown_table(rows)
    assert "Tolerance 10 mm" in table and "Tolerance 4 mm" in table
    assert "| a | 10 | 20.0 | 3 | 1 (33%) |" in table and "| 3.0 | 0.15 | 1 / 0 / 1 |" in table
    assert plot_success(rows, tmp_path / "fig.png").stat().st_size > 0


def test_paired_comparisons_match_goals_and_pick_each_variants_own_model(tmp_path: Path) -> None:
    def trial(model: str, trial: int, error: float) -> Trial:
        return Trial(model, 20, trial, "ok", "length", 20.0, error, 15.0, error, 20, 1, 0.1)

    errors = {"direct": [2, 12, 12, 12], "a": [2, 2, 2, 12], "a+mpc5": [2, 2, 2, 2], "do_nothing": [20] * 4}
    trials = [trial(m, i, e) for m, es in errors.items() for i, e in enumerate(es)]
    comparisons = {(c.model, c.against): c for c in paired(trials, (10.0,))}
    assert set(comparisons) == {("a", "direct"), ("a+mpc5", "a")}  # baselines are not compared
    a = comparisons["a", "direct"]
    assert (a.goals, a.wins, a.losses) == (4, 2, 0) and a.difference == pytest.approx(0.5)
    assert a.ci_low <= a.difference <= a.ci_high
    assert comparisons["a+mpc5", "a"].difference == pytest.approx(0.25)
    assert "| a | direct | 10 | 4 | +50% |" in paired_table(list(comparisons.values()))

    stored = tmp_path / "peg_in_hole.json"
    stored.write_text(json.dumps({"config": {"tolerances_mm": [10.0]}, "trials": [t.__dict__ for t in trials]}))
    assert t42(["peg-in-hole", "--from-json", str(stored)]) == 0
    assert "| a+mpc5 | a | 10 |" in (tmp_path / "peg_in_hole.md").read_text()
    assert (tmp_path / "peg_in_hole.png").stat().st_size > 0
