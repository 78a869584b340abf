"""The hand's two servos through dynamixel-sdk: open, check, configure, one sync read and one sync write a step.

Every failure is a :class:`ServoFault` naming the servo and what went wrong, in one of five kinds: the port
(gone, or not a serial port), no answer (timeout), a garbled answer (CRC), a Hardware Error Status bit
(decoded), or the torque found off on a servo that was turned on (it restarted: a supply dip; XM430s come back
with Torque Enable 0 and no error bit, so only Torque Enable tells).  pyserial's own errors never escape.
Nothing here needs ROS; the driver node wraps it.

A read of the port waits for the servos' answer in ``select`` (:data:`READ_WAIT_S` at a time) instead of
polling: dynamixel-sdk opens the port non-blocking and spins on it until the answer or its packet timeout,
which burns the CPU for the whole round trip of every exchange.
"""

from __future__ import annotations

import contextlib
import errno
import termios
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from t42_transfer.hardware import protocol as p
from t42_transfer.hardware import xm430 as xm

PORT, TIMEOUT, CORRUPT, HARDWARE, REFUSED = "port", "timeout", "corrupt", "hardware", "refused"
TORQUE_OFF = "torque_off"
TORQUE_CHECK_S = 1.0
"""How often :meth:`HandServos.read_state` also reads Torque Enable of the servos turned on (one more sync read of
one byte, the first read after the torque came on included): a servo that restarted holds nothing, and says so
nowhere else."""
_PORT_ERRORS = (OSError, termios.error, serial.SerialException, ValueError)
READ_WAIT_S = 0.001
"""Longest one read of the port blocks for bytes; dynamixel-sdk checks its own packet timeout between reads, so a
silent servo is still reported after that timeout (at most this much later)."""


class ServoFault(RuntimeError):
    """``kind`` (``port``, ``timeout``, ``corrupt``, ``hardware``, ``torque_off`` or ``refused``) on servo
    ``servo_id`` (None: the port); one line."""

    def __init__(self, kind: str, servo_id: int | None, detail: str) -> None:
        where = "" if servo_id is None and kind == PORT else " on the port" if servo_id is None else \
            f" on servo {servo_id}"
        super().__init__(f"{kind}{where}: {detail}")
        self.kind, self.servo_id, self.detail = kind, servo_id, detail


@dataclass(frozen=True)
class ServoState:
    """One sync read: Present Position (ticks) and Present Current (units) per servo id."""

    positions: dict[int, int]
    currents: dict[int, int]


TORQUE_ATTEMPTS = 2
"""Writes of Torque Enable each servo gets before it counts as failed (a lost reply is retried once)."""
@dataclass(frozen=True)
class ServoInfo:
    """What ``t42 hw read`` shows of one servo, read with its torque as it was."""

    model: int
    position: int
    """Present Position, raw ticks (2048 at 0 rad; the driver's angles are relative to ``open_ticks``)."""
    current: int
    """Present Current, units of :data:`~t42_transfer.hardware.xm430.CURRENT_A_PER_UNIT`."""
    hardware_error: int
    """Hardware Error Status bits (0: none)."""

    def describe(self) -> str:
        model = "XM430-W350" if self.model == xm.XM430_W350 else "not an XM430-W350"
        errors = ", ".join(xm.hardware_errors(self.hardware_error)) or "none"
        return (f"model {self.model} ({model}), Present Position {self.position} ticks, Present Current "
                f"{self.current} ({self.current * xm.CURRENT_A_PER_UNIT * 1e3:.1f} mA), Hardware Error Status "
                f"{self.hardware_error} ({errors})")


SDK_LATENCY_TIMER_MS = 16.0
"""The USB adapter's latency timer dynamixel-sdk assumes (FTDI's default) when it times an answer out."""


class PortInUse(OSError):
    """The port is held by another program (:class:`_Port` opens it exclusively)."""


