"""Backend choice (argument, T42_TRANSPORT, auto) and the rclpy backend's wiring against a fake rclpy.

ROS 2 is not installable here, so :class:`FakeRos` stands in for ``rclpy`` and
``rosidl_runtime_py``: it records calls and loops published bytes back to
subscriptions.  Its messages are opaque byte holders (``serialize_message`` gives
back exactly the bytes ``deserialize_message`` got), which is what the backend
may assume of rclpy's generated classes.  This shows the wiring, not ROS itself.
"""

from __future__ import annotations

import random
import sys
import threading
import time
import types
from collections import deque
from enum import Enum
from typing import Any, Callable

import pytest

from t42_transfer.ros import qos
from t42_transfer.ros.backends import make_transport, resolve_backend
from t42_transfer.ros.transport import deserialize, message_class, serialize, service_classes

POSE = "geometry_msgs/msg/PoseStamped"
TRIGGER = "std_srvs/srv/Trigger"
STRING = "std_msgs/msg/String"


class FakeMsg:
    """An rclpy message stand-in: just its CDR bytes."""

    typename = "?"

    def __init__(self, data: bytes = b"") -> None:
        self.data = data


class FakeFuture:
    def __init__(self, result: Any) -> None:
        self._result = result

    def done(self) -> bool:
        return True

    def result(self) -> Any:
        return self._result


class FakeTask:
    """An rclpy executor's handler task: runs once, keeps its exception."""

    def __init__(self, work: Callable[[], None]) -> None:
        self.work, self.error = work, None

    def __call__(self) -> None:
        try:
            self.work()
        except Exception as exc:
            self.error = exc

    def exception(self) -> Exception | None:
        return self.error


class FakeTimeout(Exception):
    """``rclpy.executors.TimeoutException``."""


