"""Benchmark: planner quality per compute, judged on the true simulated target hand.

Writes bench/results/planner_quality.json and prints a markdown summary.  Every
optimiser solves the same problem with the same model: from a peg-in-hole
goal's grasp, choose ``steps`` actions in ``[-1, 1]^2`` (fixed length, 40 by
default) minimising the model's predicted final distance to the goal; a
sequence whose prediction is NaN, over the load limit or outside the trained
workspace at any step is unusable (cost inf; for MPPI, whose weights need
finite costs, a 1000 mm penalty).  Each plan is then executed open loop on the
true target hand (:func:`~t42_transfer.planning.execution.execute`) and judged
by :func:`~t42_transfer.evaluation.peg_in_hole.verdict` at 10 and 4 mm.  The
budget B counts B model rollouts of the whole horizon per plan:

- ``default``: the Planner with its default configuration (:class:`~t42_transfer.planning.planner.PlannerConfig`,
  the planner node's and ``t42 peg-in-hole``'s), ``samples = B / (refine_iterations + 1)`` (its refinement keeps
  the elites, so it rolls out slightly fewer than B; ``rollouts`` records how many);
- ``default_search``: the same with horizon search (the shortest prefix predicted within the tolerance), then
  holding still (zero actions) for the rest of the goal's steps: what the rule "shortest sequence, then hold"
  costs against optimising the whole fixed horizon to its final state;
- ``default_settled``: the default, its cost the predicted distance after the plan and :data:`DRIFT_STEPS` more
  steps of holding still (zero actions), where the hand has settled (the issue's "cost on the settled end
  state"); the executed plan is the same ``steps`` actions, judged at its last step like every other (each
  of its rollouts is :data:`DRIFT_STEPS` steps longer than the others' and counts as one);
- ``default_robust``: the default with the planner's perturbed copies (``PlannerConfig.perturbations =
  robust_copies``, ``perturbation_std = robust_sigma``): each sequence scored by the mean final distance
  over it and its copies with fixed action perturbations, at the same rollout budget (``samples /
  robust_copies`` sequences a round): a plan whose end is insensitive to its actions should be
  insensitive to the model's errors too;
- ``ours``: the Planner with the piecewise sampler (holds of 5-40 steps), ``samples = B``, no refinement;
- ``ours_cem``: the same with ``refine_iterations = r`` and ``samples = B / (r + 1)``, the Planner's default
  before ``default`` (until 2026-12-04);
- ``random_shooting``: the Planner with i.i.d. uniform actions (``sampler="uniform"``), ``samples = B``;
- ``cem``: a plain cross-entropy method written here: a per-step Gaussian over the sequence (mean 0, std
  ``cem_std``) clipped to the box, ``B / cem_iterations`` samples per iteration, refitted to the best 10 %
  (no elitism, no smoothing, no std floor); it returns the best sequence it evaluated.  It rolls out with
  the planner's fused path (planning/fused.py), in the planner's chunks.  The Planner's own refinement with
  ``sampler="uniform"`` is not this: it keeps the elites in the population, floors the std at 0.05 and
  starts from uniform samples;
- ``cem_mean``: the same CEM returning its last fitted mean (the mean of the last round's elites) instead of
  the best sequence it evaluated, when that mean is safe (else the best), as MPPI returns its weighted mean:
  an average of good sequences leans less on any one of the model's errors; its one extra rollout counts;
- ``mppi``: pytorch_mppi 0.9.1 ``MPPI`` as an open-loop optimiser: dynamics = the model's one-step map
  (``latent_step``, eager, under no_grad: pytorch_mppi steps a batch one step at a time, so the fused path
  does not apply), running cost 0, terminal cost = final distance to the goal (mm, + the penalty), horizon
  = steps, ``num_samples = B / mppi_iterations``, ``U_init`` zeros, then ``mppi_iterations`` calls of
  ``command(x0, shift_nominal_trajectory=False)``; the plan is the nominal sequence ``U`` clipped to the
  box, its prediction one more rollout.

The baselines' settings were tuned on goals of another seed (12 goals of seed 1, 40 steps, the
naive_finetune model) for the median predicted error at budgets 100, 300, 1000 and 3000: CEM over
std {0.3, 0.5, 1} x iterations {3, 5, 10} (std 1, 10 iterations best but at 100 rollouts, where 5 did
slightly better); MPPI over sigma {0.3, 0.5, 0.7, 1} x lambda {0.01 ... 10} x iterations {3, 5, 10}
(sigma 0.5, lambda 0.03, 10 iterations; lambda 1 and above averages the samples into near-still plans,
predicted 10-30 mm off).  The Planner's settings are its defaults (refinement: 3 rounds, best of {1, 3, 5}).

Goals, their order and every optimiser's seed are fixed (the goal's reset seed), so reruns repeat the
successes; timings vary with the machine's load, recorded before and after.  Goals x budgets x optimisers
run interleaved (per goal, every budget and optimiser in turn), so a change of load hits all alike.
``time_to_rate`` gives, per optimiser and tolerance, the smallest median planning time among budgets
whose success rate reaches each target (null: no budget did).  ``against_default`` pairs, per tolerance, each
optimiser's best budget with the default's best goal by goal (hits only one of them made, the sign test's p) and
says whether the default reaches that rate at most a third of the other's plan time (issue 23's target).

    .venv/bin/python bench/bench_planner_quality.py                  # 30 goals, budgets 30 ... 10000
    .venv/bin/python bench/bench_planner_quality.py --goals 5 --budgets 100 1000 --out /tmp/pq.json
    .venv/bin/python bench/bench_planner_quality.py --seed 1 --optimisers default --planner '{answer: elite_mean}'
    .venv/bin/python bench/bench_planner_quality.py --plot-from bench/results/planner_quality.json   # the figure only

Beside the JSON it draws ``.png``: success against median plan time per tolerance (:func:`plot`).

The model is the paper-size transferred naive_finetune model of ``t42 experiment
configs/peg_in_hole_models.yaml --out runs`` (``--model`` for another).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from t42_transfer.config import from_mapping, inline_mapping
from t42_transfer.evaluation.peg_in_hole import VERDICTS, Goal, PegInHoleConfig, make_goals, progress_towards, verdict
from t42_transfer.evaluation.stats import sign_test, wilson_interval
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.planning.execution import execute
from t42_transfer.planning.fused import make_rollout
from t42_transfer.planning.planner import CHUNK, MAX_PERTURBATIONS, Plan, Planner, PlannerConfig
from t42_transfer.planning.workspace import Workspace

RESULTS = Path(__file__).parent / "results" / "planner_quality.json"
DEFAULT_MODELS = Path("runs/peg_in_hole_models/models")
MAKE_MODELS = "t42 experiment configs/peg_in_hole_models.yaml --out runs"
OPTIMISERS = ("default", "default_search", "default_settled", "default_robust", "ours", "ours_cem", "random_shooting",
              "cem", "cem_mean", "mppi")
DRIFT_STEPS = 10
"""Steps of holding still (1 s) after a completed plan over which the object's drift is measured."""
UNSAFE_PENALTY_MM = 1000.0
"""Added to an MPPI sample's terminal cost when its prediction breaks a safety rule (MPPI needs finite costs)."""


