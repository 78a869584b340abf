"""The planner-quality benchmark's core on a toy model: report shape and bounds, budgets, time to a rate."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_planner import Toy

from bench import bench_planner_quality as bench
from t42_transfer.evaluation.peg_in_hole import PegInHoleConfig, make_goals
from t42_transfer.planning.workspace import Workspace

pytestmark = pytest.mark.usefixtures("one_torch_thread")

WORKSPACE = Workspace.box(-200.0, 200.0, -100.0, 300.0, load_limit=1e6)
STEPS = 10
TOY = bench.Setting(budgets=(20, 320), cem_iterations=2, mppi_iterations=2, refine_iterations=1)
"""Few iterations keep the tiny runs quick; every optimiser still runs through its whole code path."""


GAIN = 2.0
"""The toy hand (test_planner.Toy): the object moves GAIN mm per unit action along x and y; loads stay put."""


def drift() -> Toy:
    return Toy(gain=GAIN)


@pytest.fixture(scope="module")
def goals() -> list:
    cfg = PegInHoleConfig(distances=(STEPS,), trials=2, min_distance_factor=0.5)
    return make_goals(cfg, WORKSPACE)


@pytest.fixture(scope="module")
def result(goals: list) -> dict:
    trials = bench.run(drift(), WORKSPACE, goals, TOY)
    return json.loads(json.dumps(bench.report(trials, goals, TOY)))  # JSON-able, as written


def test_report_has_every_optimiser_and_budget_with_sound_rates_and_intervals(result: dict) -> None:
    rows = result["rows"]
    assert [(r["optimiser"], r["budget"]) for r in rows] == [(o, b) for o in bench.OPTIMISERS for b in TOY.budgets]
    assert result["goals"]["count"] == 2 and result["goals"]["steps"] == [STEPS]
    for r in rows:
        assert r["trials"] == 2
        assert [s["tolerance_mm"] for s in r["success"]] == [10.0, 4.0]
        for s in r["success"]:
            assert 0.0 <= s["ci_low"] <= s["success_rate"] <= s["ci_high"] <= 1.0
            assert s["successes"] == s["verdicts"]["hit"] and sum(s["verdicts"].values()) == 2
        # 4 mm is stricter than 10 mm: never more successes
        assert r["success"][1]["successes"] <= r["success"][0]["successes"]
        assert r["median_plan_seconds"] > 0 and r["median_final_error_mm"] >= 0
        assert 2 <= r["median_rollouts"] <= r["budget"] + 1  # MPPI's one extra: the rollout of its plan
    assert len(result["time_to_rate"]) == len(bench.OPTIMISERS) * 2 * len(TOY.targets)
    assert len(result["trials"]) == 2 * len(rows)
    for t in result["trials"]:
        assert t["end_reason"] == "length" or t["verdicts"]["10"] == "incomplete"


def _predicted(name: str, goal, budget: int, seed: int) -> float:
    x0 = torch.as_tensor(goal.grasp, dtype=torch.float32)
    target = torch.as_tensor(goal.position, dtype=torch.float32)
    out = bench.optimise(name, drift(), WORKSPACE, x0, target, STEPS, budget, seed, TOY)
    assert out.actions.shape == (STEPS, 2) and np.abs(out.actions).max() <= 1.0
    return out.predicted_error_mm


@pytest.mark.parametrize("name", bench.OPTIMISERS)
def test_a_larger_budget_predicts_no_worse(name: str, goals: list) -> None:
    """Random shooting's 320 samples begin with the 20 it draws at budget 20 (same generator), so its best can
    only improve, seed by seed; the others draw differently per budget, so the property is their average."""
    small = [_predicted(name, g, 20, seed) for g in goals for seed in range(3)]
    large = [_predicted(name, g, 320, seed) for g in goals for seed in range(3)]
    assert all(math.isfinite(e) and e >= 0 for e in small + large)
    if name == "random_shooting":
        assert all(b <= a for a, b in zip(small, large, strict=True))
    assert np.mean(large) < np.mean(small)


@pytest.mark.parametrize("name", ["ours", "ours_cem", "cem", "cem_mean", "mppi"])
def test_each_optimiser_solves_a_reachable_toy_goal(name: str, goals: list) -> None:
    """The toy moves 2 mm per unit action: a goal 8 mm along x in 10 steps needs mean action 0.4 on x."""
    x0 = torch.as_tensor(goals[0].grasp, dtype=torch.float32)
    target = x0[:2] + torch.tensor([8.0, 0.0])
    out = bench.optimise(name, drift(), WORKSPACE, x0, target, STEPS, 2000, 0, bench.Setting())
    assert out.predicted_safe and out.predicted_error_mm < 1.0
    end = x0[:2].numpy() + GAIN * out.actions.sum(0)  # the toy's exact answer
    assert np.linalg.norm(end - target.numpy()) == pytest.approx(out.predicted_error_mm, abs=1e-3)


def test_time_to_rate_is_the_fastest_budget_reaching_it() -> None:
    setting = bench.Setting(budgets=(10, 100, 1000), optimisers=("ours",), tolerances_mm=(10.0,),
                            targets=(0.5, 0.8, 0.95))
    rows = [{"optimiser": "ours", "budget": b, "median_plan_seconds": s,
             "success": [{"tolerance_mm": 10.0, "success_rate": rate}]}
            for b, s, rate in ((10, 0.01, 0.2), (100, 0.05, 0.6), (1000, 0.2, 0.9))]
    got = {t["success_rate"]: (t["budget"], t["median_plan_seconds"]) for t in bench.time_to_rate(rows, setting)}
    assert got == {0.5: (100, 0.05), 0.8: (1000, 0.2), 0.95: (None, None)}


def test_without_the_model_it_says_how_to_make_it(tmp_path, capsys: pytest.CaptureFixture) -> None:
    assert bench.main(["--model", str(tmp_path / "absent.safetensors"), "--out", str(tmp_path / "q.json")]) == 2
    assert bench.MAKE_MODELS in capsys.readouterr().err
    assert not (tmp_path / "q.json").exists()


def test_trials_carry_the_planners_status_and_the_drift_after_a_completed_plan(result: dict) -> None:
    planners = {"default", "default_search", "default_settled", "default_robust", "ours", "ours_cem", "random_shooting"}
    for t in result["trials"]:
        assert (t["status"] != "") == (t["optimiser"] in planners)
        assert (t["drift_mm"] is not None) == (t["end_reason"] == "length")
        assert t["drift_mm"] is None or t["drift_mm"] >= 0.0
    for r in result["rows"]:
        assert sum(r["planner_status"].values()) == (r["trials"] if r["optimiser"] in planners else 0)


def test_search_then_hold_pads_the_shortest_prefix_with_zeros_to_the_goals_steps(goals: list) -> None:
    x0 = torch.as_tensor(goals[0].grasp, dtype=torch.float32)
    target = torch.as_tensor(goals[0].position, dtype=torch.float32)
    out = bench.optimise("default_search", drift(), WORKSPACE, x0, target, STEPS, 320, 0, TOY)
    assert out.actions.shape == (STEPS, 2) and out.status == "ok"
    moving = np.abs(out.actions).sum(1) > 0
    first_hold = int(np.argmin(moving))  # the toy moves 2 mm a step: the goal is reached well before STEPS
    assert 0 < first_hold < STEPS and moving[:first_hold].all() and not moving[first_hold:].any()


def test_cem_mean_returns_the_last_fitted_mean_not_a_sample(goals: list) -> None:
    """The same draws as ``cem``; the answer is their last elites' mean, scored by its own rollout."""
    x0 = torch.as_tensor(goals[0].grasp, dtype=torch.float32)
    target = x0[:2] + torch.tensor([8.0, 0.0])
    best = bench.optimise("cem", drift(), WORKSPACE, x0, target, STEPS, 300, 0, bench.Setting())
    mean = bench.optimise("cem_mean", drift(), WORKSPACE, x0, target, STEPS, 300, 0, bench.Setting())
    assert mean.rollouts == best.rollouts + 1 and not np.array_equal(mean.actions, best.actions)
    assert np.abs(mean.actions).max() <= 1.0 and mean.predicted_safe
    end = x0[:2].numpy() + GAIN * mean.actions.sum(0)
    assert np.linalg.norm(end - target.numpy()) == pytest.approx(mean.predicted_error_mm, abs=1e-3)


