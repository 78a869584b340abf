"""Plan results <-> plain Python: ``t42_interfaces/msg/PlanResult``, the planner's ``t42/plan_result``.

Inside the package a result is :class:`PlanResult` (millimetres, as the planner works); on the wire it is metres in
``FRAME_ID`` (REP 103), one division per direction, so goal and start positions (float32 mm) survive the round trip
bit for bit.  What has no value travels as a flag (``has_goal``, ``has_start``) or NaN (``predicted_error_m``).
rclpy's classes by default, as for the Reach action: ``t42_interfaces`` is ours, not in rosbags' Jazzy typestore.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.hand import _MM_PER_M, _header, stamp_to_ns
from msg_adapters.kit import RCLPY, MessageKit
from msg_adapters.wire import FRAME_ID

PLAN_RESULT_MSG = "t42_interfaces/msg/PlanResult"

_UINT32 = 2**32 - 1
_INT32 = 2**31


@dataclass(frozen=True)
class PlanResult:
    """What became of one goal of the planner: accepted, or refused with a status and a reason."""

    accepted: bool
    status: str
    """``ok`` when accepted; else a planner status (``unreachable``, ``goal_outside_workspace``, ...) or
    ``bad_goal``, ``no_model``, ``no_state``, ``stale_state``, ``superseded``, ``episode_ended`` (planned, and the
    episode ended before the plan went out), ``error``."""
    reason: str
    goal_mm: list[float] | None
    """None when the goal message could not be read."""
    goal_stamp_ns: int
    start_mm: list[float] | None = None
    predicted_error_mm: float | None = None
    horizon: int = 0
    """Steps of the plan (of the published trajectory when accepted)."""
    samples_evaluated: int = 0
    planning_time_s: float = 0.0
    model: str = ""
    method: str = ""
    replan_every: int = 0
    """0: the whole plan was sent; k: its first k steps, the rest replanned as they run."""


def plan_result_msg(result: PlanResult, stamp_ns: int, kit: MessageKit = RCLPY) -> Any:
    """The ``PlanResult`` message of ``result``, stamped ``stamp_ns`` (when published) in ``FRAME_ID``.

    Total for what the planner hands over: a goal stamp outside ``builtin_interfaces/Time`` (a refused goal's
    own) is clamped into it, counts into ``uint32``; a non-finite predicted error is sent as NaN.
    """
    error = result.predicted_error_mm
    return kit.make(
        PLAN_RESULT_MSG,
        header=_header(stamp_ns, FRAME_ID, kit),
        accepted=bool(result.accepted), status=str(result.status), reason=str(result.reason),
        has_goal=result.goal_mm is not None, goal=_point(result.goal_mm, kit),
        goal_stamp=_any_stamp(result.goal_stamp_ns, kit),
        has_start=result.start_mm is not None, start=_point(result.start_mm, kit),
        predicted_error_m=math.nan if error is None or not math.isfinite(error) else float(error) / _MM_PER_M,
        horizon=_count(result.horizon), samples_evaluated=_count(result.samples_evaluated),
        planning_time_s=float(result.planning_time_s), model=str(result.model), method=str(result.method),
        replan_every=_count(result.replan_every),
    )


def plan_result(msg: Any) -> PlanResult:
    """The :class:`PlanResult` a ``PlanResult`` message carries (positions in mm, float32 values); ValueError for
    positions in another frame than ``FRAME_ID``."""
    if msg.header.frame_id != FRAME_ID:
        raise ValueError(f"plan result is in frame {msg.header.frame_id!r}, expected {FRAME_ID!r}")
    error = float(msg.predicted_error_m)
    return PlanResult(
        accepted=bool(msg.accepted), status=str(msg.status), reason=str(msg.reason),
        goal_mm=_xy_mm(msg.goal) if msg.has_goal else None, goal_stamp_ns=stamp_to_ns(msg.goal_stamp),
        start_mm=_xy_mm(msg.start) if msg.has_start else None,
        predicted_error_mm=error * _MM_PER_M if math.isfinite(error) else None,
        horizon=int(msg.horizon), samples_evaluated=int(msg.samples_evaluated),
        planning_time_s=float(msg.planning_time_s), model=str(msg.model), method=str(msg.method),
        replan_every=int(msg.replan_every),
    )


def _point(xy_mm: Sequence[float] | None, kit: MessageKit) -> Any:
    x, y = (0.0, 0.0) if xy_mm is None else (float(v) / _MM_PER_M for v in xy_mm)
    return kit.make("geometry_msgs/msg/Point", x=x, y=y, z=0.0)


def _xy_mm(point: Any) -> list[float]:
    return (np.array([point.x, point.y], np.float64) * _MM_PER_M).astype(np.float32).tolist()


def _any_stamp(stamp_ns: int, kit: MessageKit) -> Any:
    """``builtin_interfaces/Time`` of any nanosecond count (negative ones too, as a header can hold them)."""
    sec, nanosec = divmod(int(stamp_ns), 10**9)
    if not -_INT32 <= sec < _INT32:
        sec, nanosec = (-_INT32, 0) if sec < 0 else (_INT32 - 1, 10**9 - 1)
    return kit.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def _count(value: int) -> int:
    return min(max(int(value), 0), _UINT32)
