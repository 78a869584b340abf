"""In-process backend of :class:`~t42_transfer.ros.transport.Transport` for fast unit tests.

Several :class:`InProcessTransport` nodes share one :class:`InProcessBus`.  Messages
travel as the same CDR bytes a DDS backend would send; each subscription has its own
queue (KEEP_LAST ``depth`` drops the oldest) and callbacks run only in the subscribing
node's :meth:`~InProcessTransport.spin_once`.  Writers and readers match as in DDS:
a BEST_EFFORT writer does not feed a RELIABLE reader, a VOLATILE writer not a
TRANSIENT_LOCAL reader (a warning is logged); TRANSIENT_LOCAL writers replay their
last ``depth`` messages to late TRANSIENT_LOCAL readers.  One topic has one type;
a second type raises :class:`TopicTypeError`.

Differences from ROS, on purpose: a service handler runs synchronously in the
caller's :meth:`~InProcessClient.call` (so one thread can drive client and server),
and its exceptions propagate to the caller.  Calls from several threads therefore
run their handlers concurrently, whether the service was registered with
``concurrent=True`` or not (the flag is accepted and changes nothing here).  Timers fire in ``spin_once`` against
the bus clock: wall time (``time.time_ns``) or a :class:`FakeClock` the test advances.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

from t42_transfer.ros.naming import (
    dds_type_name,
    request_type,
    response_type,
    validate_name,
    validate_node_name,
)
from t42_transfer.ros.qos import DEFAULT, Durability, History, QoSProfile
from t42_transfer.ros.transport import (
    Callback,
    Client,
    Publisher,
    Transport,
    deserialize,
    message_class,
    serialize,
)


class TopicTypeError(TypeError):
    """An endpoint's message type differs from the type already on its topic."""


class FakeClock:
    """A clock the test moves: ``clock()`` -> ns, ``clock.advance(seconds)``."""

    def __init__(self, start_ns: int = 0) -> None:
        self._ns = int(start_ns)

    def __call__(self) -> int:
        return self._ns

    def advance(self, seconds: float = 0.0, ns: int = 0) -> int:
        step = round(seconds * 1e9) + int(ns)
        if step < 0:
            raise ValueError("a clock does not go backwards")
        self._ns += step
        return self._ns


class InProcessBus:
    """Topics, services and the clock shared by the nodes of one test."""

    def __init__(self, clock: Callable[[], int] | None = None) -> None:
        self.clock: Callable[[], int] = clock if clock is not None else time.time_ns
        self._wall = clock is None
        self.cond = threading.Condition()
        self.publishers: dict[str, list[InProcessPublisher]] = {}
        self.subscriptions: dict[str, list[_Subscription]] = {}
        self.services: dict[str, tuple[str, Callable[[Any], Any]]] = {}

    def topic_type(self, topic: str) -> str | None:
        for endpoint in self.publishers.get(topic, []) + self.subscriptions.get(topic, []):
            return endpoint.msgtype
        return None

    def check_type(self, topic: str, msgtype: str) -> None:
        dds_type_name(msgtype)
        message_class(msgtype)
        existing = self.topic_type(topic)
        if existing is not None and existing != msgtype:
            raise TopicTypeError(f"topic {topic} carries {existing}, not {msgtype}")


class _Subscription:
    def __init__(self, node: "InProcessTransport", topic: str, msgtype: str, qos: QoSProfile,
                 callback: Callback, raw: bool) -> None:
        self.node, self.topic, self.msgtype, self.qos = node, topic, msgtype, qos
        self.callback, self.raw = callback, raw
        self.queue: deque[bytes] = deque(maxlen=qos.depth if qos.history is History.KEEP_LAST else None)


class InProcessPublisher(Publisher):
    def __init__(self, node: "InProcessTransport", topic: str, msgtype: str, qos: QoSProfile) -> None:
        super().__init__(topic, msgtype, qos)
        self._node = node
        latched = qos.durability is Durability.TRANSIENT_LOCAL
        self.history: deque[bytes] | None = (
            deque(maxlen=qos.depth if qos.history is History.KEEP_LAST else None) if latched else None
        )

    def publish_raw(self, data: bytes) -> None:
        if self._node.closed:
            raise RuntimeError(f"node {self._node.node_name} is closed")
        data = bytes(data)
        bus = self._node.bus
        with bus.cond:
            if self.history is not None:
                self.history.append(data)
            for sub in bus.subscriptions.get(self.topic, []):
                if self.qos.compatible_with(sub.qos):
                    sub.queue.append(data)
            bus.cond.notify_all()


class InProcessClient(Client):
    def __init__(self, node: "InProcessTransport", name: str, srvtype: str) -> None:
        super().__init__(name, srvtype)
        self._bus = node.bus

    def service_is_ready(self) -> bool:
        return self.name in self._bus.services

    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout_s
        with self._bus.cond:
            while self.name not in self._bus.services:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no server for service {self.name} within {timeout_s} s")
                self._bus.cond.wait(remaining)
            srvtype, handler = self._bus.services[self.name]
        if srvtype != self.srvtype:
            raise TopicTypeError(f"service {self.name} is {srvtype}, not {self.srvtype}")
        req_bytes = serialize(request_type(srvtype), request)
        response = handler(deserialize(request_type(srvtype), req_bytes))
        return deserialize(response_type(srvtype), serialize(response_type(srvtype), response))


