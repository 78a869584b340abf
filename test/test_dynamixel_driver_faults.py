"""The Dynamixel driver's faults on the emulated servo bus, each on a rig of its own: what is latched, what recovers,
what a cleanup and configure start over, and what a second program on the port meets.

The rig is :mod:`test_dynamixel_driver`'s (the bus on a pty with the simulated hand behind it, the driver on
rclpy's EventsExecutor, the lifecycle through the stock services).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from ros_rig import RosRig
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_dynamixel_driver import Rig

from msg_adapters import names, status_report
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS, PtyBus, t42_bus
from t42_transfer.hardware.servos import TORQUE_OFF
from t42_transfer.nodes.dynamixel_driver import STATUS_NAME, DynamixelDriver
from t42_transfer.ros.qos import profile

pytestmark = pytest.mark.events_executor


@pytest.fixture
def rig(ros: RosRig) -> Iterator[Rig]:
    """A rig of the test's own, the driver active (torque on, holding; no episode)."""
    r = Rig(ros)
    try:
        assert r.transition(Transition.TRANSITION_CONFIGURE) and r.transition(Transition.TRANSITION_ACTIVATE)
        r.forget()
        yield r
    finally:
        r.bench.bus.bus.faults.dead.clear()
        r.driver.close()  # torque off while the bus is still there
        r.bench.close()


def test_a_fault_held_at_cleanup_is_gone_after_configure_and_a_reset_is_taken(rig: Rig) -> None:
    """Servo 1 stops answering; the user deactivates and cleans up, fixes the cable, configures and activates: the
    hand is healthy, and hand/reset used to be refused for the fault held since before the cleanup."""
    faults = rig.bench.bus.bus.faults
    faults.dead.add(1)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 3.0), rig.events()
    assert rig.transition(Transition.TRANSITION_DEACTIVATE) and rig.transition(Transition.TRANSITION_CLEANUP)
    faults.dead.clear()  # the cable fixed
    rig.forget()
    assert rig.transition(Transition.TRANSITION_CONFIGURE)
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 2.0), rig.events()
    assert "configured" in rig.statuses[-1].data and "servo 1" in rig.statuses[-1].data  # after the fault it said
    assert rig.transition(Transition.TRANSITION_ACTIVATE)
    answer = rig.reset_client.call_async(Trigger.Request())  # at once: taken, the grasp begins (not waited for)
    assert rig.ros.spin_until(lambda: names.GRASPING in rig.events() or answer.done(), 5.0), rig.events()
    assert not answer.done(), answer.result()


def test_a_servo_that_restarted_while_active_is_a_fault_and_its_torque_comes_back(rig: Rig) -> None:
    """A supply dip restarts both servos: Torque Enable 0, no error bit.  The driver stepped on with limp fingers,
    saying nothing; now it reads Torque Enable each second: a fault on hand/status and diagnostics, then the usual
    recovery (torque on, holding) and ``recovered``."""
    diagnostics = rig.listen(DiagnosticArray, names.DIAGNOSTICS)
    bus = rig.bench.bus.bus
    with bus.lock:
        for servo in bus.servos.values():
            servo.reboot()
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.5), rig.events()
    assert "torque_off on servo 1" in rig.statuses[-1].data, rig.statuses[-1].data
    assert rig.ros.spin_until(lambda: any(status_report(d, STATUS_NAME).values.get("fault_kind") == TORQUE_OFF
                                          for d in diagnostics), 2.0)
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 3.0), rig.events()
    assert rig.bench.torque() == [True, True]


def test_a_second_driver_on_the_port_is_refused_as_in_use_and_the_first_holds_on(rig: Rig) -> None:
    """A params-file slip: a second driver (another namespace) on the same port.  Its configure wrote Torque
    Enable 0 to the servos the first held; now the port is opened exclusively and its configure fails, saying so."""
    other = rig.ros.add(DynamixelDriver, {"port": rig.bench.bus.port, "latency_timer_ms": EMULATED_LATENCY_TIMER_MS},
                        namespace="/other")
    theirs = rig.listen(String, f"/other/{names.HAND_STATUS}", profile(names.EVENTS))
    handled = rig.bench.bus.bus.handled
    assert other.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert rig.ros.spin_until(lambda: bool(theirs), 2.0)
    assert f"fault: configure failed: port: {rig.bench.bus.port} is in use by another program" in theirs[-1].data
    rig.ros.spin_for(0.5)
    assert rig.bench.torque() == [True, True] and rig.driver.fault is None and names.FAULT not in rig.events()
    assert rig.bench.bus.bus.handled > handled  # the first steps on


