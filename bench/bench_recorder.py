"""Benchmark: the recorder node over rclpy (Fast DDS) on localhost at kHz rates: loss, CPU per message, memory.

Writes bench/results/recorder.json.  A publisher process (rclpy, raw CDR bytes from
rosbags) sends hand messages (PoseStamped, JointState, JointState for the applied
action: the three hand topics in turn, one step per three messages) at a fixed
total rate for N seconds, RELIABLE KEEP_LAST 1000; a receiver process records or
counts them.  The main runs spin each receiver as ``t42 node recorder`` does
(:func:`t42_transfer.ros.runner.make_executor`: the recorder asks for no threads,
so a SingleThreadedExecutor, ``spin_once`` until stopped):

- ``recorder``: the :class:`~t42_transfer.nodes.recorder.Recorder` node (default
  parameters: queue depth 1000, flush every 1 s, steps grouped by stamp);
- ``sink`` (baseline): a bare rclpy node whose raw subscriptions (same QoS) only
  count, on the executor ``make_executor`` gives a plain node (single-threaded too).

Reported per run: sent vs received vs written to the bag, the receiver's CPU time
per message while messages flowed (process CPU between the 1 s samples around the
stream; also from ready to stop, idle spinning included), its RSS every second.
For comparison only, NOT what the runner uses: both receivers at 5 kHz on a
MultiThreadedExecutor with 4 threads (``multi4``), which spins busily while a
mutually exclusive callback runs.  Also the recorder's own per-message work
without ROS (decode the stamp, group by step, write to the bag) measured
in-process.  The machine's load average is recorded before and after: on a
shared machine the numbers vary with it.  Each run has its own ROS_DOMAIN_ID (random in
100-200 unless ROS_DOMAIN_ID is set) and LOCALHOST discovery.

    .venv/bin/python bench/bench_recorder.py           # recorder 1 kHz x 30 s; the rest 10 s each
    .venv/bin/python bench/bench_recorder.py --quick   # 5 s runs
    .venv/bin/python bench/bench_recorder.py --run-seconds 0.5   # a smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from msg_adapters import (  # noqa: E402
    HAND_TOPICS,
    TYPESTORE,
    applied_action_msg,
    joint_state_msg,
    object_pose_msg,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "recorder.json"
TOPICS = list(HAND_TOPICS)
QUEUE_DEPTH = 1000
MULTI_THREADS = 4
"""Threads of the comparison MultiThreadedExecutor (as many as the transfer server asks for)."""


def hand_messages(steps: int) -> list[tuple[str, bytes]]:
    """``steps`` control steps of CDR hand messages, the three topics in turn, stamps one period apart."""
    out = []
    for k in range(steps):
        stamp = 1_000_000_000 + k * CONTROL_PERIOD_NS
        for topic, msg in (
            (TOPICS[0], object_pose_msg([k % 40 - 20.0, 3.0], stamp)),
            (TOPICS[1], joint_state_msg([k % 300 - 150.0, 12.5], [0.1, 0.2], stamp)),
            (TOPICS[2], applied_action_msg([0.5, -0.5], stamp)),
        ):
            out.append((topic, bytes(TYPESTORE.serialize_cdr(msg, HAND_TOPICS[topic]))))
    return out


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


# --------------------------------------------------------------------------- roles (subprocesses)
def role_publisher(rate: float, seconds: float) -> None:
    import rclpy
    from rclpy.duration import Duration
    from rclpy.node import Node

    from msg_adapters import rclpy_class
    from t42_transfer.ros.qos import recording

    total = int(rate * seconds)
    messages = hand_messages(total // 3 + 1)[:total]
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("bench_hand", context=context)
    pubs = {t: node.create_publisher(rclpy_class(HAND_TOPICS[t]), t, recording(QUEUE_DEPTH)) for t in TOPICS}
    deadline = time.monotonic() + 30
    while not all(p.get_subscription_count() for p in pubs.values()):
        if time.monotonic() > deadline:
            raise SystemExit("no subscriber matched")
        time.sleep(0.02)
    time.sleep(1.0)  # the receiver matches this side on its own
    start, sent = time.perf_counter(), 0
    while sent < total:
        due = min(total, int((time.perf_counter() - start) * rate) + 1)
        while sent < due:
            topic, data = messages[sent]
            pubs[topic].publish(data)
            sent += 1
        time.sleep(0.0005)
    elapsed = time.perf_counter() - start
    acked = all(p.wait_for_all_acked(Duration(seconds=10)) for p in pubs.values())
    node.destroy_node()
    rclpy.shutdown(context=context)
    print(json.dumps({"sent": sent, "seconds": elapsed, "acked": acked}), flush=True)


def role_receiver(kind: str, out_dir: str, stop_file: str, executor_kind: str) -> None:
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from msg_adapters import rclpy_class
    from t42_transfer.nodes.recorder import Recorder
    from t42_transfer.ros.qos import recording
    from t42_transfer.ros.runner import make_executor

    context = rclpy.Context()
    rclpy.init(context=context)
    if executor_kind == "runner":  # as t42 node spins this node class
        executor: Any = make_executor(Recorder if kind == "recorder" else Node, context)
    else:  # the comparison, not what the runner uses
        executor = MultiThreadedExecutor(num_threads=MULTI_THREADS, context=context)
    counted = [0]
    if kind == "recorder":
        node: Any = Recorder(context=context, parameter_overrides=[Parameter("out_dir", value=out_dir)])
    else:
        node = Node("bench_sink", context=context)
        for topic in TOPICS:
            node.create_subscription(rclpy_class(HAND_TOPICS[topic]), topic,
                                     lambda data: counted.__setitem__(0, counted[0] + 1),
                                     recording(QUEUE_DEPTH), raw=True)
    executor.add_node(node)
    samples: list[tuple[float, float, float, int]] = []
    """Every second: (time since ready, RSS MB, process CPU s, messages handled)."""
    t0 = time.monotonic()
    done = threading.Event()

    def handled() -> int:
        return node.received if kind == "recorder" else counted[0]

    def sample() -> None:
        while not done.wait(1.0):
            samples.append((round(time.monotonic() - t0, 2), round(rss_mb(), 1), cpu_s(), handled()))

    threading.Thread(target=sample, daemon=True).start()
    print("ready", flush=True)
    cpu0 = cpu_s()
    while not os.path.exists(stop_file):
        executor.spin_once(timeout_sec=0.1)
    cpu = cpu_s() - cpu0
    done.set()
    if kind == "recorder":
        received, dropped = node.received, node.dropped
        node.close()
        from rosbags.highlevel import AnyReader

        with AnyReader(node.bags) as reader:
            in_bag: int | None = reader.message_count
    else:
        received, dropped, in_bag = counted[0], 0, None
    executor.shutdown(timeout_sec=5.0)
    node.destroy_node()
    rclpy.shutdown(context=context)
    print(json.dumps({"executor_class": type(executor).__name__, "received": received, "dropped": dropped,
                      "in_bag": in_bag, "cpu_s": cpu, "samples": samples}), flush=True)


# --------------------------------------------------------------------------- orchestration
def _spawn(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, __file__, *args], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def run_stream(kind: str, rate: float, seconds: float, executor: str = "runner") -> dict[str, Any]:
    """One publisher -> receiver run on its own domain (the caller's ROS_DOMAIN_ID when set)."""
    domain = os.environ.get("ROS_DOMAIN_ID") or str(random.randint(100, 200))  # a caller's (a test's) own
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(REPO))
    with tempfile.TemporaryDirectory() as tmp:
        stop = Path(tmp) / "stop"
        receiver = _spawn("--role", kind, "--out-dir", tmp, "--stop-file", str(stop), "--executor", executor,
                          env=env)
        assert receiver.stdout is not None
        if receiver.stdout.readline().strip() != "ready":
            raise RuntimeError(f"{kind} did not start: {receiver.communicate()[1][-2000:]}")
        publisher = _spawn("--role", "publisher", "--rate", str(rate), "--seconds", str(seconds), env=env)
        pub_out, pub_err = publisher.communicate(timeout=seconds + 120)
        if publisher.returncode:
            receiver.kill()
            raise RuntimeError(f"publisher failed: {pub_err[-2000:]}")
        time.sleep(1.0)  # the last step's messages are handled
        stop.touch()
        rec_out, rec_err = receiver.communicate(timeout=120)
        if receiver.returncode:
            raise RuntimeError(f"{kind} failed: {rec_err[-2000:]}")
    sent, got = json.loads(pub_out), json.loads(rec_out.strip().splitlines()[-1])
    samples = got.pop("samples")
    # CPU while messages flowed: from the last sample before the first message to the first after the last
    counts = [s[3] for s in samples]
    first = max((i for i, c in enumerate(counts) if c == 0), default=0)
    last = next((i for i, c in enumerate(counts) if c == counts[-1]), len(counts) - 1)
    streamed = counts[last] - counts[first]
    result = {
        "receiver": kind, "executor": executor, "executor_class": got["executor_class"], "rate_hz": rate,
        "seconds": seconds, "queue_depth": QUEUE_DEPTH,
        "sent": sent["sent"], "acked": sent["acked"], "received": got["received"],
        "lost": sent["sent"] - got["received"], "dropped": got["dropped"], "in_bag": got["in_bag"],
        "publish_seconds": round(sent["seconds"], 3),
        "cpu_us_per_msg": round((samples[last][2] - samples[first][2]) / max(streamed, 1) * 1e6, 2),
        "cpu_us_per_msg_ready_to_stop": round(got["cpu_s"] / max(got["received"], 1) * 1e6, 2),
        "rss_mb_first": samples[0][1] if samples else None, "rss_mb_end": samples[-1][1] if samples else None,
        "rss_mb_peak": max((s[1] for s in samples), default=None),
        "rss_mb_samples": [[s[0], s[1]] for s in samples],
    }
    print(json.dumps({k: v for k, v in result.items() if k != "rss_mb_samples"}), flush=True)
    return result


