"""The Dynamixel XM430-W350 as the T42 uses it: control-table fields, units, modes and error bits.

Facts from ROBOTIS' control table (dynamixel-sdk ships it): each field is ``(address, size in bytes, signed)``.
Positions are 4096 ticks a turn with 2048 at 0 rad; Present Current counts 2.69 mA a unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Field:
    """One control-table entry."""

    address: int
    size: int
    signed: bool = False
    writable: bool = False

    def decode(self, data: bytes) -> int:
        return int.from_bytes(data[: self.size], "little", signed=self.signed)

    def encode(self, value: int) -> bytes:
        return int(value).to_bytes(self.size, "little", signed=self.signed)


MODEL_NUMBER = Field(0, 2)
FIRMWARE_VERSION = Field(6, 1)
ID = Field(7, 1, writable=True)
BAUD_RATE = Field(8, 1, writable=True)
OPERATING_MODE = Field(11, 1, writable=True)
MAX_POSITION_LIMIT = Field(48, 4, writable=True)
MIN_POSITION_LIMIT = Field(52, 4, writable=True)
TORQUE_ENABLE = Field(64, 1, writable=True)
LED = Field(65, 1, writable=True)
HARDWARE_ERROR_STATUS = Field(70, 1)
GOAL_POSITION = Field(116, 4, signed=True, writable=True)
MOVING = Field(122, 1)
PRESENT_CURRENT = Field(126, 2, signed=True)
PRESENT_VELOCITY = Field(128, 4, signed=True)
PRESENT_POSITION = Field(132, 4, signed=True)
PRESENT_TEMPERATURE = Field(146, 1)

TABLE_SIZE = 147
"""Bytes of the table the emulator holds (up to Present Temperature)."""
STATE_BLOCK = (PRESENT_CURRENT.address, PRESENT_POSITION.address + PRESENT_POSITION.size - PRESENT_CURRENT.address)
"""One sync read of (address, length) covers Present Current, Velocity and Position."""

XM430_W350 = 1020
"""Model Number of the XM430-W350."""
FIRMWARE = 48
POSITION_MODE = 3
CURRENT_BASED_POSITION_MODE = 5
OPERATING_MODES = {POSITION_MODE: "position", CURRENT_BASED_POSITION_MODE: "current-based position"}
TICKS_PER_TURN = 4096
ZERO_TICK = 2048
RAD_PER_TICK = 2 * math.pi / TICKS_PER_TURN
MAX_TICK = TICKS_PER_TURN - 1
CURRENT_A_PER_UNIT = 2.69e-3

BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000, 7: 4_500_000}
"""Baud Rate field values and the rates they set."""

HARDWARE_ERRORS = {0: "input voltage error", 2: "overheating error", 3: "motor encoder error",
                   4: "electrical shock error", 5: "overload error"}
"""Hardware Error Status bits and what each means (a set bit shuts the torque off until a reboot)."""


def hardware_errors(status: int) -> list[str]:
    """The faults a Hardware Error Status value names, lowest bit first (``[]`` for 0)."""
    return [name for bit, name in sorted(HARDWARE_ERRORS.items()) if status & (1 << bit)]



TORQUE_NM_PER_A = 4.1 / 2.3
"""XM430-W350 at 12 V: 4.1 N m stall torque at 2.3 A stall current (ROBOTIS' e-manual), taken as linear."""


def current_to_load(units: float, load_unit_nm: float) -> float:
    """Present Current units -> the hand's load units (``load_unit_nm`` N m each), through the servo's torque."""
    return units * CURRENT_A_PER_UNIT * TORQUE_NM_PER_A / load_unit_nm


def load_to_current(load: float, load_unit_nm: float) -> int:
    """The hand's load units -> the Present Current a servo holding that load reports."""
    return int(round(load * load_unit_nm / TORQUE_NM_PER_A / CURRENT_A_PER_UNIT))
