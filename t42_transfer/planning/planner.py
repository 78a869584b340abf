"""Monte Carlo open-loop planner: sample action sequences, roll them out in one batch, keep the nearest.

By default the draw is refined (cross-entropy rounds around the best, ``refine_iterations``); the paper's planner,
the best of many sampled sequences and nothing more, is ``refine_iterations=0`` (docs/evaluation.md, section 7,
compares the two on the transfer methods).

Shapes (K samples, horizon T; float32):

    state            [4]         x mm, y mm, load1, load2 (raw units): where the plan starts
    goal             [2]         x mm, y mm of the object centre
    samples          [K, T, 2]   action sequences in [-1, 1] (see sampling.py)
    rollout          [K, T+1, 4] predictions, ``model.rollout`` (any model kind) or the fused
                                 MLP path (fused.py), in chunks of at most ``chunk`` samples
    Plan.actions     [L, 2]      the chosen sequence; L = T, or with horizon search the
                                 shortest prefix reaching the goal; L = 0 when refused
    Plan.predicted   [L+1, 4]    its predicted states, ``predicted[0] == state``

Safety. A sample is rejected from its first predicted state that is NaN/inf, exceeds the load limit, or leaves the
trained workspace (workspace.py); only states before that step may be used. The planner never returns an action
outside ``[-1, 1]``, a NaN, or a prediction that breaks these rules; instead :class:`Plan` says ``ok=False`` with a
``status`` code and a readable ``reason``. A plan whose best safe prediction misses the goal by more than the
tolerance is returned (``status="unreachable"``, ``ok=False``) with that predicted error, since executing it is the
caller's choice. Bad arguments (wrong shapes, non-finite state or goal) raise ``ValueError``.

Selection. Without horizon search (fixed-length plans) the cost is the final predicted distance to the goal. With
it, a sample's cost is ``t + e / tol`` for the first step ``t`` at which it is within ``tol`` (shortest first, then
nearest), or ``T + 1 + the nearest approach`` if it never is. Refinement (cross-entropy) refits a per-step Gaussian
to the best samples and redraws the rest; the best samples stay in the population, so the returned cost never gets
worse. With ``answer="elite_mean"`` the plan is instead the mean of the last population's elites, rolled out once
more, when that mean is safe.

Perturbations. A search strong enough finds sequences that exploit the model's errors: their predicted end is near
the goal and their true end is not. With ``perturbations = P > 1`` each sequence is also rolled out with ``P - 1``
fixed perturbations of its actions (N(0, ``perturbation_std``) per step, clipped; drawn once per plan from its seed,
the same for every sequence), and its cost is the mean final distance over the P rollouts, unusable when any breaks
a safety rule. A sequence whose end depends on the exact actions then costs more. The plan and its prediction are
the unperturbed sequence's. The rollout budget stays ``samples``: ``samples // P`` sequences are drawn. Fixed-length
plans only; each rejected copy counts in ``rejected``.

Polish. With ``polish_steps = N > 0`` the best sequence of the search then takes N gradient steps (Adam, step
``polish_lr``) on its predicted final distance, through the model's differentiable rollout, its actions clipped onto
the box after each; the polished sequence is rolled out once more and replaces the best only when it is safe and
predicted nearer. A plain model of the contract, fixed-length plans only.

Warm start. With ``warm_start`` a replan starts from the rest of the plan it replaces (``plan(previous=...)``;
iCEM's shifted mean): the first draw is that rest, cut or padded with holds (zero actions) to the horizon, and
``count - 1`` sequences around it (N(0, ``init_std``) per step, coloured by ``noise_beta``), each projected as the
sampler projects (the discrete sampler has no hold: its padding becomes the nearest move). Since the rest is among
the sequences scored, the best one's cost is never above the rest's: with the default cost and answer (one model,
final distance, ``answer="best"``, no ``rerank``) the replan is never predicted further from the goal than going on
with the old plan. Without ``previous`` (a goal's first plan) the draw is the cold one.

Uncertainty. A transferred model is trusted far outside its few target episodes. With ``uncertainty="ensemble"``
(several models) or ``"dropout"`` (``members`` dropout samples of one model) every sequence is predicted by each
member; safety and the returned prediction use the members' mean, and the cost is risk-averse: ``mean + risk * std``
of the members' final distances. The rollout budget stays ``samples``: ``samples // members`` sequences are drawn,
so a comparison at equal ``samples`` is at equal compute. Fixed-length plans only.

Rerank (``rerank``, off by default). The search's best sequence is often one the model is wrong about. Its best
``rerank`` sequences are predicted once more by ``rerank_members`` thinned copies of the model (dropout masks held
fixed, members.py), and the plan is the one they agree on most; the member rollouts count in ``evaluated``."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from t42_transfer.config import FRACTION, NON_NEGATIVE, Rule, between, check, one_of
from t42_transfer.conventions import (
    MAX_PLAN_HORIZON,
    MAX_PLAN_SAMPLES,
    MAX_REFINE,
    MAX_SAMPLED_STEPS,
    RANDOM_POLICY_LIMIT,
    STATE_DIM,
)
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.planning.fused import TimeMajorRollout, make_rollout
from t42_transfer.planning.members import DropoutRollout, MembersRollout, can_rerank, robust_choice
from t42_transfer.planning.sampling import SAMPLERS, colored_noise, project, sample_actions, stream_generator
from t42_transfer.planning.workspace import Workspace

CHUNK = 1000
"""Samples rolled out together: the three hidden buffers (1.5 MB) stay in L2, and memory stays bounded
at any K.  Measured at K = 10k (1 thread): chunks of 500-2000 alike, 5000 -23 %, 10000 -30 %."""

UNCERTAINTY = ("none", "dropout", "ensemble")
ANSWERS = ("best", "elite_mean")
MAX_CANDIDATES = 50
"""Most candidate paths a plan keeps (:attr:`PlannerConfig.candidates`): a picture, not a data set."""
MAX_PERTURBATIONS = 64
"""Most rollouts per sequence: beyond a few the mean settles and only the number of sequences drawn falls."""
MAX_NOISE_BETA = 4.0
"""Most colour of the sampling noise: beyond brown (2) a draw is nearly one slow drift per sequence."""
MAX_POLISH_STEPS = 1000
"""Most gradient steps of a polish: each costs a whole differentiable rollout of the plan."""
MAX_RERANK = 10_000
"""Most member rollouts of a rerank (sequences x members): they are one batch."""
REJECTIONS = {"nan": "predicted NaN/inf", "load": "over the load limit", "workspace": "left the workspace"}
"""Why a sample was rejected (key: description), in order of precedence at its first bad step."""


@dataclass(frozen=True)
class PlannerConfig:
    samples: int = 30
    """Sequences drawn per round; a plan rolls out about ``samples * (1 + refine_iterations)`` in all."""
    horizon: int = 100
    sampler: str = "gaussian"
    hold_steps: tuple[int, int] = (5, 40)
    """Piecewise sampler: each action is held for this many steps (inclusive range)."""
    init_std: float = 1.0
    """Gaussian sampler: the std of the first draw's actions (clipped to the box)."""
    noise_beta: float = 0.0
    """Colour of the gaussian sampler's first draw and of every refinement round's noise: power spectrum along
    time ``1 / f**beta`` (0: independent steps; 1 pink, 2 brown: smoother sequences; sampling.colored_noise)."""
    tolerance_mm: float = 2.0
    """A prediction within this of the goal reaches it (``ok``; the horizon search's target)."""
    horizon_search: bool = False
    refine_iterations: int = 9
    """Cross-entropy rounds after the first draw.  The defaults (30 clipped N(0, 1) sequences, ten draws, the best
    10 %) were chosen on 100 goals of seeds 1-5 (tuning; the benchmark's goals are seed 0), executed on the true
    target hand: more rollouts predict better but land worse (at 1000, 79 % / 28 % at 10 / 4 mm against 83 % /
    42 % at 300), since a stronger search finds more of the model's errors; the old default, piecewise holds of
    5-40 steps refined 3 times from 250, drove the object where the model, trained on holds of 1-5 steps, is
    wrong (16-20 % at 4 mm).  bench/results/planner_quality.json: the ``default`` rows."""
    elite_fraction: float = 0.1
    refine_min_std: float = 0.05
    """Floor of the refitted action std, so refinement keeps exploring."""
    answer: str = "best"
    """What a plan returns: ``best``, the lowest-cost sequence evaluated, or ``elite_mean``, the mean of the
    last population's elites (one more rollout), when it is safe (else the best): an average of good sequences
    leans less on any one of the model's errors, as MPPI's weighted mean does."""
    chunk: int = CHUNK
    fast_path: bool = True
    """Use the fused MLP rollout for plain transition models (fused.py)."""
    uncertainty: str = "none"
    """``none``, ``dropout`` (``members`` dropout samples of the model) or ``ensemble`` (one member per model)."""
    members: int = 1
    """Dropout samples per sequence; an ensemble has one member per model."""
    risk: float = 1.0
    """Weight of the members' spread in the cost (``mean + risk * std`` of the final distances)."""
    perturbations: int = 1
    """Rollouts per sequence for the robust cost (the module docstring's Perturbations); 1 scores the sequence alone."""
    perturbation_std: float = 0.1
    """Std of the fixed action perturbations of the copies, in the actions' [-1, 1] units."""
    polish_steps: int = 0
    """Gradient steps on the search's best sequence (the module docstring's Polish); 0: none.  One step through a
    40-step rollout costs about as much as 200 rollouts in the search (autograd on one sequence is dispatch-bound)."""
    polish_lr: float = 0.05
    """Adam's step size for the polish, in the actions' [-1, 1] units."""
    warm_start: bool = False
    """A replan's first draw centres on the rest of the plan it replaces (the module docstring's Warm start)."""
    rerank: int = 0
    """Last step: of this many of the final population's best sequences (never trading one predicted within the
    tolerance for one that is not), the one ``rerank_members`` dropout members agree on most (the lowest ``mean + risk
    * std`` of their final distances; planning/members.py); a model without dropout members keeps the search's
    best.  Fixed-length plans of one model, the best as the answer, no perturbations or polish.  0 (the default):
    none.  On 200 held-out goals ``rerank: 30`` hit 5 more at 10 mm and 4 fewer at 4 mm, at 1.45 times the plan
    time: docs/experiments/planner_tuning."""
    rerank_members: int = 8
    seed: int = 0
    candidates: int = 0
    """Keep the predicted object paths of this many lowest-cost sequences (:attr:`Plan.candidates`), for a user
    to see what the search weighed; 0 keeps none and costs nothing."""

    def __post_init__(self) -> None:
        check(self, PLANNER_RULES)  # here, so the CLI, the planner node and code share one message
        if self.samples * self.horizon > MAX_SAMPLED_STEPS:  # the sampled actions alone: 8 bytes a step
            raise ValueError(f"samples {self.samples} x horizon {self.horizon} is over {MAX_SAMPLED_STEPS} "
                             "sampled steps")
        if self.uncertainty != "none" and self.horizon_search:
            raise ValueError("uncertainty-aware planning scores fixed-length plans: set horizon_search false")
        if self.polish_steps and (self.horizon_search or self.uncertainty != "none" or self.perturbations > 1):
            raise ValueError("the polish refines a fixed-length plan of one model: set horizon_search false, "
                             "uncertainty 'none' and perturbations 1")
        if self.perturbations > 1 and (self.horizon_search or self.uncertainty != "none"):
            raise ValueError("perturbations score fixed-length plans of one deterministic model: set horizon_search "
                             "false and uncertainty 'none'")
        if self.rerank and (self.horizon_search or self.uncertainty != "none" or self.perturbations > 1
                            or self.answer != "best" or self.polish_steps or
                            self.rerank * self.rerank_members > MAX_RERANK):
            raise ValueError("rerank chooses the answer of a fixed-length plan of one deterministic model: set "
                             "horizon_search false, uncertainty 'none', perturbations 1, answer 'best', polish_steps 0,"
                             f" and rerank x rerank_members at most {MAX_RERANK}")