def own_work_us_per_msg(count: int = 30_000) -> float:
    """The recorder's per-message work without ROS: decode the stamp, group by step, write to a bag."""
    from msg_adapters import stamp_to_ns
    from t42_transfer.data.bag import BagWriter
    from t42_transfer.data.bag.steps import StepBuffer

    messages = hand_messages(count // 3)
    with tempfile.TemporaryDirectory() as tmp:
        bag = BagWriter(Path(tmp) / "direct", dict(HAND_TOPICS))
        buffer = StepBuffer(TOPICS, hold_s=1.0)
        start = time.perf_counter()
        for i, (topic, data) in enumerate(messages):
            stamp = stamp_to_ns(TYPESTORE.deserialize_cdr(data, HAND_TOPICS[topic]).header.stamp)
            released, _ = buffer.add(topic, stamp, i, data, 0.0)
            for step in released:
                for message in step.messages:
                    bag.write(*message)
        bag.close()
        return (time.perf_counter() - start) / len(messages) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("publisher", "recorder", "sink"), default=None)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out-dir", default="")
    parser.add_argument("--stop-file", default="")
    parser.add_argument("--executor", choices=("runner", "multi4"), default="runner")
    parser.add_argument("--quick", action="store_true", help="5 s runs")
    parser.add_argument("--run-seconds", type=float, default=None,
                        help="every run this long (overrides --quick)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.role == "publisher":
        return role_publisher(args.rate, args.seconds)
    if args.role in ("recorder", "sink"):
        return role_receiver(args.role, args.out_dir, args.stop_file, args.executor)

    from machine import machine_info  # imports torch: kept out of the measured processes

    long_s, short_s = (5.0, 5.0) if args.quick else (30.0, 10.0)
    if args.run_seconds is not None:
        long_s = short_s = args.run_seconds
    info = machine_info()
    runs = [run_stream("recorder", 1000, long_s)]  # also the RSS run
    runs += [run_stream("sink", 1000, short_s)]
    for rate in (5000, 10000):
        runs += [run_stream("recorder", rate, short_s), run_stream("sink", rate, short_s)]
    runs += [run_stream("recorder", 5000, short_s, "multi4"), run_stream("sink", 5000, short_s, "multi4")]
    own = own_work_us_per_msg()

    def run(kind: str, rate: int, executor: str = "runner") -> dict[str, Any]:
        return next(r for r in runs if r["receiver"] == kind and r["rate_hz"] == rate and r["executor"] == executor)

    def recorded(r: dict[str, Any]) -> str:
        return f"{r['received'] if r['in_bag'] is None else r['in_bag']}/{r['sent']}"

    def cpu_vs_sink(rate: int, executor: str = "runner") -> list[float]:
        rec, sink = run("recorder", rate, executor)["cpu_us_per_msg"], run("sink", rate, executor)["cpu_us_per_msg"]
        return [rec, sink, round(rec / sink, 2)]

    result = {
        "benchmark": "recorder node over rclpy (rmw_fastrtps_cpp) on localhost; publisher and receiver in separate "
                     "processes; receivers spun as t42 node spins them (make_executor: a SingleThreadedExecutor, "
                     "executor 'runner'); for comparison only, not what the runner uses: a 4-thread "
                     "MultiThreadedExecutor at 5 kHz (executor 'multi4')",
        "command": " ".join(shlex.quote(a) for a in [".venv/bin/python", "bench/bench_recorder.py", *sys.argv[1:]]),
        "machine": info,
        "load_average_after": os.getloadavg(),
        "runs": runs,
        "summary": {
            "executor": f"{runs[0]['executor_class']} (recorder), {runs[1]['executor_class']} (sink)",
            "recorder_sent_recorded": {f"{r['rate_hz'] // 1000}khz": recorded(r) for r in runs
                                       if r["receiver"] == "recorder" and r["executor"] == "runner"},
            "sink_sent_counted": {f"{r['rate_hz'] // 1000}khz": recorded(r) for r in runs
                                  if r["receiver"] == "sink" and r["executor"] == "runner"},
            "cpu_us_per_msg_recorder_vs_sink_and_ratio": {f"{rate // 1000}khz": cpu_vs_sink(rate)
                                                          for rate in (1000, 5000, 10000)},
            "recorder_rss_mb_30s_run_first_peak_end": [runs[0]["rss_mb_first"], runs[0]["rss_mb_peak"],
                                                       runs[0]["rss_mb_end"]],
            "recorder_own_work_us_per_msg": round(own, 2),
            "not_the_runner_multi4_5khz": {
                "recorder_sent_recorded": recorded(run("recorder", 5000, "multi4")),
                "sink_sent_counted": recorded(run("sink", 5000, "multi4")),
                "cpu_us_per_msg_recorder_vs_sink_and_ratio": cpu_vs_sink(5000, "multi4"),
            },
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["summary"], indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
