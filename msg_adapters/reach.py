"""Reach action messages (``t42_interfaces/action/Reach``) <-> numpy, for the planner's ``t42/reach`` and its
clients (:func:`reach_goal`, :func:`reach_progress`, :func:`reach_outcome`).

Same rules as :mod:`msg_adapters.planning`: metres in ``FRAME_ID`` on the wire, mm inside the package.
The goal reader refuses another frame, a non-finite value and a negative tolerance with a ``ValueError``
that says why (the words of :func:`~msg_adapters.planning.goal_xy_mm`, as ``t42/goal`` refuses them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from msg_adapters.hand import _MM_PER_M, stamp_to_ns
from msg_adapters.kit import RCLPY, rclpy_class
from msg_adapters.planning import goal_msg, goal_xy_mm, path_msg, path_xy_mm
from msg_adapters.wire import CONTROL_PERIOD_NS

REACH = "t42_interfaces/action/Reach"


def reach_type() -> Any:
    """rclpy's ``Reach`` action class (imported on first use: t42_interfaces is built by scripts/bootstrap.sh)."""
    return rclpy_class(REACH)


@dataclass(frozen=True)
class ReachRequest:
    """A Reach goal as the planner reads it; zeros mean "the node's parameter"."""

    xy_mm: np.ndarray
    stamp_ns: int
    tolerance_mm: float
    steps: int
    replan_every: int


def reach_request(goal: Any) -> ReachRequest:
    """The planner's view of a ``Reach.Goal``; ``ValueError`` for a goal no plan can serve."""
    xy = goal_xy_mm(goal.target)
    tolerance = float(goal.tolerance_m)
    if not (math.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"goal tolerance must be finite and >= 0, got {tolerance!r} m")
    return ReachRequest(xy, stamp_to_ns(goal.target.header.stamp), tolerance * _MM_PER_M, int(goal.steps),
                        int(goal.replan_every))


def reach_feedback(step: int, error_mm: float, predicted_final_error_mm: float) -> Any:
    """``Reach.Feedback``: steps executed, measured and predicted final distance to the goal (metres)."""
    return reach_type().Feedback(step=int(step), error_m=float(error_mm) / _MM_PER_M,
                                 predicted_final_error_m=float(predicted_final_error_mm) / _MM_PER_M)


def reach_result(verdict: str, reason: str, final_error_mm: float | None, executed_mm: np.ndarray,
                 executed_start_ns: int, predicted_mm: np.ndarray, predicted_start_ns: int) -> Any:
    """``Reach.Result``; success exactly when ``verdict`` is ``hit``; paths stamped one control period apart."""
    result_cls = reach_type().Result
    return result_cls(
        success=verdict == result_cls.VERDICT_HIT,
        final_error_m=math.nan if final_error_mm is None else float(final_error_mm) / _MM_PER_M,
        verdict=verdict,
        reason=reason,
        executed=path_msg(_xy(executed_mm), executed_start_ns, CONTROL_PERIOD_NS, RCLPY),
        predicted=path_msg(_xy(predicted_mm), predicted_start_ns, CONTROL_PERIOD_NS, RCLPY),
    )


def _xy(points: Any) -> np.ndarray:
    return np.asarray(points, np.float32).reshape(-1, 2)


def reach_goal(xy_mm: Any, stamp_ns: int, tolerance_mm: float = 0.0, steps: int = 0, replan_every: int = 0) -> Any:
    """A ``Reach.Goal`` for the object's centre at ``xy_mm`` (a client's side; zeros: the planner's parameters)."""
    return reach_type().Goal(target=goal_msg(xy_mm, stamp_ns, RCLPY), tolerance_m=float(tolerance_mm) / _MM_PER_M,
                             steps=int(steps), replan_every=int(replan_every))


class ReachProgress(NamedTuple):
    """A ``Reach.Feedback`` in mm: steps executed, the measured distance to the goal, the predicted final one."""

    step: int
    error_mm: float
    predicted_final_error_mm: float


def reach_progress(feedback: Any) -> ReachProgress:
    return ReachProgress(int(feedback.step), float(feedback.error_m) * _MM_PER_M,
                         float(feedback.predicted_final_error_m) * _MM_PER_M)


@dataclass(frozen=True)
class ReachOutcome:
    """A ``Reach.Result`` in mm: the verdict, why, the final error (None: unknown), the measured path and the
    predicted one with the stamp of its first pose (when the plan was sent)."""

    success: bool
    verdict: str
    reason: str
    final_error_mm: float | None
    executed_mm: np.ndarray
    predicted_mm: np.ndarray
    predicted_start_ns: int


def reach_outcome(result: Any) -> ReachOutcome:
    """The :class:`ReachOutcome` of a ``Reach.Result``; ValueError for paths in another frame."""
    error = float(result.final_error_m)
    return ReachOutcome(bool(result.success), str(result.verdict), str(result.reason),
                        error * _MM_PER_M if math.isfinite(error) else None, path_xy_mm(result.executed),
                        path_xy_mm(result.predicted), stamp_to_ns(result.predicted.header.stamp))
