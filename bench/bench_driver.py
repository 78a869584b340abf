"""Dynamixel driver on the emulated bus: step jitter, late steps, CPU per step, and a bare dynamixel-sdk loop beside it.

    .venv/bin/python bench/bench_driver.py [--seconds 60] [--out bench/results/driver.json]

The emulated servo bus runs in this process (a pty, servos that follow their goals); the driver runs as
``t42 node dynamixel_driver`` (autostart, holding: one sync read and one sync write a step) in its own
process, whose CPU time is read from /proc.  The steps' timing is what the bus saw: the arrival of each
sync read.  Beside it, a bare loop (its own process too) does the same sync read and sync write every
period with dynamixel-sdk's calls and nothing else; its round trip is the time of one read plus one write.
Target: driver CPU per step at most 1.5x the bare loop's, and no late step (> 1.5 periods) on a quiet
machine; ``target_met`` says whether this run met it.  The machine's load is recorded after each run: on
a shared machine, repeat on a quiet one before quoting.

Two more runs say where the driver's CPU goes, beside the target (which they do not change):

* ``bare_sdk_loop_select_reads``: the same bare loop with its port's reads waiting in ``select`` as the
  driver's do (``servos.READ_WAIT_S``); the stock loop spins on the port, as dynamixel-sdk does, for the
  whole round trip;
* ``idle_rclpy_node``: a plain rclpy node with one no-op timer at the control period, spun as ``t42 node``
  spins its node: the CPU any rclpy node pays per period (executor and DDS) before its callback does anything.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.machine import machine_info  # noqa: E402
from t42_transfer.conventions import CONTROL_PERIOD_S  # noqa: E402
from t42_transfer.hardware import protocol as p  # noqa: E402
from t42_transfer.hardware.emulator import PtyBus, t42_bus  # noqa: E402
from t42_transfer.hardware.servos import READ_WAIT_S  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "driver.json"
REPO = Path(__file__).resolve().parents[1]
TICK_S = os.sysconf("SC_CLK_TCK")

BARE_LOOP = """
import sys, time
from dynamixel_sdk import GroupSyncWrite, PacketHandler, PortHandler
port = PortHandler(sys.argv[1]); port.openPort(); port.setBaudRate(1000000)
if len(sys.argv) > 4: port.ser.timeout = float(sys.argv[4])  # reads wait in select (the stock SDK: 0, they spin)
ph = PacketHandler(2.0); ids = [1, 2]; seconds = float(sys.argv[2]); period = float(sys.argv[3])
for i in ids: ph.write1ByteTxRx(port, i, 64, 1)
trips = []; steps = 0; start = time.perf_counter(); cpu = time.process_time(); next_t = start
while time.perf_counter() - start < seconds:
    t0 = time.perf_counter()
    ph.syncReadTx(port, 126, 10, ids, 2, False)
    data = [ph.readRx(port, i, 10) for i in ids]
    w = GroupSyncWrite(port, ph, 116, 4)
    for i in ids: w.addParam(i, (2048).to_bytes(4, "little"))
    w.txPacket()
    trips.append(time.perf_counter() - t0); steps += 1
    next_t += period; time.sleep(max(0.0, next_t - time.perf_counter()))
