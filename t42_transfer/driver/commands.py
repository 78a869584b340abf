"""What a hand driver accepts and applies, for the mock and the real driver alike: one set of rules.

:func:`validate_command` and :func:`validate_trajectory` turn a ``hand/command`` JointState and a
``hand/trajectory`` JointTrajectory into checked actions, or a :class:`CommandRejected` saying why (NaN/inf,
``|a| > ACTION_LIMIT``, missing actuators, points not one period apart, unset, stale or future stamps).
:class:`ActionQueue` decides what each step applies: a running trajectory's next point, else the latest
single-step command (held for one step only), else ``(0, 0)``.  A new command cancels a trajectory; a new
trajectory pre-empts a running one; an empty trajectory just cancels.  Nothing here needs ROS.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np

from msg_adapters import (
    JOINT_STATE,
    JOINT_TRAJECTORY,
    applied_action,
    joint_trajectory_to_actions,
    rclpy_message,
    stamp_to_ns,
)
from t42_transfer.conventions import ACTION_DIM, ACTION_LIMIT, MAX_PLAN_HORIZON

T = TypeVar("T")
_LIMIT_SLACK = 1e-6
"""Relative slack on ACTION_LIMIT: wire round trips may land a hair past +-1.5."""


class CommandRejected(ValueError):
    """An input message the driver will not execute; the message says why."""


def check_stamp(stamp_ns: int, now_ns: int, max_age_ns: int, what: str = "command") -> None:
    """Refuse an unset (zero), stale (older than ``max_age_ns``) or future (beyond ``max_age_ns``) stamp."""
    if stamp_ns == 0:
        raise CommandRejected(f"{what} header stamp is unset (0)")
    age = now_ns - stamp_ns
    if age > max_age_ns:
        raise CommandRejected(f"{what} is stale: stamped {age / 1e9:.3f} s ago, limit {max_age_ns / 1e9:.3f} s")
    if -age > max_age_ns:
        raise CommandRejected(
            f"{what} is stamped {-age / 1e9:.3f} s in the future, limit {max_age_ns / 1e9:.3f} s"
        )


def check_actions(actions: np.ndarray, what: str = "action") -> np.ndarray:
    """``actions`` ([..., 2]) clipped onto the limit if within slack; CommandRejected if non-finite or too large."""
    acts = np.asarray(actions, dtype=np.float64)
    if acts.shape[-1:] != (ACTION_DIM,):
        raise CommandRejected(f"{what} must have {ACTION_DIM} components, got shape {acts.shape}")
    if not np.all(np.isfinite(acts)):
        raise CommandRejected(f"{what} has a non-finite value: {acts.tolist()}")
    too_big = np.abs(acts) > ACTION_LIMIT * (1.0 + _LIMIT_SLACK)
    if np.any(too_big):
        where = np.argwhere(too_big)[0].tolist()
        raise CommandRejected(
            f"{what} {acts[tuple(where)]:.6g} at index {where} is outside [-{ACTION_LIMIT}, {ACTION_LIMIT}]"
        )
    return np.clip(acts, -ACTION_LIMIT, ACTION_LIMIT)


def validate_command(msg: Any, now_ns: int, max_age_ns: int) -> np.ndarray:
    """The single-step action (float64 [2]) of a command ``JointState`` (or its CDR bytes, size-checked before
    they are read), or CommandRejected saying why.

    The action is decoded from ``velocity`` by :func:`msg_adapters.applied_action`
    (velocity = action * ACTION_UNIT_RAD / CONTROL_PERIOD_S per actuator).
    """
    msg = _read(msg, JOINT_STATE, MAX_COMMAND_BYTES, "command")
    check_stamp(stamp_to_ns(msg.header.stamp), now_ns, max_age_ns, "command")
    try:
        action = applied_action(msg, "command")
    except ValueError as err:
        raise CommandRejected(str(err)) from None
    return check_actions(action, "command action")


def validate_trajectory(msg: Any, start_angles: np.ndarray | Sequence[float], now_ns: int,
                        max_age_ns: int) -> np.ndarray:
    """Actions ``[T, 2]`` (float64) of a ``JointTrajectory`` (or its CDR bytes, size-checked before they are
    read) started from ``start_angles``, or CommandRejected.

    Decoded by :func:`msg_adapters.joint_trajectory_to_actions` (points every
    control period, actuator-angle targets).  A zero header stamp means "start
    now" (ROS convention); any other stamp must be fresh as for commands.  An
    empty trajectory is valid and gives ``T = 0``; one longer than any plan is refused.
    """
    msg = _read(msg, JOINT_TRAJECTORY, MAX_TRAJECTORY_BYTES, "trajectory")
    if len(msg.points) > MAX_PLAN_HORIZON:
        raise CommandRejected(f"trajectory of {len(msg.points)} points: no plan is longer than {MAX_PLAN_HORIZON}")
    stamp = stamp_to_ns(msg.header.stamp)
    if stamp != 0:
        check_stamp(stamp, now_ns, max_age_ns, "trajectory")
    try:
        actions = joint_trajectory_to_actions(msg, start_angles)
    except ValueError as err:
        raise CommandRejected(f"trajectory: {err}") from None
    return check_actions(actions.reshape(-1, ACTION_DIM), "trajectory action")


MAX_COMMAND_BYTES = 4096
"""A command names two actuators: its CDR is under 100 bytes (a 4 KiB one is no command)."""
MAX_TRAJECTORY_BYTES = 128 * MAX_PLAN_HORIZON + 65_536
"""The longest plan's CDR with room to spare (40-56 bytes a point as planners send it; 128 allows velocities and
efforts too)."""


def _read(msg: Any, typename: str, max_bytes: int, what: str) -> Any:
    """``msg`` itself, or the message of a raw subscription's bytes, refused unread (:class:`CommandRejected`)
    when larger than any such message needs: a driver reads the size before it spends seconds deserializing."""
    if not isinstance(msg, (bytes, bytearray, memoryview)):
        return msg
    data = bytes(msg)
    try:
        return rclpy_message(data, typename, max_bytes)
    except ValueError as err:
        raise CommandRejected(f"{what}: {err}") from None


def accept(log: Any, topic: str, check: Callable[[], T]) -> T | None:
    """What ``check()`` returns, or None with the reason logged on ``log``: a driver's callback never raises."""
    try:
        return check()
    except CommandRejected as err:
        log.warning(f"rejected {topic}: {err}; ignored (the hand goes on as before: holding, or the trajectory it "
                    "runs)")
    except Exception as err:  # a message no check foresaw
        log.error(f"rejected {topic}: could not read the message ({err!r})")
    return None


class ActionQueue:
    """The actions steps apply, fed by commands and trajectories (see the module docstring)."""

    def __init__(self) -> None:
        self.command: np.ndarray | None = None
        self.plan: list[np.ndarray] = []

    @property
    def pending(self) -> int:
        """Trajectory points still to apply."""
        return len(self.plan)

    def set_command(self, action: np.ndarray) -> int:
        """A single-step command for the next step; the trajectory points it cancelled."""
        cancelled, self.plan, self.command = len(self.plan), [], action
        return cancelled

    def set_plan(self, actions: np.ndarray) -> int:
        """A trajectory's actions from the next step on; the points of the one it pre-empted."""
        pre_empted, self.plan, self.command = len(self.plan), list(actions), None
        return pre_empted

    def clear(self) -> None:
        self.command, self.plan = None, []

    def next(self) -> tuple[np.ndarray, bool]:
        """(this step's action as float32 values, whether it is a trajectory's last point)."""
        if self.plan:
            action = self.plan.pop(0)
            last = not self.plan
        else:
            action = self.command if self.command is not None else np.zeros(ACTION_DIM)
            self.command, last = None, False  # a single-step command is held for one step only
        return np.asarray(action, np.float32).astype(np.float64), last