class FakeRos:
    """The fake ``rclpy`` world: modules to inject, and what the backend did to them."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.initialised = False
        self.subscriptions: dict[str, list[tuple[Callable[[bytes], None], bool, deque[bytes]]]] = {}
        self.published: list[tuple[str, bytes]] = []
        self.services: dict[str, tuple[Any, Callable[[Any, Any], Any]]] = {}
        self.service_entities: dict[str, Any] = {}
        self.requests: deque[tuple[str, Any]] = deque()
        """Requests from outside the process, taken by the executor: (service name, rclpy request)."""
        self.responses: list[Any] = []
        self.classes: dict[str, type] = {}

    def msg_class(self, name: str) -> type:
        return self.classes.setdefault(name, type(name.replace("/", "_"), (FakeMsg,), {"typename": name}))

    def modules(self) -> dict[str, types.ModuleType]:
        world = self

        class Policy(Enum):
            RELIABLE, BEST_EFFORT, VOLATILE, TRANSIENT_LOCAL, KEEP_LAST, KEEP_ALL = range(6)

        class QoSProfile:
            def __init__(self, **kwargs: Any) -> None:
                self.__dict__.update(kwargs)

        class Publisher:
            def __init__(self, topic: str) -> None:
                self.topic = topic

            def publish(self, msg: Any) -> None:
                assert isinstance(msg, bytes), "the backend publishes serialised bytes"
                world.published.append((self.topic, msg))
                for _, _, queue in world.subscriptions.get(self.topic, []):
                    queue.append(msg)

        class Client:
            def __init__(self, srv: Any, name: str) -> None:
                self.srv, self.name = srv, name

            def service_is_ready(self) -> bool:
                return self.name in world.services

            def wait_for_service(self, timeout_sec: float) -> bool:
                return self.service_is_ready()

            def call_async(self, request: Any) -> FakeFuture:
                assert isinstance(request, self.srv.Request)
                world.calls.append(("call_async", request.data))
                srv, callback = world.services[self.name]
                return FakeFuture(callback(request, srv.Response()))

        class Clock:
            def now(self) -> Any:
                return types.SimpleNamespace(nanoseconds=time.time_ns())

        class Node:
            def __init__(self, name: str) -> None:
                world.calls.append(("Node", name))
                self.name = name

            def create_publisher(self, cls: type, topic: str, qos_profile: Any) -> Publisher:
                world.calls.append(("create_publisher", (cls.typename, topic, qos_profile)))
                return Publisher(topic)

            def create_subscription(self, cls: type, topic: str, callback: Callable[[bytes], None],
                                    qos_profile: Any, raw: bool = False) -> None:
                world.calls.append(("create_subscription", (cls.typename, topic, qos_profile, raw)))
                world.subscriptions.setdefault(topic, []).append((callback, raw, deque()))

            def create_service(self, srv: Any, name: str, callback: Callable[[Any, Any], Any],
                               callback_group: Any = None) -> Any:
                world.calls.append(("create_service", (srv.typename, name, type(callback_group).__name__)))
                world.services[name] = (srv, callback)
                return world.service_entities.setdefault(name, types.SimpleNamespace(srv_name=name))

            def create_client(self, srv: Any, name: str) -> Client:
                return Client(srv, name)

            def get_clock(self) -> Clock:
                return Clock()

            def destroy_node(self) -> None:
                world.calls.append(("destroy_node", self.name))

        class SingleThreadedExecutor:
            def add_node(self, node: Node) -> None:
                self.node = node

            def remove_node(self, node: Node) -> None:
                world.calls.append(("remove_node", node.name))

            def shutdown(self) -> None:
                pass

            def wait_for_ready_callbacks(self, timeout_sec: float | None = None) -> tuple[FakeTask, Any, Node]:
                for callback, raw, queue in (s for subs in world.subscriptions.values() for s in subs):
                    if queue:
                        return FakeTask(lambda c=callback, m=queue.popleft(): c(m)), None, self.node
                if world.requests:
                    name, request = world.requests.popleft()
                    srv, callback = world.services[name]
                    work = lambda: world.responses.append(callback(request, srv.Response()))  # noqa: E731
                    return FakeTask(work), world.service_entities[name], self.node
                time.sleep(min(timeout_sec or 0.0, 0.01))
                raise FakeTimeout()

            def spin_until_future_complete(self, future: FakeFuture, timeout_sec: float | None = None) -> None:
                pass

        def init(**kwargs: Any) -> None:
            world.calls.append(("init", kwargs))
            world.initialised = True

        def try_shutdown() -> None:
            world.calls.append(("try_shutdown", None))
            world.initialised = False

        def get_service(name: str) -> Any:
            srv = world.msg_class(name)
            srv.Request, srv.Response = world.msg_class(name + "_Request"), world.msg_class(name + "_Response")
            return srv

        spaces = {
            "rclpy": {"init": init, "ok": lambda: world.initialised, "try_shutdown": try_shutdown},
            "rclpy.node": {"Node": Node},
            "rclpy.executors": {"SingleThreadedExecutor": SingleThreadedExecutor, "TimeoutException": FakeTimeout,
                                "ShutdownException": type("ShutdownException", (Exception,), {}),
                                "ExternalShutdownException": type("ExternalShutdownException", (Exception,), {})},
            "rclpy.callback_groups": {"ReentrantCallbackGroup": type("ReentrantCallbackGroup", (), {})},
            "rclpy.qos": {"QoSProfile": QoSProfile, "ReliabilityPolicy": Policy, "DurabilityPolicy": Policy,
                          "HistoryPolicy": Policy},
            "rclpy.serialization": {"serialize_message": lambda msg: msg.data,
                                    "deserialize_message": lambda data, cls: cls(bytes(data))},
            "rclpy.signals": {"SignalHandlerOptions": types.SimpleNamespace(NO="NO", ALL="ALL")},
            "rosidl_runtime_py": {},
            "rosidl_runtime_py.utilities": {"get_message": world.msg_class, "get_service": get_service},
        }
        return {name: types.SimpleNamespace(**attrs) for name, attrs in spaces.items()}  # type: ignore[misc]


@pytest.fixture
def fake_ros(monkeypatch: pytest.MonkeyPatch) -> FakeRos:
    world = FakeRos()
    for name, module in world.modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.delitem(sys.modules, "t42_transfer.ros.rclpy_backend", raising=False)
    return world


@pytest.fixture
def no_rclpy(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rclpy", None)  # `import rclpy` raises ImportError


# ------------------------------------------------------------------ backend choice
def test_explicit_argument_beats_the_environment(monkeypatch: pytest.MonkeyPatch, no_rclpy: None) -> None:
    monkeypatch.setenv("T42_TRANSPORT", "rclpy")
    assert resolve_backend("cyclone") == "cyclone"


@pytest.mark.parametrize("value", ["", "auto", "AUTO", "cyclone"])
def test_without_rclpy_auto_and_cyclone_mean_cyclone(monkeypatch: pytest.MonkeyPatch, no_rclpy: None,
                                                     value: str) -> None:
    monkeypatch.setenv("T42_TRANSPORT", value)
    assert resolve_backend() == "cyclone"


def test_auto_prefers_rclpy_when_it_imports(monkeypatch: pytest.MonkeyPatch, fake_ros: FakeRos) -> None:
    monkeypatch.delenv("T42_TRANSPORT", raising=False)
    assert resolve_backend() == "rclpy"
    monkeypatch.setenv("T42_TRANSPORT", "cyclone")
    assert resolve_backend() == "cyclone"


def test_unknown_or_missing_backend_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, no_rclpy: None) -> None:
    monkeypatch.setenv("T42_TRANSPORT", "fastdds")
    with pytest.raises(ValueError, match="T42_TRANSPORT='fastdds': expected one of auto, rclpy, cyclone"):
        resolve_backend()
    with pytest.raises(ValueError, match="rclpy backend was requested but rclpy is not importable"):
        resolve_backend("rclpy")


def test_make_transport_cyclone(monkeypatch: pytest.MonkeyPatch, no_rclpy: None) -> None:
    from t42_transfer.ros.cyclone import CycloneTransport

    monkeypatch.setenv("T42_TRANSPORT", "auto")
    with make_transport("backend_probe", domain_id=random.randint(1, 200)) as transport:
        assert isinstance(transport, CycloneTransport)


# ------------------------------------------------------------------ rclpy backend on the fake
def test_qos_mapping(fake_ros: FakeRos) -> None:
    from t42_transfer.ros.rclpy_backend import rclpy_qos

    mapped = rclpy_qos(qos.SENSOR_DATA)
    assert (mapped.reliability.name, mapped.durability.name, mapped.history.name, mapped.depth) == \
        ("BEST_EFFORT", "VOLATILE", "KEEP_LAST", 5)
    mapped = rclpy_qos(qos.TRANSIENT_LOCAL)
    assert (mapped.reliability.name, mapped.durability.name, mapped.history.name, mapped.depth) == \
        ("RELIABLE", "TRANSIENT_LOCAL", "KEEP_LAST", 1)


def test_rclpy_transport_wiring(fake_ros: FakeRos) -> None:
    talker = make_transport("talker", backend="rclpy", domain_id=42)
    listener = make_transport("listener", backend="rclpy")
    from t42_transfer.ros.rclpy_backend import RclpyTransport

    assert isinstance(talker, RclpyTransport)
    inits = [kw for name, kw in fake_ros.calls if name == "init"]
    assert inits == [{"domain_id": 42, "signal_handler_options": "NO"}], "rclpy.init once, its signal handlers off"

    # Bytes out == bytes in; typed callbacks get typestore objects.
    typed: list[Any] = []
    raw: list[bytes] = []
    listener.subscribe("/hand/object_pose", POSE, qos.SENSOR_DATA, typed.append)
    listener.subscribe("/hand/object_pose", POSE, qos.DEFAULT, raw.append, raw=True)
    pub = talker.publisher("/hand/object_pose", POSE, qos.DEFAULT)
    msg = message_class(POSE)(
        header=message_class("std_msgs/msg/Header")(stamp=message_class("builtin_interfaces/msg/Time")(sec=3, nanosec=4),
                                                    frame_id="hand"),
        pose=message_class("geometry_msgs/msg/Pose")(
            position=message_class("geometry_msgs/msg/Point")(x=1.0, y=2.0, z=3.0),
            orientation=message_class("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
    )
    pub.publish(msg)
    assert listener.spin_once(0.1) == 1 and listener.spin_once(0.1) == 1
    data = serialize(POSE, msg)
    assert fake_ros.published == [("/hand/object_pose", data)]
    assert raw == [data]
    assert typed[0].pose.position.y == 2.0 and typed[0].header.frame_id == "hand"
    subs = [args for name, args in fake_ros.calls if name == "create_subscription"]
    assert all(args[0] == POSE and args[3] is True for args in subs), "subscriptions are raw, typed by get_message"
    assert subs[0][2].reliability.name == "BEST_EFFORT" and subs[0][2].depth == 5

    # Service: rclpy request -> bytes -> ours -> handler -> ours -> bytes -> rclpy response, and back in the client.
    Request, Response = service_classes(TRIGGER)
    seen: list[Any] = []

    def handler(request: Any) -> Any:
        seen.append(request)
        return Response(success=True, message="done")

    listener.service("/recorder/start", TRIGGER, handler)
    client = talker.client("/recorder/start", TRIGGER)
    assert client.service_is_ready()
    response = client.call(Request(structure_needs_at_least_one_member=0))
    assert response.success is True and response.message == "done"
    assert type(seen[0]).__name__ == type(Request()).__name__
    assert [d for name, d in fake_ros.calls if name == "call_async"] == [serialize(Request.__msgtype__, Request())]

    # Timers run from spin_once on the node clock.
    ticks: list[int] = []
    timer = talker.timer(0.01, lambda: ticks.append(1))
    deadline = time.monotonic() + 2.0
    while not ticks and time.monotonic() < deadline:
        talker.spin_once(0.05)
    assert ticks
    timer.cancel()

    talker.close()
    assert ("try_shutdown", None) not in fake_ros.calls, "rclpy stays up while a transport is open"
    listener.close()
    listener.close()
    assert [name for name, _ in fake_ros.calls].count("try_shutdown") == 1
    assert ("destroy_node", "talker") in fake_ros.calls and ("destroy_node", "listener") in fake_ros.calls
    with pytest.raises(RuntimeError, match="closed"):
        pub.publish(msg)


def test_rclpy_concurrent_service_runs_its_handlers_in_threads(fake_ros: FakeRos) -> None:
    node = make_transport("server", backend="rclpy")
    Request, Response = service_classes(TRIGGER)
    release = threading.Event()
    running: list[str] = []

    def slow(request: Any) -> Any:
        running.append(threading.current_thread().name)
        assert release.wait(5.0)
        return Response(success=True, message="slow")

    node.service("/slow", TRIGGER, slow, concurrent=True)
    node.service("/quick", TRIGGER, lambda request: Response(success=True, message="quick"))
    groups = {args[1]: args[2] for name, args in fake_ros.calls if name == "create_service"}
    assert groups == {"/slow": "ReentrantCallbackGroup", "/quick": "NoneType"}
    heard: list[Any] = []
    node.subscribe("/chatter", STRING, qos.DEFAULT, heard.append)
    request = fake_ros.msg_class(TRIGGER + "_Request")(serialize(Request.__msgtype__, Request()))
    fake_ros.requests.extend([("/slow", request), ("/slow", request)])
    assert node.spin_once(0.1) == 1 and node.spin_once(0.1) == 1, "each request starts a thread and returns"
    node.publisher("/chatter", STRING).publish(message_class(STRING)(data="hi"))
    fake_ros.requests.append(("/quick", request))
    assert node.spin_once(0.1) == 1 and node.spin_once(0.1) == 1
    assert [m.data for m in heard] == ["hi"]

    def answers() -> list[str]:
        return [deserialize(Response.__msgtype__, r.data).message for r in fake_ros.responses]

    assert answers() == ["quick"], "the slow requests are still running"
    deadline = time.monotonic() + 5.0
    while len(running) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(running) == 2 and threading.current_thread().name not in running
    release.set()
    while len(fake_ros.responses) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert answers() == ["quick", "slow", "slow"]
    node.close()
