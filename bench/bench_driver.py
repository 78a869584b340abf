"""Dynamixel driver on the emulated bus: step jitter, late steps, CPU per step, and a bare dynamixel-sdk loop beside it.

    .venv/bin/python bench/bench_driver.py [--seconds 60] [--out bench/results/driver.json]

The emulated hand runs in this process (the ``hw_emulator`` node: its servo bus on a pty, the simulated hand
behind it, its tracker on ``tracker/object_pose``); the driver runs as ``t42 node dynamixel_driver`` (autostart)
in its own process, whose CPU time is read from /proc.  Before the timed window this process calls
``hand/reset`` (the grasp) and then sends a slow single-step command each period, so every step of the window
is an episode's full step: one sync read, ``hand/joint_states``, ``hand/object_pose`` and ``hand/applied_action``
published, one sync write of the goals the command moved (``driver.episode`` counts what came out; with no
episode the driver would only read and hold).  The steps' timing is what the bus saw: the arrival of each sync
read.  Beside it, a bare loop (its own process too) does the same sync read and sync write every period with
dynamixel-sdk's calls and nothing else; its round trip is the time of one read plus one write.  It runs twice:

* ``bare_sdk_loop``: stock dynamixel-sdk, whose reads spin on the port for the whole round trip (polling);
  ``cpu_ratio_driver_to_stock_sdk_loop`` is the driver beside it;
* ``bare_sdk_loop_select_reads``: its port's reads waiting in ``select`` as the driver's do
  (``servos.READ_WAIT_S``): the same work as the driver's bus side; ``cpu_ratio_driver_to_select_reads_loop``.

Target (``target``): driver CPU per step at most 1.5x the bare loop doing the same work
(``cpu_ratio_driver_to_select_reads_loop``), no late step (> 1.5 periods) on a quiet machine, and every step
of the window published; ``target_met`` says whether this run met it and ``target_missed_because`` why not.
The machine's load is recorded after each run: on a shared machine, repeat on a quiet one before quoting.

Two more runs say where the driver's CPU goes:

* ``idle_rclpy_node`` and ``idle_rclpy_node_events_executor``: a plain rclpy node with one no-op timer at the
  control period, on the SingleThreadedExecutor and on rclpy's EventsExecutor (C++ event queue, no wait set
  rebuilt per wake; the executor ``t42 node`` spins the driver on): the CPU any rclpy node pays per period
  before its callback does anything;
* ``rclpy_interface_floor``: the driver's ROS traffic and nothing else on the driver's executor (each period
  a timer wake, the tracker's pose and a command taken, the three step messages published), beside the same
  peers as the driver's run: what rclpy and Fast DDS cost any node with the driver's interface, without a bus.
  ``driver_cpu_above_interface_floor_ms_per_step`` is what is left for the driver's own work (the bus, the
  limits, building the messages), and ``cpu_ratio_driver_above_floor_to_select_reads_loop`` sets it beside the
  bare loop; neither replaces the target's ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from geometry_msgs.msg import PoseStamped  # noqa: E402

from bench.machine import machine_info  # noqa: E402
from msg_adapters import RCLPY, applied_action_msg, names, stamp_to_ns  # noqa: E402
from t42_transfer.conventions import CONTROL_PERIOD_S  # noqa: E402
from t42_transfer.hardware import protocol as p  # noqa: E402
from t42_transfer.hardware.emulator import EMULATED_LATENCY_TIMER_MS, PtyBus, t42_bus  # noqa: E402
from t42_transfer.hardware.servos import READ_WAIT_S  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "driver.json"
REPO = Path(__file__).resolve().parents[1]
TICK_S = os.sysconf("SC_CLK_TCK")
COMMAND_ACTION = 0.1
"""The driver's window: each period a single-step command of this action on both actuators (slow: 2.5 mrad)."""

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

