"""Benchmark: pub/sub round trip of hand messages between two processes over rclpy on localhost.

Writes bench/results/pubsub_latency.json.  A ping process publishes hand-state
messages (geometry_msgs/PoseStamped, sensor_msgs/JointState) on ``bench/ping/*``;
an echo process (a plain rclpy node with raw subscriptions) publishes the same CDR
bytes back on ``bench/pong/*``; the pinger's typed subscription receives them.
Default QoS (RELIABLE, KEEP_LAST 10), the middleware rclpy loads (rmw_fastrtps_cpp
from the wheels).  One round trip is timed from building the message to having
its values back as numpy, so each case includes its conversions:

- ``ours``: built with msg_adapters (``object_pose_msg`` / ``joint_state_msg``,
  ``kit=RCLPY``), read back with ``object_xy_mm`` / ``joint_state_arrays``;
- ``bare`` (baseline): the same rclpy classes filled field by field and read
  field by field into numpy, with the same arithmetic and no checks.

Both cases and both types are interleaved trip by trip (order rotated each round)
through the same two processes at a fixed, modest rate, so they share the
machine's load; every reply is checked against the values sent.  The run has its
own ROS_DOMAIN_ID (random in 150-230 unless set) and LOCALHOST discovery.

    .venv/bin/python bench/bench_pubsub_latency.py                # 2000 round trips per case, 200 trips/s
    .venv/bin/python bench/bench_pubsub_latency.py --trips 500
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from msg_adapters import joint_state_arrays, joint_state_msg, object_pose_msg, object_xy_mm
from t42_transfer.conventions import ACTUATOR_NAMES, FRAME_ID, LOAD_UNIT_NM
from t42_transfer.ros.runner import keep_discovery_local

RESULTS = Path(__file__).parent / "results" / "pubsub_latency.json"
KINDS = ("pose", "joint_state")
DEPTH = 10
"""rclpy's default KEEP_LAST depth, as the hand's nodes publish with."""
_MM_PER_M = 1000.0


def _classes() -> dict[str, type]:
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    return {"pose": PoseStamped, "joint_state": JointState}


# --------------------------------------------------------------------------- echo process


def role_echo() -> None:
    """Return every ping's CDR bytes unchanged on the matching pong topic until SIGINT/SIGTERM."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init()
    node = rclpy.create_node("bench_echo")
    for kind, cls in _classes().items():
        pong = node.create_publisher(cls, f"bench/pong/{kind}", DEPTH)
        node.create_subscription(cls, f"bench/ping/{kind}", pong.publish, DEPTH, raw=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# --------------------------------------------------------------------------- ping process


class Case(NamedTuple):
    """How one case builds the message of trip ``i`` (with the values it should get back) and reads a reply."""

    kind: str
    build: Callable[[int], tuple[Any, np.ndarray]]
    read: Callable[[Any], np.ndarray]


def _values(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Trip ``i``'s object position (mm), loads, actuator angles (float32) and stamp (ns)."""
    xy = np.array([i % 40 - 20.0, 3.0 + i % 7], np.float32)
    loads = np.array([i % 300 - 150.0, 12.5], np.float32)
    angles = np.array([0.01 * (i % 50), -0.2], np.float32)
    return xy, loads, angles, 1_000_000_000 + i * 5_000_000


def ours_cases() -> list[Case]:
    from msg_adapters import RCLPY

    def pose(i: int) -> tuple[Any, np.ndarray]:
        xy, _, _, stamp = _values(i)
        return object_pose_msg(xy, stamp, kit=RCLPY), xy

    def joints(i: int) -> tuple[Any, np.ndarray]:
        _, loads, angles, stamp = _values(i)
        return joint_state_msg(loads, angles, stamp, kit=RCLPY), np.concatenate([loads, angles])

    def joint_values(msg: Any) -> np.ndarray:
        loads, angles = joint_state_arrays(msg)
        return np.concatenate([loads, angles])

    return [Case("pose", pose, object_xy_mm), Case("joint_state", joints, joint_values)]


def bare_cases() -> list[Case]:
    classes = _classes()

    def pose(i: int) -> tuple[Any, np.ndarray]:
        xy, _, _, stamp = _values(i)
        msg = classes["pose"]()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        msg.header.frame_id = FRAME_ID
        msg.pose.position.x = float(xy[0]) / _MM_PER_M
        msg.pose.position.y = float(xy[1]) / _MM_PER_M
        msg.pose.orientation.w = 1.0
        return msg, xy

    def pose_values(msg: Any) -> np.ndarray:
        position = msg.pose.position
        return np.array([position.x * _MM_PER_M, position.y * _MM_PER_M]).astype(np.float32)

    def joints(i: int) -> tuple[Any, np.ndarray]:
        _, loads, angles, stamp = _values(i)
        msg = classes["joint_state"]()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        msg.name = list(ACTUATOR_NAMES)
        msg.position = [float(a) for a in angles]
        msg.effort = [float(load) * LOAD_UNIT_NM for load in loads]
        return msg, np.concatenate([loads, angles])

    def joint_values(msg: Any) -> np.ndarray:
        loads = np.array(msg.effort) / LOAD_UNIT_NM
        return np.concatenate([loads, np.array(msg.position)]).astype(np.float32)

    return [Case("pose", pose, pose_values), Case("joint_state", joints, joint_values)]


def role_ping(trips: int, warmup: int, rate: float) -> None:
    """Time ``warmup + trips`` round trips of every case, interleaved; print the times (ms) as one JSON line."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    rclpy.init()
    node = rclpy.create_node("bench_ping")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    replies: dict[str, Any] = {}

    def keep(kind: str) -> Callable[[Any], None]:
        return lambda msg: replies.__setitem__(kind, msg)

    pubs, subs = {}, []
    for kind, cls in _classes().items():
        pubs[kind] = node.create_publisher(cls, f"bench/ping/{kind}", DEPTH)
        subs.append(node.create_subscription(cls, f"bench/pong/{kind}", keep(kind), DEPTH))

    def spin_until(done: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                return False
            executor.spin_once(timeout_sec=0.05)
        return True

    def matched() -> bool:
        return all(p.get_subscription_count() for p in pubs.values()) and all(s.get_publisher_count() for s in subs)

    def echoed(kind: str, msg: Any) -> bool:
        """Graph discovery can precede endpoint matching: ping every 0.2 s until one comes back."""
        for _ in range(100):
            pubs[kind].publish(msg)
            if spin_until(lambda: kind in replies, 0.2):
                return True
        return False

    cases = {("ours", c.kind): c for c in ours_cases()} | {("bare", c.kind): c for c in bare_cases()}
    try:
        if not spin_until(matched, 30.0):
            raise SystemExit("the echo process did not appear within 30 s")
        for kind in KINDS:
            if not echoed(kind, cases[("ours", kind)].build(0)[0]):
                raise SystemExit(f"no {kind} echo within 20 s")
        spin_until(lambda: False, 0.3)  # drain late echoes of the priming pings
        replies.clear()

        names = list(cases)
        times: dict[tuple[str, str], list[float]] = {name: [] for name in names}
        period = 1.0 / rate
        next_start = time.perf_counter()
        for i in range(warmup + trips):
            for name in names[i % len(names) :] + names[: i % len(names)]:
                next_start += period
                time.sleep(max(0.0, next_start - time.perf_counter()))
                next_start = max(next_start, time.perf_counter())  # running late: no catch-up burst
                case = cases[name]
                start = time.perf_counter_ns()
                msg, expected = case.build(i)
                pubs[case.kind].publish(msg)
                if not spin_until(lambda case=case: case.kind in replies, 5.0):
                    raise SystemExit(f"{name} trip {i}: no echo within 5 s")
                got = case.read(replies.pop(case.kind))
                elapsed = time.perf_counter_ns() - start
                if not np.array_equal(got, expected):
                    raise SystemExit(f"{name} trip {i}: sent {expected.tolist()}, got back {got.tolist()}")
                if i >= warmup:
                    times[name].append(elapsed / 1e6)
        print(
            json.dumps(
                {
                    "rmw": rclpy.get_rmw_implementation_identifier(),
                    "times_ms": {f"{impl}/{kind}": ts for (impl, kind), ts in times.items()},
                }
            )
        )
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


# --------------------------------------------------------------------------- orchestration


def stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> str:
    """SIGINT ``proc`` if it still runs, kill it after ``timeout_s``; its stderr."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err or ""


def stats(ms: list[float]) -> dict[str, float]:
    arr = np.asarray(ms)
    return {
        "median_ms": round(float(np.median(arr)), 4),
        "p90_ms": round(float(np.percentile(arr, 90)), 4),
        "p99_ms": round(float(np.percentile(arr, 99)), 4),
        "mean_ms": round(float(arr.mean()), 4),
        "max_ms": round(float(arr.max()), 4),
    }


def run(trips: int, warmup: int, rate: float, env: dict[str, str]) -> dict:
    """Start the echo and ping processes, wait for the pinger's times, stop both; the pinger's report."""

    def start(*args: str) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, __file__, "--role", *args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    echo = start("echo")
    ping = None
    try:
        ping = start("ping", "--trips", str(trips), "--warmup", str(warmup), "--rate", str(rate))
        budget_s = 90.0 + 3 * len(KINDS) * 2 * (trips + warmup) / rate  # 3x the paced time, plus start-up
        out, err = ping.communicate(timeout=budget_s)
        if ping.returncode:
            raise SystemExit(f"ping process failed ({ping.returncode}): {err[-3000:]}")
    finally:
        if ping is not None and ping.returncode is None:
            stop(ping)
        echo_err = stop(echo)
    if echo.returncode:
        raise SystemExit(f"echo process failed ({echo.returncode}): {echo_err[-3000:]}")
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("echo", "ping"), help=argparse.SUPPRESS)
    parser.add_argument("--trips", type=int, default=2000, help="timed round trips per case")
    parser.add_argument("--warmup", type=int, default=100, help="untimed round trips per case first")
    parser.add_argument("--rate", type=float, default=200.0, help="round trips per second, all cases together")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.role == "echo":
        return role_echo()
    if args.role == "ping":
        return role_ping(args.trips, args.warmup, args.rate)

    sys.path.insert(0, str(Path(__file__).parent))
    from machine import machine_info

    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = env.get("ROS_DOMAIN_ID") or str(random.randint(150, 230))
    discovery = keep_discovery_local(env)
    info = machine_info()
    load_before = os.getloadavg()
    started = time.monotonic()
    report = run(args.trips, args.warmup, args.rate, env)
    wall_s = time.monotonic() - started
    load_after = os.getloadavg()

    times = report["times_ms"]
    per_type = {}
    for kind in KINDS:
        ours, bare = stats(times[f"ours/{kind}"]), stats(times[f"bare/{kind}"])
        per_type[kind] = {
            "ours_msg_adapters": ours,
            "baseline_bare_rclpy": bare,
            "ratio_ours_over_bare": {k: round(ours[k] / bare[k], 3) for k in ("median_ms", "p90_ms", "p99_ms")},
        }
        print(kind, json.dumps(per_type[kind]), flush=True)
    result = {
        "benchmark": "pub/sub round trip of hand messages between two processes over rclpy on localhost",
        "command": " ".join(
            shlex.quote(a) for a in [".venv/bin/python", "bench/bench_pubsub_latency.py", *sys.argv[1:]]
        ),
        "machine": info,
        "load_average_before": load_before,
        "load_average_after": load_after,
        "wall_s": round(wall_s, 1),
        "ros": {
            "rmw": report["rmw"],
            "domain_id": int(env["ROS_DOMAIN_ID"]),
            "discovery_range": discovery,
            "qos": f"RELIABLE KEEP_LAST {DEPTH} VOLATILE",
            "echo": "raw subscription, Publisher.publish(bytes)",
        },
        "round_trips_per_case": args.trips,
        "warmup_per_case": args.warmup,
        "rate_hz_all_cases": args.rate,
        "timed": "build message -> publish -> echo -> typed receive -> values back as numpy (checked equal)",
        "geometry_msgs/PoseStamped": per_type["pose"],
        "sensor_msgs/JointState": per_type["joint_state"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