_AT_LEAST_ONE = between(1, math.inf)
PLANNER_RULES: dict[str, Rule] = {
    "samples": between(1, MAX_PLAN_SAMPLES), "horizon": between(1, MAX_PLAN_HORIZON), "chunk": _AT_LEAST_ONE,
    "sampler": one_of(SAMPLERS), "tolerance_mm": ((lambda v: v > 0), "positive"),
    "refine_iterations": between(0, MAX_REFINE),
    "elite_fraction": FRACTION, "init_std": ((lambda v: 0 < v < math.inf), "positive and finite"),
    "uncertainty": one_of(UNCERTAINTY), "members": _AT_LEAST_ONE, "risk": NON_NEGATIVE,
    "candidates": between(0, MAX_CANDIDATES), "perturbations": between(1, MAX_PERTURBATIONS),
    "perturbation_std": between(0, RANDOM_POLICY_LIMIT), "noise_beta": between(0, MAX_NOISE_BETA),
    "answer": one_of(ANSWERS), "polish_steps": between(0, MAX_POLISH_STEPS), "rerank": between(0, MAX_RERANK),
    "rerank_members": between(1, MAX_RERANK),
    "polish_lr": between(0, 2 * RANDOM_POLICY_LIMIT, low_open=True),
}
"""What each :class:`PlannerConfig` setting must be beyond its type."""