FLOOR_NODE = """
import os, sys, time
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
seconds, period, kind = float(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
context = rclpy.Context(); rclpy.init(args=["floor"], context=context)
node = Node("floor", context=context); ticks = []; outs = []
if kind == "traffic":
    from geometry_msgs.msg import PoseStamped
    from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
    from sensor_msgs.msg import JointState
    from msg_adapters import RCLPY, applied_action_msg, joint_state_msg, names, object_pose_msg
    pub = {"event_callbacks": PublisherEventCallbacks(use_default_callbacks=False)}
    sub = {"event_callbacks": SubscriptionEventCallbacks(use_default_callbacks=False)}
    outs = [(node.create_publisher(JointState, names.JOINT_STATES, 10, **pub),
             joint_state_msg([1.0, 2.0], [0.5, 0.6], 0, RCLPY)),
            (node.create_publisher(PoseStamped, names.OBJECT_POSE, 10, **pub), object_pose_msg([1.0, 90.0], 0, RCLPY)),
            (node.create_publisher(JointState, names.APPLIED_ACTION, 10, **pub),
             applied_action_msg([0.1, 0.1], 0, RCLPY))]
    node.create_subscription(PoseStamped, names.TRACKER_POSE, lambda m: None, 10, **sub)
    node.create_subscription(JointState, names.HAND_COMMAND, lambda m: None, 10, raw=True, **sub)
def tick():
    ticks.append(None)
    if outs:
        now = node.get_clock().now().to_msg()
        for publisher, msg in outs:
            msg.header.stamp = now; publisher.publish(msg)
node.create_timer(period, tick)
executor = (SingleThreadedExecutor if kind == "single" else EventsExecutor)(context=context); executor.add_node(node)
warm = time.monotonic() + 3.0
while time.monotonic() < warm: executor.spin_once(timeout_sec=0.1)
first, cpu, start = len(ticks), time.process_time(), time.monotonic()
while time.monotonic() - start < seconds: executor.spin_once(timeout_sec=0.1)
print(time.process_time() - cpu, len(ticks) - first)
"""
"""A node with one timer at the control period, its CPU per period measured: ``single`` and ``events``, doing
nothing on the SingleThreadedExecutor or the EventsExecutor; ``traffic``, on the EventsExecutor, the driver's ROS
traffic and nothing else (each period the tracker's pose and a command taken, the command raw, and the three step
messages published, built once with their stamps renewed), no servo bus: what rclpy and Fast DDS cost any node
with the driver's interface."""


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


