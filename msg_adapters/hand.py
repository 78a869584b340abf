"""Hand messages <-> numpy: the one place that knows the wire units.

Inside the package a state is (x mm, y mm, load1, load2) and an action a pair of
normalised actuator-angle increments, all float32: ``unit_rad`` (default the suite's
``wire.ACTION_UNIT_RAD``) is the step of an action of 1, the unit of the model or data
the actions belong to.  On the wire (REP 103) they are
metres, N m, rad and rad/s in float64.  Every conversion goes float32 -> float64 ->
SI -> float64 -> float32 with one multiplication or division per direction, so a
value survives the round trip bit for bit (float64 has 29 bits to spare).
Builders make rosbags objects by default and rclpy's with ``kit=RCLPY``
(:mod:`msg_adapters.kit`); the readers touch only fields, so they take either.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msg_adapters import names, wire
from msg_adapters.kit import ROSBAGS, MessageKit

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"

OBJECT_POSE_TOPIC = "/" + names.OBJECT_POSE
JOINT_STATES_TOPIC = "/" + names.JOINT_STATES
APPLIED_ACTION_TOPIC = "/" + names.APPLIED_ACTION
"""The hand topics as a bag of a suite in the root namespace names them (resolved, absolute)."""
HAND_TOPICS = {
    OBJECT_POSE_TOPIC: POSE_STAMPED,
    JOINT_STATES_TOPIC: JOINT_STATE,
    APPLIED_ACTION_TOPIC: JOINT_STATE,
}
"""The hand's recorded topics and their message types, in per-step publish order."""

_MM_PER_M = 1000.0
_MAX_STAMP_NS = 2**31 * 10**9
"""builtin_interfaces/Time holds int32 seconds."""
_SPACING_TOLERANCE_NS = 1_000
"""Trajectory point times may carry float rounding from their producer; 1 us of it."""

_NO_VALUES = np.zeros(0, np.float64)


def ns_to_stamp(stamp_ns: int, kit: MessageKit = ROSBAGS) -> Any:
    """``builtin_interfaces/Time`` of a non-negative nanosecond count."""
    if not 0 <= stamp_ns < _MAX_STAMP_NS:
        raise ValueError(f"stamp {stamp_ns} ns is outside builtin_interfaces/Time's range [0, 2^31 s)")
    sec, nanosec = divmod(int(stamp_ns), 10**9)
    return kit.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (or Duration)."""
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def _duration(ns: int, kit: MessageKit) -> Any:
    sec, nanosec = divmod(ns, 10**9)
    return kit.make("builtin_interfaces/msg/Duration", sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str, kit: MessageKit) -> Any:
    return kit.make("std_msgs/msg/Header", stamp=ns_to_stamp(stamp_ns, kit), frame_id=frame_id)


def _pair(name: str, value: np.ndarray | Sequence[float]) -> np.ndarray:
    """A finite float32 pair widened to float64, ready for SI arithmetic."""
    arr = np.asarray(value, dtype=np.float32)
    if arr.shape != (wire.ACTION_DIM,):
        raise ValueError(f"{name} must have shape ({wire.ACTION_DIM},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has a non-finite value: {arr.tolist()}")
    return arr.astype(np.float64)


def _to_f32(name: str, value: np.ndarray) -> np.ndarray:
    """Narrow wire values to float32, refusing NaN, inf and values float32 cannot hold."""
    with np.errstate(over="ignore"):
        out = np.asarray(value, dtype=np.float64).astype(np.float32)
    if not np.isfinite(out).all():  # NaN and inf stay so; too large values become inf
        why = "has a non-finite value" if not np.isfinite(value).all() else "is outside float32 range"
        raise ValueError(f"{name} {why}: {np.asarray(value).tolist()}")
    return out


def _actuator_columns(names: Sequence[str], what: str) -> list[int]:
    """Where each actuator sits in a message's name list (messages may order or add joints)."""
    names = list(names)
    missing = [n for n in wire.ACTUATOR_NAMES if n not in names]
    if missing:
        raise ValueError(f"{what} lacks actuator(s) {missing}; it names {names}")
    return [names.index(n) for n in wire.ACTUATOR_NAMES]


def _per_joint(values: np.ndarray, names: Sequence[str], field: str) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if len(values) != len(names):
        raise ValueError(f"{field} has {len(values)} values for {len(names)} joint names")
    return values


