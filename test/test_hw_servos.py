"""hardware.servos against the emulated bus: what the driver does each step, and each fault as one ServoFault."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from t42_transfer.conventions import GRASP_LOAD, LOAD_UNIT_NM
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.hardware import servos as s
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.emulator import PtyBus, t42_bus
from t42_transfer.hardware.hand_plant import HandPlant

LIMITS = {1: (2048, 3400), 2: (2048, 3400)}


@pytest.fixture
def hand() -> Iterator[tuple[PtyBus, s.HandServos]]:
    with PtyBus(t42_bus()) as bus:
        servos = s.HandServos(bus.port, 1_000_000, (1, 2))
        servos.open()
        try:
            yield bus, servos
        finally:
            servos.close()


def test_check_configure_torque_and_one_step(hand) -> None:
    bus, servos = hand
    assert servos.check() == {1: xm.XM430_W350, 2: xm.XM430_W350}
    servos.configure(xm.POSITION_MODE, LIMITS)
    assert all(servos.read(i, xm.MIN_POSITION_LIMIT) == 2048 for i in (1, 2))
    servos.torque(True)
    servos.write_goals({1: 2100, 2: 2200})
    state = servos.read_state()
    assert state.positions == {1: 2100, 2: 2200} and state.currents == {1: 0, 2: 0}
    servos.torque(False)
    assert [bus.bus.servos[i].torque for i in (1, 2)] == [False, False]


@pytest.mark.parametrize("inject, kind, servo", [
    (lambda bus: setattr(bus.bus.faults, "drop_replies", 1), s.TIMEOUT, 1),
    (lambda bus: setattr(bus.bus.faults, "corrupt_replies", 1), s.CORRUPT, 1),
    (lambda bus: bus.bus.faults.dead.add(2), s.TIMEOUT, 2),
    (lambda bus: bus.bus.servos[2].raise_error(1 << 5), s.HARDWARE, 2),
    (lambda bus: bus.close_port(), s.PORT, None),
    (lambda bus: bus.bus.servos[2].reboot(), s.TORQUE_OFF, 2),  # a supply dip: torque off, no error bit
], ids=["dropped", "corrupt", "dead", "error bit", "unplugged", "restarted"])
def test_each_fault_is_one_servo_fault_naming_the_servo(hand, inject, kind: str, servo: int | None) -> None:
    bus, servos = hand
    servos.torque(True)
    inject(bus)
    with pytest.raises(s.ServoFault) as fault:
        servos.read_state()
    assert (fault.value.kind, fault.value.servo_id) == (kind, servo), fault.value
    if kind == s.HARDWARE:
        assert "overload error" in str(fault.value)
        servos.reboot(2)
        assert servos.hardware_status(2) == 0 and servos.read_state().positions[2] == xm.ZERO_TICK


def test_a_port_that_is_no_dynamixel_bus(tmp_path) -> None:
    plain = tmp_path / "not_a_port"
    plain.write_text("")
    servos = s.HandServos(str(plain), 1_000_000, (1, 2))
    with pytest.raises(s.ServoFault) as fault:
        servos.open()
        servos.check()
    assert fault.value.kind in (s.PORT, s.TIMEOUT)


def test_a_grasp_through_the_bus_closes_until_the_load() -> None:
    """Behind the bus the simulated hand closes on the object; its loads come back through Present Current."""
    plant = HandPlant(SimulatedHand("target"))
    with PtyBus(t42_bus(plant=plant)) as bus:
        servos = s.HandServos(bus.port, 1_000_000, (1, 2))
        servos.open()
        servos.torque(True)
        goals, closed = {1: xm.ZERO_TICK, 2: xm.ZERO_TICK}, {1: False, 2: False}
        for _ in range(200):
            state = servos.read_state()
            loads = {i: xm.current_to_load(state.currents[i], LOAD_UNIT_NM) for i in (1, 2)}
            closed = {i: closed[i] or abs(loads[i]) > GRASP_LOAD for i in (1, 2)}
            if all(closed.values()):
                break
            goals = {i: g + (0 if closed[i] else 7) for i, g in goals.items()}
            servos.write_goals(goals)
            plant.tick()
        servos.close()
    assert all(closed.values())
    true_loads = plant.hand.loads
    assert np.all(np.abs(true_loads) > GRASP_LOAD * 0.8)
    assert [np.sign(loads[i]) for i in plant.geometry.servo_ids] == list(np.sign(true_loads))


@pytest.mark.parametrize("latency_timer_ms, answered", [(s.SDK_LATENCY_TIMER_MS, False), (200.0, True)])
def test_the_adapters_latency_timer_sets_how_long_an_answer_is_awaited(latency_timer_ms: float,
                                                                        answered: bool) -> None:
    """A servo answering 60 ms late: past dynamixel-sdk's 34 ms for a 16 ms adapter, in time for a slow link."""
    import time

    with PtyBus(t42_bus()) as bus:
        handle = bus.bus.handle

        def late(ins):  # noqa: ANN001, ANN202
            time.sleep(0.06)
            return handle(ins)

        bus.bus.handle = late
        servos = s.HandServos(bus.port, 1_000_000, (1, 2), latency_timer_ms=latency_timer_ms)
        servos.open()
        try:
            if answered:
                assert servos.ping(1) == xm.XM430_W350
            else:
                with pytest.raises(s.ServoFault) as fault:
                    servos.ping(1)
                assert fault.value.kind == s.TIMEOUT
        finally:
            servos.close()


