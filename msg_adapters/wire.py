"""What a hand's messages mean on the wire: the control period, actuators, frame and unit scales.

These facts belong to the hand's interface, so they are defined here, in the layer
that converts messages, and :mod:`t42_transfer.conventions` re-exports them for
the rest of the package (msg_adapters imports nothing from t42_transfer).
"""

from __future__ import annotations

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
"""Actuator-angle change (rad) of an action component of 1.0 over one control period."""

LOAD_UNIT_NM = 0.0041
"""Torque (N m) of one raw load unit: 0.1 % of a Dynamixel XM430's 4.1 N m stall torque."""
