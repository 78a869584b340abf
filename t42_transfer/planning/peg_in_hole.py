"""Peg-in-hole: plan with a model, execute open loop on the true (simulated) target hand, count hits.

As in the paper, a goal is ``n`` steps away: it is where the true target hand
puts the object after a random piecewise-constant sequence of ``n`` steps from
the grasp, so every goal is reachable and farther goals (larger ``n``) test
longer open-loop predictions; goals outside the trained workspace are redrawn.
For each model and goal the planner plans from the grasp state (same reset
seed, hence the same grasp and sensor noise as when the goal was made); the plan
is executed open loop on the true hand and succeeds when the final object
centre is within ``tolerance_mm`` of the goal and the hand did not drop the
object or stop on overload.  Plans the planner refuses (no safe sequence) count
as failures; a plan predicted to miss (``unreachable``) is still executed, since
only the true hand decides success.

    t42 peg-in-hole runs/x/models/*.safetensors \\
        --workspace bags/source_small bags/target_small --out docs/peg_in_hole
"""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from t42_transfer.hand.collect import run_episode
from t42_transfer.hand.params import variant
from t42_transfer.hand.sim import GraspFailed, SimulatedHand
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.planning.planner import Planner, PlannerConfig
from t42_transfer.planning.sampling import sample_actions
from t42_transfer.planning.workspace import Workspace

GOAL_ATTEMPTS = 20
"""Goal sequences drawn per goal at most, while the true hand drops the object or ends outside the workspace."""
MAX_TRIALS = 10_000
MAX_THREADS = 1024


@dataclass(frozen=True)
class PegInHoleConfig:
    distances: tuple[int, ...] = (10, 20, 40, 60, 80, 100)
    """Goal distances in control steps from the grasp."""
    trials: int = 10
    """Goals per distance."""
    tolerance_mm: float = 10.0
    hand: str = "target"
    hold_steps: tuple[int, int] = (5, 40)
    """Holds of the goal-making sequences (the piecewise sampler's)."""
    planner: PlannerConfig = field(default_factory=lambda: PlannerConfig(horizon_search=True, tolerance_mm=3.0))
    """Plans aim tighter than the success tolerance: open-loop execution adds error."""
    seed: int = 0


@dataclass(frozen=True)
class Goal:
    steps: int
    trial: int
    seed: int
    """Reset seed of the true hand: the same grasp (and noise) for making the goal and executing the plan."""
    grasp: np.ndarray
    position: np.ndarray

    @property
    def distance_mm(self) -> float:
        return float(np.linalg.norm(self.position - self.grasp[:2]))


@dataclass(frozen=True)
class Trial:
    model: str
    steps: int
    success: bool
    status: str
    """The planner's status."""
    end_reason: str
    """How execution ended: 'length', 'dropped', ..., or 'not_executed'."""
    goal_distance_mm: float
    final_error_mm: float | None
    predicted_error_mm: float | None
    plan_steps: int


@dataclass(frozen=True)
class Row:
    model: str
    steps: int
    trials: int
    successes: int
    success_rate: float
    goal_distance_mm: float
    """Mean straight-line distance of the goals from the grasp."""
    final_error_mm: float | None
    """Median true final error over executed plans."""
    predicted_ok: int
    """Plans predicted to reach the goal (status ok)."""
    refused: int
    """Plans the planner refused (nothing executed)."""


def make_goals(cfg: PegInHoleConfig, workspace: Workspace | None = None) -> list[Goal]:
    """``cfg.trials`` goals per distance, made on the true hand; deterministic in ``cfg.seed``.

    With a ``workspace``, goals outside it are redrawn: every planner would refuse
    them, so they would measure the training data's coverage, not the models.
    """
    hand = SimulatedHand(cfg.hand)
    goals = []
    for steps in cfg.distances:
        for trial in range(cfg.trials):
            goals.append(_make_goal(hand, cfg, steps, trial, workspace))
    return goals


def _make_goal(hand: SimulatedHand, cfg: PegInHoleConfig, steps: int, trial: int, workspace: Workspace | None) -> Goal:
    seeds = (int(np.random.SeedSequence([cfg.seed, steps, trial, attempt]).generate_state(1)[0])
             for attempt in range(GOAL_ATTEMPTS))
    return reachable_goal(hand, steps, cfg.hold_steps, seeds, workspace, trial=trial)


