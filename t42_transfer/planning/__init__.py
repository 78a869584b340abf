"""Open-loop planning with any learned model: the Monte Carlo planner, its workspace guard, peg-in-hole."""

from t42_transfer.planning.planner import Plan, Planner, PlannerConfig, PlanStopped
from t42_transfer.planning.sampling import DISCRETE_ACTIONS, SAMPLERS, sample_actions
from t42_transfer.planning.workspace import Workspace

__all__ = ["DISCRETE_ACTIONS", "SAMPLERS", "Plan", "PlanStopped", "Planner", "PlannerConfig", "Workspace",
           "sample_actions"]
