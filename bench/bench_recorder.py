"""Benchmark: the recorder over Cyclone DDS on localhost at kHz rates: loss, throughput, memory.

Writes bench/results/recorder.json.  A publisher process sends pre-serialised hand
messages (PoseStamped, JointState, JointState for action: the three hand topics in
turn) at a fixed total rate for N seconds, RELIABLE KEEP_LAST 10 (ROS default); a
recorder process (CycloneTransport + Recorder) records them.  Reported per run:
sent vs recorded, recorder RSS over time (1 s samples), and the recorder process's
CPU time per message.  Baselines measured in the same run: the same stream into a
bare sink process (same transport, raw subscriptions whose callback only counts),
and writing the same messages straight into a bag in-process (no DDS).

    .venv/bin/python bench/bench_recorder.py                 # 1 kHz x 30 s; 5 and 10 kHz x 10 s; depth 10
    .venv/bin/python bench/bench_recorder.py --quick         # 5 s runs
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
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from msg_adapters import HAND_TOPICS, applied_action_msg, joint_state_msg, object_pose_msg  # noqa: E402
from t42_transfer.conventions import CONTROL_PERIOD_NS  # noqa: E402
from t42_transfer.ros.transport import serialize  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "recorder.json"
TOPICS = list(HAND_TOPICS)


def hand_messages(steps: int) -> list[tuple[str, bytes]]:
    """``steps`` control steps of pre-serialised hand messages, the three topics in turn."""
    out = []
    for k in range(steps):
        stamp = 1_000_000_000 + k * CONTROL_PERIOD_NS
        for topic, msg in (
            (TOPICS[0], object_pose_msg([k % 40 - 20.0, 3.0], stamp)),
            (TOPICS[1], joint_state_msg([k % 300 - 150.0, 12.5], [0.1, 0.2], stamp)),
            (TOPICS[2], applied_action_msg([0.5, -0.5], stamp)),
        ):
            out.append((topic, serialize(HAND_TOPICS[topic], msg)))
    return out


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


# --------------------------------------------------------------------------- roles (subprocesses)


def role_publisher(rate: float, seconds: float) -> None:
    from t42_transfer.ros import qos
    from t42_transfer.ros.cyclone import CycloneTransport

    total = int(rate * seconds)
    messages = hand_messages(total // 3 + 1)[:total]
    with CycloneTransport("bench_hand") as node:
        pubs = {t: node.publisher(t, HAND_TOPICS[t], qos.DEFAULT) for t in TOPICS}
        deadline = time.monotonic() + 30
        while not all(p.writer.get_matched_subscriptions() for p in pubs.values()):
            if time.monotonic() > deadline:
                raise SystemExit("no subscriber matched")
            time.sleep(0.02)
        time.sleep(0.5)
        start, sent = time.perf_counter(), 0
        while sent < total:
            due = min(total, int((time.perf_counter() - start) * rate) + 1)
            while sent < due:
                topic, data = messages[sent]
                pubs[topic].publish_raw(data)
                sent += 1
            time.sleep(0.0005)
        elapsed = time.perf_counter() - start
        time.sleep(1.0)  # let reliable delivery finish before the writers go away
    print(json.dumps({"sent": sent, "seconds": elapsed}), flush=True)


def role_receiver(kind: str, out_dir: str, stop_file: str, queue_depth: int) -> None:
    from t42_transfer.nodes.recorder import Recorder, RecorderParams
    from t42_transfer.ros import qos
    from t42_transfer.ros.cyclone import CycloneTransport

    class Node(CycloneTransport):
        def service(self, name, srvtype, handler):  # type: ignore[no-untyped-def]
            try:
                super().service(name, srvtype, handler)
            except NotImplementedError:  # a backend without services: not used here
                pass

    samples: list[tuple[float, float]] = []
    counted = [0]
    with Node(f"bench_{kind}") as node:
        if kind == "recorder":
            recorder = Recorder(node, RecorderParams(out_dir, queue_depth=queue_depth))
        else:
            for topic in TOPICS:
                node.subscribe(topic, HAND_TOPICS[topic], qos.QoSProfile(depth=queue_depth),
                               lambda data: counted.__setitem__(0, counted[0] + 1), raw=True)
        t0 = time.monotonic()
        node.timer(1.0, lambda: samples.append((round(time.monotonic() - t0, 2), round(rss_mb(), 1))))
        print("ready", flush=True)
        cpu0 = cpu_s()
        node.spin(until=lambda: os.path.exists(stop_file))
        cpu = cpu_s() - cpu0
        if kind == "recorder":
            count, dropped = recorder.current_count, recorder.dropped
            recorder.close()
            from rosbags.highlevel import AnyReader

            with AnyReader(recorder.bags) as reader:
                in_bag = reader.message_count
        else:
            count, dropped, in_bag = counted[0], 0, None
    print(json.dumps({"received": count, "dropped": dropped, "in_bag": in_bag, "cpu_s": cpu,
                      "rss_mb": samples}), flush=True)


# --------------------------------------------------------------------------- orchestration


def _spawn(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, __file__, *args], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def run_stream(kind: str, rate: float, seconds: float, queue_depth: int) -> dict:
    """One publisher -> receiver run on a fresh random domain."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(100, 200)), PYTHONPATH=str(REPO))
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    env.pop("CYCLONEDDS_URI", None)
    with tempfile.TemporaryDirectory() as tmp:
        stop = Path(tmp) / "stop"
        receiver = _spawn("--role", kind, "--out-dir", tmp, "--stop-file", str(stop),
                          "--queue-depth", str(queue_depth), env=env)
        assert receiver.stdout is not None
        if receiver.stdout.readline().strip() != "ready":
            raise RuntimeError(f"{kind} did not start: {receiver.communicate()[1][-2000:]}")
        publisher = _spawn("--role", "publisher", "--rate", str(rate), "--seconds", str(seconds), env=env)
        pub_out, pub_err = publisher.communicate(timeout=seconds + 120)
        if publisher.returncode:
            raise RuntimeError(f"publisher failed: {pub_err[-2000:]}")
        stop.touch()
        rec_out, rec_err = receiver.communicate(timeout=120)
        if receiver.returncode:
            raise RuntimeError(f"{kind} failed: {rec_err[-2000:]}")
    sent, got = json.loads(pub_out), json.loads(rec_out.strip().splitlines()[-1])
    rss = got.pop("rss_mb")
    at_10s = next((mb for t, mb in rss if t >= 10), None)
    result = {
        "receiver": kind, "rate_hz": rate, "seconds": seconds, "queue_depth": queue_depth,
        "sent": sent["sent"], "received": got["received"], "lost": sent["sent"] - got["received"],
        "in_bag": got["in_bag"], "publish_seconds": round(sent["seconds"], 3),
        "achieved_msgs_per_s": round(got["received"] / sent["seconds"], 1),
        "cpu_us_per_msg": round(got["cpu_s"] / max(got["received"], 1) * 1e6, 2),
        "rss_mb_at_10s": at_10s, "rss_mb_end": rss[-1][1] if rss else None,
        "rss_mb_peak": max((mb for _, mb in rss), default=None), "rss_mb_samples": rss,
    }
    print(json.dumps({k: v for k, v in result.items() if k != "rss_mb_samples"}), flush=True)
    return result