@dataclass(frozen=True)
class Plan:
    """The planner's answer; ``ok`` only when a safe sequence is predicted to reach the goal."""

    ok: bool
    status: str
    """``ok``, ``unreachable``, ``no_safe_sequence``, ``start_outside_workspace`` or ``goal_outside_workspace``."""
    reason: str
    """Why not ok, readable ('' when ok)."""
    actions: np.ndarray
    """``[L, 2]`` float32 in ``[-1, 1]``; ``L = 0`` when nothing safe was found."""
    predicted: np.ndarray
    """``[L + 1, 4]``: the model's prediction of the sequence, from the start state."""
    error_mm: float
    """Predicted final distance to the goal (inf when there is no sequence)."""
    goal: np.ndarray
    evaluated: int = 0
    """Samples rolled out, refinement included."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Samples whose prediction broke a rule within the horizon, by the rule at their first bad step
    (with horizon search their safe prefixes stay usable)."""
    candidates: tuple[np.ndarray, ...] = ()
    """With ``PlannerConfig.candidates`` K: the predicted object paths (``[n + 1, 2]`` mm, from the start) of the K
    lowest-cost safe sequences evaluated, lowest first (the first is the plan's); empty when refused."""

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for key in ("actions", "predicted", "goal"):
            out[key] = getattr(self, key).tolist()
        out["candidates"] = [c.tolist() for c in self.candidates]
        out["error_mm"] = None if math.isinf(self.error_mm) else self.error_mm
        return out


