"""The online loop's own yardstick: each round's model on executed plans that no model trained on.

A loop that records its executed plans and transfers again learns the regime it plans in (actions held for
several steps, larger moves per step) and may lose accuracy on random actions for it
(docs/experiments/online_loop). Held-out random-action episodes see only that loss; this scores the models on
the episodes of the loop's last round, recorded after its last transfer, from each episode's first commanded
step (the settling after a grasp, before the plan, is left out).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from t42_transfer.conventions import MIN_EPISODE_STEPS
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.metrics import evaluate_model
from t42_transfer.models.dynamics import LatentDynamics


def commanded(data: TrajectorySet, to_last_command: bool = False, min_steps: int = MIN_EPISODE_STEPS) -> TrajectorySet:
    """Each episode from its first commanded (non-zero) action to its end, or to its last commanded action
    (``to_last_command``); episodes with no command, or fewer than ``min_steps`` steps left, are dropped."""
    kept = []
    for t in data:
        moved = np.flatnonzero(np.abs(t.actions).sum(axis=1) > 0)
        if not len(moved):
            continue
        first, end = int(moved[0]), (int(moved[-1]) + 1 if to_last_command else len(t.actions))
        if end - first >= min_steps:
            kept.append(Trajectory(t.states[first:end + 1], t.actions[first:end], end_reason="length", hand=t.hand))
    return TrajectorySet(kept, hand=data.hand)


def idle_share(data: TrajectorySet) -> float:
    """The share of steps whose action is zero (holding still)."""
    return _idle(np.concatenate([t.actions for t in data]))


def _idle(actions: np.ndarray) -> float:
    return float((np.abs(actions).sum(axis=1) == 0).mean()) if len(actions) else 1.0


PLAN_IDLE_SHARE = 0.5
"""An episode idle (zero action) on at least this share of its steps is an executed plan: the suite's plan episodes
settle after the grasp, run a plan and hold (0.79 of their steps idle in the measured loop); exploration with
random actions is about 0.05 idle (docs/experiments/online_loop)."""
EPISODE_KINDS = ("exploration", "plan")


def episode_kind(episode: Trajectory) -> str:
    """``"plan"`` for an episode that mostly holds still (:data:`PLAN_IDLE_SHARE`), else ``"exploration"``."""
    return "plan" if _idle(episode.actions) >= PLAN_IDLE_SHARE else "exploration"


def scores_on(models: Mapping[str, LatentDynamics], data: TrajectorySet) -> dict[str, dict[str, float]]:
    """Divergence (4 mm, steps) and position MSE (mm²) of each model on ``data``."""
    scores = {}
    for name, model in models.items():
        result = evaluate_model(model, data)
        scores[name] = {"divergence_steps": float(result["divergence_mean"]),
                        "position_mse_mm2": float(result["position_mse_mean"])}
    return scores


def executed_plan_scores(models: Mapping[str, LatentDynamics],
                         episodes: TrajectorySet) -> tuple[int, dict[str, dict[str, float]]]:
    """How many of ``episodes`` have a plan (:func:`commanded`), and each model's :func:`scores_on` them."""
    plans = commanded(episodes)
    if not len(plans):
        raise ValueError(f"none of the {len(episodes)} episodes has {MIN_EPISODE_STEPS} steps from its first command")
    return len(plans), scores_on(models, plans)