@pytest.mark.parametrize("inject, failed, off", [
    (lambda bus: setattr(bus.bus.faults, "drop_replies", 1), {}, [True, True]),
    (lambda bus: setattr(bus.bus.faults, "drop_replies", 2), {1: s.TIMEOUT}, [True, True]),
    (lambda bus: bus.bus.faults.dead.add(1), {1: s.TIMEOUT}, [False, True]),
    (lambda bus: bus.bus.servos[1].raise_error(1 << 5), {}, [True, True]),  # its replies raise the alert bit
], ids=["one reply dropped", "two replies dropped", "servo 1 dead", "error bit"])
def test_torque_off_tries_every_servo_whatever_the_one_before_did(hand, inject, failed: dict, off: list) -> None:
    """A lost reply is written again; a servo that never confirms is named, and the other still goes off."""
    bus, servos = hand
    servos.torque(True)
    assert [bus.bus.servos[i].torque for i in (1, 2)] == [True, True]
    inject(bus)
    result = servos.set_torque(False)
    assert {i: f.kind for i, f in result.items()} == failed
    assert [not bus.bus.servos[i].torque for i in (1, 2)] == off  # Torque Enable of the emulated servos themselves


def test_torque_off_names_every_servo_that_failed_after_trying_all(hand) -> None:
    bus, servos = hand
    servos.torque(True)
    bus.bus.faults.dead.add(1)
    with pytest.raises(s.ServoFault) as fault:
        servos.torque(False)
    assert fault.value.servo_id == 1 and "servo 1" in str(fault.value) and "servo 2" not in str(fault.value)
    assert bus.bus.servos[2].torque is False


@pytest.mark.parametrize("inject, failed", [
    (lambda bus: setattr(bus.bus.faults, "drop_replies", 1), None),  # servo 1's first answer lost: written again
    (lambda bus: bus.bus.faults.dead.add(1), 1),
], ids=["one reply dropped", "servo 1 dead"])
def test_configure_turns_the_torque_off_on_every_servo_before_it_fails(hand, inject, failed: int | None) -> None:
    """configure used to stop at the first servo whose torque-off write failed, the other servo's torque left on."""
    bus, servos = hand
    servos.torque(True)
    inject(bus)
    if failed is None:
        servos.configure(xm.POSITION_MODE, LIMITS)
        assert all(servos.read(i, xm.MAX_POSITION_LIMIT) == 3400 for i in (1, 2))
    else:
        with pytest.raises(s.ServoFault) as fault:
            servos.configure(xm.POSITION_MODE, LIMITS)
        assert fault.value.servo_id == failed and "servo 2" not in str(fault.value), fault.value
    assert bus.bus.servos[2].torque is False  # Torque Enable of the emulated servo itself
    assert bus.bus.servos[1].torque is (failed == 1)


def test_after_the_port_failed_mid_packet_the_next_packets_still_reach_it(hand) -> None:
    """dynamixel-sdk marks its port busy for a packet and leaves the mark when the port raises mid-packet: every
    packet after, the torque off at shutdown too, was refused unsent ("Port is in use!") as a timeout."""
    bus, servos = hand
    servos.torque(True)
    bus.close_port()  # the adapter pulled: the terminal's writes fail with an I/O error
    with pytest.raises(s.ServoFault) as fault:
        servos.write_goals({1: 2100, 2: 2100})
    assert fault.value.kind == s.PORT and str(fault.value).startswith("port: sync write:"), fault.value
    failed = servos.set_torque(False)
    assert sorted(failed) == [1, 2]
    assert all(f.kind == s.PORT and "in use" not in str(f) for f in failed.values()), failed  # tried on the port


def test_an_error_status_of_bits_without_a_name_is_reported_by_its_value(hand) -> None:
    """Bit 1 is reserved on an XM430: the fault gives the status value, not "alert without an error bit" (review)."""
    bus, servos = hand
    servos.torque(True)
    bus.bus.servos[2].raise_error(1 << 1)
    with pytest.raises(s.ServoFault, match="Hardware Error Status 2") as fault:
        servos.read_state()
    assert (fault.value.kind, fault.value.servo_id) == (s.HARDWARE, 2)
