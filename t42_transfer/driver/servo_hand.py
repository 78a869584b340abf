"""A T42 on two Dynamixel servos, in the hand's own terms: actuator angles, loads, actions, a grasp.

:class:`ServoHand` turns an action into Goal Positions (``angle += a * ACTION_UNIT_RAD`` per actuator, the wire's
action unit, so the radians a trajectory or command asks for are the radians the servos move), never
outside the position limits and never closing a finger whose load is over the limit, and reads actuator
angles and loads back (load from Present Current through the servo's torque constant, in the units of the
simulated hand's loads).  :class:`Grasp` is the reset routine the authors' driver ran: open, then close
each finger until its load passes the grasp load.  Hands A and B are mirror images: ``servo_ids`` lists the
servos in action order, ``directions`` says which way each closes.  Nothing here needs ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from t42_transfer.config import POSITIVE, between, check
from t42_transfer.conventions import ACTION_DIM, ACTION_UNIT_RAD, GRASP_LOAD, LOAD_UNIT_NM
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.servos import HandServos

MAX_TRAVEL_RAD = 4.0
"""How far a T42 finger's servo turns from open to fully closed on its tendon."""
RANGE_MARGIN_RAD = 0.1
"""How far outside [0, max_angle_rad] a finger may stand at configure (about 65 ticks; a slack tendon lets an open
finger's servo sit a little below its open tick): activate sets the goals where the fingers stand, clamped onto the
range, so a finger further out would move there by itself."""


@dataclass(frozen=True)
class HandGeometry:
    """Where the servos sit and how far they may go; the driver's hand parameters, checked here."""

    servo_ids: tuple[int, int] = (1, 2)
    """Servo ids in action order (hand A and hand B list them in opposite orders)."""
    open_ticks: tuple[int, int] = (xm.ZERO_TICK, xm.ZERO_TICK)
    """Present Position of each servo with its finger open (tendon just slack)."""
    directions: tuple[int, int] = (1, 1)
    """+1: ticks above the open tick close the finger; -1: ticks below it do."""
    max_angle_rad: tuple[float, float] = (3.0, 3.0)
    """Position limit of each servo, from open (the driver never writes a goal past it)."""
    load_limit: float = 280.0
    """No finger closes further while its load is over this (the authors' driver refused moves at 280)."""
    grasp_load: float = GRASP_LOAD
    """A reset closes each finger until its load passes this (the authors: 100)."""
    grasp_increment: float = 0.5
    """Action units a finger closes per step while grasping."""
    grasp_max_steps: int = 200

    def __post_init__(self) -> None:
        for name in ("servo_ids", "open_ticks", "directions", "max_angle_rad"):  # one per actuator, as a list
            value = getattr(self, name)
            if not isinstance(value, tuple | list) or len(value) != ACTION_DIM:
                raise ValueError(f"{name} must list {ACTION_DIM} values, one per actuator, got {value!r}")
        check(self, {"servo_ids": between(0, 252), "open_ticks": between(0, xm.MAX_TICK),
                     "directions": ((lambda v: v in (-1, 1)), "+1 or -1"),
                     "max_angle_rad": between(0, MAX_TRAVEL_RAD, low_open=True), "load_limit": POSITIVE,
                     "grasp_load": POSITIVE, "grasp_increment": between(0, 1.5, low_open=True),
                     "grasp_max_steps": between(1, 10_000)})
        if len(set(self.servo_ids)) != ACTION_DIM:
            raise ValueError(f"servo_ids must name two different servos, got {self.servo_ids}")
        if not self.grasp_load < self.load_limit:
            raise ValueError(f"grasp_load must be below load_limit, got {self.grasp_load} and {self.load_limit}")
        for k in range(ACTION_DIM):
            far = self.open_ticks[k] + self.directions[k] * math.ceil(self.max_angle_rad[k] / xm.RAD_PER_TICK)
            if not 0 <= far <= xm.MAX_TICK:
                raise ValueError(f"servo {self.servo_ids[k]}: open at tick {self.open_ticks[k]}, "
                                 f"{self.max_angle_rad[k]} rad of travel leaves the servo's range (tick {far})")

    def ticks(self, angles: np.ndarray) -> dict[int, int]:
        """Goal Positions of actuator ``angles`` (rad, action order), clamped onto the limits."""
        return self.positions(self.clamp(angles))

    def clamp(self, angles: np.ndarray) -> list[float]:
        """``angles`` onto [0, max_angle_rad] (NaN: 0), one float each: on two actuators every step, numpy's
        clip and nan_to_num cost several times the arithmetic."""
        return [0.0 if a != a else min(max(a, 0.0), high)
                for a, high in zip(map(float, angles), self.max_angle_rad, strict=True)]

    def positions(self, angles: np.ndarray) -> dict[int, int]:
        """Servo positions (ticks) of finite actuator ``angles``, unclamped: where the fingers are, as servos say."""
        return {i: self.open_ticks[k] + self.directions[k] * int(round(angles[k] / xm.RAD_PER_TICK))
                for k, i in enumerate(self.servo_ids)}

    def currents(self, loads: np.ndarray) -> dict[int, int]:
        """Present Current of each servo holding ``loads`` (the hand's units, action order): :meth:`loads` inverted."""
        return {i: self.directions[k] * xm.load_to_current(loads[k], LOAD_UNIT_NM)
                for k, i in enumerate(self.servo_ids)}

    def angles(self, positions: dict[int, int]) -> np.ndarray:
        return np.array([self.directions[k] * (positions[i] - self.open_ticks[k]) * xm.RAD_PER_TICK
                         for k, i in enumerate(self.servo_ids)])

    def loads(self, currents: dict[int, int]) -> np.ndarray:
        return np.array([self.directions[k] * xm.current_to_load(currents[i], LOAD_UNIT_NM)
                         for k, i in enumerate(self.servo_ids)])

    def limits(self) -> dict[int, tuple[int, int]]:
        """Min/Max Position Limit of each servo: the servo itself refuses a goal beyond them too."""
        ends = self.ticks(np.zeros(ACTION_DIM)), self.ticks(np.asarray(self.max_angle_rad))
        return {i: (min(ends[0][i], ends[1][i]), max(ends[0][i], ends[1][i])) for i in self.servo_ids}