Model = LatentDynamics | TimeMajorRollout
"""What a planner predicts with: a model of the contract, or a time-major rollout function
(e.g. the true simulated hand, :mod:`t42_transfer.planning.oracle`)."""


class PlanStopped(Exception):
    """``plan``'s ``stop`` said so before a chunk: no plan (a node shutting down does not wait for a whole one)."""


class Planner:
    """Plans for one model (or an ensemble) in one workspace; ``plan`` may be called for any (state, goal)."""

    def __init__(
        self, model: Model | Sequence[Model], workspace: Workspace, config: PlannerConfig = PlannerConfig()
    ) -> None:
        models = list(model) if isinstance(model, Sequence) else [model]
        if not models:
            raise ValueError("a planner needs at least one model")
        if (config.uncertainty == "ensemble") != (len(models) > 1):
            raise ValueError(f"uncertainty={config.uncertainty!r} with {len(models)} models: "
                             "an ensemble needs several models, and several models need uncertainty='ensemble'")
        if config.uncertainty == "dropout" and not isinstance(models[0], LatentDynamics):
            raise ValueError("dropout samples need a model of the contract")
        if config.polish_steps and not isinstance(models[0], LatentDynamics):
            raise ValueError("the polish needs a model of the contract (a differentiable rollout)")
        self.models = models
        self.model = models[0]
        self.workspace = workspace
        self.config = config

    def plan(
        self, state: np.ndarray | Tensor, goal: np.ndarray | Tensor, seed: int | None = None,
        horizon: int | None = None, stop: Callable[[], bool] | None = None,
        previous: np.ndarray | Tensor | None = None,
    ) -> Plan:
        """The best sampled sequence from ``state`` towards ``goal``; ``seed`` and ``horizon`` override the config's.
        ``stop``, asked before each chunk of rollouts, ends the search with :class:`PlanStopped` when true.
        ``previous`` (``[n, 2]`` finite, else ValueError): the actions of an earlier plan for this goal still to
        come from ``state``, where a warm start (``warm_start``) begins; else only checked."""
        cfg = self.config
        x0 = _vector(state, STATE_DIM, "state")
        target = _vector(goal, 2, "goal")
        horizon = cfg.horizon if horizon is None else int(horizon)
        if horizon < 1:
            raise ValueError(f"horizon must be positive, got {horizon}")
        warm = None if previous is None else _previous(previous, horizon)
        refused = self._check_ends(x0, target)
        if refused is not None:
            return refused
        seed = cfg.seed if seed is None else seed
        gen = torch.Generator().manual_seed(seed)
        search = _Search(self._rollouts(seed), self.workspace, x0, target, cfg, _perturbations(cfg, horizon, seed),
                         stop)
        count = max(1, cfg.samples // (len(search.rollouts) * cfg.perturbations))
        if cfg.warm_start and warm is not None:
            noise = colored_noise(count - 1, horizon, cfg.noise_beta, gen)
            actions = torch.cat([project(cfg.sampler, warm[None]), project(cfg.sampler, warm + cfg.init_std * noise)])
        else:
            actions = sample_actions(cfg.sampler, count, horizon, gen, cfg.hold_steps, cfg.init_std, cfg.noise_beta)
        cost = search.evaluate(actions)
        elite_count = max(2, int(cfg.elite_fraction * count))
        for _ in range(cfg.refine_iterations):
            order = _elites(cost, elite_count)
            if len(order) < 2:
                break
            elites, elite_cost = actions[order], cost[order]
            mean, std = elites.mean(0), elites.std(0).clamp_min(cfg.refine_min_std)
            noise = colored_noise(max(1, count - len(order)), horizon, cfg.noise_beta, gen)
            fresh = project(cfg.sampler, mean + std * noise)
            actions, cost = torch.cat([elites, fresh]), torch.cat([elite_cost, search.evaluate(fresh)])
        if cfg.rerank and can_rerank(self.model):
            self._rerank(search, x0, target, actions, cost, seed)
        if cfg.answer == "elite_mean":
            order = _elites(cost, elite_count)
            if len(order):
                search.answer_with(project(cfg.sampler, actions[order].mean(0, keepdim=True)))
        if cfg.polish_steps and len(search.best_actions) == horizon:
            search.evaluate(_polish(self.model, x0, target, search.best_actions, cfg)[None])  # kept when nearer
        return search.result()

    def _rerank(self, search: _Search, x0: Tensor, goal: Tensor, actions: Tensor, cost: Tensor, seed: int) -> None:
        """Make the members' choice among the best sequences the answer (module docstring, Rerank)."""
        cfg = self.config
        order = _elites(cost, cfg.rerank)
        if len(order) and cost[order[0]] <= cfg.tolerance_mm:  # a plan that reaches stays one that reaches
            order = order[cost[order] <= cfg.tolerance_mm]
        if len(order) < 2:
            return
        members = MembersRollout(self.model, cfg.rerank_members, seed)
        chosen = robust_choice(members, self.workspace, x0, goal, actions[order], cfg.risk)
        search.evaluated += len(order) * cfg.rerank_members
        if chosen:  # not None, and not the best already
            search.answer_with(actions[order[chosen]][None])

    def _rollouts(self, seed: int) -> list[TimeMajorRollout]:
        cfg = self.config
        if cfg.uncertainty == "dropout":
            sampler = DropoutRollout(self.model, seed)
            return [sampler] * cfg.members
        return [m if not isinstance(m, LatentDynamics) else make_rollout(m, cfg.fast_path) for m in self.models]

    def _check_ends(self, x0: Tensor, goal: Tensor) -> Plan | None:
        ws = self.workspace
        if not ws.allows(x0):
            x, y, load_1, load_2 = x0.tolist()
            reason = (f"start state (x {x:.1f} mm, y {y:.1f} mm, loads {load_1:.0f} {load_2:.0f}) is outside the "
                      f"trained workspace ({ws.describe_xy()}) or over the load limit ({ws.load_limit:g})")
            return _refusal("start_outside_workspace", reason, x0, goal)
        if not ws.contains_xy(goal):
            x, y = goal.tolist()
            reason = f"goal (x {x:.1f} mm, y {y:.1f} mm) is outside the trained workspace ({ws.describe_xy()})"
            return _refusal("goal_outside_workspace", reason, x0, goal)
        return None


def _polish(model: LatentDynamics, x0: Tensor, goal: Tensor, actions: Tensor, cfg: PlannerConfig) -> Tensor:
    """``actions[T, 2]`` after ``cfg.polish_steps`` Adam steps on the predicted final distance to ``goal``, clipped
    onto the box after each step (dropout off; the model's own parameters are left untouched)."""
    polished = actions.detach().float().clone()[None].requires_grad_(True)
    optimiser = torch.optim.Adam([polished], lr=cfg.polish_lr)
    was_training = model.training
    model.eval()
    try:
        with torch.enable_grad():
            for _ in range(cfg.polish_steps):
                optimiser.zero_grad(set_to_none=True)
                final = model.rollout_with_grad(x0[None], polished)[0, -1, :2]
                distance = torch.linalg.vector_norm(final - goal)
                if not torch.isfinite(distance):
                    break
                (grad,) = torch.autograd.grad(distance, polished)
                polished.grad = grad
                optimiser.step()
                with torch.no_grad():
                    polished.clamp_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT)
    finally:
        model.train(was_training)
    return polished.detach()[0]


