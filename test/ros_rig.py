"""In-process rclpy for node tests: one context on the test's domain, one executor spun on demand."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import rclpy
from rclpy.action import ActionClient, ActionServer
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

N = TypeVar("N", bound=Node)
REPO = Path(__file__).resolve().parents[1]


class RosRig:
    """``threads > 1``: a MultiThreadedExecutor, for nodes with callbacks that run beside each other;
    ``events``: rclpy's EventsExecutor, as ``t42 node`` spins a node that asks for it (the driver)."""

    def __init__(self, domain_id: int, threads: int = 1, events: bool = False) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        if events:
            self.executor = EventsExecutor(context=self.context)
        else:
            self.executor = (SingleThreadedExecutor(context=self.context) if threads <= 1
                             else MultiThreadedExecutor(num_threads=threads, context=self.context))
        self.nodes: list[Node] = []

    def add(self, node_cls: Callable[..., N], params: dict[str, Any] | None = None, **kwargs: Any) -> N:
        """``node_cls(context=..., parameter_overrides=params, **kwargs)``, added to the executor."""
        overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
        node = node_cls(context=self.context, parameter_overrides=overrides, **kwargs)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str = "tester", **kwargs: Any) -> Node:
        """A plain node for the test's own publishers, subscriptions and clients."""
        return self.add(Node, node_name=name, **kwargs)

    def spin_until(self, condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
        """Spin until ``condition()`` holds (True) or ``timeout_s`` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def call(self, client: Any, request: Any, timeout_s: float = 10.0) -> Any:
        """Call a service through ``client`` (waiting for it first); the response, or AssertionError."""
        assert client.wait_for_service(timeout_sec=timeout_s), f"service {client.srv_name} not available"
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout_s), f"no answer from {client.srv_name} within {timeout_s} s"
        return future.result()

    def shutdown(self) -> None:
        for node in reversed(self.nodes):
            close = getattr(node, "close", None)
            if callable(close):
                close()
        self.executor.shutdown(timeout_sec=5.0)
        for node in self.nodes:
            node.destroy_node()
            # destroy_node leaves a node's action servers and clients, which hold its rcl node and so the
            # context's participant: node and server lived on its graph until a garbage collection freed their
            # reference cycle, seen by the next test that took the domain (a second /t42/reach server there)
            for waitable in list(node.waitables):
                if isinstance(waitable, ActionServer | ActionClient):
                    waitable.destroy()
        if self.context.ok():
            rclpy.shutdown(context=self.context)


class Tester:
    """The test's own node beside the nodes under test: it listens, publishes and calls as a user would,
    and waits on what the graph shows (publisher and subscriber counts), never on a node's private state."""

    __test__ = False  # a helper, not a test class

    def __init__(self, ros: RosRig, name: str = "tester", namespace: str = "") -> None:
        self.ros = ros
        self.tester = ros.node(name, namespace=namespace)

    def listen(self, msgtype: Any, topic: str, qos: Any = 100) -> list[Any]:
        """Every message on ``topic`` from now on, in arrival order."""
        got: list[Any] = []
        self.tester.create_subscription(msgtype, topic, got.append, qos)
        return got

    def wait_graph(self, publishers: dict[str, int] | None = None, subscribers: dict[str, int] | None = None,
                   timeout_s: float = 10.0) -> bool:
        """Spin until, as the tester sees the graph, each topic has (at least) these publishers / subscribers."""
        def seen() -> bool:
            return (all(self.tester.count_publishers(t) >= n for t, n in (publishers or {}).items())
                    and all(self.tester.count_subscribers(t) >= n for t, n in (subscribers or {}).items()))
        return self.ros.spin_until(seen, timeout_s)


def start_node(name: str, *ros_args: str, log: Path | None = None) -> subprocess.Popen:
    """``t42 node NAME --ros-args ...`` as a process (environment inherited: the test's domain)."""
    cmd = [sys.executable, "-u", "-m", "t42_transfer.cli", "node", name]
    if ros_args:
        cmd += ["--ros-args", *ros_args]
    if log is None:
        return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    with open(log, "w") as out:  # the child keeps its own descriptor
        return subprocess.Popen(cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT)


def unbuffered_env(**extra: str) -> dict[str, str]:
    """The test's environment (its domain and LOCALHOST discovery, from ``ros_domain``), unbuffered, plus ``extra``."""
    return dict(os.environ, PYTHONUNBUFFERED="1", **extra)


def stop(procs: Sequence[subprocess.Popen], timeout_s: float = 10.0, sig: int = signal.SIGINT) -> list[int]:
    """``sig`` to each process, then kill what is still running after ``timeout_s``; the exit codes."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(sig)
    codes = []
    for proc in procs:
        try:
            codes.append(proc.wait(timeout=timeout_s))
        except subprocess.TimeoutExpired:
            proc.kill()
            codes.append(proc.wait())
    return codes


class Rosout:
    """Log lines of one node as a ROS user sees them (/rosout)."""

    WARN = 30

    def __init__(self, ros: RosRig, node_name: str) -> None:
        from rcl_interfaces.msg import Log
        from rclpy.qos import DurabilityPolicy, QoSProfile

        self.ros, self.node_name, self.lines = ros, node_name, []
        # TRANSIENT_LOCAL: /rosout's history, so no line is lost while the subscription is being matched
        qos = QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        ros.node(f"rosout_{node_name}").create_subscription(Log, "/rosout", self.lines.append, qos)

    def warnings(self) -> list[str]:
        return [m.msg for m in self.lines if m.level == self.WARN and m.name.endswith(self.node_name)]

    def wait_warnings(self, count: int = 1, timeout_s: float = 3.0) -> list[str]:
        """The node's warnings once at least ``count`` arrived (or ``timeout_s`` passed), and a moment more."""
        self.ros.spin_until(lambda: len(self.warnings()) >= count, timeout_s)
        self.ros.spin_for(0.1)
        return self.warnings()

    def clear(self) -> None:
        self.ros.spin_for(0.1)
        self.lines.clear()


def assert_one_line_errors(cases: Sequence[tuple[list[str], str]]) -> None:
    """``t42 node ARGS...`` exits 2 with exactly one ``t42: error:`` line containing the text, and no traceback,
    for each ``(args, text)``.  All at once: each process is mostly interpreter start and imports, which overlap
    on two cores."""
    t42 = [sys.executable, "-m", "t42_transfer.cli", "node"]
    procs = [subprocess.Popen([*t42, *args], cwd=REPO, env=unbuffered_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for args, _ in cases]
    try:
        for proc, (args, match) in zip(procs, cases, strict=True):
            try:
                stdout, stderr = proc.communicate(timeout=60)
            except subprocess.TimeoutExpired:  # name the case that hung, and what it had said
                proc.kill()
                stdout, stderr = proc.communicate()
                raise AssertionError(f"{args} did not exit within 60 s; stdout {stdout[-2000:]!r}, "
                                     f"stderr {stderr[-2000:]!r}") from None
            assert proc.returncode == 2, (args, stdout, stderr)
            errors = [line for line in stderr.splitlines() if line.startswith("t42: error:")]
            assert len(errors) == 1 and match in errors[0] and "Traceback" not in stderr, (args, stderr)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
