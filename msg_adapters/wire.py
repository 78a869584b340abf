"""What a hand's messages mean on the wire: the control period, actuators, frame and unit scales.

These facts belong to the hand's interface, so they are defined here, in the layer
that converts messages, and :mod:`t42_transfer.conventions` re-exports them for
the rest of the package (msg_adapters imports nothing from t42_transfer).
"""

from __future__ import annotations

import math
import numbers

CONTROL_PERIOD_S = 0.1
"""The hands run at 10 Hz: one action per 0.1 s."""
CONTROL_PERIOD_NS = 100_000_000
LATE_STEP_NS = 3 * CONTROL_PERIOD_NS // 2
"""A step stamped more than this after the previous one is late (a driver says so on ``hand/status``)."""
MIN_STEP_NS = CONTROL_PERIOD_NS // 2
"""Two steps are never stamped closer than this: a driver catching up after a late step skips the tick."""

ACTUATOR_NAMES = ("actuator_1", "actuator_2")
ACTION_DIM = len(ACTUATOR_NAMES)
FRAME_ID = "t42_base"

ACTION_UNIT_RAD = 0.025
"""Actuator-angle change (rad) of an action component of 1.0 over one control period: the suite's unit, that of
the simulated hands' actions and the default of every conversion (data and models of another unit say so)."""

LOAD_UNIT_NM = 0.0041
"""Torque (N m) of one raw load unit: 0.1 % of a Dynamixel XM430's 4.1 N m stall torque."""

AUTHORS_ACTION_UNIT_RAD = 0.00065 * 0.95 * 2 * math.pi
"""The paper authors' unit (0.00388 rad): their ROS 1 driver moved a servo ``0.065 * a / 100`` of its normalised
range a step, and their copy of the OpenHand driver spans 0.95 of an XM servo's turn (motorMin 0.05, motorMax
1.0).  Their real-hand data and models are in it; a model file says which unit its actions are in."""

MAX_ACTION_UNIT_RAD = 0.1
"""Largest unit accepted (1 rad/s at an action of 1): a larger one is a typo, not a hand's step."""


def checked_action_unit(unit_rad: float) -> float:
    """``unit_rad`` as a float, or ValueError when it is no unit a hand steps in."""
    if isinstance(unit_rad, bool) or not isinstance(unit_rad, numbers.Real) or not 0 < unit_rad <= MAX_ACTION_UNIT_RAD:
        raise ValueError(f"an action unit must be a number of rad in (0, {MAX_ACTION_UNIT_RAD:g}], got {unit_rad!r}")
    return float(unit_rad)


def same_action_unit(a_rad: float, b_rad: float) -> bool:
    """Whether two units are one within 0.1 %: the authors' written to three figures (0.00388) is theirs."""
    return math.isclose(a_rad, b_rad, rel_tol=1e-3)
