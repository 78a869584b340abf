"""driver.faults.recover on the emulated bus, no ROS: a servo found with an error bit is the servos' own hardware
fault (naming the bits), raised before any servo is torqued; without one the torque comes back."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from t42_transfer.driver.faults import recover
from t42_transfer.driver.servo_hand import HandGeometry, ServoHand
from t42_transfer.hardware import servos as s
from t42_transfer.hardware.emulator import PtyBus, t42_bus


@pytest.fixture
def hand() -> Iterator[tuple[PtyBus, ServoHand]]:
    with PtyBus(t42_bus()) as bus:
        servos = s.HandServos(bus.port, 1_000_000, (1, 2))
        servos.open()
        try:
            yield bus, ServoHand(servos, HandGeometry())
        finally:
            servos.close()


def test_a_servo_with_an_error_bit_is_a_hardware_fault_and_nothing_is_torqued(hand) -> None:
    bus, servo_hand = hand
    bus.bus.servos[2].raise_error(1 << 5)  # overload
    with pytest.raises(s.ServoFault) as fault:
        recover(servo_hand, s.ServoFault(s.TIMEOUT, 2, "no answer"), torque=True)
    assert (fault.value.kind, fault.value.servo_id) == (s.HARDWARE, 2) and "overload error" in str(fault.value)
    assert [bus.bus.servos[i].torque for i in (1, 2)] == [False, False]


def test_without_an_error_bit_the_torque_comes_back(hand) -> None:
    bus, servo_hand = hand
    recover(servo_hand, s.ServoFault(s.TIMEOUT, 1, "no answer"), torque=True)
    assert [bus.bus.servos[i].torque for i in (1, 2)] == [True, True]
