"""The emulated servo bus as dynamixel-sdk sees it: the library a driver uses, on the pty the emulator serves."""

from __future__ import annotations

import termios
import time
from collections.abc import Iterator

import pytest
import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from t42_transfer.hardware import protocol as p
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.emulator import PtyBus, t42_bus


@pytest.fixture
def wire() -> Iterator[tuple[PtyBus, PortHandler, PacketHandler]]:
    with PtyBus(t42_bus()) as bus:
        port = PortHandler(bus.port)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            yield bus, port, PacketHandler(2.0)
        finally:
            port.closePort()


def test_the_crc_is_the_protocols() -> None:
    # the protocol manual's example: a PING of id 1 ends in CRC 19 4E
    assert p.instruction_packet(1, p.PING) == bytes.fromhex("FFFFFD0001030001194E")
    assert p.crc16(b"") == 0


def test_stuffing_and_a_stream_of_noise_cut_and_joined_packets() -> None:
    params = b"\x74\x00\xff\xff\xfd\x00"  # a Goal Position write whose data holds the header's bytes
    packet = p.instruction_packet(1, p.WRITE, params)
    assert b"\xff\xff\xfd\xfd" in packet
    reader = p.PacketReader()
    stream = b"\x00\x12" + packet + p.instruction_packet(2, p.PING)
    got = list(reader.feed(stream[:9])) + list(reader.feed(stream[9:]))
    assert [(g.servo_id, g.instruction, g.params, g.crc_ok) for g in got] == [
        (1, p.WRITE, params, True), (2, p.PING, b"", True)]
    bad = bytearray(p.instruction_packet(1, p.PING))
    bad[-1] ^= 1
    (wrong,) = reader.feed(bytes(bad))
    assert not wrong.crc_ok


def test_ping_reads_the_model_of_both_servos(wire) -> None:
    _, port, ph = wire
    for servo in (1, 2):
        assert ph.ping(port, servo) == (xm.XM430_W350, COMM_SUCCESS, 0)
    result = ph.ping(port, 3)
    assert result[1] == COMM_RX_TIMEOUT  # no servo 3 on this bus


@pytest.mark.parametrize("f, value", [(xm.OPERATING_MODE, xm.CURRENT_BASED_POSITION_MODE), (xm.TORQUE_ENABLE, 1),
                                      (xm.GOAL_POSITION, 3000), (xm.MIN_POSITION_LIMIT, 1000),
                                      (xm.MAX_POSITION_LIMIT, 3500), (xm.LED, 1)])
def test_each_field_the_driver_writes_reads_back(wire, f: xm.Field, value: int) -> None:
    _, port, ph = wire
    write = {1: ph.write1ByteTxRx, 2: ph.write2ByteTxRx, 4: ph.write4ByteTxRx}[f.size]
    read = {1: ph.read1ByteTxRx, 2: ph.read2ByteTxRx, 4: ph.read4ByteTxRx}[f.size]
    other = read(port, 2, f.address)
    assert write(port, 1, f.address, value) == (COMM_SUCCESS, 0)
    assert read(port, 1, f.address) == (value, COMM_SUCCESS, 0)
    assert read(port, 2, f.address) == other  # the other servo is untouched


def test_the_servo_rules_eeprom_limits_and_read_only_fields(wire) -> None:
    _, port, ph = wire
    assert ph.write4ByteTxRx(port, 1, xm.MAX_POSITION_LIMIT.address, 3000) == (COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, xm.GOAL_POSITION.address, 3500) == (COMM_SUCCESS, p.DATA_LIMIT_ERROR)
    assert ph.read4ByteTxRx(port, 1, xm.GOAL_POSITION.address)[0] == xm.ZERO_TICK  # refused: not written
    assert ph.write1ByteTxRx(port, 1, xm.TORQUE_ENABLE.address, 1) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, xm.OPERATING_MODE.address, 5) == (COMM_SUCCESS, p.ACCESS_ERROR)  # EEPROM
    assert ph.write4ByteTxRx(port, 1, xm.PRESENT_POSITION.address, 7) == (COMM_SUCCESS, p.ACCESS_ERROR)


