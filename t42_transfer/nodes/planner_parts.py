"""The planner node's data and pure parts: what a goal's result says (:class:`PlanResult`, from
:mod:`msg_adapters.plan_result`), refusals, the model with its workspace,
and the hand state planned from (no rclpy here; :mod:`t42_transfer.nodes.planner_node` uses them)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from msg_adapters import names
from msg_adapters.plan_result import PlanResult
from t42_transfer.conventions import ACTION_UNIT_RAD, MAX_STEP_RAD, RANDOM_POLICY_LIMIT
from t42_transfer.models.checkpoint import UNIT_ASSUMED_KEY, UNIT_KEY, load_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.planning import Planner, PlannerConfig, Workspace

if TYPE_CHECKING:
    from t42_transfer.nodes.reach import ReachRun


class Refused(Exception):
    """A goal the node will not plan for: ``status`` code and readable ``reason``."""

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status, self.reason = status, reason


@dataclass(frozen=True)
class LoadedModel:
    """A model and the workspace it was trained in; planners are built per goal with the current settings."""

    path: str
    method: str
    model: LatentDynamics
    workspace: Workspace
    action_unit_rad: float = ACTION_UNIT_RAD
    """The unit of the model's actions (its data's): the authors' models step 0.00388 rad at an action of 1."""
    unit_assumed: bool = False
    """The file was saved before units were stored: its unit is assumed (``checkpoint.UNIT_ASSUMED_KEY``)."""

    def planner(self, config: PlannerConfig) -> Planner:
        return Planner(self.model, self.workspace, config)


def load_planner_model(path: str | Path) -> LoadedModel:
    """The model in ``path`` with its stored workspace.

    Raises :class:`~t42_transfer.models.checkpoint.CheckpointError` for an unreadable
    file and ``ValueError`` for a file without a workspace (see the module docstring).
    """
    model, meta = load_model(path)
    workspace = Workspace.from_metadata(meta, path)
    if workspace is None:
        raise ValueError(f"{path} stores no workspace (metadata extra.workspace): "
                         "the planner cannot tell where its predictions hold")
    if (step := RANDOM_POLICY_LIMIT * meta[UNIT_KEY]) > MAX_STEP_RAD * (1 + 1e-9):
        raise ValueError(f"{path}: its actions step up to {step:.4g} rad (unit {meta[UNIT_KEY]:.4g} rad), more than a "
                         f"driver takes ({MAX_STEP_RAD:g} rad)")
    return LoadedModel(str(path), str(meta.get("method", "")), model, workspace, meta[UNIT_KEY],
                       bool(meta.get(UNIT_ASSUMED_KEY)))


@dataclass(frozen=True)
class HandState:
    state: np.ndarray
    """``[4]`` float32 in STATE_NAMES order."""
    angles: np.ndarray
    """``[2]`` actuator angles (rad) the trajectory starts from."""


def hand_state(pose: tuple[int, np.ndarray] | None, joints: tuple[int, np.ndarray, np.ndarray | None] | None,
               now_ns: int, max_age_ns: int) -> HandState:
    """The state to plan from, given the latest ``(stamp, xy)`` pose and ``(stamp, loads, angles)`` joints."""
    if pose is None or joints is None:
        missing = [name for name, got in (("object pose", pose), ("joint states", joints)) if got is None]
        raise Refused("no_state", f"no hand state yet (no {' or '.join(missing)} received)")
    (pose_ns, xy), (joints_ns, loads, angles) = pose, joints
    if angles is None:
        raise Refused("no_state", "joint states carry no actuator angles: a trajectory needs its start angles")
    age_ns = max(abs(now_ns - pose_ns), abs(now_ns - joints_ns))
    if age_ns > max_age_ns:
        raise Refused("stale_state", f"hand state is {age_ns / 1e9:.3f} s from now (limit {max_age_ns / 1e9:.3f} s): "
                                     "is the driver publishing?")
    return HandState(np.concatenate([xy, loads]).astype(np.float32), angles)


@dataclass(frozen=True)
class Goal:
    xy: np.ndarray
    stamp_ns: int
    run: ReachRun | None = None
    """The action goal's run (:class:`~t42_transfer.nodes.reach.ReachRun`; None: a t42/goal goal)."""
    tolerance_mm: float = 0.0
    steps: int = 0
    replan_every: int = 0


def superseded(goal: Goal, planned: PlanResult | None = None, reason: str = "") -> PlanResult:
    """The result of a goal a newer one replaced (``planned``: what its finished plan had been), or that was
    cancelled (``reason``)."""
    base = planned or PlanResult(False, "", "", goal.xy.tolist(), goal.stamp_ns)
    if not reason:
        reason = "a newer goal arrived" + (" while it was planned; the plan was discarded" if planned else "")
    return PlanResult(**{**asdict(base), "accepted": False, "status": names.SUPERSEDED, "reason": reason})


def unsent(goal: Goal, planned: PlanResult, cancelled: bool, episode_ended: bool) -> PlanResult:
    """The result of a goal planned but stopped before its first piece went out: cancelled, its episode ended
    meanwhile, or a newer goal arrived."""
    if cancelled:
        return superseded(goal, planned, "cancelled while it was planned")
    if episode_ended:
        return replace(superseded(goal, planned), status="episode_ended",
                       reason="the episode ended before the plan was sent (reset the hand)")
    return superseded(goal, planned)
