"""Emulated XM430 servos on a pseudo-terminal: what the driver finds where a real hand's USB adapter would be.

The bus answers Dynamixel protocol 2.0 (:mod:`.protocol`) as the servos do: PING, READ, WRITE, SYNC_READ,
SYNC_WRITE and REBOOT, each servo with its control table (:mod:`.xm430`), EEPROM fields locked while the
torque is on, goals outside the position limits refused, a Hardware Error Status bit turning the torque off
and raising the alert bit of every reply until a reboot.  A :class:`Plant` moves behind it: Goal Position and
Torque Enable go to the plant, Present Position and Present Current come from it.

Faults are injected through :class:`Faults`: replies dropped, corrupted or late, a servo that stops answering,
an error bit, the port closing.  Nothing here needs ROS.
"""

from __future__ import annotations

import os
import random
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from t42_transfer.hardware import protocol as p
from t42_transfer.hardware import xm430 as xm

EEPROM_END = xm.TORQUE_ENABLE.address
"""Fields below this address are EEPROM: written only while the torque is off."""


class Plant(Protocol):
    """What the servos drive: goals and torque in, present position and current out (ticks and current units)."""

    def command(self, goals: dict[int, int], torque: dict[int, bool]) -> None: ...

    def present(self) -> dict[int, tuple[int, int]]: ...


class FollowingPlant:
    """A plant whose servos reach their goal at once while torqued, and stay put otherwise (no load)."""

    def __init__(self, ids: Iterable[int]) -> None:
        self.positions = {i: xm.ZERO_TICK for i in ids}

    def command(self, goals: dict[int, int], torque: dict[int, bool]) -> None:
        for i, goal in goals.items():
            if torque.get(i):
                self.positions[i] = goal

    def present(self) -> dict[int, tuple[int, int]]:
        return {i: (pos, 0) for i, pos in self.positions.items()}