class _Port(PortHandler):
    """dynamixel-sdk's port with the adapter's real latency timer in its answer timeout (the SDK fixes 16 ms):
    an adapter set to 1 ms times out sooner, a slow link (an emulated bus on a busy machine) later; and opened
    exclusively: pyserial's ``exclusive`` locks it (``flock``) before it touches the line's settings, so a second
    program of ours (another driver, ``t42 hw read``) is refused instead of resetting the baud rate and writing
    to servos the driver holds.  (The lock is advisory: a program that does not ask for it, Dynamixel Wizard say,
    still opens the port.)"""

    def __init__(self, name: str, latency_timer_ms: float) -> None:
        super().__init__(name)
        self.extra_ms = 2.0 * (latency_timer_ms - SDK_LATENCY_TIMER_MS)

    def setupPort(self, cflag_baud: int) -> bool:  # noqa: N802 (dynamixel-sdk's name; its own, exclusive=True)
        if self.is_open:
            self.closePort()
        try:
            self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                                     timeout=0, exclusive=True)
        except serial.SerialException as err:
            if err.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise PortInUse(err.errno, "in use by another program (a driver, t42 hw read or reboot?); "
                                           f"fuser -v {self.port_name} names it") from None
            raise
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 (dynamixel-sdk's name)
        super().setPacketTimeout(packet_length)
        self.packet_timeout += self.extra_ms


class HandServos:
    """The servos ``ids`` on ``port`` at ``baud``, protocol 2.0; ``latency_timer_ms``: the adapter's."""

    def __init__(self, port: str, baud: int, ids: Sequence[int],
                 latency_timer_ms: float = SDK_LATENCY_TIMER_MS) -> None:
        self.port_name, self.baud, self.ids = port, baud, tuple(ids)
        self.latency_timer_ms = latency_timer_ms
        self._port: PortHandler | None = None
        self._packets = PacketHandler(2.0)
        self._torqued: set[int] = set()
        """Servos whose Torque Enable this turned on (and not off since): :meth:`read_state` checks they still are."""
        self._torque_checked_s = 0.0

    # ------------------------------------------------------------------ port
    def open(self) -> None:
        port = _Port(self.port_name, self.latency_timer_ms)
        try:
            opened = port.openPort() and port.setBaudRate(self.baud)
            if opened:
                port.ser.timeout = READ_WAIT_S
        except PortInUse as err:
            raise ServoFault(PORT, None, f"{self.port_name} is {err.strerror}") from None
        except _PORT_ERRORS as err:
            raise ServoFault(PORT, None, f"cannot open {self.port_name}: {err}") from None
        if not opened:
            raise ServoFault(PORT, None, f"cannot open {self.port_name} at {self.baud} baud")
        self._port = port

    def close(self) -> None:
        port, self._port = self._port, None
        self._torqued.clear()
        if port is not None:
            try:
                port.closePort()
            except _PORT_ERRORS:
                pass

    def _need_port(self) -> PortHandler:
        if self._port is None:
            raise ServoFault(PORT, None, "the port is not open")
        return self._port

    # ------------------------------------------------------------------ single-servo exchanges
    def _check(self, servo_id: int, result: int, error: int, what: str) -> None:
        if result == COMM_RX_TIMEOUT:
            raise ServoFault(TIMEOUT, servo_id, f"no answer to {what}")
        if result == COMM_RX_CORRUPT:
            raise ServoFault(CORRUPT, servo_id, f"garbled answer to {what} (CRC or framing)")
        if result != COMM_SUCCESS:
            raise ServoFault(TIMEOUT, servo_id, f"{what}: {self._packets.getTxRxResult(result)}")
        if error & p.ALERT:
            status = self.hardware_status(servo_id)
            named = ", ".join(xm.hardware_errors(status))
            raise ServoFault(HARDWARE, servo_id, named or (f"Hardware Error Status {status}" if status else
                                                            "alert without an error bit"))
        if error:
            raise ServoFault(REFUSED, servo_id, f"{what} refused ({self._packets.getRxPacketError(error)})")

    def _call(self, servo_id: int, what: str, fn: Callable[..., tuple], *args: object) -> tuple:
        port = self._need_port()
        with self._port_errors(what):
            return fn(port, servo_id, *args)

    @contextlib.contextmanager
    def _port_errors(self, what: str) -> Iterator[None]:
        """The port's errors in one exchange as a ServoFault, and dynamixel-sdk's busy flag cleared: the SDK sets it
        for a packet and leaves it set when the port raises mid-packet, so every later packet, torque off included,
        would be refused without reaching the bus ("Port is in use!")."""
        try:
            yield
        except _PORT_ERRORS as err:
            if self._port is not None:
                self._port.is_using = False
            raise ServoFault(PORT, None, f"{what}: {err}") from None

    def ping(self, servo_id: int) -> int:
        """The servo's Model Number."""
        model, result, error = self._call(servo_id, "ping", self._packets.ping)
        self._check(servo_id, result, error & ~p.ALERT, "ping")
        return model

    def read(self, servo_id: int, f: xm.Field, alert_ok: bool = False) -> int:
        """Field ``f`` of the servo; ``alert_ok``: also from a servo whose Hardware Error Status is set."""
        fn = {1: self._packets.read1ByteTxRx, 2: self._packets.read2ByteTxRx, 4: self._packets.read4ByteTxRx}[f.size]
        value, result, error = self._call(servo_id, f"read of {f.address}", fn, f.address)
        self._check(servo_id, result, error & ~p.ALERT if alert_ok else error, f"read of address {f.address}")
        return f.decode(int(value).to_bytes(f.size, "little", signed=False))

    def write(self, servo_id: int, f: xm.Field, value: int) -> None:
        fn = {1: self._packets.write1ByteTxRx, 2: self._packets.write2ByteTxRx,
              4: self._packets.write4ByteTxRx}[f.size]
        unsigned = int.from_bytes(f.encode(value), "little")
        result, error = self._call(servo_id, f"write of {f.address}", fn, f.address, unsigned)
        self._check(servo_id, result, error, f"write of {value} to address {f.address}")

    def hardware_status(self, servo_id: int) -> int:
        """Hardware Error Status, read without raising on the alert it causes."""
        value, result, _ = self._call(servo_id, "read of the error status", self._packets.read1ByteTxRx,
                                      xm.HARDWARE_ERROR_STATUS.address)
        if result != COMM_SUCCESS:
            raise ServoFault(TIMEOUT, servo_id, "no answer to the read of Hardware Error Status")
        return int(value)

    def info(self, servo_id: int) -> ServoInfo:
        """Model, Present Position, Present Current and Hardware Error Status of one servo: reads only (the
        torque and every setting stay as they are), also of a servo with an error bit set."""
        model = self.ping(servo_id)
        return ServoInfo(model, *(self.read(servo_id, f, alert_ok=True) for f in (
            xm.PRESENT_POSITION, xm.PRESENT_CURRENT, xm.HARDWARE_ERROR_STATUS)))

    def reboot(self, servo_id: int) -> None:
        """Reboot the servo: its Hardware Error Status cleared, its torque off (as this asked: not a fault)."""
        self._torqued.discard(servo_id)
        result, error = self._call(servo_id, "reboot", self._packets.reboot)
        self._check(servo_id, result, error & ~p.ALERT, "reboot")

    # ------------------------------------------------------------------ the hand
    def check(self) -> dict[int, int]:
        """Ping every servo; the Model Number of each.  A servo that is no XM430-W350 is refused."""
        models = {i: self.ping(i) for i in self.ids}
        wrong = {i: m for i, m in models.items() if m != xm.XM430_W350}
        if wrong:
            raise ServoFault(REFUSED, next(iter(wrong)), f"model {wrong} is no XM430-W350 ({xm.XM430_W350})")
        return models

    def configure(self, mode: int, limits: dict[int, tuple[int, int]]) -> None:
        """Torque off, then the operating mode and position limits (EEPROM: written only without torque).  The
        torque goes off on every servo first, each tried on its own (:meth:`torque`): one that does not answer
        leaves no other as it was; then the :class:`ServoFault` names each that failed, and nothing else is written."""
        self.torque(False)
        for i in self.ids:
            if self.read(i, xm.OPERATING_MODE) != mode:
                self.write(i, xm.OPERATING_MODE, mode)
            low, high = limits[i]
            self.write(i, xm.MIN_POSITION_LIMIT, low)
            self.write(i, xm.MAX_POSITION_LIMIT, high)

    def torque(self, on: bool) -> None:
        """Torque Enable on every servo.  Each servo is tried on its own (:meth:`set_torque`): one that does not
        answer leaves no other as it was; a :class:`ServoFault` afterwards names the first that failed, and all."""
        failed = self.set_torque(on)
        if failed:
            first = next(iter(failed.values()))
            raise ServoFault(first.kind, first.servo_id, "; ".join(f"torque {'on' if on else 'off'} failed on "
                                                                  f"servo {i}: {err.detail}"
                                                                  for i, err in failed.items()))

    def set_torque(self, on: bool, attempts: int = TORQUE_ATTEMPTS) -> dict[int, ServoFault]:
        """Torque Enable on each servo, each tried up to ``attempts`` times whatever the others did; the servos
        that never confirmed it, with their last fault ({} when all did)."""
        failed: dict[int, ServoFault] = {}
        for i in self.ids:
            for _ in range(attempts):
                try:
                    self.write(i, xm.TORQUE_ENABLE, int(on))
                except ServoFault as err:
                    if err.kind == HARDWARE and not on:  # the alert bit of a servo with an error: the write was
                        failed.pop(i, None)  # done (such a servo has turned its torque off itself anyway)
                        break
                    failed[i] = err
                else:
                    failed.pop(i, None)
                    break
            if on and i not in failed:
                self._torqued.add(i)
            elif not on:
                self._torqued.discard(i)
        return failed

    def read_state(self) -> ServoState:
        """One sync read of Present Current, Velocity and Position of every servo, each answer's error byte checked;
        every :data:`TORQUE_CHECK_S` also Torque Enable of the servos turned on (:meth:`check_torque`)."""
        address, _ = xm.STATE_BLOCK
        positions, currents = {}, {}
        for i, block in self._sync_read(*xm.STATE_BLOCK, self.ids).items():
            positions[i] = xm.PRESENT_POSITION.decode(block[xm.PRESENT_POSITION.address - address:])
            currents[i] = xm.PRESENT_CURRENT.decode(block[xm.PRESENT_CURRENT.address - address:])
        if self._torqued and time.monotonic() - self._torque_checked_s >= TORQUE_CHECK_S:
            self.check_torque()
        return ServoState(positions, currents)

    def check_torque(self) -> None:
        """One sync read of Torque Enable of the servos turned on; a ``torque_off`` :class:`ServoFault` naming the
        first found off: it restarted (a supply dip, a loose power wire) and its finger went limp."""
        turned_on = [i for i in self.ids if i in self._torqued]
        answers = self._sync_read(xm.TORQUE_ENABLE.address, xm.TORQUE_ENABLE.size, turned_on)
        self._torque_checked_s = time.monotonic()
        off = [i for i, data in answers.items() if not xm.TORQUE_ENABLE.decode(data)]
        if off:
            raise ServoFault(TORQUE_OFF, off[0], f"Torque Enable reads 0 on servo(s) {off}, turned on before: "
                                                 "the servo restarted (a supply dip, a loose power wire?)")

    def _sync_read(self, address: int, length: int, ids: Sequence[int]) -> dict[int, bytes]:
        """One sync read of ``length`` bytes from ``address`` of servos ``ids``, each answer's error byte checked.

        dynamixel-sdk's GroupSyncRead drops the error byte (where a Hardware Error Status alert shows), so
        the sync read is sent and its answers taken with the packet handler's own calls.
        """
        port = self._need_port()
        with self._port_errors("sync read"):
            result = self._packets.syncReadTx(port, address, length, list(ids), len(ids), False)
            if result != COMM_SUCCESS:
                raise ServoFault(PORT, None, f"sync read: {self._packets.getTxRxResult(result)}")
            answers = {i: self._packets.readRx(port, i, length) for i in ids}  # all, before any other exchange
        for i, (_, result, error) in answers.items():
            self._check(i, result, error, "sync read")
        return {i: bytes(data) for i, (data, _, _) in answers.items()}

    def write_goals(self, goals: dict[int, int]) -> None:
        """One sync write of Goal Position (no answer comes: limits are the caller's to keep)."""
        group = GroupSyncWrite(self._need_port(), self._packets, xm.GOAL_POSITION.address, xm.GOAL_POSITION.size)
        for i, goal in goals.items():
            group.addParam(i, xm.GOAL_POSITION.encode(goal))
        with self._port_errors("sync write"):
            result = group.txPacket()
        if result != COMM_SUCCESS:
            raise ServoFault(PORT, None, f"sync write: {self._packets.getTxRxResult(result)}")