class ServoHand:
    """The hand on its servos: read angles and loads, apply actions, hold, open (see the module docstring)."""

    def __init__(self, servos: HandServos, geometry: HandGeometry) -> None:
        self.servos, self.geometry = servos, geometry
        self.goal = np.zeros(ACTION_DIM)
        """Goal angles last written (rad, action order)."""
        self.angles = np.zeros(ACTION_DIM)
        self.loads = np.zeros(ACTION_DIM)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """One sync read: (actuator angles rad, loads), in action order."""
        state = self.servos.read_state()
        self.angles, self.loads = self.geometry.angles(state.positions), self.geometry.loads(state.currents)
        return self.angles.copy(), self.loads.copy()

    def start_from_present(self) -> None:
        """Goals where the servos stand (after configure, before torque: nothing moves when it comes on)."""
        self.read()
        self.goal = np.array(self.geometry.clamp(self.angles))

    def check_range(self, margin_rad: float = RANGE_MARGIN_RAD) -> None:
        """ValueError naming a servo that stands (at the last read) more than ``margin_rad`` outside its range: the
        goal activate gives it, clamped onto the range, would move its finger (``open_ticks`` not this hand's, most
        likely)."""
        g = self.geometry
        ticks, limits = g.positions(self.angles), g.limits()
        for k, i in enumerate(g.servo_ids):
            if -margin_rad <= self.angles[k] <= g.max_angle_rad[k] + margin_rad:
                continue
            raise ValueError(
                f"servo {i} stands at tick {ticks[i]}, outside its range {limits[i][0]}..{limits[i][1]} (open_ticks "
                f"{g.open_ticks[k]}, directions {g.directions[k]:+d}, max_angle_rad {g.max_angle_rad[k]:g}) by more "
                f"than {margin_rad:g} rad: activate would move the finger there. Read the servos with t42 hw read, "
                "the finger open, and set open_ticks (and directions) to this hand's")

    def apply(self, action: np.ndarray) -> str:
        """Move by ``action`` (one sync write); why part of it was not applied ("" when all of it was)."""
        g = self.geometry
        delta = np.asarray(action, float) * ACTION_UNIT_RAD
        straining = (delta > 0) & (np.abs(self.loads) > g.load_limit)
        target = self.goal + np.where(straining, 0.0, delta)
        clamped = np.clip(target, 0.0, g.max_angle_rad)
        reasons = []
        if np.any(straining):
            reasons.append(f"load over {g.load_limit:g} on actuator(s) {np.flatnonzero(straining).tolist()}")
        if np.any(clamped != target):
            reasons.append(f"position limit on actuator(s) {np.flatnonzero(clamped != target).tolist()}")
        self.goal = clamped
        self.servos.write_goals(g.ticks(self.goal))
        return "; ".join(reasons)

    def hold(self) -> None:
        """Goals where the fingers are now: the hand stays as it is."""
        clamped = self.geometry.clamp(self.angles)
        self.goal = np.array(clamped)
        self.servos.write_goals(self.geometry.ticks(clamped))

    def open(self) -> None:
        self.goal = np.zeros(ACTION_DIM)
        self.servos.write_goals(self.geometry.ticks(self.goal))


class Grasp:
    """The reset routine, one step at a time: open until the fingers stand open, then close until loaded."""

    OPEN_STEPS = 10
    """Steps the hand waits open (the object is placed meanwhile)."""

    def __init__(self, hand: ServoHand) -> None:
        self.hand = hand
        self.steps = 0
        self.closed = np.zeros(ACTION_DIM, dtype=bool)
        self.done = False
        self.failed = ""

    def step(self) -> None:
        """One control period of the routine (after :meth:`ServoHand.read`)."""
        g = self.hand.geometry
        self.steps += 1
        if self.steps <= self.OPEN_STEPS:
            self.hand.open()
            return
        self.closed |= np.abs(self.hand.loads) > g.grasp_load
        if self.closed.all():
            self.done = True
            self.hand.hold()
            return
        if self.steps > self.OPEN_STEPS + g.grasp_max_steps:
            self.failed = f"the fingers did not reach the grasp load {g.grasp_load:g} in {g.grasp_max_steps} steps"
            self.hand.open()
            return
        self.hand.apply(np.where(self.closed, 0.0, g.grasp_increment))