def reachable_goal(
    hand: SimulatedHand, steps: int, hold_steps: tuple[int, int], action_seeds: Iterable[int],
    workspace: Workspace | None = None, grasp_seed: int | None = None, trial: int = 0, settle_steps: int = 0,
) -> Goal:
    """The first goal ``steps`` away that the true hand reaches without a drop (inside ``workspace``).

    Each attempt samples a piecewise-constant sequence from the next action seed and
    runs it from a grasp made with ``grasp_seed`` (a driver's reset seed), or with
    the action seed itself when None.  With ``settle_steps`` the hand first holds
    still that long (the object sinks into the fingers after a grasp); the goal's
    ``grasp`` is then the settled state, where a plan that starts later begins.
    """
    tried = 0
    for seed in action_seeds:
        tried += 1
        grasp_with = seed if grasp_seed is None else grasp_seed
        actions = sample_actions("piecewise", 1, steps, torch.Generator().manual_seed(seed), hold_steps)[0].numpy()
        try:
            traj = run_episode(hand, np.concatenate([np.zeros((settle_steps, actions.shape[1])), actions]), grasp_with)
        except GraspFailed:
            continue
        start = traj.states[min(settle_steps, len(traj.states) - 1)].astype(np.float64)
        goal = Goal(steps, trial, grasp_with, start, traj.states[-1, :2].astype(np.float64))
        inside = workspace is None or bool(workspace.contains_xy(torch.as_tensor(goal.position)))
        if traj.end_reason == "length" and len(traj) == settle_steps + steps and inside:
            return goal
    raise RuntimeError(
        f"no goal {steps} steps away without a drop (inside the workspace) in {tried} attempts (trial {trial})"
    )


def run_trial(name: str, planner: Planner, hand: SimulatedHand, goal: Goal, tolerance_mm: float) -> Trial:
    """Plan from the goal's grasp, execute open loop on ``hand``, and score the end."""
    plan = planner.plan(goal.grasp, goal.position, seed=goal.seed)
    predicted = None if np.isinf(plan.error_mm) else plan.error_mm
    if len(plan.actions) == 0:
        return Trial(name, goal.steps, False, plan.status, "not_executed", goal.distance_mm, None, predicted, 0)
    traj = run_episode(hand, plan.actions.astype(np.float64), goal.seed)
    error = float(np.linalg.norm(traj.states[-1, :2] - goal.position))
    completed = traj.end_reason == "length" and len(traj) == len(plan.actions)
    return Trial(
        name,
        goal.steps,
        completed and error <= tolerance_mm,
        plan.status,
        traj.end_reason,
        goal.distance_mm,
        error,
        predicted,
        len(plan.actions),
    )


def evaluate(
    models: Mapping[str, LatentDynamics],
    workspace: Workspace,
    cfg: PegInHoleConfig = PegInHoleConfig(),
    goals: Sequence[Goal] | None = None,
    progress: bool = True,
) -> tuple[list[Row], list[Trial]]:
    """Success rate per model and distance (rows), and every trial; all models face the same goals."""
    from tqdm.auto import tqdm

    goals = list(goals) if goals is not None else make_goals(cfg, workspace)
    hand = SimulatedHand(cfg.hand)
    trials = []
    with tqdm(total=len(models) * len(goals), desc="peg-in-hole", unit="plan", disable=not progress) as bar:
        for name, model in models.items():
            planner = Planner(model, workspace, cfg.planner)
            for goal in goals:
                trials.append(run_trial(name, planner, hand, goal, cfg.tolerance_mm))
                bar.update()
    return summarise(trials), trials


def summarise(trials: Sequence[Trial]) -> list[Row]:
    """One row per (model, distance), in the order first seen."""
    groups: dict[tuple[str, int], list[Trial]] = {}
    for t in trials:
        groups.setdefault((t.model, t.steps), []).append(t)
    rows = []
    for (name, steps), group in groups.items():
        successes = sum(t.success for t in group)
        errors = [t.final_error_mm for t in group if t.final_error_mm is not None]
        rows.append(
            Row(
                model=name,
                steps=steps,
                trials=len(group),
                successes=successes,
                success_rate=successes / len(group),
                goal_distance_mm=float(np.mean([t.goal_distance_mm for t in group])),
                final_error_mm=float(np.median(errors)) if errors else None,
                predicted_ok=sum(t.status == "ok" for t in group),
                refused=sum(t.end_reason == "not_executed" for t in group),
            )
        )
    return rows


