"""The scene ``t42 view`` draws, as plain data: the hand from its actuator angles, the object, the goal with its
tolerance circle, the planned path and candidate rollouts (millimetres in ``t42_base``, z = 0).

The drawing uses the simulated hand's geometry (:mod:`t42_transfer.hand.params`, as :mod:`~t42_transfer.hand.mjcf`
builds it): finger bases at ``x = -/+ base_half_width_mm``, links of ``proximal_mm`` and ``distal_mm`` pointing
along +y at rest and flexing towards the centre line, the palm block between the bases.  ``hand/joint_states``
gives only the two servo angles; the fingers are underactuated, so the phalanges' angles are not measured.  They
are taken quasi-statically: the servo reels in ``spool_radius_mm * angle`` of tendon, shared by the two joints in
proportion to their moment arms over their spring stiffnesses (the tension that balances both springs), each joint
kept in its travel; with an object, the tension is cut to where the links first touch it (a bisection), so the
fingers wrap the object instead of passing through it.  A picture, not a simulation: good to a few millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from t42_transfer.hand.mjcf import FINGER_SIDES, LINK_RADIUS_MM
from t42_transfer.hand.params import FingerParams, HandParams, variant

PROXIMAL_TRAVEL_RAD = (-0.8, 1.9)
"""Proximal joint range (rad), as :data:`t42_transfer.hand.mjcf.PROXIMAL_RANGE`."""
DISTAL_TRAVEL_RAD = (-0.2, 1.7)
"""Distal joint range (rad), as the MJCF's distal joints."""
DEFAULT_TOLERANCE_MM = 2.0
"""The planner's default tolerance (:class:`~t42_transfer.planning.PlannerConfig`), drawn round a goal."""
_SWEEP_STEPS = 40
_BISECTIONS = 20


def finger_joint_angles(finger: FingerParams, reel_mm: float, scale: float = 1.0) -> tuple[float, float]:
    """(proximal, distal) joint angles (rad, flexion positive) of a finger whose tendon is reeled ``reel_mm`` in
    from slack, its pull scaled by ``scale`` in [0, 1] (1: the free finger, 0: the springs' rest pose)."""
    rest = math.radians(finger.rest_deg)
    if reel_mm <= 0.0 or scale <= 0.0:
        return rest, 0.0
    rp, rd = finger.r_proximal_mm, finger.r_distal_mm
    # Springs k (theta - rest) = T r at both joints, tendon rp dp + rd dd = reel: T = reel / (rp^2/kp + rd^2/kd).
    tension = scale * reel_mm / (rp * rp / finger.k_proximal + rd * rd / finger.k_distal)
    proximal = float(np.clip(rest + tension * rp / finger.k_proximal, *PROXIMAL_TRAVEL_RAD))
    distal = float(np.clip(tension * rd / finger.k_distal, *DISTAL_TRAVEL_RAD))
    return proximal, distal


