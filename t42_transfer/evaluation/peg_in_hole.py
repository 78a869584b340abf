"""Peg-in-hole: plan with a model, execute on the true (simulated) target hand, and judge honestly.

As in the paper, a goal is ``n`` steps away: where the true target hand puts the
object after a random piecewise-constant sequence of ``n`` steps from the grasp,
so every goal is reachable.  Goals outside the trained workspace are redrawn,
and so are goals nearer than ``min_distance_factor`` times the largest
tolerance to the start or to where the object ends when the hand holds still
for ``n`` steps: a freshly grasped object sinks into the fingers (about 30 mm
in 80 steps on the simulated hands), so a plan that does nothing would hit
goals in that direction.  Each contender plans from the goal's
grasp (same reset seed, hence the same grasp and sensor noise as when the goal
was made); the plan runs on the true hand, open loop by default or replanning
every k steps (``replan_every``).  A trial succeeds at tolerance ``tol`` when
(see :func:`verdict`) the sequence ran to its end, the object moved at least
half way towards the goal, and the final object centre is within ``tol``.

Plans have exactly ``n`` steps by default (``plan_length="fixed"``): the
paper's horizon axis, since goal ``n`` then tests an ``n``-step open-loop
prediction; ``"search"`` keeps the shortest plan predicted to reach the goal.
Every evaluation carries two baselines on the same goals: ``do_nothing`` (``n``
zero actions; scores 0 by construction of the goals) and ``oracle`` (the same
planner with the true hand as its model, :mod:`~t42_transfer.planning.oracle`).

    t42 peg-in-hole runs/x/models/*.safetensors --out docs/experiments/peg_in_hole
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from t42_transfer.conventions import ACTION_DIM, ACTION_UNIT_RAD, PLAN_LENGTHS
from t42_transfer.evaluation.stats import wilson_interval
from t42_transfer.hand.collect import Settled, run_episode, run_settled, settle
from t42_transfer.hand.sim import GraspFailed, SimulatedHand
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.planning.execution import Execution, execute
from t42_transfer.planning.oracle import HandRollout
from t42_transfer.planning.planner import Plan, Planner, PlannerConfig
from t42_transfer.planning.sampling import sample_actions
from t42_transfer.planning.workspace import Workspace

GOAL_ATTEMPTS = 50
"""Goal sequences drawn per goal at most, while the true hand drops the object, ends outside the
workspace or too near the start."""
DO_NOTHING, ORACLE = "do_nothing", "oracle"
BASELINES = (DO_NOTHING, ORACLE)
VERDICTS = ("hit", "miss", "no_progress", "incomplete")
HELD_STILL_KEPT = 256
"""Hold-still ends kept by :func:`held_still` (the oldest goes first)."""
_held_still: dict[tuple[object, int, int], np.ndarray] = {}


@dataclass(frozen=True)
class PegInHoleConfig:
    distances: tuple[int, ...] = (20, 40, 80)
    """Goal distances in control steps from the grasp."""
    trials: int = 30
    """Goals per distance."""
    tolerances_mm: tuple[float, ...] = (10.0, 4.0)
    """Success tolerances; the first is the paper's (10 mm)."""
    min_distance_factor: float = 2.0
    """Goals lie at least this many times the largest tolerance from the start."""
    hand: str = "target"
    hold_steps: tuple[int, int] = (5, 40)
    """Holds of the goal-making sequences (the piecewise sampler's)."""
    plan_length: str = "fixed"
    """``fixed``: plans of exactly ``n`` steps for goal ``n``; ``search``: the shortest predicted to reach it."""
    replan_every: int = 0
    """0: open loop (the paper's setting); k: replan from the measured state every k steps (MPC)."""
    planner: PlannerConfig = field(default_factory=lambda: PlannerConfig(tolerance_mm=3.0))
    """Search mode aims tighter than the success tolerance: open-loop execution adds error."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.plan_length not in PLAN_LENGTHS:
            raise ValueError(f"plan_length must be one of {PLAN_LENGTHS}, got {self.plan_length!r}")
        if self.replan_every < 0 or (self.replan_every and self.plan_length != "fixed"):
            raise ValueError("replan_every must be >= 0, and replanning needs fixed-length plans")
        if not self.tolerances_mm or min(self.tolerances_mm) <= 0:
            raise ValueError(f"tolerances must be positive, got {self.tolerances_mm}")

    @property
    def min_distance_mm(self) -> float:
        return self.min_distance_factor * max(self.tolerances_mm)


@dataclass(frozen=True)
class Goal:
    steps: int
    trial: int
    seed: int
    """Reset seed of the true hand: the same grasp (and noise) for making the goal and executing the plan."""
    grasp: np.ndarray
    position: np.ndarray
    still: np.ndarray | None = None
    """Where the object ends when the hand holds still for ``steps`` (same grasp and noise)."""

    @property
    def distance_mm(self) -> float:
        return float(np.linalg.norm(self.position - self.grasp[:2]))

    @property
    def still_distance_mm(self) -> float | None:
        return None if self.still is None else float(np.linalg.norm(self.position - self.still))


@dataclass(frozen=True)
class Contender:
    """Something that plans peg-in-hole goals: a model (or an ensemble), a baseline, open or closed loop."""

    name: str
    models: tuple[LatentDynamics, ...] = ()
    """Empty for the baselines."""
    baseline: str = ""
    """``do_nothing`` or ``oracle`` for a baseline, else ''."""
    planner: PlannerConfig | None = None
    """The contender's own planner settings (default: the evaluation's)."""
    replan_every: int | None = None
    """Its own execution mode (default: the evaluation's)."""


@dataclass(frozen=True)
class Trial:
    model: str
    steps: int
    trial: int
    status: str
    """The (first) plan's status; ``do_nothing`` for that baseline."""
    end_reason: str
    """How execution ended: 'length', 'dropped', ..., 'refused' (nothing to execute)."""
    goal_distance_mm: float
    final_error_mm: float | None
    """Distance of the final object centre from the goal; None when nothing was executed."""
    progress_mm: float | None
    """How far the object moved towards the goal (along the start-goal line)."""
    predicted_error_mm: float | None
    plan_steps: int
    """Actions executed."""
    plans: int
    """Plans made (1 open loop; more with replanning)."""
    plan_seconds: float

    @property
    def completed(self) -> bool:
        return self.end_reason == "length"

    def verdict(self, tolerance_mm: float) -> str:
        return verdict(self.goal_distance_mm, self.final_error_mm, self.progress_mm, self.completed, tolerance_mm)

    def success(self, tolerance_mm: float) -> bool:
        return self.verdict(tolerance_mm) == "hit"


def verdict(
    goal_distance_mm: float, final_error_mm: float | None, progress_mm: float | None, completed: bool,
    tolerance_mm: float,
) -> str:
    """``hit`` only when the run completed, the object moved at least half way towards the goal and ended
    within the tolerance; else why not (``incomplete``, ``no_progress``, ``miss``)."""
    if not completed or final_error_mm is None or progress_mm is None:
        return "incomplete"
    if progress_mm < 0.5 * goal_distance_mm:
        return "no_progress"
    return "hit" if final_error_mm <= tolerance_mm else "miss"


def progress_towards(start_xy: np.ndarray, goal_xy: np.ndarray, final_xy: np.ndarray) -> float:
    """Displacement of the object projected on the start-to-goal direction (mm)."""
    line = np.asarray(goal_xy, float) - np.asarray(start_xy, float)
    length = float(np.linalg.norm(line))
    if length == 0.0:
        return 0.0
    return float(np.dot(np.asarray(final_xy, float) - start_xy, line) / length)


@dataclass(frozen=True)
class Row:
    model: str
    steps: int
    tolerance_mm: float
    trials: int
    successes: int
    success_rate: float
    ci_low: float
    ci_high: float
    """95 % Wilson interval of the success rate."""
    goal_distance_mm: float
    """Median straight-line distance of the goals from the grasp."""
    final_error_mm: float | None
    """Median true final error over executed plans."""
    relative_error: float | None
    """Median of final error / goal distance (1: no closer than the start; 0: in the hole)."""
    verdicts: dict[str, int]
    """Trials per verdict (hit, miss, no_progress, incomplete)."""


def summarise(trials: Sequence[Trial], tolerances_mm: Sequence[float] = (10.0,)) -> list[Row]:
    """One row per (model, distance, tolerance), models in the order first seen."""
    groups: dict[tuple[str, int], list[Trial]] = {}
    for t in trials:
        groups.setdefault((t.model, t.steps), []).append(t)
    rows = []
    for (name, steps), group in groups.items():
        errors = [t.final_error_mm for t in group if t.final_error_mm is not None]
        relative = [t.final_error_mm / t.goal_distance_mm for t in group if t.final_error_mm is not None]
        for tol in tolerances_mm:
            verdicts = [t.verdict(tol) for t in group]
            successes = verdicts.count("hit")
            low, high = wilson_interval(successes, len(group))
            rows.append(
                Row(
                    model=name, steps=steps, tolerance_mm=float(tol), trials=len(group), successes=successes,
                    success_rate=successes / len(group), ci_low=low, ci_high=high,
                    goal_distance_mm=float(np.median([t.goal_distance_mm for t in group])),
                    final_error_mm=float(np.median(errors)) if errors else None,
                    relative_error=float(np.median(relative)) if relative else None,
                    verdicts={v: verdicts.count(v) for v in VERDICTS},
                )
            )
    return rows


def make_goals(cfg: PegInHoleConfig, workspace: Workspace | None = None) -> list[Goal]:
    """``cfg.trials`` goals per distance, made on the true hand; deterministic in ``cfg.seed``.

    With a ``workspace``, goals outside it are redrawn: every planner would refuse
    them, so they would measure the training data's coverage, not the models.
    """
    hand = SimulatedHand(cfg.hand)
    goals = []
    for steps in cfg.distances:
        for trial in range(cfg.trials):
            seeds = (int(np.random.SeedSequence([cfg.seed, steps, trial, attempt]).generate_state(1)[0])
                     for attempt in range(GOAL_ATTEMPTS))
            goals.append(reachable_goal(hand, steps, cfg.hold_steps, seeds, workspace, trial=trial,
                                        min_distance_mm=cfg.min_distance_mm))
    return goals


class NoGoal(ValueError):
    """No attempt of :func:`reachable_goal` made a goal (its action seeds ran out): the settings admit none."""


def reachable_goal(
    hand: SimulatedHand, steps: int, hold_steps: tuple[int, int], action_seeds: Iterable[int],
    workspace: Workspace | None = None, grasp_seed: int | None = None, trial: int = 0, settle_steps: int = 0,
    min_distance_mm: float = 0.0,
) -> Goal:
    """The first goal ``steps`` away that the true hand reaches without a drop (inside ``workspace``, at least
    ``min_distance_mm`` from the start and from where holding still ends).

    Each attempt samples a piecewise-constant sequence from the next action seed and
    runs it from a grasp made with ``grasp_seed`` (a driver's reset seed), or with
    the action seed itself when None.  With ``settle_steps`` the hand first holds
    still that long (the object sinks into the fingers after a grasp); the goal's
    ``grasp`` is then the settled state, where a plan that starts later begins.
    """
    tried = 0
    settled: Settled | None = None
    """One grasp for every attempt (``grasp_seed``): its settling simulated once, each attempt going on from it."""
    for seed in action_seeds:
        tried += 1
        grasp_with = seed if grasp_seed is None else grasp_seed
        actions = sample_actions("piecewise", 1, steps, torch.Generator().manual_seed(seed), hold_steps)[0].numpy()
        try:
            if grasp_seed is not None and settle_steps:
                settled = settled or settle(hand, grasp_seed, settle_steps)
                traj = run_settled(hand, settled, actions)
            else:
                traj = run_episode(hand, np.concatenate([np.zeros((settle_steps, actions.shape[1])), actions]),
                                   grasp_with)
        except GraspFailed:
            continue
        if traj.end_reason != "length" or len(traj) != settle_steps + steps:
            continue
        start = traj.states[min(settle_steps, len(traj.states) - 1)].astype(np.float64)
        still = held_still(hand, grasp_with, settle_steps + steps) if min_distance_mm > 0 else None
        goal = Goal(steps, trial, grasp_with, start, traj.states[-1, :2].astype(np.float64), still)
        inside = workspace is None or bool(workspace.contains_xy(torch.as_tensor(goal.position)))
        far = goal.distance_mm >= min_distance_mm and (still is None or goal.still_distance_mm >= min_distance_mm)
        if inside and far:
            return goal
    raise NoGoal(
        f"no goal {steps} steps away without a drop (inside the workspace, at least {min_distance_mm:g} mm from the "
        f"start and from where holding still ends) in {tried} attempts (trial {trial})"
    )


def held_still(hand: SimulatedHand, grasp_seed: int, steps: int) -> np.ndarray:
    """Where the object ends when ``hand`` holds still for ``steps`` from the grasp made with ``grasp_seed``.

    Simulated once per hand model, seed and length, however many goal attempts share a grasp: each reset
    reseeds the hand's noise and places the object anew, so the run is the same every time.
    """
    key = (hand.params, grasp_seed, steps)
    still = _held_still.get(key)
    if still is None:
        held = run_episode(hand, np.zeros((steps, ACTION_DIM)), grasp_seed)
        still = held.states[-1, :2].astype(np.float64)
        if len(_held_still) >= HELD_STILL_KEPT:
            del _held_still[next(iter(_held_still))]
        _held_still[key] = still
    return still.copy()


def run_trial(
    contender: Contender, workspace: Workspace, hand: SimulatedHand, goal: Goal, cfg: PegInHoleConfig,
    oracle_hand: SimulatedHand | None = None,
) -> Trial:
    """Plan from the goal's grasp, execute on ``hand`` (open loop or replanning), and record the end."""
    replan = cfg.replan_every if contender.replan_every is None else contender.replan_every
    pcfg = contender.planner or cfg.planner
    fixed = cfg.plan_length == "fixed"
    pcfg = replace(pcfg, horizon_search=not fixed, horizon=goal.steps if fixed else pcfg.horizon)
    hand.reset(goal.seed)
    seconds = 0.0

    if contender.baseline == DO_NOTHING:
        run = execute(hand, lambda state, left, _: _still(state, goal, left), goal.steps)
        return _trial(contender.name, goal, run, "do_nothing", None, 0.0)
    if contender.baseline == ORACLE:
        oracle = oracle_hand or SimulatedHand(cfg.hand)

        def planner_now() -> Planner:
            return Planner(HandRollout(oracle, hand.snapshot()), workspace, pcfg)
    elif contender.baseline:
        raise ValueError(f"unknown baseline {contender.baseline!r}; known: {BASELINES}")
    else:
        planner = Planner(contender.models if len(contender.models) > 1 else contender.models[0], workspace, pcfg)

        def planner_now() -> Planner:
            return planner

    def plan_at(state: np.ndarray, left: int, previous: np.ndarray) -> Plan:
        nonlocal seconds
        begin = time.perf_counter()
        plan = planner_now().plan(state, goal.position, seed=goal.seed, horizon=left if fixed else None,
                                  previous=previous)
        seconds += time.perf_counter() - begin
        return plan

    if fixed:
        run = execute(hand, plan_at, goal.steps, replan)
    else:
        first = plan_at(hand.state, pcfg.horizon, np.zeros((0, ACTION_DIM)))
        run = execute(hand, lambda state, left, _: first, max(1, len(first.actions)))
    first_plan = run.plans[0]
    predicted = None if np.isinf(first_plan.error_mm) else first_plan.error_mm
    return _trial(contender.name, goal, run, first_plan.status, predicted, seconds)


def _still(state: np.ndarray, goal: Goal, steps: int) -> Plan:
    """The do-nothing plan: ``steps`` zero actions, predicted to leave the object where it is."""
    predicted = np.repeat(np.asarray(state, np.float32)[None], steps + 1, axis=0)
    error = float(np.linalg.norm(predicted[-1, :2] - goal.position))
    return Plan(False, "do_nothing", "holds still", np.zeros((steps, 2), np.float32), predicted, error,
                goal.position.astype(np.float32))


def _trial(name: str, goal: Goal, run: Execution, status: str, predicted: float | None, seconds: float) -> Trial:
    executed = len(run.actions) > 0
    final = run.states[-1, :2]
    return Trial(
        model=name, steps=goal.steps, trial=goal.trial, status=status, end_reason=run.end_reason,
        goal_distance_mm=goal.distance_mm,
        final_error_mm=float(np.linalg.norm(final - goal.position)) if executed else None,
        progress_mm=progress_towards(goal.grasp[:2], goal.position, final) if executed else None,
        predicted_error_mm=predicted, plan_steps=len(run.actions), plans=len(run.plans), plan_seconds=seconds,
    )


def evaluate(
    contenders: Sequence[Contender] | Mapping[str, LatentDynamics],
    workspace: Workspace,
    cfg: PegInHoleConfig = PegInHoleConfig(),
    goals: Sequence[Goal] | None = None,
    progress: bool = True,
    baselines: Sequence[str] = BASELINES,
) -> tuple[list[Row], list[Trial]]:
    """Rows per contender, distance and tolerance, and every trial; all contenders face the same goals.

    ``contenders`` may be a mapping of name to model (one open-loop contender each); the ``baselines``
    are added first.
    """
    from t42_transfer.progress import progress_bar

    if isinstance(contenders, Mapping):
        contenders = [Contender(name, (model,)) for name, model in contenders.items()]
    everyone = [Contender(b, baseline=b) for b in baselines] + list(contenders)
    named = [c.name for c in everyone]
    if twice := sorted({n for n in named if named.count(n) > 1}):  # rows and trials are keyed by name
        raise ValueError(f"contender name(s) {twice} given twice (the baselines are {list(baselines)}); name each "
                         "model file NAME=PATH")
    goals = list(goals) if goals is not None else make_goals(cfg, workspace)
    hand, oracle_hand = SimulatedHand(cfg.hand), SimulatedHand(cfg.hand)
    trials = []
    with progress_bar(total=len(everyone) * len(goals), desc="peg-in-hole", unit="goal", disable=not progress) as bar:
        for contender in everyone:
            bar.set_postfix_str(contender.name)
            for goal in goals:
                trials.append(run_trial(contender, workspace, hand, goal, cfg, oracle_hand))
                bar.update()
    return summarise(trials, cfg.tolerances_mm), trials


def load_models(paths: Sequence[str]) -> tuple[dict[str, LatentDynamics], dict]:
    """Models from files given as ``PATH`` (named by the file's stem) or ``NAME=PATH``, and the first file's
    metadata (its stored workspace is the default one)."""
    from t42_transfer.evaluation.model_files import check_action_unit
    from t42_transfer.models.checkpoint import load_model

    models, first = {}, None
    for spec in paths:
        name, file = model_spec(spec)
        models[name], meta = load_model(file)
        check_action_unit(file, meta, ACTION_UNIT_RAD, "the simulated hands")
        first = meta if first is None else first
    return models, first or {}


def model_spec(spec: str) -> tuple[str, Path]:
    """``NAME=PATH`` or ``PATH`` (named by the file's stem) as (name, path)."""
    name, _, file = spec.partition("=") if "=" in spec else ("", "", spec)
    return name or Path(file).stem, Path(file)


def contenders_for(
    models: Mapping[str, LatentDynamics], planner: PlannerConfig, mpc: int = 0, dropout: int = 0,
    ensemble: Sequence[str] = (), variants_of: Sequence[str] | None = None, risk: float = 1.0,
) -> list[Contender]:
    """Every model open loop as evaluated, plus the asked-for variants of the models in ``variants_of``
    (default all): closed loop every ``mpc`` steps, ``dropout`` samples per sequence, and one ensemble."""
    out = [Contender(name, (model,)) for name, model in models.items()]
    chosen = [n for n in models if variants_of is None or n in variants_of]
    if dropout:
        dcfg = replace(planner, uncertainty="dropout", members=dropout, risk=risk)
        out += [Contender(f"{n}+dropout{dropout}", (models[n],), planner=dcfg) for n in chosen]
    if ensemble:
        missing = sorted(set(ensemble) - set(models))
        if missing or len(ensemble) < 2:
            raise ValueError(f"an ensemble needs at least two of the given models {sorted(models)}, "
                             f"got {list(ensemble)}")
        ecfg = replace(planner, uncertainty="ensemble", risk=risk)
        out.append(Contender(f"ensemble{len(ensemble)}", tuple(models[n] for n in ensemble), planner=ecfg))
    if mpc:
        out += [Contender(f"{n}+mpc{mpc}", (models[n],), replan_every=mpc) for n in chosen]
    return out