class EpisodeClient:
    """This process's side of the driver's episode: the emulated hand (its bus, its tracker on
    ``tracker/object_pose``), ``hand/reset``, a slow single-step command each period, and what the driver
    published, all on one executor spun in a thread of its own."""

    def __init__(self, link: str) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from t42_transfer.nodes.hw_emulator import HwEmulator
        from t42_transfer.ros.qos import profile

        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.emulator = HwEmulator(context=self.context, parameter_overrides=[Parameter("link", value=link)])
        self.node = Node("bench_driver_client", context=self.context)
        self.joints: list[int] = []
        """Header stamps (ns) of the driver's joint states."""
        self.actions: list[Any] = []
        self.poses: list[int] = []
        self.statuses: list[str] = []
        self.commands = 0
        self.commanding = False
        self.node.create_subscription(JointState, names.JOINT_STATES,
                                      lambda m: self.joints.append(stamp_to_ns(m.header.stamp)), 100)
        self.node.create_subscription(JointState, names.APPLIED_ACTION, self.actions.append, 100)
        self.node.create_subscription(PoseStamped, names.OBJECT_POSE,
                                      lambda m: self.poses.append(stamp_to_ns(m.header.stamp)), 100)
        self.node.create_subscription(String, names.HAND_STATUS, lambda m: self.statuses.append(m.data),
                                      profile(names.EVENTS))
        self._command = self.node.create_publisher(JointState, names.HAND_COMMAND, 10)
        self._reset = self.node.create_client(Trigger, names.HAND_RESET, qos_profile=profile(names.REQUESTS))
        self._trigger = Trigger.Request
        self.node.create_timer(CONTROL_PERIOD_S, self._on_timer)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.emulator)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="bench-ros", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def _on_timer(self) -> None:
        """A slow command, closing 10 steps then opening 10 (the fingers stay about where the grasp left them)."""
        if not self.commanding:
            return
        action = COMMAND_ACTION * (1.0 if (self.commands // 10) % 2 == 0 else -1.0)
        self._command.publish(applied_action_msg([action, action], self.node.get_clock().now().nanoseconds, RCLPY))
        self.commands += 1

    def reset(self, timeout_s: float = 60.0) -> tuple[bool, str]:
        """``hand/reset``, again after a fault that interrupted or refused the grasp (up to 3 tries)."""
        if not self._reset.wait_for_service(timeout_sec=timeout_s):
            raise RuntimeError("no hand/reset service")
        answer = (False, "")
        for _ in range(3):
            future = self._reset.call_async(self._trigger())
            deadline = time.monotonic() + timeout_s
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.05)
            if not future.done():
                raise RuntimeError("hand/reset did not answer")
            answer = (future.result().success, future.result().message)
            if answer[0]:
                break
            time.sleep(2.0)  # the driver retries a fault once a second
        return answer

    def close(self) -> None:
        self.commanding = False
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.emulator.close()
        self.executor.shutdown()
        self.node.destroy_node()
        self.emulator.destroy_node()
        self.context.try_shutdown()


def driver_run(seconds: float) -> dict:
    """The driver stepping an episode: hand/reset (the grasp) first, then a single-step command each period
    through the timed window, so every step reads, publishes joint_states, object_pose and applied_action, and
    writes the goals the command moves (with no episode the driver only reads and holds)."""
    with tempfile.TemporaryDirectory(prefix="bench_driver_") as tmp:
        client = EpisodeClient(str(Path(tmp) / "ttyT42"))
        watch = Watch(client.emulator.bus)
        proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "node", "dynamixel_driver", "--ros-args",
                                 "-p", f"port:={client.emulator.port}", "-p", "autostart:=true",
                                 "-p", f"latency_timer_ms:={EMULATED_LATENCY_TIMER_MS}"], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60.0
            while len(watch.times) < 5:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("the driver never stepped")
                time.sleep(0.05)
            reset = client.reset()
            if not reset[0]:
                raise RuntimeError(f"hand/reset failed: {reset[1]}")
            client.commanding = True
            time.sleep(5 * CONTROL_PERIOD_S)  # the commands reach the steps
            first, cpu0 = len(watch.times), cpu_s(proc.pid)
            joints0, actions0, poses0, statuses0 = (len(client.joints), len(client.actions), len(client.poses),
                                                    len(client.statuses))
            commands0 = client.commands
            time.sleep(seconds)
            steps, cpu = len(watch.times) - first, cpu_s(proc.pid) - cpu0
            joints, actions = client.joints[joints0:], client.actions[actions0:]
            poses, statuses = client.poses[poses0:], client.statuses[statuses0:]
            commands = client.commands - commands0
        finally:
            proc.terminate()
            proc.wait(timeout=15)
            client.close()
    intervals = np.diff(watch.times[first - 1: first + steps])
    moved = sum(bool(np.any(np.abs(np.asarray(a.velocity)) > 0)) for a in actions)
    return {"steps": steps, "cpu_ms_per_step": 1e3 * cpu / max(steps, 1),
            "interval_ms": {"mean": 1e3 * float(intervals.mean()), "std": 1e3 * float(intervals.std()),
                            "p99": 1e3 * float(np.percentile(intervals, 99)), "max": 1e3 * float(intervals.max())},
            "late_steps": int(np.sum(intervals > 1.5 * CONTROL_PERIOD_S)),
            "episode": {"reset": reset[1], "joint_states": len(joints), "object_poses": len(poses),
                        "applied_actions": len(actions), "actions_that_moved": moved, "commands_sent": commands,
                        "faults": [s for s in statuses if s.startswith(names.FAULT)]},
            "load_after": os.getloadavg()}


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