def _elites(cost: Tensor, count: int) -> Tensor:
    """Indices of the ``count`` lowest costs (ties: the earlier sample), the unusable (inf) left out."""
    order = torch.argsort(cost, stable=True)[:count]
    return order[torch.isfinite(cost[order])]


def _perturbations(cfg: PlannerConfig, horizon: int, seed: int) -> Tensor | None:
    """``[P - 1, horizon, 2]`` action shifts of the copies, from a generator of their own (the draws of a plan without
    perturbations stay as they were); None when P is 1."""
    if cfg.perturbations <= 1:
        return None
    gen = stream_generator(seed, horizon)
    return cfg.perturbation_std * torch.randn(cfg.perturbations - 1, horizon, 2, generator=gen)


def _previous(actions: np.ndarray | Tensor, horizon: int) -> Tensor | None:
    """``actions[n, 2]`` as ``[horizon, 2]``: cut, or padded with holds (zero actions); None when ``n`` is 0;
    ValueError unless finite ``[n, 2]``."""
    rest = torch.as_tensor(np.asarray(actions, dtype=np.float32))
    if rest.ndim != 2 or rest.shape[1] != 2 or not torch.isfinite(rest).all():
        raise ValueError(f"previous must be [n, 2] finite actions, got shape {tuple(rest.shape)}")
    if len(rest) == 0:
        return None
    out = torch.zeros(horizon, 2)
    out[: min(horizon, len(rest))] = rest[:horizon]
    return out


