"""Dynamixel protocol 2.0 from the servo's side: instruction packets in, status packets out.

A packet is ``FF FF FD 00 | id | length (2, LE) | instruction | params | CRC-16 (2, LE)``, length counting
the instruction, the params and the CRC; a status packet's instruction is ``0x55`` followed by an error
byte.  ``FF FF FD`` inside a packet is stuffed to ``FF FF FD FD``.  The CRC is CRC-16 with polynomial
0x8005 (MSB first, initial value 0) over every byte before it.  The driver speaks the other side through
dynamixel-sdk; this module is what the emulated servos answer with, written from the protocol's facts.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55
PING, READ, WRITE, REBOOT, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x08, 0x82, 0x83

# Status packet error byte: bit 7 is the hardware alert, the rest one of these.
RESULT_FAIL, INSTRUCTION_ERROR, CRC_ERROR, DATA_RANGE_ERROR, DATA_LENGTH_ERROR, DATA_LIMIT_ERROR, ACCESS_ERROR = (
    1, 2, 3, 4, 5, 6, 7)
ALERT = 0x80
MAX_PACKET = 1024
"""Longest packet read; a length field beyond it is noise, not a packet."""


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return table


_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """The protocol's CRC of ``data``."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) ^ _TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """``FF FF FD`` in a packet's instruction and params becomes ``FF FF FD FD``."""
    return body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    return body.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def status_packet(servo_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A servo's reply: its id, the error byte, the params, framed and checked."""
    body = stuff(bytes([STATUS, error]) + params)
    head = HEADER + bytes([servo_id]) + (len(body) + 2).to_bytes(2, "little")
    packet = head + body
    return packet + crc16(packet).to_bytes(2, "little")


def instruction_packet(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction, framed and checked (what dynamixel-sdk sends; the tests build their packets with it)."""
    body = stuff(bytes([instruction]) + params)
    packet = HEADER + bytes([servo_id]) + (len(body) + 2).to_bytes(2, "little") + body
    return packet + crc16(packet).to_bytes(2, "little")


@dataclass(frozen=True)
class Instruction:
    """One instruction packet as received; ``crc_ok`` False when its CRC did not match."""

    servo_id: int
    instruction: int
    params: bytes
    crc_ok: bool = True


class PacketReader:
    """Instruction packets out of a byte stream that may hold noise, cut packets and several packets at once."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> Iterator[Instruction]:
        """Every complete packet the bytes so far hold, in order; noise before a header is skipped."""
        self._buffer += data
        while True:
            start = self._buffer.find(HEADER)
            if start < 0:
                del self._buffer[: max(0, len(self._buffer) - len(HEADER) + 1)]
                return
            del self._buffer[:start]
            if len(self._buffer) < 7:
                return
            length = int.from_bytes(self._buffer[5:7], "little")
            if length < 3 or length > MAX_PACKET:  # no packet: skip this header
                del self._buffer[: len(HEADER)]
                continue
            end = 7 + length
            if len(self._buffer) < end:
                return
            packet = bytes(self._buffer[:end])
            del self._buffer[:end]
            body = unstuff(packet[7:-2])
            crc_ok = crc16(packet[:-2]) == int.from_bytes(packet[-2:], "little")
            yield Instruction(packet[4], body[0], body[1:], crc_ok)