def floor_node_run(seconds: float, kind: str) -> dict:
    """CPU per period of :data:`FLOOR_NODE` of ``kind``; ``traffic`` beside this process's peers of the driver's
    run (the emulated hand's tracker, a command each period, subscribers of the three step messages)."""
    command = [sys.executable, "-c", FLOOR_NODE, str(seconds), str(CONTROL_PERIOD_S), kind]
    run = {}
    if kind == "traffic":
        with tempfile.TemporaryDirectory(prefix="bench_driver_") as tmp:
            client = EpisodeClient(str(Path(tmp) / "ttyT42"))
            client.commanding = True
            try:
                out = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=seconds + 60,
                                     check=True)
                run["joint_states_received"] = len(client.joints)
            finally:
                client.close()
    else:
        out = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=seconds + 60, check=True)
    cpu, ticks = (float(v) for v in out.stdout.split())
    return {"periods": int(ticks), "cpu_ms_per_period": 1e3 * cpu / max(ticks, 1), **run,
            "load_after": os.getloadavg()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="timed window of each run (60)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    threading.current_thread().name = "bench"
    machine = machine_info()
    driver, bare = driver_run(args.seconds), bare_run(args.seconds)
    bare_select, idle_run = bare_run(args.seconds, READ_WAIT_S), floor_node_run(args.seconds, "single")
    idle_events, floor = floor_node_run(args.seconds, "events"), floor_node_run(args.seconds, "traffic")
    floor_ms = floor["cpu_ms_per_period"]
    idle_ms = idle_run["cpu_ms_per_period"]
    stock = driver["cpu_ms_per_step"] / bare["cpu_ms_per_step"]
    same_work = driver["cpu_ms_per_step"] / bare_select["cpu_ms_per_step"]
    target = {"ratio": "cpu_ratio_driver_to_select_reads_loop", "cpu_ratio_max": 1.5, "late_steps": 0,
              "every_step_published": True}
    episode = driver["episode"]
    missed = []
    if same_work > target["cpu_ratio_max"]:
        select_ms = bare_select["cpu_ms_per_step"]
        missed.append(f"the driver's CPU per step ({driver['cpu_ms_per_step']:.2f} ms) is {same_work:.2f}x the bare "
                      f"loop's doing the same reads and writes with its reads waiting in select as the driver's do "
                      f"({select_ms:.2f} ms); on the EventsExecutor the driver spins on, a node with the driver's "
                      f"traffic (a timer wake, two messages taken and three published each period) and no bus costs "
                      f"{floor_ms:.2f} ms a period ({floor_ms / select_ms:.2f}x that loop) before any work of its own "
                      f"(an idle node: {idle_events['cpu_ms_per_period']:.2f} ms there, {idle_ms:.2f} ms on the "
                      f"SingleThreadedExecutor), which leaves {driver['cpu_ms_per_step'] - floor_ms:.2f} ms a step "
                      f"for the driver's own work (the bus, the limits, building the messages)")
    if driver["late_steps"] > target["late_steps"]:
        missed.append(f"{driver['late_steps']} late step(s) (> 1.5 periods), load {driver['load_after'][0]:.2f}")
    if episode["joint_states"] < driver["steps"] - 1 or episode["applied_actions"] < driver["steps"] - 1:
        missed.append(f"{episode['joint_states']} joint states and {episode['applied_actions']} actions published "
                      f"for {driver['steps']} steps (faults: {episode['faults']}): the window is not all full steps")
    result = {
        "command": f"python bench/bench_driver.py --seconds {args.seconds:g}",
        "machine": machine,
        "load_after": os.getloadavg(),
        "seconds": args.seconds,
        "driver": driver,
        "bare_sdk_loop": bare,
        "bare_sdk_loop_select_reads": bare_select,
        "cpu_ratio_driver_to_stock_sdk_loop": stock,
        "cpu_ratio_driver_to_select_reads_loop": same_work,
        "target": target,
        "target_met": not missed,
        "target_missed_because": missed,
        "target_note": "the target is the same-work ratio: the driver beside the bare loop doing the same sync read "
                       "and sync write with its reads waiting in select as the driver's do "
                       "(cpu_ratio_driver_to_select_reads_loop). Stock dynamixel-sdk spins on the port for the whole "
                       "round trip, so cpu_ratio_driver_to_stock_sdk_loop compares the driver with that polling, "
                       "not with the same work",
        "idle_rclpy_node": idle_run,
        "idle_rclpy_node_events_executor": idle_events,
        "driver_cpu_above_idle_node_ms_per_step": driver["cpu_ms_per_step"] - idle_ms,
        "rclpy_interface_floor": floor,
        "driver_cpu_above_interface_floor_ms_per_step": driver["cpu_ms_per_step"] - floor_ms,
        "cpu_ratio_driver_above_floor_to_select_reads_loop":
            (driver["cpu_ms_per_step"] - floor_ms) / bare_select["cpu_ms_per_step"],
        "cpu_ratio_interface_floor_to_select_reads_loop": floor_ms / bare_select["cpu_ms_per_step"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
