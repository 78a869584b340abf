"""Units, layouts and defaults shared by every layer (one place, so they cannot drift).

Inside the package a hand state is ``(object x mm, object y mm, load1, load2)`` with
loads in raw servo units, and an action is a pair of normalised actuator-angle
increments applied for one control period.  On the ROS wire everything is SI
(REP 103); the conversions live in :mod:`msg_adapters`.  The wire facts (control
period, actuators, frame, unit scales) and the episode end reasons, which are also
status words, are defined there, in the layer below, and re-exported here.
"""

from __future__ import annotations

from msg_adapters.names import DROPPED, LOST_CONTACT, OVERLOAD, RESET
from msg_adapters.wire import (
    ACTION_DIM,
    ACTION_UNIT_RAD,
    ACTUATOR_NAMES,
    AUTHORS_ACTION_UNIT_RAD,
    CONTROL_PERIOD_NS,
    CONTROL_PERIOD_S,
    FRAME_ID,
    LATE_STEP_NS,
    LOAD_UNIT_NM,
    MAX_ACTION_UNIT_RAD,
    MIN_STEP_NS,
    checked_action_unit,
    same_action_unit,
)

STATE_DIM = 4
STATE_NAMES = ("x_mm", "y_mm", "load1", "load2")

ACTION_LIMIT = 1.5
"""Largest accepted |action| component: the real hands' discrete set contains +-1.5."""
MAX_STEP_RAD = ACTION_LIMIT * ACTION_UNIT_RAD
"""The largest actuator step a driver takes in one period (0.0375 rad: an action of ACTION_LIMIT in the suite's
unit); actions of a larger unit that would step further are refused there."""

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

MAX_OBJECT_DISTANCE_MM = 1000.0
"""A held object is a few centimetres above the palm: a tracker pose farther than this from ``t42_base`` is not
of the object in the hand (a marker elsewhere in view, a bridge's unit error) and no driver publishes it."""

MAX_PLAN_SAMPLES = 1_000_000
MAX_PLAN_HORIZON = 10_000
MAX_REFINE = 1000
MAX_SAMPLED_STEPS = 20_000_000
"""Planner samples x horizon at most (CLI, planner node and code alike): the sampled actions alone are 8 bytes
a step, 160 MB here."""
MAX_TRIALS = 10_000
"""Peg-in-hole trials per goal distance at most."""
MAX_THREADS = 1024
"""Torch threads a peg-in-hole run may ask for at most."""
PLAN_LENGTHS = ("fixed", "search")
"""Peg-in-hole plan lengths: exactly the goal's steps, or the shortest predicted to reach the goal."""

GRASP_LOAD = 100.0
"""The grasp-closing routine closes until |load| passes this (as the real driver)."""

OVERLOAD_LOAD = 280.0
"""|load| above this ends an episode (the real driver refused moves past it)."""

MM_PER_M = 1000.0
"""The science works in mm (the paper's unit); ROS messages and parameters are in metres (REP 103)."""

DROP_JUMP_MM = 8.0
"""An object jump larger than this in one step counts as a drop (paper's data rule)."""

MIN_EPISODE_STEPS = 15
"""Episodes shorter than this are discarded (paper's data rule)."""

END_REASONS = ("", "length", RESET, DROPPED, OVERLOAD, LOST_CONTACT)
"""Why an episode ended: not recorded, its planned length, the hand grasped anew after it (a bag's ``reset``
status), or one of the hand's end events."""
DROP_REASONS = (DROPPED, LOST_CONTACT)
"""End reasons that mean the object left the grasp."""