def test_sync_write_then_sync_read_of_the_state_block(wire) -> None:
    _, port, ph = wire
    for servo in (1, 2):
        assert ph.write1ByteTxRx(port, servo, xm.TORQUE_ENABLE.address, 1) == (COMM_SUCCESS, 0)
    writer = GroupSyncWrite(port, ph, xm.GOAL_POSITION.address, xm.GOAL_POSITION.size)
    for servo, goal in ((1, 2500), (2, 1700)):
        assert writer.addParam(servo, xm.GOAL_POSITION.encode(goal))
    assert writer.txPacket() == COMM_SUCCESS
    reader = GroupSyncRead(port, ph, *xm.STATE_BLOCK)
    for servo in (1, 2):
        assert reader.addParam(servo)
    assert reader.txRxPacket() == COMM_SUCCESS
    assert reader.getData(1, xm.PRESENT_POSITION.address, 4) == 2500  # the plant followed the goal
    assert reader.getData(2, xm.PRESENT_POSITION.address, 4) == 1700
    assert reader.getData(2, xm.PRESENT_CURRENT.address, 2) == 0


def test_faults_a_driver_must_see(wire) -> None:
    bus, port, ph = wire
    bus.bus.faults.corrupt_replies = 1
    assert ph.read4ByteTxRx(port, 1, xm.PRESENT_POSITION.address)[1] == COMM_RX_CORRUPT  # the CRC caught it
    assert ph.read4ByteTxRx(port, 1, xm.PRESENT_POSITION.address)[1] == COMM_SUCCESS
    bus.bus.faults.drop_replies = 1
    assert ph.ping(port, 1)[1] == COMM_RX_TIMEOUT
    bus.bus.faults.dead.add(2)
    assert ph.ping(port, 2)[1] == COMM_RX_TIMEOUT and ph.ping(port, 1)[1] == COMM_SUCCESS
    bus.bus.faults.dead.clear()
    assert ph.write1ByteTxRx(port, 2, xm.TORQUE_ENABLE.address, 1) == (COMM_SUCCESS, 0)
    bus.bus.servos[2].raise_error(1 << 5)  # overload
    status, result, error = ph.read1ByteTxRx(port, 2, xm.HARDWARE_ERROR_STATUS.address)
    assert result == COMM_SUCCESS and error & p.ALERT and xm.hardware_errors(status) == ["overload error"]
    assert ph.read1ByteTxRx(port, 2, xm.TORQUE_ENABLE.address)[0] == 0  # the servo shut its torque off
    assert ph.write1ByteTxRx(port, 2, xm.TORQUE_ENABLE.address, 1)[1] == p.RESULT_FAIL | p.ALERT
    assert ph.reboot(port, 2) == (COMM_SUCCESS, p.ALERT)
    assert ph.read1ByteTxRx(port, 2, xm.HARDWARE_ERROR_STATUS.address) == (0, COMM_SUCCESS, 0)


def test_a_slow_answer_comes_late_and_whole() -> None:
    """``slow_replies`` holds back whole answers (a busy host): the packet is intact, only late, and the count
    runs down.  (The driver's port, whose answer timeout allows for the emulated bus's latency timer.)"""
    from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS
    from t42_transfer.hardware.servos import HandServos

    with PtyBus(t42_bus()) as bus:
        servos = HandServos(bus.port, 1_000_000, (1, 2), EMULATED_LATENCY_TIMER_MS)
        servos.open()
        try:
            bus.bus.faults.reply_delay_s, bus.bus.faults.slow_replies = 0.1, 1
            began = time.monotonic()
            assert servos.ping(1) == xm.XM430_W350
            assert time.monotonic() - began >= 0.1 and bus.bus.faults.slow_replies == 0
            assert servos.read_state() is not None  # the next answers as ever
        finally:
            servos.close()


