"""The simulated hand behind the emulated servos: Goal Position drives its tendons, its physics answers.

The servos sit on the fingers as the driver's :class:`~t42_transfer.driver.servo_hand.HandGeometry` says
(which servo turns which finger, the tick at which it is open, the direction that closes it).  A torqued
servo holds its goal; a servo without torque lets its tendon go slack.  The plant steps one control period
per :meth:`tick`, on whatever clock the emulator keeps.  When both servos stand open the object is placed
again, as a person at the bench does before the next grasp.  Loads come back as Present Current through the
servo's torque constant, so a driver that converts back gets the hand's own load units.
"""

from __future__ import annotations

import threading

import numpy as np

from t42_transfer.driver.servo_hand import HandGeometry
from t42_transfer.hand.sim import SimulatedHand, StepInfo

T42 = HandGeometry()
"""The hand as it ships: servos 1 and 2, open at tick 2048, closing upwards."""
OPEN_RAD = 0.02
"""Servo angles at most this far from open count as an open hand."""


class HandPlant:
    """A :class:`SimulatedHand` as a :class:`~t42_transfer.hardware.emulator.Plant`; thread-safe."""

    def __init__(self, hand: SimulatedHand, geometry: HandGeometry = T42, seed: int = 0) -> None:
        self.hand = hand
        self.geometry = geometry
        """How the servos sit on the hand: the driver's own :class:`HandGeometry`, so both agree by construction."""
        self._goals = geometry.positions(np.zeros(2))
        self._torque = dict.fromkeys(geometry.servo_ids, False)
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
            positions = self.geometry.positions(self.hand.actuator_angles)
            currents = self.geometry.currents(self.hand.loads)
            return {i: (positions[i], currents[i]) for i in positions}

    def angles(self) -> np.ndarray:
        """Where the servos drive the fingers now (rad, action order): the goal if torqued, slack if not."""
        torqued = np.array([self._torque[i] for i in self.geometry.servo_ids])
        return np.where(torqued, np.maximum(self.geometry.angles(self._goals), 0.0), 0.0)

    def tick(self) -> StepInfo:
        """One control period of the hand's physics; the object is placed again once the hand stands open."""
        with self._lock:
            target = self.angles()
            if np.any(self.hand.actuator_angles > OPEN_RAD):
                self._closed = True
            elif self._closed and np.all(target <= OPEN_RAD):
                self._place()
            return self.hand.hold(target)