def markdown_table(rows: Sequence[Row]) -> str:
    head = (
        "| model | goal steps | goal distance mm | trials | success rate | median final error mm | predicted ok | refused |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| {r.model} | {r.steps} | {r.goal_distance_mm:.1f} | {r.trials} | {r.success_rate:.0%} "
        f"| {'-' if r.final_error_mm is None else f'{r.final_error_mm:.1f}'} | {r.predicted_ok} | {r.refused} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def plot_success(rows: Sequence[Row], path: Path, tolerance_mm: float | None = None) -> Path:
    """Success rate against goal distance (steps), one line per model."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name in dict.fromkeys(r.model for r in rows):
        mine = sorted((r for r in rows if r.model == name), key=lambda r: r.steps)
        ax.plot([r.steps for r in mine], [r.success_rate for r in mine], marker="o", label=name)
    ax.set_xlabel("goal distance (control steps from the grasp)")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.03, 1.03)
    ax.set_title("Peg-in-hole, open loop" + (f" (tolerance {tolerance_mm:g} mm)" if tolerance_mm else ""), fontsize=10)
    ax.legend(fontsize=7)
    return save(fig, path)


def load_models(paths: Sequence[str]) -> tuple[dict[str, LatentDynamics], Workspace | None]:
    """Models from files given as ``PATH`` (named by the file's stem) or ``NAME=PATH``, and the
    workspace the first of them stores (None when it stores none)."""
    from t42_transfer.models.checkpoint import load_model

    models, workspace = {}, None
    for spec in paths:
        name, file = _model_spec(spec)
        models[name], meta = load_model(file)
        workspace = workspace or Workspace.from_metadata(meta)
    return models, workspace


def _model_spec(spec: str) -> tuple[str, Path]:
    """``NAME=PATH`` or ``PATH`` (named by the file's stem) as (name, path)."""
    name, _, file = spec.partition("=") if "=" in spec else ("", "", spec)
    return name or Path(file).stem, Path(file)


def main(argv: Sequence[str] | None = None) -> int:
    from t42_transfer.cli import (
        MAX_HORIZON,
        MAX_SAMPLES,
        SEED_MAX,
        OneLineParser,
        check_plan_size,
        existing_dir,
        existing_file,
        float_arg,
        int_arg,
        output_dir,
    )
    from t42_transfer.data.bag_io import read_bag

    parser = OneLineParser(prog="t42 peg-in-hole", description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", help="model files, PATH or NAME=PATH")
    parser.add_argument(
        "--workspace", nargs="+", type=Path, default=None,
        help="bags whose states define the trained workspace (default: the one the first model file stores)"
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for peg_in_hole.{json,md,png}")
    parser.add_argument("--distances", nargs="+", type=int_arg(1, MAX_HORIZON), default=list(PegInHoleConfig.distances))
    parser.add_argument("--trials", type=int_arg(1, MAX_TRIALS), default=PegInHoleConfig.trials)
    parser.add_argument("--tolerance", type=float_arg(0, low_open=True), default=PegInHoleConfig.tolerance_mm,
                        help="success tolerance (mm)")
    parser.add_argument("--samples", type=int_arg(1, MAX_SAMPLES), default=PlannerConfig.samples)
    parser.add_argument("--horizon", type=int_arg(1, MAX_HORIZON), default=PlannerConfig.horizon)
    parser.add_argument("--hand", default="target")
    parser.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    parser.add_argument("--threads", type=int_arg(1, MAX_THREADS), default=1,
                        help="torch threads (default 1: robust on a busy machine)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    # Everything the user gave is checked before a model is loaded or a goal made.
    check_plan_size(args.samples, args.horizon)
    variant(args.hand)
    for spec in args.models:
        existing_file(_model_spec(spec)[1])
    for bag in args.workspace or []:
        existing_dir(bag)
    output_dir(args.out)
    torch.set_num_threads(args.threads)

    models, stored = load_models(args.models)
    if args.workspace:
        workspace = Workspace.from_trajectories(t for bag in args.workspace for t in read_bag(bag))
    elif stored is not None:
        workspace = stored
    else:
        parser.error(f"{args.models[0]} stores no workspace: pass --workspace BAG ... (the models' training data)")
    planner = replace(PegInHoleConfig().planner, samples=args.samples, horizon=args.horizon)
    cfg = PegInHoleConfig(
        tuple(args.distances), args.trials, args.tolerance, args.hand, planner=planner, seed=args.seed
    )
    rows, trials = evaluate(models, workspace, cfg, progress=not args.quiet)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {
        "command": shlex.join([*parser.prog.split(), *(sys.argv[1:] if argv is None else argv)]),
        "config": asdict(cfg),
        "workspace": workspace.to_dict(),
        "rows": [asdict(r) for r in rows],
        "trials": [asdict(t) for t in trials],
    }
    (args.out / "peg_in_hole.json").write_text(json.dumps(report, indent=2) + "\n")
    table = markdown_table(rows)
    (args.out / "peg_in_hole.md").write_text(table)
    plot_success(rows, args.out / "peg_in_hole.png", cfg.tolerance_mm)
    print(table)
    print(f"wrote {args.out / 'peg_in_hole.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    from t42_transfer.cli import main as t42_main  # one-line errors, as `t42 peg-in-hole`

    sys.exit(t42_main(["peg-in-hole", *sys.argv[1:]]))