def direct_write_us_per_msg(count: int = 30_000) -> float:
    """The same messages written straight into a bag in-process (rosbags writer, no DDS)."""
    from t42_transfer.nodes.recorder import _Bag

    messages = hand_messages(count // 3)
    with tempfile.TemporaryDirectory() as tmp:
        bag = _Bag(Path(tmp) / "direct", HAND_TOPICS)
        start = time.perf_counter()
        for i, (topic, data) in enumerate(messages):
            bag.write(topic, i, data, i)
        bag.close()
        return (time.perf_counter() - start) / len(messages) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("publisher", "recorder", "sink"), default=None)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out-dir", default="")
    parser.add_argument("--stop-file", default="")
    parser.add_argument("--queue-depth", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="5 s runs")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.role == "publisher":
        return role_publisher(args.rate, args.seconds)
    if args.role in ("recorder", "sink"):
        return role_receiver(args.role, args.out_dir, args.stop_file, args.queue_depth)

    from machine import machine_info  # imports torch: kept out of the measured processes' RSS

    long_s, short_s = (5.0, 5.0) if args.quick else (30.0, 10.0)
    info = machine_info()
    runs = [
        run_stream("recorder", 1000, long_s, 1000),
        run_stream("sink", 1000, short_s, 1000),
        run_stream("recorder", 5000, short_s, 1000),
        run_stream("sink", 5000, short_s, 1000),
        run_stream("recorder", 1000, short_s, 10),
        run_stream("recorder", 5000, short_s, 10),
        run_stream("recorder", 10000, short_s, 1000),
    ]
    direct = direct_write_us_per_msg()
    rec_5k = runs[2]["cpu_us_per_msg"]
    sink_5k = runs[3]["cpu_us_per_msg"]
    result = {
        "benchmark": "recorder over Cyclone DDS on localhost (publisher and recorder in separate processes)",
        "command": " ".join(shlex.quote(a) for a in [".venv/bin/python", "bench/bench_recorder.py", *sys.argv[1:]]),
        "machine": info,
        "load_average_after": os.getloadavg(),
        "runs": runs,
        "baseline": {
            "sink_cpu_us_per_msg_5khz": sink_5k,
            "direct_bag_write_us_per_msg": round(direct, 2),
            "recorder_over_sink_cpu_ratio_5khz": round(rec_5k / sink_5k, 2),
            "recorder_over_direct_write_cpu_ratio_5khz": round(rec_5k / direct, 2),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["baseline"], indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
