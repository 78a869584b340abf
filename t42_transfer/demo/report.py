"""The demo's report: planned vs executed paths, the goal and round tables, and report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from t42_transfer.demo.goals import GoalRun
from t42_transfer.demo.settings import TOLERANCE_MM

DOING_NOTHING = {"sim": "on the same grasps (a copy of the hand grasped with the driver's seed, held still)",
                 "camera": "on the same grasps (a copy of the hand grasped with the driver's seed, held still)",
                 "emulated": "on the same grasps (the object left where it settled: goals lie at least twice the "
                             "tolerance from there)"}
HELDOUT = {"sim": "", "emulated": " (collected on the same simulated hand directly, not through the servo bus)",
           "camera": " (collected on the same simulated hand directly, with its true poses)"}
JUDGED = {"sim": "", "emulated": " Final errors are the simulator's true pose (sim/object_pose).",
          "camera": " Final errors are the simulator's true pose (sim/object_pose), not the tracked one the suite "
                    "planned from; each goal was also run again from the same grasp with the simulator's pose "
                    "(unrecorded), to show what the camera costs."}


def plot_paths(runs: list[GoalRun], path: Path, hand: str = "the simulated target hand") -> Path:
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    cols = min(4, max(1, len(runs)))
    rows = (len(runs) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax, run in zip(axes.flat, runs, strict=False):
        if run.planned:
            planned = np.asarray(run.planned)
            ax.plot(planned[:, 0], planned[:, 1], "--", color="tab:blue", label="planned")
        if run.executed:
            executed = np.asarray(run.executed)
            ax.plot(executed[:, 0], executed[:, 1], "-", color="tab:orange", label="executed")
        ax.plot(*run.start_mm, "ko", ms=4, label="start")
        ax.add_patch(plt.Circle(run.goal_mm, TOLERANCE_MM, color="tab:green", alpha=0.2))
        ax.plot(*run.goal_mm, "g*", ms=10, label="goal")
        verdict = run.verdict if run.accepted else "refused"
        error = "" if run.error_mm is None else f", {run.error_mm:.1f} mm"
        ax.set_title(f"round {run.round}, {run.steps} steps: {verdict}{error}", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(runs):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"peg-in-hole on {hand} (tolerance {TOLERANCE_MM:g} mm)", fontsize=10)
    return save(fig, path)


def goal_table(runs: list[GoalRun]) -> str:
    again = any(run.sim_pose_verdict for run in runs)
    lines = ["| round | goal | steps | start->goal mm | plan | predicted mm | final error mm | end | verdict "
             "| doing nothing: error mm |" + (" with the simulator's pose: error mm |" if again else ""),
             "|---:|---:|---:|---:|---|---:|---:|---|---|---:|" + ("---:|" if again else "")]
    for k, run in enumerate(runs):
        predicted = "" if run.predicted_error_mm is None else f"{run.predicted_error_mm:.1f}"
        error = "" if run.error_mm is None else f"{run.error_mm:.1f}"
        plan = f"{run.horizon} steps" if run.accepted else f"refused ({run.status})"
        line = (f"| {run.round} | {k + 1} | {run.steps} | {run.start_distance_mm:.1f} | {plan} | {predicted} "
                f"| {error} | {run.end} | {run.verdict} | {run.still_error_mm:.1f} ({run.still_verdict}) |")
        if again:
            sim_error = "" if run.sim_pose_error_mm is None else f"{run.sim_pose_error_mm:.1f} "
            line += f" {sim_error}({run.sim_pose_verdict}) |"
        lines.append(line)
    return "\n".join(lines)


def rounds_table(rounds: list[dict[str, Any]]) -> str:
    """Per round: success against doing nothing, and divergence on the held-out episodes against the baselines."""
    again = any("sim_pose_hits" in r for r in rounds)
    lines = ["| round | target episodes used | goals hit | doing nothing hits | "
             + ("the same goals with the simulator's pose | " if again else "")
             + "held-out divergence, model (steps) | source alone | hold still |",
             "|---:|---:|---|---|" + ("---|" if again else "") + "---:|---:|---:|"]
    for r in rounds:
        d = r["heldout"]
        sim_pose = f"{r['sim_pose_hits']}/{r['goals']} | " if again else ""
        lines.append(f"| {r['round']} | {r['episodes']} | {r['hits']}/{r['goals']} | {r['still_hits']}/{r['goals']} "
                     f"| {sim_pose}{d['model']:.1f} | {d['source']:.1f} | {d['hold_still']:.1f} |")
    return "\n".join(lines)


def executed_plans_section(plans: dict[str, Any] | None) -> list[str]:
    """The report's lines on each round's model scored on the last round's executed plans (none: no lines)."""
    if not plans:
        return []
    if not plans["scores"]:
        return ["## The models on executed plans", "", f"Nothing to score: {plans['why']}.", ""]
    lines = ["## The models on executed plans", "",
             f"Divergence (4 mm) and position MSE of each round's model on round {plans['round']}'s executed goal "
             f"episodes ({plans['episodes']}, from each one's first command), which no model trained on: the regime "
             "the planner uses, which random-action held-out episodes do not show (docs/evaluation.md, section 9).",
             "", "| model | divergence (steps) | position MSE (mm²) |", "|---|---:|---:|"]
    lines += [f"| {name} | {s['divergence_steps']:.1f} | {s['position_mse_mm2']:.2f} |"
              for name, s in plans["scores"].items()]
    return [*lines, ""]


def write_report(run_dir: Path, summary: dict[str, Any], runs: list[GoalRun]) -> Path:
    lines = [
        "# t42 demo",
        "",
        f"Run {run_dir.name}: {summary['mode']}; suite of rclpy nodes over {summary['middleware']} on ROS domain "
        f"{summary['domain']} (discovery {summary['discovery']}).",
        "",
        "## Data and transfer",
        "",
        f"- Hand: `{summary['driver']}` ({summary['hardware']}); the object pose from {summary['pose_source']}.",
        f"- Source model: `{summary['source_model']}`.",
        f"- Target data: {summary['exploration']['bags']} explored episode bags recorded through topics in `bags/`, "
        "then each goal's episode.",
        *(f"- Round {r['round']}: the `/t42/transfer` action goal ended in {r['transfer']['seconds']:.1f} s: "
          f"{r['transfer']['message']}" for r in summary["rounds"]),
        "",
        "## Rounds",
        "",
        f"Goals hit within {TOLERANCE_MM:g} mm (open loop; completed, at least half way, within the tolerance), "
        f"doing nothing scored by the same rule {DOING_NOTHING[summary['hardware']]}, and the divergence time "
        f"(4 mm) of each round's model on {summary['heldout']['episodes']} held-out target episodes the suite never "
        f"saw{HELDOUT[summary['hardware']]}.{JUDGED[summary['hardware']]}",
        "",
        rounds_table(summary["rounds"]),
        "",
        *executed_plans_section(summary.get("executed_plans")),
        "## Peg-in-hole goals",
        "",
        goal_table(runs),
        "",
        "![planned vs executed paths](paths.png)",
        "",
    ]
    path = run_dir / "report.md"
    path.write_text("\n".join(lines))
    return path