def finger_points(side: str, finger: FingerParams, base_half_width_mm: float,
                  proximal: float, distal: float) -> np.ndarray:
    """Base, knuckle and tip ``[3, 2]`` (mm) of the ``left`` or ``right`` finger at these joint angles."""
    if side not in FINGER_SIDES:
        raise ValueError(f"side must be one of {FINGER_SIDES}, got {side!r}")
    inward = 1.0 if side == "left" else -1.0  # flexion turns the left finger towards +x, the right towards -x
    base = np.array([-inward * base_half_width_mm, 0.0])
    knuckle = base + finger.proximal_mm * np.array([inward * math.sin(proximal), math.cos(proximal)])
    total = proximal + distal
    tip = knuckle + finger.distal_mm * np.array([inward * math.sin(total), math.cos(total)])
    return np.stack([base, knuckle, tip])


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(point - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def _touches(points: np.ndarray, centre: np.ndarray, clearance_mm: float) -> bool:
    return any(_segment_distance(centre, points[i], points[i + 1]) < clearance_mm for i in range(len(points) - 1))


def _first_contact(touches: Callable[[float], bool]) -> float:
    """The largest ``u`` in [0, 1] up to which ``touches(u)`` stays false, sweeping from 0 (a finger closes
    continuously, so the first touch is what stops it): 1.0 when it never touches, 0.0 when it already does."""
    if touches(0.0):
        return 0.0
    low = 0.0
    for k in range(1, _SWEEP_STEPS + 1):
        high = k / _SWEEP_STEPS
        if touches(high):
            for _ in range(_BISECTIONS):
                mid = 0.5 * (low + high)
                low, high = (low, mid) if touches(mid) else (mid, high)
            return low
        low = high
    return 1.0


def _wrapped(side: str, finger: FingerParams, half_width: float, reel: float, centre: np.ndarray,
             clearance: float) -> tuple[float, float]:
    """Joint angles of a finger closing on the object: free until a link touches it; a proximal link held there
    leaves the rest of the tendon to the distal joint, which closes until its pad touches too."""
    def points(proximal: float, distal: float) -> np.ndarray:
        return finger_points(side, finger, half_width, proximal, distal)

    scale = _first_contact(lambda u: _touches(points(*finger_joint_angles(finger, reel, u)), centre, clearance))
    proximal, distal = finger_joint_angles(finger, reel, scale)
    if scale >= 1.0 or reel <= 0.0:
        return proximal, distal
    knuckle, _ = points(proximal, distal)[1:]
    if _segment_distance(centre, points(proximal, distal)[0], knuckle) >= clearance * 1.001:
        return proximal, distal  # the pad touched first: the object stops the finger
    rest = math.radians(finger.rest_deg)
    spare = reel - finger.r_proximal_mm * (proximal - rest) - finger.r_distal_mm * distal
    most = float(np.clip(distal + max(spare, 0.0) / finger.r_distal_mm, *DISTAL_TRAVEL_RAD))
    pad = _first_contact(lambda u: _touches(points(proximal, distal + u * (most - distal))[1:], centre, clearance))
    return proximal, distal + pad * (most - distal)


def hand_fingers(params: HandParams, actuator_angles: Sequence[float] | None,
                 object_xy_mm: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The (left, right) fingers' base, knuckle and tip ``[3, 2]`` (mm) at ``actuator_angles`` (rad, action order:
    ``actuator_1, actuator_2`` as ``hand/joint_states`` names them; None: the springs' rest pose), wrapped round
    the object at ``object_xy_mm`` when given."""
    servo = np.zeros(2)
    if actuator_angles is not None:
        angles = np.asarray(actuator_angles, dtype=float)
        if angles.shape != (2,) or not np.all(np.isfinite(angles)):
            raise ValueError(f"actuator angles must be 2 finite numbers, got {actuator_angles!r}")
        servo[list(params.actuator_order)] = angles  # action component i turns finger actuator_order[i]
    centre = None if object_xy_mm is None else np.asarray(object_xy_mm, dtype=float)
    clearance = params.object_radius_mm + LINK_RADIUS_MM
    fingers = []
    for side, finger, angle in zip(FINGER_SIDES, (params.left, params.right), servo, strict=True):
        reel = params.spool_radius_mm * float(angle)
        proximal, distal = finger_joint_angles(finger, reel)
        if centre is not None:
            proximal, distal = _wrapped(side, finger, params.base_half_width_mm, reel, centre, clearance)
        fingers.append(finger_points(side, finger, params.base_half_width_mm, proximal, distal))
    return fingers[0], fingers[1]


def palm_outline(params: HandParams) -> np.ndarray:
    """The palm block's closed outline ``[5, 2]`` (mm), as the MJCF's palm box."""
    half = params.base_half_width_mm - 9.0
    top = params.palm_height_mm
    return np.array([[-half, 0.0], [half, 0.0], [half, top], [-half, top], [-half, 0.0]])


def _xy(name: str, value: Sequence[float] | None) -> np.ndarray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=float)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 2 finite numbers (mm), got {value!r}")
    return arr


def _path(name: str, value: np.ndarray | Sequence[Sequence[float]] | None) -> np.ndarray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=float).reshape(-1, 2) if len(value) else np.zeros((0, 2))
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has a non-finite position")
    return arr


@dataclass(frozen=True)
class Scene:
    """Everything drawn, in mm in ``t42_base``; what is None (or empty) is not drawn."""

    fingers: tuple[np.ndarray, ...]
    """Each finger's base, knuckle and tip ``[3, 2]``."""
    palm: np.ndarray
    """The palm's closed outline ``[5, 2]``."""
    link_radius_mm: float
    object_radius_mm: float
    extent_mm: tuple[float, float, float, float]
    """(x min, x max, y min, y max) that holds the hand at any pose: a fixed frame for pictures."""
    object_xy_mm: np.ndarray | None = None
    goal_xy_mm: np.ndarray | None = None
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    path_xy_mm: np.ndarray | None = None
    """The planned (predicted) object path ``[N, 2]``."""
    candidates: tuple[np.ndarray, ...] = field(default_factory=tuple)
    """Other rollouts the planner weighed (its top K), each ``[N, 2]``."""
    goal_refused: str = ""
    """The planner's status word when it refused the goal (``unreachable``...), drawn beside it; empty: not
    refused (or not known)."""


def hand_extent(params: HandParams) -> tuple[float, float, float, float]:
    """A frame round the hand at any pose: its fingers' reach on every side, 10 mm beyond the base."""
    reach = max(f.proximal_mm + f.distal_mm for f in (params.left, params.right))
    half = params.base_half_width_mm + reach * 0.75
    return -half, half, -10.0, reach + 10.0


def build_scene(hand: HandParams | str = "target", *, actuator_angles: Sequence[float] | None = None,
                object_xy_mm: Sequence[float] | None = None, goal_xy_mm: Sequence[float] | None = None,
                tolerance_mm: float = DEFAULT_TOLERANCE_MM, path_xy_mm: np.ndarray | None = None,
                candidates: Sequence[np.ndarray] = (), goal_refused: str = "") -> Scene:
    """The :class:`Scene` of one moment; ValueError names a bad input (NaN, wrong shape, a tolerance <= 0)."""
    params = variant(hand) if isinstance(hand, str) else hand
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance must be a positive number of mm, got {tolerance_mm!r}")
    obj = _xy("object position", object_xy_mm)
    return Scene(
        fingers=hand_fingers(params, actuator_angles, obj),
        palm=palm_outline(params),
        link_radius_mm=LINK_RADIUS_MM,
        object_radius_mm=params.object_radius_mm,
        extent_mm=hand_extent(params),
        object_xy_mm=obj,
        goal_xy_mm=_xy("goal", goal_xy_mm),
        tolerance_mm=float(tolerance_mm),
        path_xy_mm=_path("path", path_xy_mm),
        candidates=tuple(p for p in (_path("candidate", c) for c in candidates) if p is not None),
        goal_refused=str(goal_refused),
    )
