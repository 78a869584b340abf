"""The planner node's ROS parameters (:class:`PlannerNodeParams`), checked in the dataclass as every node's are."""

from __future__ import annotations

import math
from dataclasses import dataclass

from t42_transfer.conventions import MAX_PLAN_HORIZON, MAX_PLAN_SAMPLES, MAX_REFINE, MAX_SAMPLED_STEPS, MM_PER_M
from t42_transfer.planning import PlannerConfig
from t42_transfer.planning.planner import MAX_CANDIDATES, MAX_RERANK
from t42_transfer.ros.params import param, torch_threads_param

_DEFAULTS = PlannerConfig()


@dataclass(frozen=True)
class PlannerNodeParams:
    """Parameters of :class:`PlannerNode` (the node's ROS parameters)."""

    model: str = param("", "model file to start with (a relative one under the namespace's folder, as the "
                           "transfer server writes it); empty or missing: wait for t42/model_updated (goals are "
                           "refused meanwhile)", read_only=True)
    samples: int = param(_DEFAULTS.samples, "action sequences sampled per round of a plan (samples x horizon at "
                                            f"most {MAX_SAMPLED_STEPS})", min=1, max=MAX_PLAN_SAMPLES)
    refine_iterations: int = param(_DEFAULTS.refine_iterations, "cross-entropy rounds after the first draw "
                                                                "(a plan rolls out samples x (1 + this))", min=0,
                                   max=MAX_REFINE)
    horizon: int = param(_DEFAULTS.horizon, "steps of a sampled sequence (0.1 s each); with horizon_search "
                                            "the longest plan", min=1, max=MAX_PLAN_HORIZON)
    horizon_search: bool = param(_DEFAULTS.horizon_search, "plan the shortest sequence predicted to reach the "
                                                          "goal, then hold (false: plan horizon steps, or a goal's "
                                                          "steps, to the final state)")
    tolerance_m: float = param(_DEFAULTS.tolerance_mm / MM_PER_M, "a prediction this close to the goal reaches it "
                                                                 "(m)", min=0.0, constraints="positive, finite",
                               renamed_from="tolerance_mm")
    seed: int = param(_DEFAULTS.seed, "seed of the action sampler: same model, state, goal and seed, same plan")
    max_state_age_s: float = param(0.5, "plan only from a hand state at most this old (or this far in the future)",
                                   min=0.0, constraints="positive, finite")
    max_goal_age_s: float = param(30.0, "refuse a goal stamped longer ago than this (or this far in the future); "
                                       "a zero stamp means now", min=0.0, constraints="positive, finite")
    replan_every: int = param(0, "0: open loop, the whole plan at once; k: send k steps, then replan the rest "
                                 "from the measured state (MPC)", min=0)
    warm_start: bool = param(_DEFAULTS.warm_start, "with replan_every: each replan's search starts from the rest "
                                                  "of the plan it replaces (false: a fresh search)")
    piece_timeout_s: float = param(30.0, "longest wait (wall time) for a piece (with replan_every; else the "
                                         "whole plan) to run beyond its own length at 10 Hz",
                                   min=0.0, constraints="positive, finite")
    candidates: int = param(_DEFAULTS.candidates, "publish the predicted paths of each plan's this many "
                                                  "lowest-cost sequences on t42/plan_candidates (0: off)",
                            min=0, max=MAX_CANDIDATES)
    rerank: int = param(_DEFAULTS.rerank, "re-score this many of a plan's best sequences with dropout members of "
                                          "the model and plan the one they agree on most (0: off; a plan predicted "
                                          "to reach is kept one; fixed-length plans only)", min=0, max=MAX_RERANK)
    torch_threads: int = torch_threads_param()

    def __post_init__(self) -> None:
        _ = self.planner_config  # PlannerConfig validates the planner fields
        if not math.isfinite(self.tolerance_m):
            raise ValueError(f"tolerance_m must be finite, got {self.tolerance_m!r}")
        for name in ("max_state_age_s", "max_goal_age_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive and finite, got {value!r}")
        if self.replan_every < 0 or not (math.isfinite(self.piece_timeout_s) and self.piece_timeout_s > 0):
            raise ValueError("replan_every must be >= 0 and piece_timeout_s positive and finite")

    @property
    def planner_config(self) -> PlannerConfig:
        return PlannerConfig(samples=self.samples, refine_iterations=self.refine_iterations, horizon=self.horizon,
                             horizon_search=self.horizon_search,
                             tolerance_mm=self.tolerance_m * MM_PER_M, seed=self.seed, candidates=self.candidates,
                             warm_start=self.warm_start, rerank=self.rerank)

    @property
    def max_state_age_ns(self) -> int:
        return round(self.max_state_age_s * 1e9)
