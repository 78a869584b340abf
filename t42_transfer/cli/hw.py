"""``t42 hw emulate``: emulated T42 hardware (a servo bus on a pty, the simulated hand, a tracker) as a node;
``t42 hw read``: what the servos on a port say (model, position, current, error bits), the torque untouched;
``t42 hw reboot``: each servo rebooted (a Hardware Error Status cleared), then what it says."""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from t42_transfer.cli.args import SEED_MAX, float_arg, int_arg

if TYPE_CHECKING:
    from t42_transfer.hardware.servos import HandServos

FAULTS = ("drop_replies", "corrupt_replies", "slow_replies", "reply_delay_s", "dead_servos", "error_bits",
          "port_closed")
FAULT = re.compile(rf"^({'|'.join(FAULTS)})=(\S+)$")
"""``--fault NAME=VALUE``: one of the emulator's fault parameters (see ``t42_transfer.nodes.hw_emulator``)."""


def fault_arg(text: str) -> str:
    """An argparse type: ``NAME=VALUE`` naming a fault parameter, returned as a ROS ``-p`` argument."""
    match = FAULT.match(text)
    if match is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE with NAME one of {', '.join(FAULTS)}")
    return f"{match.group(1)}:={match.group(2)}"


def _cmd_emulate(args: argparse.Namespace) -> int:
    from t42_transfer.ros.runner import keep_discovery_local, run_node

    params = [f"rate_factor:={args.rate_factor}", f"seed:={args.seed}", f"pose_rate_hz:={args.pose_rate}",
              f"sim_time:={str(args.sim_time).lower()}", f"hand:={args.hand}", *args.fault]
    if args.link:
        params.append(f"link:={args.link.absolute()}")
    if args.camera:
        params.append(f"camera_rate_hz:={args.camera}")
    keep_discovery_local()
    ros_args = ["--ros-args"] + [a for p in params for a in ("-p", p)] + list(args.ros_args)
    return run_node("hw_emulator", ros_args)


def ids_arg(text: str) -> tuple[int, ...]:
    """An argparse type: servo ids ``1,2`` (0-252, different)."""
    try:
        ids = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not servo ids like 1,2") from None
    if not all(0 <= i <= 252 for i in ids) or len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"{text!r}: servo ids are different numbers from 0 to 252")
    return ids


REBOOT_WAIT_S = 2.0
"""How long ``t42 hw reboot`` waits for a rebooted servo to answer again (an XM430 restarts in well under that)."""


def _open_servos(args: argparse.Namespace) -> HandServos:
    """The bus of ``--port``/``--baud``/``--ids``/``--latency-timer``, opened; ServoFault when it cannot be."""
    from t42_transfer.hardware.servos import SDK_LATENCY_TIMER_MS, HandServos

    latency = SDK_LATENCY_TIMER_MS if args.latency_timer is None else args.latency_timer
    servos = HandServos(args.port, args.baud, args.ids, latency_timer_ms=latency)
    servos.open()
    return servos


def _each_servo(args: argparse.Namespace, line: Callable[[HandServos, int], str]) -> int:
    """``servo <id>: line(servos, id)`` for each servo, a fault in its place; exit 1 when one (or the port) failed."""
    from t42_transfer.hardware.servos import ServoFault

    try:
        servos = _open_servos(args)
    except ServoFault as err:
        print(f"t42: error: {err}", file=sys.stderr)
        return 1
    failed = 0
    try:
        for i in args.ids:
            try:
                print(f"servo {i}: {line(servos, i)}")
            except ServoFault as err:
                failed += 1
                print(f"servo {i}: {err}")
    finally:
        servos.close()
    return 1 if failed else 0


def _cmd_read(args: argparse.Namespace) -> int:
    """One line per servo; exit 1 when a servo (or the port) did not answer."""
    return _each_servo(args, lambda servos, i: servos.info(i).describe())


