"""The simulated hand behind the emulated servos: Goal Position drives its tendons, its physics answers.

Each servo is mounted on one finger (``actuator``, the action's index) with the tick at which the finger is
open and the direction that closes it (hands A and B are mirror images).  A torqued servo holds its goal; a
servo without torque lets its tendon go slack.  The plant steps one control period per :meth:`tick`, on
whatever clock the emulator keeps.  When both servos stand open the object is placed again, as a person at
the bench does before the next grasp.  Loads come back as Present Current through the servo's torque
constant, so a driver that converts back gets the hand's own load units.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from t42_transfer.conventions import LOAD_UNIT_NM
from t42_transfer.hand.sim import SimulatedHand, StepInfo
from t42_transfer.hardware import xm430 as xm

OPEN_RAD = 0.02
"""Servo angles at most this far from open count as an open hand."""


@dataclass(frozen=True)
class ServoMount:
    """How one servo sits on the hand."""

    servo_id: int
    actuator: int
    """Index of the finger's actuator in the action (0 or 1)."""
    open_tick: int = xm.ZERO_TICK
    sign: int = 1
    """+1: ticks above ``open_tick`` close the finger; -1: ticks below it do."""

    def to_rad(self, ticks: int) -> float:
        return self.sign * (ticks - self.open_tick) * xm.RAD_PER_TICK

    def to_ticks(self, rad: float) -> int:
        return self.open_tick + self.sign * int(round(rad / xm.RAD_PER_TICK))


T42_MOUNTS = (ServoMount(1, 0), ServoMount(2, 1))


class HandPlant:
    """A :class:`SimulatedHand` as a :class:`~t42_transfer.hardware.emulator.Plant`; thread-safe."""

    def __init__(self, hand: SimulatedHand, mounts: Sequence[ServoMount] = T42_MOUNTS, seed: int = 0) -> None:
        self.hand = hand
        self.mounts = {m.servo_id: m for m in mounts}
        self._goals = {m.servo_id: m.open_tick for m in mounts}
        self._torque = {m.servo_id: False for m in mounts}
        self._lock = threading.Lock()
        self.placements = 0
        """Objects placed so far (one per opening of the hand)."""
        self._seed = seed
        self._place()

    def _place(self) -> None:
        self.hand.place(self._seed + self.placements)
        self.placements += 1
        self._closed = False
        """Whether the fingers closed since the object was placed."""

    def command(self, goals: dict[int, int], torque: dict[int, bool]) -> None:
        with self._lock:
            self._goals.update({i: g for i, g in goals.items() if i in self._goals})
            self._torque.update({i: t for i, t in torque.items() if i in self._torque})

    def present(self) -> dict[int, tuple[int, int]]:
        with self._lock:
            angles, loads = self.hand.actuator_angles, self.hand.loads
            return {i: (m.to_ticks(angles[m.actuator]), m.sign * xm.load_to_current(loads[m.actuator], LOAD_UNIT_NM))
                    for i, m in self.mounts.items()}

    def angles(self) -> np.ndarray:
        """Where the servos drive the fingers now (rad, action order): the goal if torqued, slack if not."""
        target = np.zeros(2)
        for i, m in self.mounts.items():
            target[m.actuator] = max(0.0, m.to_rad(self._goals[i])) if self._torque[i] else 0.0
        return target

    def tick(self) -> StepInfo:
        """One control period of the hand's physics; the object is placed again once the hand stands open."""
        with self._lock:
            target = self.angles()
            if np.any(self.hand.actuator_angles > OPEN_RAD):
                self._closed = True
            elif self._closed and np.all(target <= OPEN_RAD):
                self._place()
            return self.hand.hold(target)