@dataclass(frozen=True)
class Setting:
    """Everything but the model and goals that decides the results."""

    budgets: tuple[int, ...] = (30, 100, 300, 1000, 3000, 10000)
    """Model rollouts of the whole horizon per plan."""
    optimisers: tuple[str, ...] = OPTIMISERS
    tolerances_mm: tuple[float, ...] = (10.0, 4.0)
    targets: tuple[float, ...] = (0.5, 0.8)
    """Success rates whose planning time ``time_to_rate`` reports."""
    refine_iterations: int = 3
    """ours_cem: the Planner's refinement rounds."""
    cem_iterations: int = 10
    cem_elite_fraction: float = 0.1
    cem_std: float = 1.0
    """Plain CEM's initial per-step std (uniform on [-1, 1] has 0.58)."""
    mppi_iterations: int = 10
    mppi_sigma: float = 0.5
    """MPPI's per-action noise std (``noise_sigma = sigma^2 I``)."""
    mppi_lambda: float = 0.03
    """MPPI's temperature, in mm of terminal cost."""
    robust_copies: int = 3
    """default_robust: rollouts per sequence (the first unperturbed)."""
    robust_sigma: float = 0.1
    """default_robust: std of the fixed action perturbations of the other copies."""
    planner: dict[str, Any] = field(default_factory=dict)
    """PlannerConfig settings that replace the default's in the default family (``--planner '{answer:
    elite_mean}'``), to try another setting on tuning goals; empty: the default itself."""

    def __post_init__(self) -> None:
        unknown = sorted(set(self.optimisers) - set(OPTIMISERS))
        if unknown or not self.optimisers:
            raise ValueError(f"optimisers must be among {OPTIMISERS}, got {list(self.optimisers)}")
        if not self.budgets or min(self.budgets) < 2:
            raise ValueError(f"budgets must be at least 2 rollouts, got {list(self.budgets)}")
        if min(self.refine_iterations, self.cem_iterations, self.mppi_iterations, self.robust_copies) < 1:
            raise ValueError("iterations and robust_copies must be positive")
        if self.robust_copies > MAX_PERTURBATIONS or not 0 <= self.robust_sigma <= 1:
            raise ValueError(f"need robust_copies <= {MAX_PERTURBATIONS} and 0 <= robust_sigma <= 1")
        if not 0 < self.cem_elite_fraction < 1 or min(self.cem_std, self.mppi_sigma, self.mppi_lambda) <= 0:
            raise ValueError("need 0 < cem_elite_fraction < 1 and positive cem_std, mppi_sigma, mppi_lambda")


