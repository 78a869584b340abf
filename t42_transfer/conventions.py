"""Units, layouts and defaults shared by every layer (one place, so they cannot drift).

Inside the package a hand state is ``(object x mm, object y mm, load1, load2)`` with
loads in raw servo units, and an action is a pair of normalised actuator-angle
increments applied for one control period.  On the ROS wire everything is SI
(REP 103); the conversions live in :mod:`msg_adapters`.
"""

from __future__ import annotations

STATE_DIM = 4
ACTION_DIM = 2
STATE_NAMES = ("x_mm", "y_mm", "load1", "load2")

CONTROL_PERIOD_S = 0.1
"""The hands run at 10 Hz: one action per 0.1 s."""
CONTROL_PERIOD_NS = 100_000_000

ACTION_UNIT_RAD = 0.025
"""Actuator-angle change (rad) of an action component of 1.0 over one control period."""

ACTION_LIMIT = 1.5
"""Largest accepted |action| component: the real hands' discrete set contains +-1.5."""

RANDOM_POLICY_LIMIT = 1.0
"""The paper's random policy and the planner draw actions in [-1, 1]^2."""

REAL_HAND_ACTIONS = (
    (1.0, 1.0),
    (-1.0, -1.0),
    (-1.0, 1.0),
    (1.0, -1.0),
    (1.5, 0.0),
    (-1.5, 0.0),
    (0.0, 1.5),
    (0.0, -1.5),
)
"""The real hands' discrete moves: both fingers together, against each other, or one alone."""

LOAD_UNIT_NM = 0.0041
"""Torque (N m) of one raw load unit: 0.1 % of a Dynamixel XM430's 4.1 N m stall torque."""

GRASP_LOAD = 100.0
"""The grasp-closing routine closes until |load| passes this (as the real driver)."""

OVERLOAD_LOAD = 280.0
"""|load| above this ends an episode (the real driver refused moves past it)."""

DROP_JUMP_MM = 8.0
"""An object jump larger than this in one step counts as a drop (paper's data rule)."""

MIN_EPISODE_STEPS = 15
"""Episodes shorter than this are discarded (paper's data rule)."""

ACTUATOR_NAMES = ("actuator_1", "actuator_2")
FRAME_ID = "t42_base"