def _vector(value: np.ndarray | Tensor, size: int, name: str) -> Tensor:
    """The float32 vector, checked in float64 first so a number beyond float32's range is refused, not cast to inf."""
    wide = np.asarray(value, dtype=np.float64).reshape(-1)
    if wide.size != size or not np.all(np.abs(wide) <= np.finfo(np.float32).max):
        raise ValueError(f"{name} must be {size} finite numbers, got {wide.tolist()}")
    return torch.as_tensor(wide.astype(np.float32))


def _refusal(
    status: str, reason: str, x0: Tensor, goal: Tensor, evaluated: int = 0, rejected: dict[str, int] | None = None
) -> Plan:
    return Plan(
        ok=False,
        status=status,
        reason=reason,
        actions=np.zeros((0, 2), np.float32),
        predicted=x0.numpy()[None].copy(),
        error_mm=math.inf,
        goal=goal.numpy().copy(),
        evaluated=evaluated,
        rejected=rejected or dict.fromkeys(REJECTIONS, 0),
    )


def _shifted(chunk: Tensor, shifts: Tensor) -> Tensor:
    """The copies of ``chunk[N, T, 2]`` shifted by each of ``shifts[P - 1, T, 2]``, clipped, copy-major
    ``[(P - 1) N, T, 2]``."""
    copies = (chunk.unsqueeze(0) + shifts.unsqueeze(1)).clamp_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT)
    return copies.reshape(-1, *chunk.shape[1:])