class EmulatedServo:
    """One XM430-W350's control table and its rules."""

    def __init__(self, servo_id: int, model: int = xm.XM430_W350) -> None:
        self.table = bytearray(xm.TABLE_SIZE)
        self._set(xm.MODEL_NUMBER, model)
        self._set(xm.FIRMWARE_VERSION, xm.FIRMWARE)
        self._set(xm.ID, servo_id)
        self._set(xm.BAUD_RATE, 3)
        self._set(xm.OPERATING_MODE, xm.POSITION_MODE)
        self._set(xm.MAX_POSITION_LIMIT, xm.MAX_TICK)
        self._set(xm.MIN_POSITION_LIMIT, 0)
        self._set(xm.GOAL_POSITION, xm.ZERO_TICK)
        self._set(xm.PRESENT_POSITION, xm.ZERO_TICK)
        self._set(xm.PRESENT_TEMPERATURE, 30)

    @property
    def servo_id(self) -> int:
        return self.get(xm.ID)

    def get(self, f: xm.Field) -> int:
        return f.decode(bytes(self.table[f.address: f.address + f.size]))

    def _set(self, f: xm.Field, value: int) -> None:
        self.table[f.address: f.address + f.size] = f.encode(value)

    @property
    def torque(self) -> bool:
        return bool(self.get(xm.TORQUE_ENABLE))

    @property
    def alert(self) -> int:
        return p.ALERT if self.get(xm.HARDWARE_ERROR_STATUS) else 0

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error byte, data) of a READ."""
        if length < 1 or address + length > len(self.table):
            return p.DATA_RANGE_ERROR | self.alert, b""
        return self.alert, bytes(self.table[address: address + length])

    def write(self, address: int, data: bytes) -> int:
        """The error byte of a WRITE; nothing is written when it is not 0 (but the alert bit)."""
        if not data or address + len(data) > len(self.table):
            return p.DATA_RANGE_ERROR | self.alert
        fields = [f for f in _FIELDS if f.address < address + len(data) and address < f.address + f.size]
        if any(not f.writable for f in fields):
            return p.ACCESS_ERROR | self.alert
        if address < EEPROM_END and self.torque:
            return p.ACCESS_ERROR | self.alert
        staged = bytearray(self.table)
        staged[address: address + len(data)] = data
        goal = xm.GOAL_POSITION.decode(bytes(staged[xm.GOAL_POSITION.address:]))
        low = xm.MIN_POSITION_LIMIT.decode(bytes(staged[xm.MIN_POSITION_LIMIT.address:]))
        high = xm.MAX_POSITION_LIMIT.decode(bytes(staged[xm.MAX_POSITION_LIMIT.address:]))
        if xm.GOAL_POSITION in fields and not low <= goal <= high:
            return p.DATA_LIMIT_ERROR | self.alert
        if xm.TORQUE_ENABLE in fields and staged[xm.TORQUE_ENABLE.address] and self.get(xm.HARDWARE_ERROR_STATUS):
            return p.RESULT_FAIL | self.alert  # a shut-down servo takes no torque until rebooted
        self.table[:] = staged
        return self.alert

    def raise_error(self, bits: int) -> None:
        """A Hardware Error Status bit (e.g. ``1 << 5``, overload): the servo shuts its torque off."""
        self._set(xm.HARDWARE_ERROR_STATUS, self.get(xm.HARDWARE_ERROR_STATUS) | bits)
        self._set(xm.TORQUE_ENABLE, 0)

    def reboot(self) -> None:
        self._set(xm.HARDWARE_ERROR_STATUS, 0)
        self._set(xm.TORQUE_ENABLE, 0)

    def sense(self, position: int, current: int) -> None:
        self._set(xm.PRESENT_POSITION, position)
        self._set(xm.PRESENT_CURRENT, current)


_FIELDS = [v for v in vars(xm).values() if isinstance(v, xm.Field)]


@dataclass
class Faults:
    """Faults to inject; tests and ``t42 hw emulate`` set them while the bus runs."""

    drop_replies: int = 0
    """Replies still to drop (the servo heard, its answer is lost)."""
    corrupt_replies: int = 0
    """Replies still to send with one byte flipped (the driver sees a CRC error)."""
    dead: set[int] = field(default_factory=set)
    """Servo ids that no longer answer at all."""
    slow_replies: int = 0
    """Answers still to send ``reply_delay_s`` late (a busy host, a USB adapter that buffers: the read takes
    longer than the period allows, and the driver's step comes late)."""
    reply_delay_s: float = 0.05


GOALS_KEPT = 10_000
"""SYNC_WRITE goals a bus keeps for checks (:attr:`ServoBus.goals_written`): 1000 s of steps at 10 Hz."""
EMULATED_LATENCY_TIMER_MS = 100.0
"""How long a driver should treat the emulated bus's latency timer as (its ``latency_timer_ms``): the answers come
from a Python thread, which a busy machine can hold up longer than a USB adapter would."""


class ServoBus:
    """The servos on one bus and the plant behind them: instruction packets in, reply bytes out."""

    def __init__(self, servos: Iterable[EmulatedServo], plant: Plant | None = None, seed: int = 0) -> None:
        self.servos = {s.servo_id: s for s in servos}
        self.plant = plant if plant is not None else FollowingPlant(self.servos)
        self.faults = Faults()
        self.lock = threading.Lock()
        self.handled = 0
        self.sync_writes = 0
        """Goal writes so far: one per driver step (an emulator in lockstep waits for the next)."""
        self.goals_written: deque[dict[int, int]] = deque(maxlen=GOALS_KEPT)
        """Goal Position of each SYNC_WRITE as sent ({servo id: ticks}), also those the servos refused (outside
        their limits): what a driver wrote, not what the servos kept.  The newest :data:`GOALS_KEPT`."""
        self._rng = random.Random(seed)

    def handle(self, ins: p.Instruction) -> bytes:
        """The bytes the bus answers ``ins`` with (b"" for none: a broadcast write, a sync write, a dead servo)."""
        with self.lock:
            self.handled += 1
            answer = b"".join(self._faulted(r) for r in self._answer(ins))
            delay = 0.0
            if answer and self.faults.slow_replies > 0:
                self.faults.slow_replies -= 1
                delay = self.faults.reply_delay_s
        if delay:
            time.sleep(delay)  # outside the lock: the plant keeps moving meanwhile
        return answer

    def _answer(self, ins: p.Instruction) -> list[bytes]:
        targets = list(self.servos) if ins.servo_id == p.BROADCAST_ID else [ins.servo_id]
        alive = [i for i in targets if i in self.servos and i not in self.faults.dead]
        if not ins.crc_ok:
            return [p.status_packet(i, p.CRC_ERROR) for i in alive if ins.servo_id != p.BROADCAST_ID]
        if ins.instruction == p.PING:
            return [p.status_packet(i, self.servos[i].alert, xm.MODEL_NUMBER.encode(self.servos[i].get(xm.MODEL_NUMBER))
                                    + xm.FIRMWARE_VERSION.encode(self.servos[i].get(xm.FIRMWARE_VERSION)))
                    for i in alive]
        if ins.instruction == p.SYNC_WRITE:
            self.sync_writes += 1
            self._sync_write(ins.params)
            return []
        if ins.instruction == p.SYNC_READ:
            return self._sync_read(ins.params)
        replies = []
        for i in alive:
            servo = self.servos[i]
            error, data = self._single(servo, ins)
            if ins.servo_id != p.BROADCAST_ID:
                replies.append(p.status_packet(i, error, data))
        return replies

    def _single(self, servo: EmulatedServo, ins: p.Instruction) -> tuple[int, bytes]:
        if ins.instruction == p.READ and len(ins.params) == 4:
            self._sense()
            return servo.read(int.from_bytes(ins.params[:2], "little"), int.from_bytes(ins.params[2:], "little"))
        if ins.instruction == p.WRITE and len(ins.params) > 2:
            error = servo.write(int.from_bytes(ins.params[:2], "little"), ins.params[2:])
            self._command()
            return error, b""
        if ins.instruction == p.REBOOT:  # the servo answers, then restarts
            alert = servo.alert
            servo.reboot()
            self._command()
            return alert, b""
        if ins.instruction in (p.READ, p.WRITE):
            return p.DATA_LENGTH_ERROR | servo.alert, b""
        return p.INSTRUCTION_ERROR | servo.alert, b""

    def _sync_read(self, params: bytes) -> list[bytes]:
        if len(params) < 5:
            return []
        address, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        self._sense()
        replies = []
        for i in params[4:]:  # each servo answers in the order asked
            if i in self.servos and i not in self.faults.dead:
                error, data = self.servos[i].read(address, length)
                replies.append(p.status_packet(i, error, data))
        return replies

    def _sync_write(self, params: bytes) -> None:
        if len(params) < 4:
            return
        address, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        body = params[4:]
        goals = {}
        for k in range(0, len(body) - length, length + 1):
            i = body[k]
            if address == xm.GOAL_POSITION.address and length == xm.GOAL_POSITION.size:
                goals[i] = xm.GOAL_POSITION.decode(body[k + 1: k + 1 + length])
            if i in self.servos and i not in self.faults.dead:
                self.servos[i].write(address, body[k + 1: k + 1 + length])
        if goals:
            self.goals_written.append(goals)
        self._command()

    def _command(self) -> None:
        self.plant.command({i: s.get(xm.GOAL_POSITION) for i, s in self.servos.items()},
                           {i: s.torque for i, s in self.servos.items()})

    def _sense(self) -> None:
        for i, (position, current) in self.plant.present().items():
            if i in self.servos:
                self.servos[i].sense(position, current)

    def _faulted(self, reply: bytes) -> bytes:
        if self.faults.drop_replies > 0:
            self.faults.drop_replies -= 1
            return b""
        if self.faults.corrupt_replies > 0:
            self.faults.corrupt_replies -= 1
            at = self._rng.randrange(len(p.HEADER) + 3, len(reply))
            return reply[:at] + bytes([reply[at] ^ 0xFF]) + reply[at + 1:]
        return reply


def _is_pty_link(path: Path) -> bool:
    """Whether ``path`` is a symlink into /dev/pts/: an emulator's link, which a new emulator may replace."""
    return path.is_symlink() and os.readlink(path).startswith("/dev/pts/")


class PtyBus:
    """A :class:`ServoBus` on a pseudo-terminal: ``path`` (or the ``link`` made to it) is the port to open.

    A thread answers every packet written to the port.  :meth:`close_port` is the unplugged adapter: the
    terminal goes away and the driver's next read or write fails.  ``link`` replaces only an earlier
    emulator's link (one into /dev/pts/); anything else at that path is a ValueError naming it.
    """

    def __init__(self, bus: ServoBus, link: str | os.PathLike[str] | None = None) -> None:
        self.bus = bus
        self.link = None if link is None else Path(link)
        if self.link is not None and os.path.lexists(self.link):
            if not _is_pty_link(self.link):  # the user's own file or link: never replaced, never removed
                raise ValueError(f"{self.link}: exists and is not an emulator's pty link")
            self.link.unlink()  # an earlier emulator's, left behind
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: a serial line's bytes as they are
        self.path = Path(os.ttyname(self._slave))
        if self.link is not None:
            try:
                self.link.symlink_to(self.path)
            except OSError as err:  # its filename is the pty: name the user's link instead
                self._close_fds()
                raise ValueError(f"{self.link}: cannot make the link: {err.strerror}") from None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="servo-bus", daemon=True)
        self._thread.start()

    @property
    def port(self) -> str:
        """What a driver opens: the link when there is one, else the terminal itself."""
        return str(self.link or self.path)

    def _serve(self) -> None:
        reader = p.PacketReader()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except OSError:  # the port was closed
                return
            for ins in reader.feed(data):
                reply = self.bus.handle(ins)
                if reply:
                    try:
                        os.write(self._master, reply)
                    except OSError:
                        return

    def close_port(self) -> None:
        """Take the terminal away, as pulling the USB adapter does."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._close_fds()
        if self.link is not None and self.link.is_symlink() and Path(os.readlink(self.link)) == self.path:
            self.link.unlink()  # only our own link: another emulator may have taken the path since

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyBus:
        return self

    def __exit__(self, *_: object) -> None:
        self.close_port()


def t42_bus(ids: Iterable[int] = (1, 2), plant: Plant | None = None) -> ServoBus:
    """The hand's bus: two XM430-W350 servos (ids 1 and 2 as the T42 ships)."""
    return ServoBus([EmulatedServo(i) for i in ids], plant)