def _rebooted(servos: HandServos, servo_id: int) -> str:
    """Reboot one servo, then what it reads once it answers again; ServoFault when it did not come back clear."""
    from t42_transfer.hardware.servos import HARDWARE, TIMEOUT, ServoFault

    servos.reboot(servo_id)
    deadline = time.monotonic() + REBOOT_WAIT_S
    while True:
        try:
            info = servos.info(servo_id)
            break
        except ServoFault as err:
            if time.monotonic() > deadline:
                raise ServoFault(TIMEOUT, servo_id, f"rebooted, but no answer within {REBOOT_WAIT_S:g} s ({err}); "
                                                    "read it again in a moment with t42 hw read") from None
            time.sleep(0.1)
    if info.hardware_error:  # the cause is still there (a servo still too hot, a supply still too low)
        raise ServoFault(HARDWARE, servo_id, f"rebooted, but the error is back: {info.describe()}")
    return f"rebooted (torque off): {info.describe()}"


def _cmd_reboot(args: argparse.Namespace) -> int:
    """Reboot each servo (its Hardware Error Status cleared, its torque off); exit 1 when one did not come back."""
    return _each_servo(args, _rebooted)


def _bus_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", required=True, help="the servo bus, e.g. /dev/ttyUSB0")
    parser.add_argument("--ids", type=ids_arg, default=(1, 2), help="servo ids, comma-separated (default 1,2)")
    parser.add_argument("--baud", type=int_arg(9600, 4_500_000), default=1_000_000, help="baud rate (1000000)")
    parser.add_argument("--latency-timer", type=float_arg(0, 1000), default=None, metavar="MS",
                        help="the adapter's latency timer in ms (16; an emulated bus: 100)")


def add_commands(commands: argparse._SubParsersAction) -> None:
    hw = commands.add_parser("hw", help="T42 hardware: an emulated hand to drive").add_subparsers(
        dest="hw_command", metavar="ACTION")
    emu = hw.add_parser("emulate", help="two XM430 servos on a pty with the simulated hand behind them, and a "
                                        "tracker on tracker/object_pose, until Ctrl-C")
    emu.add_argument("--link", type=Path, default=None, help="symlink to the servo bus (e.g. /tmp/ttyT42)")
    emu.add_argument("--hand", default="target", help="simulated hand behind the servos (default target)")
    emu.add_argument("--rate-factor", type=float_arg(0, 100, low_open=True), default=1.0,
                     help="run this many times faster than real time (with --sim-time)")
    emu.add_argument("--sim-time", action="store_true", help="publish /clock: the graph runs on the emulator's time")
    emu.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    emu.add_argument("--pose-rate", type=float_arg(0.1, 100), default=6.0, help="tracker frames per second (6)")
    emu.add_argument("--camera", type=float_arg(0, 10), default=0.0, metavar="HZ",
                     help="render the hand with its markers at HZ (at most one frame a step) on camera/image_raw "
                          "instead of the emulated tracker; run object_tracker on it")
    emu.add_argument("--fault", type=fault_arg, action="append", default=[], metavar="NAME=VALUE",
                     help="inject a fault from the start, e.g. drop_replies=5, error_bits=[0,32], port_closed=true")
    emu.add_argument("ros_args", nargs=argparse.REMAINDER, help="more ROS arguments after --ros-args")
    emu.set_defaults(func=_cmd_emulate)
    read = hw.add_parser("read", help="each servo's model, Present Position (raw ticks), Present Current and "
                                      "Hardware Error Status, reading only: the torque stays as it is")
    _bus_arguments(read)
    read.set_defaults(func=_cmd_read)
    reboot = hw.add_parser("reboot", help="reboot each servo: a Hardware Error Status (overload, overheating...) "
                                          "cleared, the torque off; then what it reads (stop the driver first)")
    _bus_arguments(reboot)
    reboot.set_defaults(func=_cmd_reboot)