def test_while_inactive_the_servos_are_read_each_second_and_a_fault_is_said_and_recovered(rig: Rig) -> None:
    """Deactivated, the servos hold the grasp with their torque on; nothing was read or said until activate."""
    diagnostics = rig.listen(DiagnosticArray, names.DIAGNOSTICS)
    assert rig.transition(Transition.TRANSITION_DEACTIVATE)
    rig.ros.spin_for(2.2)
    said = [status_report(d, STATUS_NAME).message for d in diagnostics]
    assert said.count("inactive: torque on, holding") >= 2, said
    rig.bench.bus.bus.faults.dead.add(1)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.5), rig.events()
    assert "timeout on servo 1" in rig.statuses[-1].data
    rig.bench.bus.bus.faults.dead.clear()
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 3.0), rig.events()
    assert rig.state() == "inactive" and rig.bench.torque() == [True, True]
    # configured, never activated: the torque is off, and recovery leaves it so
    assert rig.transition(Transition.TRANSITION_CLEANUP) and rig.transition(Transition.TRANSITION_CONFIGURE)
    rig.forget()
    rig.bench.bus.bus.faults.dead.add(2)
    assert rig.ros.spin_until(lambda: names.FAULT in rig.events(), 2.5), rig.events()
    rig.bench.bus.bus.faults.dead.clear()
    assert rig.ros.spin_until(lambda: names.RECOVERED in rig.events(), 3.0), rig.events()
    assert rig.bench.torque() == [False, False]


def test_configure_refuses_a_finger_standing_outside_its_range_naming_its_tick_and_open_ticks(ros: RosRig) -> None:
    """open_ticks not this hand's: the fingers stand open at tick 2048, the driver thinks open is 2200.  Configure
    and activate passed, and activate's goals (clamped onto the range) closed the fingers by themselves."""
    r = Rig(ros)
    try:
        for name, value in (("max_angle_rad", [2.5, 2.5]), ("open_ticks", [2200, 2200])):
            assert r.driver.set_parameters([Parameter(name, value=value)])[0].successful
        assert not r.transition(Transition.TRANSITION_CONFIGURE)
        assert r.ros.spin_until(lambda: names.FAULT in r.events(), 2.0), r.events()
        said = r.statuses[-1].data
        assert "servo 1 stands at tick 2048, outside its range 2200..3830 (open_ticks 2200" in said, said
        assert r.state() == "unconfigured" and r.bench.torque() == [False, False] and r.driver.hand is None
        assert r.driver.set_parameters([Parameter("open_ticks", value=[2080, 2080])])[0].successful
        assert r.transition(Transition.TRANSITION_CONFIGURE)  # 32 ticks (0.05 rad) out: a slack tendon, accepted
    finally:
        r.driver.close()
        r.bench.close()


def test_a_hangup_stops_the_driver_process_cleanly_with_the_torque_off(ros_domain: int) -> None:
    """SIGHUP (the terminal or ssh session closed) ended ``t42 node dynamixel_driver`` at once, the torque left on;
    now it stops it as SIGINT does.  In this process (run_node as ``t42 node`` runs it): a SIGHUP that reaches the
    handler set before run_node's is one run_node left alone (the handler then stops it with SIGINT)."""
    from t42_transfer.ros.runner import run_node

    left_alone: list[int] = []

    def before(signum: int, frame: object) -> None:
        left_alone.append(signum)
        os.kill(os.getpid(), signal.SIGINT)

    previous = signal.signal(signal.SIGHUP, before)
    try:
        with PtyBus(t42_bus()) as bus:
            def hang_up() -> None:
                deadline = time.monotonic() + 30.0
                while not all(s.torque for s in bus.bus.servos.values()) and time.monotonic() < deadline:
                    time.sleep(0.05)
                time.sleep(0.3)  # a few steps
                os.kill(os.getpid(), signal.SIGHUP)

            threading.Thread(target=hang_up, daemon=True).start()
            code = run_node("dynamixel_driver", ["--ros-args", "-p", f"port:={bus.port}", "-p", "autostart:=true",
                                                 "-p", f"latency_timer_ms:={EMULATED_LATENCY_TIMER_MS}"])
            assert (code, left_alone) == (0, [])
            assert [s.torque for s in bus.bus.servos.values()] == [False, False]
    finally:
        signal.signal(signal.SIGHUP, previous)
