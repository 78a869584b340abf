"""``t42 hw read`` against the emulated servo bus on a pty: what a user reads before the first run of a real hand."""

from __future__ import annotations

import subprocess
import sys

import pytest

from t42_transfer.cli import main
from t42_transfer.hardware import protocol as p
from t42_transfer.hardware import xm430 as xm
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS, FollowingPlant, PtyBus, t42_bus
from t42_transfer.hardware.servos import HandServos


class LoadedPlant(FollowingPlant):
    """Servos standing where they are put, each holding a current (units)."""

    def __init__(self) -> None:
        super().__init__((1, 2))
        self.currents = {1: 0, 2: 0}

    def present(self) -> dict[int, tuple[int, int]]:
        return {i: (pos, self.currents[i]) for i, pos in self.positions.items()}


def _read(*args: str) -> list[str]:
    return ["hw", "read", *args, "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]


def test_hw_read_prints_each_servo_and_leaves_the_torque_as_it_was(capsys: pytest.CaptureFixture[str]) -> None:
    plant = LoadedPlant()
    with PtyBus(t42_bus(plant=plant)) as bus:
        servos = HandServos(bus.port, 1_000_000, (1, 2), latency_timer_ms=EMULATED_LATENCY_TIMER_MS)
        servos.open()
        servos.write(1, xm.TORQUE_ENABLE, 1)  # servo 1 on, servo 2 off: both stay so
        servos.close()
        plant.positions.update({1: 2731, 2: 1500})  # raw ticks: 2048 is 0 rad, whatever open_ticks is
        plant.currents.update({1: -120, 2: 37})
        bus.bus.servos[2].raise_error(1 << 5)  # overload (it also turns servo 2's torque off, as a real one)
        instructions = []
        handle = bus.bus.handle

        def seen(ins):  # noqa: ANN001, ANN202 (every packet the command sends)
            instructions.append(ins.instruction)
            return handle(ins)

        bus.bus.handle = seen
        assert main(_read("--port", bus.port)) == 0
        out = capsys.readouterr().out.splitlines()
        assert out == [
            "servo 1: model 1020 (XM430-W350), Present Position 2731 ticks, Present Current -120 (-322.8 mA), "
            "Hardware Error Status 0 (none)",
            "servo 2: model 1020 (XM430-W350), Present Position 1500 ticks, Present Current 37 (99.5 mA), "
            "Hardware Error Status 32 (overload error)",
        ]
        assert set(instructions) <= {p.PING, p.READ}, instructions  # reads only: nothing written, no reboot
        assert [bus.bus.servos[i].torque for i in (1, 2)] == [True, False]


def test_hw_read_names_a_servo_that_does_not_answer_and_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyBus(t42_bus()) as bus:
        bus.bus.faults.dead.add(2)
        assert main(_read("--port", bus.port, "--ids", "2,1")) == 1
        out = capsys.readouterr().out.splitlines()
        assert out[0] == "servo 2: timeout on servo 2: no answer to ping"
        assert out[1].startswith("servo 1: model 1020 (XM430-W350), Present Position 2048 ticks")


def test_hw_read_a_port_that_is_not_there_or_bad_ids(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(_read("--port", str(tmp_path / "ttyUSB9"))) == 1
    assert "cannot open" in capsys.readouterr().err
    for bad in ("1,x", "1,1", "300"):
        with pytest.raises(SystemExit) as exit_code:
            main(_read("--port", "/dev/null", "--ids", bad))
        assert exit_code.value.code == 2


def test_every_fault_the_emulate_command_takes_is_an_emulator_parameter() -> None:
    import argparse
    from dataclasses import fields

    from t42_transfer.cli.hw import FAULTS, fault_arg
    from t42_transfer.nodes.hw_emulator import HwEmulatorParams

    assert set(FAULTS) <= {f.name for f in fields(HwEmulatorParams)}
    assert fault_arg("slow_replies=3") == "slow_replies:=3" and fault_arg("reply_delay_s=0.1") == "reply_delay_s:=0.1"
    for bad in ("rate_factor=2", "slow_replies", "=3"):  # not a fault, no value, no name
        with pytest.raises(argparse.ArgumentTypeError, match="slow_replies"):
            fault_arg(bad)


@pytest.mark.parametrize("form", ["hw emulate --link {}", "node hw_emulator --ros-args -p link:={}"])
def test_emulate_refuses_a_link_path_it_did_not_make_in_one_line(form: str, tmp_path) -> None:
    """The user's own symlink stays as it was (it was once replaced, then removed on exit); a path that cannot
    be a link is named, not the pty."""
    (tmp_path / "precious.txt").write_text("keep me\n")
    (tmp_path / "L").symlink_to("precious.txt")
    for link, problem in (("L", "exists and is not an emulator's pty link"),
                          ("missing/tty", "cannot make the link: No such file or directory")):
        done = subprocess.run([sys.executable, "-m", "t42_transfer.cli", *form.format(tmp_path / link).split()],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stderr == f"t42: error: {tmp_path / link}: {problem}\n", done.stderr
    assert (tmp_path / "L").is_symlink() and (tmp_path / "L").read_text() == "keep me\n"


def test_hw_reboot_clears_an_error_bit_and_says_what_each_servo_reads_after(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A servo with a Hardware Error Status keeps the driver from configuring (the README's first-run checklist)."""
    with PtyBus(t42_bus()) as bus:
        bus.bus.servos[2].raise_error(1 << 5)
        argv = ["hw", "reboot", "--port", bus.port, "--ids", "2", "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]
        assert main(argv) == 0
        out = capsys.readouterr().out.splitlines()
        assert out == ["servo 2: rebooted (torque off): model 1020 (XM430-W350), Present Position 2048 ticks, "
                       "Present Current 0 (0.0 mA), Hardware Error Status 0 (none)"], out
        assert bus.bus.servos[2].get(xm.HARDWARE_ERROR_STATUS) == 0 and not bus.bus.servos[2].torque
        bus.bus.faults.dead.add(1)  # one that does not answer is named, and the exit says so
        assert main([*argv[:4], "--ids", "1,2", *argv[6:]]) == 1
        out = capsys.readouterr().out.splitlines()
        assert out[0] == "servo 1: timeout on servo 1: no answer to reboot" and out[1].startswith("servo 2: rebooted")


def test_hw_reboot_exits_1_when_the_error_comes_back(capsys: pytest.CaptureFixture[str]) -> None:
    """A servo still overheating raises its error bit again at once: the reboot did not clear it, and says so."""
    with PtyBus(t42_bus()) as bus:
        servo = bus.bus.servos[1]
        servo.raise_error(1 << 2)  # overheating
        servo.reboot = lambda: None  # the cause is still there: the bit stands after the restart
        argv = ["hw", "reboot", "--port", bus.port, "--ids", "1", "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]
        assert main(argv) == 1
        (line,) = capsys.readouterr().out.splitlines()
        assert line.startswith("servo 1: hardware on servo 1: rebooted, but the error is back:"), line
        assert "Hardware Error Status 4 (overheating error)" in line, line


@pytest.mark.parametrize("command", ["read", "reboot"])
def test_hw_read_and_reboot_say_the_port_is_in_use_while_a_driver_holds_it(
        command: str, capsys: pytest.CaptureFixture[str]) -> None:
    """A driver holds the port (opened exclusively): the command says so and exits 1, and nothing reaches the bus
    (a read used to answer beside the driver; a reboot turned its torque off under it)."""
    with PtyBus(t42_bus()) as bus:
        driver = HandServos(bus.port, 1_000_000, (1, 2), latency_timer_ms=EMULATED_LATENCY_TIMER_MS)
        driver.open()
        try:
            driver.torque(True)
            handled = bus.bus.handled
            assert main(["hw", command, "--port", bus.port, "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]) == 1
            err = capsys.readouterr().err
            assert err == f"t42: error: port: {bus.port} is in use by another program (a driver, t42 hw read or " \
                          f"reboot?); fuser -v {bus.port} names it\n", err
            assert bus.bus.handled == handled and [bus.bus.servos[i].torque for i in (1, 2)] == [True, True]
        finally:
            driver.close()
        assert main(["hw", "read", "--port", bus.port, "--latency-timer", str(EMULATED_LATENCY_TIMER_MS)]) == 0
