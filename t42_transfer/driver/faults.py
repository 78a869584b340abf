"""The fault a Dynamixel driver holds, when it tries again, and how the hand comes back; nothing here needs ROS.

Two sorts of fault (:class:`~t42_transfer.hardware.servos.ServoFault` kinds):

* latched: a Hardware Error Status bit (overheating, overload, electrical shock, a bad supply, the encoder).  The
  servo shut its torque off for a cause that may still be there (a servo still hot trips again as soon as it is
  torqued, and a reboot a second would cycle it without end), so nothing is tried: the fault stays reported until
  the operator acts (cleanup, find the cause, ``t42 hw reboot``, configure; a power cycle clears the bit too, and
  configure refuses a servo that still has one);
* everything else (no answer, a garbled answer, the port gone, the torque found off on a servo that restarted)
  recovers on its own: once a :data:`RETRY_PERIOD_S` the port is reopened if it went, the servos pinged, the
  torque turned on again if the hand had it on, and the fingers held where they stand (:func:`recover`).
"""

from __future__ import annotations

from t42_transfer.driver.servo_hand import ServoHand
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.servos import HARDWARE, PORT, ServoFault

RETRY_PERIOD_S = 1.0
"""How often a fault that recovers on its own is tried again (and a latched one reported again on diagnostics)."""
LATCHED_KINDS = frozenset({HARDWARE})


def latched_hint(port: str) -> str:
    """What the operator does about a latched fault."""
    return (f"latched, no automatic reboot: find the cause (a servo too hot, overloaded, a bad supply), then "
            f"cleanup, t42 hw reboot --port {port} (or a power cycle), configure and activate")


class FaultState:
    """The fault held (None: none) and when to try again."""

    def __init__(self) -> None:
        self.fault: ServoFault | None = None
        self.next_retry_s = 0.0

    @property
    def latched(self) -> bool:
        """Whether the fault held waits for the operator (:data:`LATCHED_KINDS`)."""
        return self.fault is not None and self.fault.kind in LATCHED_KINDS

    def hold(self, fault: ServoFault, now_s: float) -> bool:
        """Hold ``fault`` (a new one, or a retry that failed); whether its cause (kind and servo) differs from the
        one held before."""
        held, self.fault = self.fault, fault
        self.next_retry_s = now_s + RETRY_PERIOD_S
        return held is None or (fault.kind, fault.servo_id) != (held.kind, held.servo_id)

    def due(self, now_s: float) -> bool:
        """Whether a retry (or a latched fault's report) is due at ``now_s``; if so the next is a period later."""
        if now_s < self.next_retry_s:
            return False
        self.next_retry_s = now_s + RETRY_PERIOD_S
        return True

    def clear(self) -> ServoFault | None:
        """Forget the fault (recovered, or the hand released); the one held."""
        fault, self.fault, self.next_retry_s = self.fault, None, 0.0
        return fault


def recover(hand: ServoHand, fault: ServoFault, torque: bool) -> None:
    """Bring ``hand`` back after ``fault`` (one that is not latched): the port reopened if it went, every servo
    pinged, the torque on again if ``torque`` (the hand had it on), goals where the fingers stand.  A
    :class:`ServoFault` when it is not back yet; a servo found with a Hardware Error Status bit is a hardware
    fault, which latches (it is never rebooted here).  That check is the servos' own (a read without ``alert_ok``
    raises it, naming the bits), made before any torque is written so no servo is torqued beside a shut one."""
    servos = hand.servos
    if fault.kind == PORT:
        servos.close()
        servos.open()
    servos.check()
    for i in servos.ids:
        servos.read(i, xm.HARDWARE_ERROR_STATUS)
    if torque:
        servos.torque(True)
    hand.start_from_present()
    hand.hold()