def object_pose_msg(xy_mm: np.ndarray | Sequence[float], stamp_ns: int, kit: MessageKit = ROSBAGS) -> Any:
    """``PoseStamped`` of the object position (metres in wire.FRAME_ID, z = 0, identity orientation)."""
    x, y = _pair("object position", xy_mm) / _MM_PER_M
    return kit.make(
        POSE_STAMPED,
        header=_header(stamp_ns, wire.FRAME_ID, kit),
        pose=kit.make(
            "geometry_msgs/msg/Pose",
            position=kit.make("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0),
            orientation=kit.make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )


def object_xy_mm(msg: Any) -> np.ndarray:
    """Object ``(x, y)`` in mm (float32) of a ``PoseStamped``; refuses other frames."""
    if msg.header.frame_id != wire.FRAME_ID:
        raise ValueError(f"object pose is in frame {msg.header.frame_id!r}, expected {wire.FRAME_ID!r}")
    position = msg.pose.position
    return _to_f32("object position", np.array([position.x, position.y]) * _MM_PER_M)


def joint_state_msg(
    loads: np.ndarray | Sequence[float],
    angles: np.ndarray | Sequence[float] | None,
    stamp_ns: int,
    kit: MessageKit = ROSBAGS,
) -> Any:
    """``JointState`` of the actuators: effort = loads in N m, position = angles (empty if unknown)."""
    effort = _pair("loads", loads) * wire.LOAD_UNIT_NM
    position = _NO_VALUES if angles is None else _pair("actuator angles", angles)
    return _actuator_state(stamp_ns, kit, position=position, effort=effort)


def _actuator_state(stamp_ns: int, kit: MessageKit, position: np.ndarray = _NO_VALUES,
                    velocity: np.ndarray = _NO_VALUES, effort: np.ndarray = _NO_VALUES) -> Any:
    """A ``JointState`` of the two actuators, in their order; fields not given are empty."""
    return kit.make(JOINT_STATE, header=_header(stamp_ns, "", kit), name=list(wire.ACTUATOR_NAMES),
                    position=kit.floats(position), velocity=kit.floats(velocity), effort=kit.floats(effort))


def joint_state_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``(loads, angles or None)`` in raw load units and rad (float32) of a ``JointState``."""
    cols = _actuator_columns(msg.name, "joint state")
    effort = _per_joint(msg.effort, msg.name, "joint state effort")
    loads = _to_f32("joint state effort", effort[cols] / wire.LOAD_UNIT_NM)
    if len(msg.position) == 0:
        return loads, None
    position = _per_joint(msg.position, msg.name, "joint state position")
    return loads, _to_f32("joint state position", position[cols])


def applied_action_msg(action: np.ndarray | Sequence[float], stamp_ns: int, kit: MessageKit = ROSBAGS,
                       unit_rad: float = wire.ACTION_UNIT_RAD) -> Any:
    """``JointState`` whose velocity (rad/s) is the action held over one control period."""
    velocity = _pair("action", action) * wire.checked_action_unit(unit_rad) / wire.CONTROL_PERIOD_S
    return _actuator_state(stamp_ns, kit, velocity=velocity)


def applied_action(msg: Any, what: str = "applied action", unit_rad: float = wire.ACTION_UNIT_RAD) -> np.ndarray:
    """Normalised action (float32) of an applied-action ``JointState`` (or a command, ``what`` in messages: both
    carry the action as velocity over one control period)."""
    unit = wire.checked_action_unit(unit_rad)
    cols = _actuator_columns(msg.name, what)
    velocity = _per_joint(msg.velocity, msg.name, f"{what} velocity")
    return _to_f32(f"{what} velocity", velocity[cols] * wire.CONTROL_PERIOD_S / unit)


def actions_to_joint_trajectory(
    actions: np.ndarray, start_angles: np.ndarray | Sequence[float], stamp_ns: int, kit: MessageKit = ROSBAGS,
    unit_rad: float = wire.ACTION_UNIT_RAD,
) -> Any:
    """``JointTrajectory`` of actuator-angle targets, one per control period.

    Point ``k`` (at ``(k + 1) * wire.CONTROL_PERIOD_S``) is where the actuators stand
    after actions ``0..k``: ``start_angles + unit_rad * cumsum(actions)[k]``.
    """
    unit = wire.checked_action_unit(unit_rad)
    acts = np.asarray(actions, dtype=np.float32)
    if acts.ndim != 2 or acts.shape[1] != wire.ACTION_DIM:
        raise ValueError(f"actions must have shape [T, {wire.ACTION_DIM}], got {acts.shape}")
    if not np.all(np.isfinite(acts)):
        raise ValueError("actions have a non-finite value")
    targets = _pair("start angles", start_angles) + unit * np.cumsum(acts.astype(np.float64), axis=0)
    points = [
        kit.make(
            "trajectory_msgs/msg/JointTrajectoryPoint",
            positions=kit.floats(target),
            velocities=kit.floats(_NO_VALUES),
            accelerations=kit.floats(_NO_VALUES),
            effort=kit.floats(_NO_VALUES),
            time_from_start=_duration((k + 1) * wire.CONTROL_PERIOD_NS, kit),
        )
        for k, target in enumerate(targets)
    ]
    return kit.make(JOINT_TRAJECTORY, header=_header(stamp_ns, "", kit), joint_names=list(wire.ACTUATOR_NAMES),
                    points=points)


def joint_trajectory_to_actions(msg: Any, start_angles: np.ndarray | Sequence[float],
                                unit_rad: float = wire.ACTION_UNIT_RAD) -> np.ndarray:
    """Actions ``[T, 2]`` (float32, in ``unit_rad``) that move the actuators from ``start_angles`` through ``msg``'s
    points.

    Refuses trajectories the driver cannot execute step by step: missing
    actuators, points not spaced one control period apart, wrong position counts,
    non-finite targets.
    """
    unit = wire.checked_action_unit(unit_rad)
    cols = _actuator_columns(msg.joint_names, "joint trajectory")
    previous = _pair("start angles", start_angles)
    targets = np.zeros((len(msg.points), wire.ACTION_DIM), np.float64)
    for k, point in enumerate(msg.points):
        due = (k + 1) * wire.CONTROL_PERIOD_NS
        at = stamp_to_ns(point.time_from_start)
        if abs(at - due) > _SPACING_TOLERANCE_NS:
            raise ValueError(
                f"joint trajectory point {k} is at {at} ns; "
                f"points must be every {wire.CONTROL_PERIOD_NS} ns, so {due} ns"
            )
        positions = _per_joint(point.positions, msg.joint_names, f"joint trajectory point {k} positions")
        if not np.all(np.isfinite(positions[cols])):
            raise ValueError(f"joint trajectory point {k} has a non-finite position: {positions.tolist()}")
        targets[k] = positions[cols]
    steps = np.diff(np.vstack([previous, targets]), axis=0) / unit
    return _to_f32("joint trajectory actions", steps)
