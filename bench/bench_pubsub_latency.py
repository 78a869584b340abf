"""Benchmark: pub/sub round-trip latency between two processes over Cyclone DDS on localhost.

Writes bench/results/pubsub_latency.json.  A ping process publishes a pre-serialised
PoseStamped on /bench/ping and waits for an echo process to send the same bytes
back on /bench/pong: through our CycloneTransport (raw CDR bytes, ``publish_raw``,
``spin_once``), and, as the in-run baseline, through bare cyclonedds-python typed
``DataWriter.write`` / ``DataReader.take`` (IDL objects, waitset wait) with the same
QoS (RELIABLE KEEP_LAST 10).  Median, p90, p99 of the round trips after a warm-up.

    .venv/bin/python bench/bench_pubsub_latency.py              # 1000 round trips each
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from msg_adapters import POSE_STAMPED, object_pose_msg  # noqa: E402
from t42_transfer.ros.transport import serialize  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "pubsub_latency.json"
PING, PONG = "/bench/ping", "/bench/pong"
WARMUP = 100


class Bare:
    """Typed cyclonedds-python endpoints: write an IDL object, take IDL objects."""

    def __init__(self, send: str, receive: str) -> None:
        from cyclonedds.core import Policy, Qos, ReadCondition, SampleState, ViewState, InstanceState, WaitSet
        from cyclonedds.domain import Domain, DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic
        from cyclonedds.util import duration

        from t42_transfer.ros.cyclone import discovery_config, domain_id_from_env
        from t42_transfer.ros.dds_types import dds_class
        from t42_transfer.ros.naming import dds_topic

        domain_id = domain_id_from_env()
        self.domain = Domain(domain_id, discovery_config())  # the same localhost config CycloneTransport uses
        self.participant = DomainParticipant(domain_id)
        self.cls = dds_class(POSE_STAMPED)
        qos = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.Durability.Volatile,
                  Policy.History.KeepLast(10), Policy.DataRepresentation(use_cdrv0_representation=True))
        self.writer = DataWriter(self.participant, Topic(self.participant, "bare" + dds_topic(send), self.cls), qos=qos)
        self.reader = DataReader(self.participant, Topic(self.participant, "bare" + dds_topic(receive), self.cls),
                                 qos=qos)
        self.waitset = WaitSet(self.participant)
        self.waitset.attach(ReadCondition(self.reader, SampleState.Any | ViewState.Any | InstanceState.Any))

    def matched(self) -> bool:
        return bool(self.writer.get_matched_subscriptions()) and bool(self.reader.get_matched_publications())

    def send(self, obj: object) -> None:
        self.writer.write(obj)

    def receive(self) -> object:
        while True:
            samples = self.reader.take(N=1)
            if samples:
                return samples[0]
            self.waitset.wait(1_000_000_000)


class Ours:
    """Our CycloneTransport: publish_raw and raw callbacks run by spin_once."""

    def __init__(self, name: str, send: str, receive: str) -> None:
        from t42_transfer.ros import qos
        from t42_transfer.ros.cyclone import CycloneTransport

        self.node = CycloneTransport(name)
        self.pub = self.node.publisher(send, POSE_STAMPED, qos.DEFAULT)
        self.got: list[bytes] = []
        self.node.subscribe(receive, POSE_STAMPED, qos.DEFAULT, self.got.append, raw=True)

    def matched(self) -> bool:
        return bool(self.pub.writer.get_matched_subscriptions()) and \
            bool(self.node._subscriptions[0].reader.get_matched_publications())

    def send(self, data: bytes) -> None:
        self.pub.publish_raw(data)

    def receive(self) -> bytes:
        while not self.got:
            self.node.spin_once(1.0)
        return self.got.pop(0)


def _wait_matched(endpoint: Bare | Ours, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not endpoint.matched():
        if time.monotonic() > deadline:
            raise SystemExit("endpoints did not match")
        time.sleep(0.02)
    time.sleep(0.3)


def _endpoint(impl: str, role: str) -> Bare | Ours:
    send, receive = (PING, PONG) if role == "ping" else (PONG, PING)
    return Ours(f"bench_{role}", send, receive) if impl == "ours" else Bare(send, receive)


def role_echo(impl: str, trips: int) -> None:
    endpoint = _endpoint(impl, "echo")
    _wait_matched(endpoint)
    for _ in range(trips + WARMUP):
        endpoint.send(endpoint.receive())  # type: ignore[arg-type]
    time.sleep(0.5)


def ping(impl: str, trips: int, env: dict[str, str]) -> np.ndarray:
    echo = subprocess.Popen([sys.executable, __file__, "--role", "echo", "--impl", impl, "--trips", str(trips)],
                            cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    endpoint = _endpoint(impl, "ping")
    payload = serialize(POSE_STAMPED, object_pose_msg([12.5, -3.0], 1_000_000_000))
    message: object = payload if impl == "ours" else endpoint.cls.deserialize(payload)  # type: ignore[union-attr]
    send: Callable[[object], None] = endpoint.send  # type: ignore[assignment]
    _wait_matched(endpoint)
    times = []
    for i in range(trips + WARMUP):
        start = time.perf_counter()
        send(message)
        back = endpoint.receive()
        elapsed = time.perf_counter() - start
        if i >= WARMUP:
            times.append(elapsed)
    assert (back == payload) if impl == "ours" else (back.serialize() == payload)  # type: ignore[union-attr]
    _, err = echo.communicate(timeout=60)
    if echo.returncode:
        raise RuntimeError(f"echo failed: {err[-2000:]}")
    return np.array(times) * 1e3


def stats(ms: np.ndarray) -> dict[str, float]:
    return {"median_ms": round(float(np.median(ms)), 4), "p90_ms": round(float(np.percentile(ms, 90)), 4),
            "p99_ms": round(float(np.percentile(ms, 99)), 4), "mean_ms": round(float(ms.mean()), 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("echo",), default=None)
    parser.add_argument("--impl", choices=("ours", "bare"), default="ours")
    parser.add_argument("--trips", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.role == "echo":
        return role_echo(args.impl, args.trips)

    sys.path.insert(0, str(REPO / "bench"))
    from machine import machine_info

    info = machine_info()
    results = {}
    domains = random.sample(range(100, 201), 2)
    for impl, domain_id in zip(("ours", "bare"), domains):  # each on its own domain: a process configures one once
        domain = str(domain_id)
        env = dict(os.environ, ROS_DOMAIN_ID=domain, PYTHONPATH=str(REPO))
        env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        env.pop("CYCLONEDDS_URI", None)
        os.environ["ROS_DOMAIN_ID"] = domain
        results[impl] = stats(ping(impl, args.trips, env))
        print(impl, results[impl], flush=True)
    result = {
        "benchmark": "pub/sub round trip between two processes over Cyclone DDS on localhost (PoseStamped)",
        "command": " ".join(shlex.quote(a) for a in [".venv/bin/python", "bench/bench_pubsub_latency.py", *sys.argv[1:]]),
        "machine": info,
        "load_average_after": os.getloadavg(),
        "round_trips": args.trips,
        "warmup": WARMUP,
        "ours_cyclone_transport_raw": results["ours"],
        "baseline_bare_cyclonedds_typed": results["bare"],
        "median_ratio_ours_over_bare": round(results["ours"]["median_ms"] / results["bare"]["median_ms"], 3),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