@dataclass(frozen=True)
class Outcome:
    """One optimiser's plan: the sequence (``[0, 2]`` when it found nothing safe) and what it predicts."""

    actions: np.ndarray
    predicted_error_mm: float
    """The model's predicted final distance of ``actions`` (inf when there are none)."""
    predicted_safe: bool
    """Whether that prediction keeps every safety rule (the Planner and CEM only return such sequences)."""
    rollouts: int
    """Model rollouts of the whole horizon spent."""
    status: str = ""
    """The Planner's status for its plan (``ok``, ``unreachable`` ...: what the planner node would refuse), ''
    for the other optimisers."""


@dataclass(frozen=True)
class TrialResult:
    optimiser: str
    budget: int
    trial: int
    goal_distance_mm: float
    plan_seconds: float
    rollouts: int
    predicted_error_mm: float | None
    predicted_safe: bool
    end_reason: str
    final_error_mm: float | None
    progress_mm: float | None
    verdicts: dict[str, str]
    """Verdict per tolerance (its ``g`` string: '10', '4')."""
    status: str = ""
    """The Planner's status of its plan ('' for the other optimisers)."""
    drift_mm: float | None = None
    """How far the object moved in :data:`DRIFT_STEPS` of holding still after a completed plan (the hand
    settling: what a judge after the plan's last step does not see)."""


# ------------------------------------------------------------------ optimisers


def final_costs(rollout: Callable[[Tensor, Tensor], Tensor], workspace: Workspace, x0: Tensor, goal: Tensor,
                actions: Tensor) -> Tensor:
    """Predicted final distance to ``goal`` of each ``actions[N, T, 2]`` (inf when unsafe), in the planner's chunks."""
    out = []
    for start in range(0, len(actions), CHUNK):
        chunk = actions[start : start + CHUNK]
        states = rollout(x0.expand(len(chunk), -1), chunk)  # [T + 1, n, 4]
        safe = workspace.allows(states[1:].float()).all(0)
        final = states[-1, :, :2].float() - goal
        out.append(torch.hypot(final[:, 0], final[:, 1]).masked_fill_(~safe, math.inf))
    return torch.cat(out)