print(time.process_time() - cpu, steps, sum(trips) / len(trips), max(trips))
"""

IDLE_NODE = """
import os, sys, time
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
seconds, period = float(sys.argv[1]), float(sys.argv[2])
context = rclpy.Context(); rclpy.init(args=["idle"], context=context)
node = Node("idle_floor", context=context); ticks = []
node.create_timer(period, lambda: ticks.append(None))
executor = SingleThreadedExecutor(context=context); executor.add_node(node)
warm = time.monotonic() + 2.0
while time.monotonic() < warm: executor.spin_once(timeout_sec=0.1)
first, cpu, start = len(ticks), time.process_time(), time.monotonic()
while time.monotonic() - start < seconds: executor.spin_once(timeout_sec=0.1)
print(time.process_time() - cpu, len(ticks) - first)
"""


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK_S  # utime + stime


class Watch:
    """Arrival times of the sync reads the bus answers: one per driver step."""

    def __init__(self, bus) -> None:  # noqa: ANN001
        self.times: list[float] = []
        handle = bus.handle

        def watched(ins: p.Instruction) -> bytes:
            if ins.instruction == p.SYNC_READ:
                self.times.append(time.perf_counter())
            return handle(ins)

        bus.handle = watched


def driver_run(seconds: float) -> dict:
    bus = t42_bus()
    watch = Watch(bus)
    with PtyBus(bus) as pty:
        proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "node", "dynamixel_driver", "--ros-args",
                                 "-p", f"port:={pty.port}", "-p", "autostart:=true"], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60.0
            while len(watch.times) < 5:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("the driver never stepped")
                time.sleep(0.05)
            first, cpu0 = len(watch.times), cpu_s(proc.pid)
            time.sleep(seconds)
            steps, cpu = len(watch.times) - first, cpu_s(proc.pid) - cpu0
        finally:
            proc.terminate()
            proc.wait(timeout=15)
    intervals = np.diff(watch.times[first - 1: first + steps])
    return {"steps": steps, "cpu_ms_per_step": 1e3 * cpu / max(steps, 1),
            "interval_ms": {"mean": 1e3 * float(intervals.mean()), "std": 1e3 * float(intervals.std()),
                            "p99": 1e3 * float(np.percentile(intervals, 99)), "max": 1e3 * float(intervals.max())},
            "late_steps": int(np.sum(intervals > 1.5 * CONTROL_PERIOD_S)), "load_after": os.getloadavg()}


def bare_run(seconds: float, read_wait_s: float | None = None) -> dict:
    """The bare loop; ``read_wait_s``: its reads wait in select that long at a time (None: stock, they spin)."""
    bus = t42_bus()
    wait = [] if read_wait_s is None else [str(read_wait_s)]
    with PtyBus(bus) as pty:
        out = subprocess.run([sys.executable, "-c", BARE_LOOP, pty.port, str(seconds), str(CONTROL_PERIOD_S), *wait],
                             capture_output=True, text=True, timeout=seconds + 60, check=True)
    cpu, steps, trip, worst = (float(v) for v in out.stdout.split())
    return {"steps": int(steps), "cpu_ms_per_step": 1e3 * cpu / steps, "round_trip_ms": 1e3 * trip,
            "round_trip_max_ms": 1e3 * worst, "load_after": os.getloadavg()}


def idle_node_run(seconds: float) -> dict:
    """CPU per period of an rclpy node that does nothing: the floor under any node's callback."""
    out = subprocess.run([sys.executable, "-c", IDLE_NODE, str(seconds), str(CONTROL_PERIOD_S)], cwd=REPO,
                         capture_output=True, text=True, timeout=seconds + 60, check=True)
    cpu, ticks = (float(v) for v in out.stdout.split())
    return {"periods": int(ticks), "cpu_ms_per_period": 1e3 * cpu / max(ticks, 1), "load_after": os.getloadavg()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="timed window of each run (60)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    threading.current_thread().name = "bench"
    machine = machine_info()
    driver, bare = driver_run(args.seconds), bare_run(args.seconds)
    bare_select, idle = bare_run(args.seconds, READ_WAIT_S), idle_node_run(args.seconds)
    ratio = driver["cpu_ms_per_step"] / bare["cpu_ms_per_step"]
    target = {"cpu_ratio_max": 1.5, "late_steps": 0}
    result = {
        "command": f"python bench/bench_driver.py --seconds {args.seconds:g}",
        "machine": machine,
        "load_after": os.getloadavg(),
        "seconds": args.seconds,
        "driver": driver,
        "bare_sdk_loop": bare,
        "cpu_ratio_driver_to_bare": ratio,
        "target": target,
        "target_met": bool(ratio <= target["cpu_ratio_max"] and driver["late_steps"] <= target["late_steps"]),
        "target_note": "the driver's port reads wait in select; the bare loop's spin on the port as stock "
                       "dynamixel-sdk's do (see bare_sdk_loop_select_reads for the loop waiting as the driver does)",
        "bare_sdk_loop_select_reads": bare_select,
        "cpu_ratio_driver_to_bare_select_reads": driver["cpu_ms_per_step"] / bare_select["cpu_ms_per_step"],
        "idle_rclpy_node": idle,
        "driver_cpu_above_idle_node_ms_per_step": driver["cpu_ms_per_step"] - idle["cpu_ms_per_period"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