def test_planner_settings_replace_the_defaults_and_bad_ones_are_refused(goals: list, capsys) -> None:
    """``--planner`` changes the default family's planner (here its answer: one more rollout); it cannot set what
    the budget and the goal decide, nor an unknown or out-of-range setting."""
    x0 = torch.as_tensor(goals[0].grasp, dtype=torch.float32)
    target = x0[:2] + torch.tensor([8.0, 0.0])
    plain = bench.optimise("default", drift(), WORKSPACE, x0, target, STEPS, 300, 0, bench.Setting())
    mean = bench.optimise("default", drift(), WORKSPACE, x0, target, STEPS, 300, 0,
                          bench.Setting(planner=bench._planner_settings("{answer: elite_mean}")))
    assert mean.rollouts == plain.rollouts + 1 and not np.array_equal(mean.actions, plain.actions)
    for bad, says in (("{samples: 5}", "set per plan"), ("{bogus: 1}", "unknown PlannerConfig"),
                      ("{noise_beta: -1}", "noise_beta"), ("[1]", "a mapping")):
        with pytest.raises(SystemExit):
            bench.main(["--planner", bad, "--goals", "1"])
        assert says in capsys.readouterr().err


def test_the_default_is_paired_with_each_optimisers_best_budget(result: dict) -> None:
    """Goal by goal: the hits only one side made differ by exactly the two rows' hit counts; the time share is the
    default's fastest row reaching the other's rate over the other's time, and the target follows from it."""
    against = result["against_default"]
    others = [n for n in TOY.optimisers if n != "default"]
    assert [(a["tolerance_mm"], a["optimiser"]) for a in against] == [(t, n) for t in TOY.tolerances_mm for n in others]
    for a in against:
        k = TOY.tolerances_mm.index(a["tolerance_mm"])
        rows = {(r["optimiser"], r["budget"]): r for r in result["rows"]}
        assert rows["default", a["default_budget"]]["success"][k]["successes"] == a["default_successes"]
        assert rows[a["optimiser"], a["budget"]]["success"][k]["successes"] == a["successes"]
        assert a["only_default"] - a["only_other"] == a["default_successes"] - a["successes"]
        assert 0.0 <= a["sign_test_p"] <= 1.0
        reaching = [r["median_plan_seconds"] for (n, _), r in rows.items()
                    if n == "default" and r["success"][k]["successes"] >= a["successes"]]
        other_time = rows[a["optimiser"], a["budget"]]["median_plan_seconds"]
        assert a["default_time_share"] == (min(reaching) / other_time if reaching else None)
        assert a["target_met"] == (a["default_time_share"] is not None and a["default_time_share"] <= 1 / 3)
    assert "The default's best budget against" in bench.markdown(result)


def test_the_figures_curves_are_each_optimisers_budgets_in_order(result: dict) -> None:
    for k in range(2):
        drawn = bench.curves(result, k)
        assert list(drawn) == list(bench.OPTIMISERS)
        for name, points in drawn.items():
            rows = sorted((r for r in result["rows"] if r["optimiser"] == name), key=lambda r: r["budget"])
            assert points == [(1e3 * r["median_plan_seconds"], r["success"][k]["success_rate"],
                               r["success"][k]["ci_low"], r["success"][k]["ci_high"]) for r in rows]


def test_plot_from_redraws_a_stored_result_and_refuses_other_files(result: dict, tmp_path, capsys) -> None:
    stored = tmp_path / "pq.json"
    stored.write_text(json.dumps({**result, "command": "x", "machine": {}}))
    assert bench.main(["--plot-from", str(stored)]) == 0
    assert (tmp_path / "pq.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"benchmark": "planner"}))
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--plot-from", str(other)])
    assert exit_.value.code == 2 and "not a result of this benchmark" in capsys.readouterr().err
    assert not (tmp_path / "other.png").exists()