class InProcessTransport(Transport):
    """One node on an :class:`InProcessBus`."""

    def __init__(self, bus: InProcessBus, node_name: str) -> None:
        super().__init__(validate_node_name(node_name))
        self.bus = bus
        self._publishers: list[InProcessPublisher] = []
        self._subscriptions: list[_Subscription] = []
        self._services: list[str] = []

    def _warn_unmatched(self, pub: InProcessPublisher, sub: _Subscription) -> None:
        if not pub.qos.compatible_with(sub.qos):
            self.logger.warning(
                "incompatible QoS on %s: writer offers %s/%s, reader requests %s/%s; not matched",
                pub.topic, pub.qos.reliability.value, pub.qos.durability.value,
                sub.qos.reliability.value, sub.qos.durability.value,
            )

    def publisher(self, topic: str, msgtype: str, qos: QoSProfile = DEFAULT) -> InProcessPublisher:
        self._check_open()
        validate_name(topic)
        with self.bus.cond:
            self.bus.check_type(topic, msgtype)
            pub = InProcessPublisher(self, topic, msgtype, qos)
            self.bus.publishers.setdefault(topic, []).append(pub)
            for sub in self.bus.subscriptions.get(topic, []):
                self._warn_unmatched(pub, sub)
        self._publishers.append(pub)
        return pub

    def subscribe(self, topic: str, msgtype: str, qos: QoSProfile, callback: Callback,
                  raw: bool = False) -> None:
        self._check_open()
        validate_name(topic)
        with self.bus.cond:
            self.bus.check_type(topic, msgtype)
            sub = _Subscription(self, topic, msgtype, qos, callback, raw)
            for pub in self.bus.publishers.get(topic, []):
                self._warn_unmatched(pub, sub)
                if pub.history is not None and qos.durability is Durability.TRANSIENT_LOCAL \
                        and pub.qos.compatible_with(qos):
                    sub.queue.extend(pub.history)
            self.bus.subscriptions.setdefault(topic, []).append(sub)
        self._subscriptions.append(sub)

    def service(self, name: str, srvtype: str, handler: Callable[[Any], Any], concurrent: bool = False) -> None:
        """Serve ``name``; every call runs ``handler`` in the caller's thread (see the module docstring)."""
        self._check_open()
        validate_name(name, "service")
        message_class(request_type(srvtype))
        with self.bus.cond:
            if name in self.bus.services:
                raise ValueError(f"service {name} already has a server")
            self.bus.services[name] = (srvtype, handler)
            self.bus.cond.notify_all()
        self._services.append(name)

    def client(self, name: str, srvtype: str) -> InProcessClient:
        self._check_open()
        validate_name(name, "service")
        return InProcessClient(self, name, srvtype)

    def clock_ns(self) -> int:
        return int(self.bus.clock())

    def _take_ready(self) -> list[Callable[[], None]]:
        ready: list[Callable[[], None]] = []
        with self.bus.cond:
            for sub in self._subscriptions:
                while sub.queue:
                    data = sub.queue.popleft()
                    ready.append(lambda s=sub, d=data: s.callback(d if s.raw else deserialize(s.msgtype, d)))
        now = self.clock_ns()
        ready.extend(t.callback for t in self._timers if t.take_if_due(now))
        return ready

    def _wait_s(self, remaining_s: float) -> float:
        """How long to block: until a message, the deadline or (wall clock) the next timer."""
        if self.bus._wall:
            dues = [t.next_due_ns for t in self._timers if not t.cancelled]
            if dues:
                remaining_s = min(remaining_s, max(0.0, (min(dues) - self.clock_ns()) / 1e9))
        return remaining_s

    def spin_once(self, timeout_s: float = 0.0) -> int:
        """Run every callback ready now (queued messages, then due timers)."""
        self._check_open()
        deadline = time.monotonic() + timeout_s
        while True:
            ready = self._take_ready()
            if ready or time.monotonic() >= deadline:
                for callback in ready:
                    callback()
                return len(ready)
            with self.bus.cond:
                if not any(sub.queue for sub in self._subscriptions):
                    self.bus.cond.wait(self._wait_s(deadline - time.monotonic()))

    def close(self) -> None:
        if self._closed:
            return
        with self.bus.cond:
            for pub in self._publishers:
                self.bus.publishers[pub.topic].remove(pub)
            for sub in self._subscriptions:
                self.bus.subscriptions[sub.topic].remove(sub)
            for name in self._services:
                del self.bus.services[name]
        for timer in self._timers:
            timer.cancel()
        self._publishers.clear()
        self._subscriptions.clear()
        self._services.clear()
        self._timers.clear()
        self._closed = True