def test_a_closed_port_fails_the_next_exchange(wire) -> None:
    """Unplugged: pyserial raises (EIO from termios) or the exchange times out; it never succeeds."""
    bus, port, ph = wire
    assert ph.ping(port, 1)[1] == COMM_SUCCESS
    bus.close_port()
    try:
        result = ph.ping(port, 1)[1]
    except (OSError, termios.error, serial.SerialException):
        return
    assert result != COMM_SUCCESS


def test_the_link_names_the_port_and_goes_with_it(tmp_path) -> None:
    link = tmp_path / "ttyT42"
    bus = PtyBus(t42_bus(), link=link)
    try:
        assert link.resolve() == bus.path and bus.port == str(link)
        port = PortHandler(str(link))
        assert port.openPort()
        assert PacketHandler(2.0).ping(port, 1)[1] == COMM_SUCCESS
        port.closePort()
    finally:
        bus.close_port()
    assert not link.exists()


def test_the_link_replaces_only_an_earlier_emulators_link(tmp_path) -> None:
    """A stale link into /dev/pts/ (an emulator killed before its exit) goes; the user's own link stays."""
    stale = tmp_path / "ttyT42"
    stale.symlink_to("/dev/pts/999")
    with PtyBus(t42_bus(), link=stale) as bus:
        assert stale.resolve() == bus.path
    assert not stale.is_symlink()
    (tmp_path / "precious.txt").write_text("keep me\n")
    mine = tmp_path / "L"
    mine.symlink_to("precious.txt")
    with pytest.raises(ValueError, match=f"^{mine}: exists and is not an emulator's pty link$"):
        PtyBus(t42_bus(), link=mine)
    assert mine.is_symlink() and mine.read_text() == "keep me\n"


def test_a_link_path_that_cannot_be_made_is_named_not_the_pty(tmp_path) -> None:
    (tmp_path / "file").write_text("the user's\n")
    with pytest.raises(ValueError, match=f"^{tmp_path / 'file'}: exists and is not an emulator's pty link$"):
        PtyBus(t42_bus(), link=tmp_path / "file")
    assert (tmp_path / "file").read_text() == "the user's\n"
    for link, problem in ((tmp_path / "missing" / "tty", "No such file or directory"),
                          (tmp_path / "file" / "tty", "Not a directory")):
        with pytest.raises(ValueError, match=f"^{link}: cannot make the link: {problem}$"):
            PtyBus(t42_bus(), link=link)


def test_closing_leaves_a_link_another_emulator_took_since(tmp_path) -> None:
    link = tmp_path / "ttyT42"
    with PtyBus(t42_bus(), link=link):
        link.unlink()
        link.symlink_to("/dev/pts/999")  # another emulator's, made after ours
    assert link.is_symlink() and str(link.readlink()) == "/dev/pts/999"


def test_the_bus_records_every_sync_written_goal_also_those_the_servos_refuse(wire) -> None:
    """A check of the goals a driver writes reads this record: Goal Position keeps only what the servo accepted."""
    bus, port, ph = wire
    for i in (1, 2):
        assert ph.write4ByteTxRx(port, i, xm.MAX_POSITION_LIMIT.address, 3000)[0] == COMM_SUCCESS
    group = GroupSyncWrite(port, ph, xm.GOAL_POSITION.address, xm.GOAL_POSITION.size)
    for goals in ({1: 2100, 2: 2200}, {1: 3500, 2: -5}):  # the second: past the limits, refused by both servos
        group.clearParam()
        for i, goal in goals.items():
            group.addParam(i, xm.GOAL_POSITION.encode(goal))
        assert group.txPacket() == COMM_SUCCESS
    deadline = time.monotonic() + 2.0  # (no answer to wait for: the bus thread takes them in its time)
    while len(bus.bus.goals_written) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert list(bus.bus.goals_written) == [{1: 2100, 2: 2200}, {1: 3500, 2: -5}]
    assert [bus.bus.servos[i].get(xm.GOAL_POSITION) for i in (1, 2)] == [2100, 2200]  # what the servos kept