def plain_cem(model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int, budget: int,
              seed: int, setting: Setting, final_mean: bool = False) -> Outcome:
    """The textbook cross-entropy method (see the module docstring); returns the best sequence evaluated, or with
    ``final_mean`` the last fitted mean when it is safe."""
    rollout = make_rollout(model)
    gen = torch.Generator().manual_seed(seed)
    per = max(2, budget // setting.cem_iterations)
    elites = max(2, int(setting.cem_elite_fraction * per))
    mean, std = torch.zeros(steps, 2), torch.full((steps, 2), setting.cem_std)
    best_cost, best = math.inf, torch.zeros(0, 2)
    for _ in range(setting.cem_iterations):
        samples = (mean + std * torch.randn(per, steps, 2, generator=gen)).clamp_(-1.0, 1.0)
        cost = final_costs(rollout, workspace, x0, goal, samples)
        i = int(torch.argmin(cost))
        if cost[i] < best_cost:
            best_cost, best = float(cost[i]), samples[i].clone()
        order = torch.argsort(cost)[:elites]
        order = order[torch.isfinite(cost[order])]
        if len(order) >= 2:
            mean, std = samples[order].mean(0), samples[order].std(0)
    rollouts = per * setting.cem_iterations
    if final_mean:
        mean_cost = float(final_costs(rollout, workspace, x0, goal, mean[None])[0])
        if math.isfinite(mean_cost):
            return Outcome(mean.numpy(), mean_cost, True, rollouts + 1)
        rollouts += 1
    return Outcome(best.numpy(), best_cost, math.isfinite(best_cost), rollouts)


def mppi_plan(model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int, budget: int,
              seed: int, setting: Setting) -> Outcome:
    """pytorch_mppi's MPPI iterated on the whole nominal sequence, which is the plan (module docstring)."""
    from pytorch_mppi import MPPI

    samples = max(2, budget // setting.mppi_iterations)
    was_training = model.training
    model.eval()

    def dynamics(z: Tensor, a: Tensor) -> Tensor:
        return model.latent_step(z, a)

    def running_cost(z: Tensor, a: Tensor) -> Tensor:
        return torch.zeros(len(z), dtype=z.dtype)

    def terminal_cost(states: Tensor, actions: Tensor) -> Tensor:
        """``states[1, K, T, latent]`` -> ``[K]``: final distance, plus the penalty when any step is unsafe."""
        seen = model.observe(states[0].reshape(-1, model.latent_dim)).reshape(*states.shape[1:3], -1)
        safe = workspace.allows(seen.float()).all(1)
        final = seen[:, -1, :2].float() - goal
        cost = torch.hypot(final[:, 0], final[:, 1]) + UNSAFE_PENALTY_MM * (~safe).float()
        return torch.nan_to_num(cost, nan=10 * UNSAFE_PENALTY_MM, posinf=10 * UNSAFE_PENALTY_MM)

    try:
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            torch.manual_seed(seed)
            mppi = MPPI(dynamics, running_cost, nx=model.latent_dim,
                        noise_sigma=setting.mppi_sigma**2 * torch.eye(2), num_samples=samples, horizon=steps,
                        terminal_state_cost=terminal_cost, lambda_=setting.mppi_lambda,
                        u_min=-torch.ones(2), u_max=torch.ones(2), U_init=torch.zeros(steps, 2))
            z0 = model.initial_latent(x0[None])[0]
            for _ in range(setting.mppi_iterations):
                mppi.command(z0, shift_nominal_trajectory=False)
            plan = mppi.U.clamp(-1.0, 1.0).float()
    finally:
        model.train(was_training)
    states = make_rollout(model)(x0[None], plan[None])
    safe = bool(workspace.allows(states[1:].float()).all())
    error = float(torch.linalg.vector_norm(states[-1, 0, :2].float() - goal))
    return Outcome(plan.numpy(), error, safe, samples * setting.mppi_iterations + 1)


def planner_plan(model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int, budget: int,
                 seed: int, config: PlannerConfig) -> Outcome:
    plan = Planner(model, workspace, replace(config, horizon=steps, horizon_search=False)).plan(x0, goal, seed=seed)
    found = len(plan.actions) > 0
    return Outcome(plan.actions, plan.error_mm, found, plan.evaluated, plan.status)


def search_then_hold(model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int, seed: int,
                     config: PlannerConfig) -> Outcome:
    """The shortest prefix of at most ``steps`` predicted to reach the goal, then zero actions up to ``steps``;
    its predicted error is the model's for the whole padded sequence (the hold's drift included)."""
    plan = Planner(model, workspace, replace(config, horizon=steps, horizon_search=True)).plan(x0, goal, seed=seed)
    if len(plan.actions) == 0:
        return Outcome(plan.actions, math.inf, False, plan.evaluated, plan.status)
    actions = np.zeros((steps, 2), np.float32)
    actions[: len(plan.actions)] = plan.actions
    states = make_rollout(model)(x0[None], torch.as_tensor(actions)[None])
    safe = bool(workspace.allows(states[1:].float()).all())
    error = float(torch.linalg.vector_norm(states[-1, 0, :2].float() - goal))
    return Outcome(actions, error, safe, plan.evaluated + 1, plan.status)


def settled_plan(model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int, seed: int,
                 config: PlannerConfig) -> Outcome:
    """The default scored at the settled end: each sequence rolled out with :data:`DRIFT_STEPS` zero actions after it;
    the plan is the sequence alone, its predicted error the settled one."""
    rollout = make_rollout(model)

    def then_hold(start: Tensor, actions: Tensor) -> Tensor:
        return rollout(start, torch.cat([actions, actions.new_zeros(len(actions), DRIFT_STEPS, 2)], dim=1))

    plan = Planner(then_hold, workspace, replace(config, horizon=steps, horizon_search=False)).plan(x0, goal, seed=seed)
    return Outcome(plan.actions[:steps], plan.error_mm, len(plan.actions) > 0, plan.evaluated, plan.status)


def optimise(name: str, model: LatentDynamics, workspace: Workspace, x0: Tensor, goal: Tensor, steps: int,
             budget: int, seed: int, setting: Setting) -> Outcome:
    """Optimiser ``name``'s ``steps``-action plan from ``x0`` towards ``goal`` with ``budget`` rollouts."""
    if name.startswith("default"):
        default = PegInHoleConfig().planner
        cfg = replace(default, samples=max(2, budget // (default.refine_iterations + 1)))
        cfg = from_mapping(PlannerConfig, setting.planner, "--planner", base=cfg)
        if name == "default":
            return planner_plan(model, workspace, x0, goal, steps, budget, seed, cfg)
        if name == "default_settled":
            return settled_plan(model, workspace, x0, goal, steps, seed, cfg)
        if name == "default_robust":
            cfg = replace(cfg, perturbations=setting.robust_copies, perturbation_std=setting.robust_sigma)
            outcome = planner_plan(model, workspace, x0, goal, steps, budget, seed, cfg)
            return replace(outcome, rollouts=outcome.rollouts * setting.robust_copies)
        return search_then_hold(model, workspace, x0, goal, steps, seed, cfg)
    base = replace(PegInHoleConfig().planner, sampler="piecewise", hold_steps=(5, 40), refine_iterations=0)
    if name == "ours":
        return planner_plan(model, workspace, x0, goal, steps, budget, seed, replace(base, samples=budget))
    if name == "ours_cem":
        r = setting.refine_iterations
        cfg = replace(base, samples=max(2, budget // (r + 1)), refine_iterations=r)
        return planner_plan(model, workspace, x0, goal, steps, budget, seed, cfg)
    if name == "random_shooting":
        cfg = replace(base, samples=budget, sampler="uniform")
        return planner_plan(model, workspace, x0, goal, steps, budget, seed, cfg)
    if name in ("cem", "cem_mean"):
        return plain_cem(model, workspace, x0, goal, steps, budget, seed, setting, final_mean=name == "cem_mean")
    if name == "mppi":
        return mppi_plan(model, workspace, x0, goal, steps, budget, seed, setting)
    raise ValueError(f"unknown optimiser {name!r}; known: {OPTIMISERS}")


# ------------------------------------------------------------------ one trial, the whole run


def run_trial(name: str, budget: int, model: LatentDynamics, workspace: Workspace, hand: SimulatedHand, goal: Goal,
              setting: Setting) -> TrialResult:
    """Plan from the goal's grasp (timed), execute open loop on the true hand, and judge at every tolerance."""
    hand.reset(goal.seed)
    x0 = torch.as_tensor(hand.state, dtype=torch.float32)
    target = torch.as_tensor(goal.position, dtype=torch.float32)
    begin = time.perf_counter()
    outcome = optimise(name, model, workspace, x0, target, goal.steps, budget, goal.seed, setting)
    seconds = time.perf_counter() - begin
    plan = Plan(outcome.predicted_safe, "planned", "", np.asarray(outcome.actions, np.float32),
                np.zeros((0, 4), np.float32), outcome.predicted_error_mm, goal.position.astype(np.float32))
    run = execute(hand, lambda state, left, _: plan, goal.steps)
    executed = len(run.actions) > 0
    final = run.states[-1, :2]
    error = float(np.linalg.norm(final - goal.position)) if executed else None
    progress = progress_towards(goal.grasp[:2], goal.position, final) if executed else None
    verdicts = {f"{tol:g}": verdict(goal.distance_mm, error, progress, run.completed, tol)
                for tol in setting.tolerances_mm}
    predicted = None if math.isinf(outcome.predicted_error_mm) else outcome.predicted_error_mm
    drift = None
    if run.completed:
        for _ in range(DRIFT_STEPS):
            if hand.step_info(np.zeros(2)).done:
                break
        drift = float(np.linalg.norm(hand.state[:2] - final))
    return TrialResult(name, budget, goal.trial, goal.distance_mm, seconds, outcome.rollouts, predicted,
                       outcome.predicted_safe, run.end_reason, error, progress, verdicts, outcome.status, drift)


def warm_up(model: LatentDynamics, workspace: Workspace, goal: Goal, setting: Setting) -> None:
    """One small plan per optimiser: first-call dispatch and allocation stay out of the timings."""
    x0 = torch.as_tensor(goal.grasp, dtype=torch.float32)
    for name in setting.optimisers:
        optimise(name, model, workspace, x0, torch.as_tensor(goal.position, dtype=torch.float32), goal.steps,
                 min(setting.budgets), 0, setting)


def run(model: LatentDynamics, workspace: Workspace, goals: Sequence[Goal], setting: Setting,
        hand: str = "target", progress: bool = False) -> list[TrialResult]:
    """Every goal with every budget and optimiser, interleaved per goal."""
    true_hand = SimulatedHand(hand)
    warm_up(model, workspace, goals[0], setting)
    trials = []
    for i, goal in enumerate(goals):
        for budget in setting.budgets:
            for name in setting.optimisers:
                trials.append(run_trial(name, budget, model, workspace, true_hand, goal, setting))
        if progress:
            print(f"goal {i + 1}/{len(goals)} done", file=sys.stderr, flush=True)
    return trials


def _planner_settings(text: str) -> dict[str, Any]:
    """``--planner``: a YAML mapping of PlannerConfig settings, checked against the default's."""
    try:
        raw = inline_mapping(text, "--planner", "PlannerConfig settings", "{noise_beta: 1}")
        if fixed := sorted(set(raw) & {"samples", "horizon", "horizon_search", "seed"}):
            raise ValueError(f"{fixed} are set per plan by the budget, the goal and the optimiser, not by --planner")
        from_mapping(PlannerConfig, raw, "--planner", base=PegInHoleConfig().planner)
    except ValueError as err:
        raise argparse.ArgumentTypeError(" ".join(str(err).split())[:300]) from None
    return raw


def _median(values: Sequence[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.median(kept)) if kept else None


def summarise(trials: Sequence[TrialResult], setting: Setting) -> list[dict]:
    """One row per (optimiser, budget): success per tolerance (Wilson 95 %), medians of error, time, rollouts."""
    rows = []
    for name in setting.optimisers:
        for budget in setting.budgets:
            group = [t for t in trials if t.optimiser == name and t.budget == budget]
            if not group:
                continue
            success = []
            for tol in setting.tolerances_mm:
                verdicts = [t.verdicts[f"{tol:g}"] for t in group]
                hits = verdicts.count("hit")
                low, high = wilson_interval(hits, len(group))
                success.append({"tolerance_mm": float(tol), "successes": hits, "success_rate": hits / len(group),
                                "ci_low": low, "ci_high": high, "verdicts": {v: verdicts.count(v) for v in VERDICTS}})
            rows.append({
                "optimiser": name, "budget": budget, "trials": len(group), "success": success,
                "median_final_error_mm": _median([t.final_error_mm for t in group]),
                "median_predicted_error_mm": _median([t.predicted_error_mm for t in group]),
                "median_plan_seconds": _median([t.plan_seconds for t in group]),
                "median_rollouts": _median([t.rollouts for t in group]),
                "median_drift_mm": _median([t.drift_mm for t in group]),
                "planner_status": {k: sum(t.status == k for t in group) for k in sorted({t.status for t in group})
                                   if k},
                "predicted_unsafe": sum(not t.predicted_safe for t in group),
            })
    return rows


def time_to_rate(rows: Sequence[dict], setting: Setting) -> list[dict]:
    """Per optimiser, tolerance and target rate: the smallest median planning time (and its budget) among budgets
    whose success rate reaches the target; None when none does."""
    out = []
    for name in setting.optimisers:
        mine = [r for r in rows if r["optimiser"] == name]
        for tol in setting.tolerances_mm:
            for target in setting.targets:
                reached = [(r["median_plan_seconds"], r["budget"]) for r in mine
                           for s in r["success"] if s["tolerance_mm"] == tol and s["success_rate"] >= target]
                seconds, budget = min(reached) if reached else (None, None)
                out.append({"optimiser": name, "tolerance_mm": float(tol), "success_rate": target,
                            "budget": budget, "median_plan_seconds": seconds})
    return out


TIME_SHARE = 1 / 3
"""The planner's target: another optimiser's best success at most this share of its plan time (issue 23)."""


def _best(rows: Sequence[dict], name: str, k: int) -> dict:
    """``name``'s row with the most hits at tolerance index ``k`` (ties: the faster)."""
    return min((r for r in rows if r["optimiser"] == name),
               key=lambda r: (-r["success"][k]["successes"], r["median_plan_seconds"]))


def against_default(rows: Sequence[dict], trials: Sequence[TrialResult], setting: Setting) -> list[dict]:
    """Per tolerance and other optimiser: its best budget against the default's, goal by goal (the goals the
    default alone hits, those the other alone hits, the sign test's p), and whether the default reaches the
    other's best rate at most :data:`TIME_SHARE` of its plan time (``target_met``).  Empty without ``default``."""
    if "default" not in setting.optimisers:
        return []
    hit = {(t.optimiser, t.budget, t.trial, tol): v == "hit" for t in trials for tol, v in t.verdicts.items()}
    out = []
    for k, tol in enumerate(setting.tolerances_mm):
        key = f"{tol:g}"
        mine = _best(rows, "default", k)
        for name in setting.optimisers:
            if name == "default":
                continue
            other = _best(rows, name, k)
            goals = sorted({t.trial for t in trials if t.optimiser == name and t.budget == other["budget"]})
            wins, losses, _, p = sign_test([int(hit["default", mine["budget"], g, key])
                                            - int(hit[name, other["budget"], g, key]) for g in goals])
            needed = other["success"][k]["successes"]
            reaching = [r["median_plan_seconds"] for r in rows
                        if r["optimiser"] == "default" and r["success"][k]["successes"] >= needed]
            share = min(reaching) / other["median_plan_seconds"] if reaching else None
            out.append({"tolerance_mm": float(tol), "optimiser": name, "budget": other["budget"],
                        "successes": needed, "default_budget": mine["budget"],
                        "default_successes": mine["success"][k]["successes"], "only_default": wins,
                        "only_other": losses, "sign_test_p": p, "default_time_share": share,
                        "target_met": share is not None and share <= TIME_SHARE})
    return out


def report(trials: Sequence[TrialResult], goals: Sequence[Goal], setting: Setting) -> dict:
    """The JSON body (no command or machine): settings, goals, rows, time to each rate, the default against each
    other optimiser's best, every trial."""
    rows = summarise(trials, setting)
    return {
        "benchmark": "planner_quality",
        "setting": asdict(setting),
        "goals": {"count": len(goals), "steps": sorted({g.steps for g in goals}),
                  "median_distance_mm": float(np.median([g.distance_mm for g in goals])),
                  "min_distance_mm": float(min(g.distance_mm for g in goals))},
        "rows": rows,
        "time_to_rate": time_to_rate(rows, setting),
        "against_default": against_default(rows, trials, setting),
        "trials": [asdict(t) for t in trials],
    }


def markdown(result: dict) -> str:
    """Per tolerance, a table of success (95 % Wilson), errors and time per optimiser and budget; then time to rate."""
    out = []
    for k, tol in enumerate(result["setting"]["tolerances_mm"]):
        out.append(f"Tolerance {tol:g} mm ({result['goals']['count']} goals, {result['goals']['steps']} steps)\n\n"
                   "| optimiser | budget | rollouts | success | 95 % interval | median true error mm "
                   "| median predicted error mm | median drift mm | median plan ms |\n"
                   "|---|---|---|---|---|---|---|---|---|\n")
        for r in result["rows"]:
            s = r["success"][k]
            out.append(f"| {r['optimiser']} | {r['budget']} | {r['median_rollouts']:.0f} "
                       f"| {s['successes']}/{r['trials']} ({s['success_rate']:.0%}) "
                       f"| {s['ci_low']:.0%}-{s['ci_high']:.0%} | {_fmt(r['median_final_error_mm'])} "
                       f"| {_fmt(r['median_predicted_error_mm'])} | {_fmt(r['median_drift_mm'])} "
                       f"| {1e3 * r['median_plan_seconds']:.1f} |\n")
        out.append("\n")
    out.append("Median planning time to reach a success rate (budget in brackets; - : no budget reached it)\n\n"
               "| optimiser | tolerance mm | rate | plan ms |\n|---|---|---|---|\n")
    for t in result["time_to_rate"]:
        when = "-" if t["budget"] is None else f"{1e3 * t['median_plan_seconds']:.1f} ({t['budget']})"
        out.append(f"| {t['optimiser']} | {t['tolerance_mm']:g} | {t['success_rate']:.0%} | {when} |\n")
    if result.get("against_default"):
        out.append("\nThe default's best budget against each optimiser's best, goal by goal; time share: the default's "
                   f"plan time at that rate over the other's (target <= {TIME_SHARE:.2f})\n\n"
                   "| tolerance mm | optimiser (budget) | hits | default (budget) | only default | only other "
                   "| sign-test p | time share | target met |\n|---|---|---|---|---|---|---|---|---|\n")
        for a in result["against_default"]:
            share = "-" if a["default_time_share"] is None else f"{a['default_time_share']:.2f}"
            out.append(f"| {a['tolerance_mm']:g} | {a['optimiser']} ({a['budget']}) | {a['successes']} "
                       f"| {a['default_successes']} ({a['default_budget']}) | {a['only_default']} | {a['only_other']} "
                       f"| {a['sign_test_p']:.2f} | {share} | {'yes' if a['target_met'] else 'no'} |\n")
    return "".join(out)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def curves(result: dict, k: int) -> dict[str, list[tuple[float, float, float, float]]]:
    """Per optimiser at tolerance index ``k``, its budgets in order as ``(median plan ms, success rate, 95 % low,
    95 % high)``: what :func:`plot` draws."""
    out: dict[str, list[tuple[float, float, float, float]]] = {}
    for r in sorted(result["rows"], key=lambda r: r["budget"]):
        s = r["success"][k]
        out.setdefault(r["optimiser"], []).append(
            (1e3 * r["median_plan_seconds"], s["success_rate"], s["ci_low"], s["ci_high"]))
    return out


def plot(result: dict, path: Path) -> Path:
    """Success against median plan time, one panel per tolerance, one line per optimiser through its budgets;
    where MPPI ran, its best rate (dashed) and a third of its time at that rate (dotted) bound the corner the
    default must reach (issue 23's target)."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()
    tolerances = result["setting"]["tolerances_mm"]
    fig, axes = plt.subplots(1, len(tolerances), figsize=(5.2 * len(tolerances), 4.2), squeeze=False)
    for k, (ax, tol) in enumerate(zip(axes.flat, tolerances, strict=True)):
        for i, (name, points) in enumerate(curves(result, k).items()):
            ms, rate, low, high = (np.array(v) for v in zip(*points, strict=True))
            main = name in ("default", "mppi")
            ax.errorbar(ms, 100 * rate, yerr=100 * np.array([rate - low, high - rate]), color=f"C{i}",
                        marker="o" if main else ".", lw=2.0 if main else 0.8, elinewidth=0.6, capsize=2,
                        alpha=1.0 if main else 0.6, label=name, zorder=3 if main else 2)
        if "mppi" in result["setting"]["optimisers"]:
            best = _best(result["rows"], "mppi", k)
            rate = best["success"][k]["success_rate"]
            ax.axhline(100 * rate, color="grey", ls="--", lw=0.8)
            ax.axvline(1e3 * best["median_plan_seconds"] * TIME_SHARE, color="grey", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("median plan time (ms, log)")
        ax.set_ylabel("success (%), 95 % Wilson interval")
        steps = "/".join(map(str, result["goals"]["steps"]))
        ax.set_title(f"{tol:g} mm: {result['goals']['count']} goals of {steps} steps", fontsize=9)
        ax.grid(alpha=0.3, which="both")
    axes.flat[0].legend(fontsize=7, ncol=2)
    return save(fig, path)


# ------------------------------------------------------------------ command line


def default_model() -> Path | None:
    """The newest naive_finetune model file: a rerun of the experiment leaves its earlier files beside it."""
    found = sorted(DEFAULT_MODELS.glob("naive_finetune-*.safetensors"), key=lambda f: (f.stat().st_mtime, f.name))
    return found[-1] if found else None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None,
                        help=f"model file (default: the newest {DEFAULT_MODELS}/naive_finetune-*.safetensors)")
    parser.add_argument("--workspace", nargs="+", type=Path, default=None,
                        help="bags whose states define the trained workspace (default: the one the model file stores)")
    parser.add_argument("--goals", type=int, default=30, help="goals (each with every budget and optimiser)")
    parser.add_argument("--steps", type=int, default=40, help="goal distance = plan length in control steps")
    parser.add_argument("--budgets", nargs="+", type=int, default=list(Setting.budgets))
    parser.add_argument("--optimisers", nargs="+", choices=OPTIMISERS, default=list(OPTIMISERS))
    parser.add_argument("--targets", nargs="+", type=float, default=list(Setting.targets))
    parser.add_argument("--refine-iterations", type=int, default=Setting.refine_iterations)
    parser.add_argument("--cem-iterations", type=int, default=Setting.cem_iterations)
    parser.add_argument("--cem-std", type=float, default=Setting.cem_std)
    parser.add_argument("--mppi-iterations", type=int, default=Setting.mppi_iterations)
    parser.add_argument("--mppi-sigma", type=float, default=Setting.mppi_sigma)
    parser.add_argument("--mppi-lambda", type=float, default=Setting.mppi_lambda)
    parser.add_argument("--robust-copies", type=int, default=Setting.robust_copies)
    parser.add_argument("--robust-sigma", type=float, default=Setting.robust_sigma)
    parser.add_argument("--planner", type=_planner_settings, default={}, metavar="MAPPING",
                        help="PlannerConfig settings replacing the default's in the default family, e.g. "
                             "'{noise_beta: 1}' (tuning)")
    parser.add_argument("--seed", type=int, default=0, help="goal seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: robust on a busy machine)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--plot-from", type=Path, default=None, metavar="JSON",
                        help="only redraw the figure of a stored result (beside it, .png), running nothing")
    args = parser.parse_args(argv)
    if args.plot_from is not None:
        try:
            stored = json.loads(args.plot_from.read_text())
        except (OSError, ValueError) as err:
            parser.error(f"--plot-from {args.plot_from}: {err}")
        if not isinstance(stored, dict) or stored.get("benchmark") != "planner_quality":
            parser.error(f"--plot-from {args.plot_from}: not a result of this benchmark (no \"benchmark\": "
                         "\"planner_quality\")")
        print(f"wrote {plot(stored, args.plot_from.with_suffix('.png'))}")
        return 0
    try:
        setting = Setting(tuple(args.budgets), tuple(args.optimisers), targets=tuple(args.targets),
                          refine_iterations=args.refine_iterations, cem_iterations=args.cem_iterations,
                          cem_std=args.cem_std, mppi_iterations=args.mppi_iterations, mppi_sigma=args.mppi_sigma,
                          mppi_lambda=args.mppi_lambda, robust_copies=args.robust_copies,
                          robust_sigma=args.robust_sigma, planner=args.planner)
    except ValueError as err:
        parser.error(str(err))
    if args.goals < 1 or args.steps < 1:
        parser.error("--goals and --steps must be positive")
    model_path = args.model or default_model()
    if model_path is None or not model_path.is_file():
        where = model_path or f"{DEFAULT_MODELS}/naive_finetune-*.safetensors"
        print(f"no model at {where}: make the peg-in-hole models with `{MAKE_MODELS}` (this benchmark trains "
              "nothing), or pass --model PATH", file=sys.stderr)
        return 2
    if "mppi" in setting.optimisers:
        try:
            import pytorch_mppi  # noqa: F401
        except ImportError:
            print("pytorch_mppi is not installed: pip install pytorch_mppi==0.9.1, or leave mppi out of --optimisers",
                  file=sys.stderr)
            return 2

    from machine import machine_info  # bench/machine.py (scripts run from bench/)

    from t42_transfer.models.checkpoint import load_model

    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()
    started = time.perf_counter()
    model, meta = load_model(model_path)
    try:
        workspace = Workspace.for_planning(args.workspace, meta, model_path)
    except ValueError as err:
        parser.error(str(err))
    goals = make_goals(PegInHoleConfig(distances=(args.steps,), trials=args.goals, tolerances_mm=setting.tolerances_mm,
                                       seed=args.seed), workspace)
    trials = run(model, workspace, goals, setting, progress=not args.quiet)
    load_end = os.getloadavg()
    result = {
        "command": shlex.join(["python", *(sys.argv if argv is None else ["bench/bench_planner_quality.py", *argv])]),
        "machine": {**machine_info(), "load_average_at_start": load_start, "load_average_at_end": load_end,
                    "oversubscribed": max(load_start[0], load_end[0]) > (os.cpu_count() or 1)},
        "model": {"path": str(model_path), "method": meta["method"], "weights_sha256": meta.get("weights_sha256")},
        "workspace": "bags " + " ".join(map(str, args.workspace)) if args.workspace else "stored in the model file",
        "seconds_total": time.perf_counter() - started,
        **report(trials, goals, setting),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    figure = plot(result, args.out.with_suffix(".png"))
    print(markdown(result))
    print(f"load average {load_start} at start, {load_end} at end; wrote {args.out} and {figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