class _Search:
    """Rolls out samples chunk by chunk, scores them, and keeps the best (sequence, prediction) seen."""

    def __init__(
        self, rollouts: list[TimeMajorRollout], workspace: Workspace, x0: Tensor, goal: Tensor, cfg: PlannerConfig,
        shifts: Tensor | None = None, stop: Callable[[], bool] | None = None,
    ) -> None:
        self.rollouts, self.workspace, self.x0, self.goal, self.cfg = rollouts, workspace, x0, goal, cfg
        self.stop = stop
        self.shifts = shifts
        """The copies' action shifts ``[P - 1, T, 2]``, or None (:func:`_perturbations`)."""
        self.best_cost = math.inf
        self.best_actions = torch.zeros(0, 2)
        self.best_states = x0[None]
        self.evaluated = 0
        self.rejected = dict.fromkeys(REJECTIONS, 0)
        self.top: list[tuple[float, Tensor]] = []
        """(cost, predicted xy path) of the ``cfg.candidates`` lowest-cost sequences so far."""

    def evaluate(self, actions: Tensor, candidates: bool = True) -> Tensor:
        """Cost of each sequence ``actions[N, T, 2]`` (inf when no usable prefix); updates the best, and with
        ``candidates`` the candidates."""
        costs = []
        copies = 1 if self.shifts is None else 1 + len(self.shifts)
        step = max(1, self.cfg.chunk // copies)
        for start in range(0, len(actions), step):
            if self.stop is not None and self.stop():
                raise PlanStopped(f"stopped after {self.evaluated + start} of the samples")
            chunk = actions[start : start + step]
            batch = chunk if self.shifts is None else torch.cat([chunk, _shifted(chunk, self.shifts)])
            x0 = self.x0.expand(len(batch), STATE_DIM)
            members = [rollout(x0, batch) for rollout in self.rollouts]
            states = members[0] if len(members) == 1 else torch.stack(members).mean(0)
            cost, length = self._score(states)
            if copies > 1:  # the copies' mean final distance (inf when any is unsafe); the unperturbed prediction
                n = len(chunk)
                cost, length, states = cost.view(copies, n).mean(0), length[:n], states[:, :n]
            if len(members) > 1:
                cost = self._risk_averse(torch.stack(members), cost)
            if self.cfg.candidates and candidates:
                self._keep_top(cost, length, states)
            i = int(torch.argmin(cost))
            if cost[i] < self.best_cost:
                n = int(length[i])
                self.best_cost = float(cost[i])
                self.best_actions = chunk[i, :n].clone()
                self.best_states = states[: n + 1, i].clone()
            costs.append(cost)
        self.evaluated += len(actions)
        return torch.cat(costs)

    def answer_with(self, actions: Tensor) -> None:
        """Evaluate the one sequence ``actions[1, T, 2]`` and make it the answer, whatever its cost, when it has a
        usable prefix (else the best stays)."""
        best = (self.best_cost, self.best_actions, self.best_states)
        self.best_cost = math.inf
        cost = float(self.evaluate(actions, candidates=False)[0])  # already among them, if good enough
        if math.isinf(cost):
            self.best_cost, self.best_actions, self.best_states = best

    def _keep_top(self, cost: Tensor, length: Tensor, states: Tensor) -> None:
        """Merge this chunk's lowest finite costs into :attr:`top` (ties: the earlier sample first)."""
        k = min(self.cfg.candidates, len(cost))
        order = torch.argsort(cost, stable=True)[:k]
        for i in order[torch.isfinite(cost[order])].tolist():
            self.top.append((float(cost[i]), states[: int(length[i]) + 1, i, :2].float().clone()))
        self.top = sorted(self.top, key=lambda t: t[0])[: self.cfg.candidates]

    def _risk_averse(self, members: Tensor, cost: Tensor) -> Tensor:
        """``mean + risk * std`` of the members' final distances (``members[M, T+1, C, 4]``), inf where unsafe."""
        final = members[:, -1, :, :2].float() - self.goal
        dist = torch.hypot(final[..., 0], final[..., 1])
        risky = dist.mean(0) + self.cfg.risk * dist.std(0)
        return torch.where(torch.isfinite(cost), risky, cost)

    def _score(self, states: Tensor) -> tuple[Tensor, Tensor]:
        """Per sample of time-major ``states[T+1, C, 4]``: cost and the length of its prefix; counts rejections."""
        horizon = states.shape[0] - 1
        future = states[1:].float().contiguous()
        safe = self.workspace.allows(future)  # NaN and inf fail it: no separate finiteness pass
        has_bad = ~safe.all(0)
        first_bad = torch.where(has_bad, (~safe).byte().argmax(0), horizon)
        if has_bad.any():
            rows = has_bad.nonzero().squeeze(1)
            bad_state = future[first_bad[rows], rows]
            nan = ~torch.isfinite(bad_state).all(-1)
            load = ~nan & ~self.workspace.loads_ok(bad_state)
            self.rejected["nan"] += int(nan.sum())
            self.rejected["load"] += int(load.sum())
            self.rejected["workspace"] += int((~nan & ~load).sum())
        if not self.cfg.horizon_search:
            final = future[-1, :, :2] - self.goal
            cost = torch.hypot(final[:, 0], final[:, 1]).masked_fill_(has_bad, math.inf)
            return cost, torch.full_like(first_bad, horizon)
        # Squared distances: only the selected ones need a square root.
        unusable = torch.arange(horizon).unsqueeze(1) >= first_bad
        dx, dy = future[..., 0] - self.goal[0], future[..., 1] - self.goal[1]
        dist2 = torch.addcmul(dx * dx, dy, dy).masked_fill_(unusable, math.inf)
        tol = self.cfg.tolerance_mm
        hit = dist2 <= tol * tol
        reached = hit.any(0)
        first_hit = hit.byte().argmax(0)
        hit_error = dist2.gather(0, first_hit.unsqueeze(0)).squeeze(0).sqrt()
        nearest2, nearest_step = dist2.min(0)
        cost = torch.where(reached, first_hit + hit_error / tol, horizon + 1 + nearest2.sqrt())
        length = torch.where(reached, first_hit, nearest_step) + 1
        return cost, length

    def result(self) -> Plan:
        cfg, x0, goal = self.cfg, self.x0, self.goal
        if math.isinf(self.best_cost):
            counts = ", ".join(f"{n} {REJECTIONS[k]}" for k, n in self.rejected.items() if n)
            reason = f"all {self.evaluated} sampled sequences were rejected ({counts})"
            if cfg.perturbations > 1:
                reason += f" (each of a sequence's {cfg.perturbations} perturbed rollouts counted)"
            elif not cfg.horizon_search:
                reason += "; horizon search would keep their safe prefixes"
            return _refusal("no_safe_sequence", reason, x0, goal, self.evaluated, dict(self.rejected))
        actions = self.best_actions.float()
        predicted = self.best_states.float()
        error = float(torch.linalg.vector_norm(predicted[-1, :2] - goal))
        # The safety contract, checked on what leaves the planner.
        if not (
            torch.isfinite(actions).all()
            and actions.abs().max() <= RANDOM_POLICY_LIMIT
            and torch.isfinite(predicted).all()
            and self.workspace.allows(predicted[1:]).all()
        ):
            raise RuntimeError("planner selected an unsafe sequence: this is a bug")
        ok = error <= cfg.tolerance_mm
        reason = (
            ""
            if ok
            else (
                f"goal unreachable: the best safe prediction ends {error:.2f} mm from it "
                f"(tolerance {cfg.tolerance_mm} mm)"
            )
        )
        return Plan(
            ok=ok,
            status="ok" if ok else "unreachable",
            reason=reason,
            actions=actions.numpy().copy(),
            predicted=predicted.numpy().copy(),
            error_mm=error,
            goal=goal.numpy().copy(),
            evaluated=self.evaluated,
            rejected=dict(self.rejected),
            candidates=tuple(path.numpy().copy() for _, path in self.top),
        )
