"""The one interface ROS nodes in this project are written against.

Backends (in-process for tests; rclpy or Cyclone DDS for the robot) implement
:class:`Transport`.  Messages are rosbags Jazzy typestore objects and travel as CDR
bytes (XCDR1, little endian, header ``00 01 00 00``); :func:`serialize` and
:func:`deserialize` are the only place that converts between the two.  Service
request/response types resolve through :func:`t42_transfer.ros.naming.typestore_for`.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from typing import Any, Callable

from t42_transfer.ros.naming import request_type, response_type, typestore_for
from t42_transfer.ros.qos import CLOCK as CLOCK_QOS
from t42_transfer.ros.qos import DEFAULT, QoSProfile

Callback = Callable[[Any], None]
CLOCK = "rosgraph_msgs/msg/Clock"


class TransportClosed(RuntimeError):
    """Raised by a closed transport's endpoints, also to a call it ends by closing meanwhile."""


def serialize(msgtype: str, msg: Any) -> bytes:
    """CDR bytes of ``msg`` (a typestore object of ``msgtype``)."""
    actual = getattr(msg, "__msgtype__", None)
    if actual != msgtype:
        raise TypeError(f"expected a {msgtype} message, got {actual or type(msg).__name__}")
    return bytes(typestore_for(msgtype).serialize_cdr(msg, msgtype))


def deserialize(msgtype: str, data: bytes | bytearray | memoryview) -> Any:
    """Typestore object of ``msgtype`` from CDR bytes."""
    return typestore_for(msgtype).deserialize_cdr(bytes(data), msgtype)


def message_class(typename: str) -> Any:
    """The typestore class of a message, service request or service response type."""
    return typestore_for(typename).types[typename]


def service_classes(srvtype: str) -> tuple[Any, Any]:
    """(request class, response class) of ``srvtype``, e.g. ``std_srvs/srv/Trigger``."""
    return message_class(request_type(srvtype)), message_class(response_type(srvtype))


class Publisher(ABC):
    """Publishes on one topic; :meth:`publish` serialises, :meth:`publish_raw` sends CDR bytes as is."""

    def __init__(self, topic: str, msgtype: str, qos: QoSProfile) -> None:
        self.topic, self.msgtype, self.qos = topic, msgtype, qos

    def publish(self, msg: Any) -> None:
        self.publish_raw(serialize(self.msgtype, msg))

    @abstractmethod
    def publish_raw(self, data: bytes) -> None: ...


class Client(ABC):
    """Calls one service."""

    def __init__(self, name: str, srvtype: str) -> None:
        self.name, self.srvtype = name, srvtype
        self.Request, self.Response = service_classes(srvtype)

    @abstractmethod
    def service_is_ready(self) -> bool: ...

    @abstractmethod
    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        """The response; TimeoutError when none arrives within ``timeout_s``."""


class Timer(ABC):
    @abstractmethod
    def cancel(self) -> None: ...


class PeriodicTimer(Timer):
    """A timer a backend polls from its spin loop against its own clock."""

    def __init__(self, period_ns: int, callback: Callable[[], None], now_ns: int) -> None:
        self.period_ns, self.callback = period_ns, callback
        self.next_due_ns = now_ns + period_ns
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True

    def take_if_due(self, now_ns: int) -> bool:
        """Whether it is due; if so schedules the next period after ``now_ns`` (missed ones are skipped, as rcl does)."""
        if self.cancelled or now_ns < self.next_due_ns:
            return False
        missed = (now_ns - self.next_due_ns) // self.period_ns
        self.next_due_ns += (missed + 1) * self.period_ns
        return True


class Transport(ABC):
    """A node's connection to the ROS graph; callbacks run inside :meth:`spin_once`.

    One exception: a service registered with ``concurrent=True`` may have its handler
    run outside the spin loop, in a thread of its own per request, with the reply sent
    from there.  Its handler must therefore be thread-safe: it can run at the same time
    as the node's other callbacks and as other requests to the same service.  It exists
    for handlers that take long (a transfer) while the node must keep publishing and
    answer other calls meanwhile.  A request still being handled when the transport
    closes gets no reply.
    """

    def __init__(self, node_name: str) -> None:
        self.node_name = node_name
        self._closed = False
        self._timers: list[PeriodicTimer] = []
        self._sim_ns: int | None = None
        """Latest ``/clock`` time once :meth:`use_sim_time` is on (0 until the first arrives, as in ROS)."""
        self.logger = logging.getLogger(f"t42_transfer.ros.{node_name}")

    def _check_open(self) -> None:
        if self._closed:
            raise TransportClosed(f"node {self.node_name} is closed")

    @abstractmethod
    def publisher(self, topic: str, msgtype: str, qos: QoSProfile = DEFAULT) -> Publisher: ...

    @abstractmethod
    def subscribe(
        self, topic: str, msgtype: str, qos: QoSProfile, callback: Callback, raw: bool = False
    ) -> None:
        """``callback(msg)`` per message; with ``raw=True`` it gets the CDR bytes."""

    @abstractmethod
    def service(self, name: str, srvtype: str, handler: Callable[[Any], Any], concurrent: bool = False) -> None:
        """Serve ``name``: ``handler(request) -> response`` (typestore objects).

        With ``concurrent=True`` requests may be handled outside :meth:`spin_once` and
        alongside each other (see the class docstring: the handler must be thread-safe).
        """

    @abstractmethod
    def client(self, name: str, srvtype: str) -> Client: ...

    def timer(self, period_s: float, callback: Callable[[], None]) -> Timer:
        """``callback()`` every ``period_s`` of :meth:`clock_ns`, run by the backend's spin loop.

        Timers pace in the backend's clock even under :meth:`use_sim_time` (rclpy's follow
        ROS time): a node's timer keeps running when no ``/clock`` is published.
        """
        self._check_open()
        period_ns = round(period_s * 1e9)
        if period_ns <= 0:
            raise ValueError(f"timer period must be positive, got {period_s} s")
        timer = PeriodicTimer(period_ns, callback, self.clock_ns())
        self._timers.append(timer)
        return timer

    @abstractmethod
    def clock_ns(self) -> int:
        """The backend's own clock in nanoseconds (system time, or a test's fake clock)."""

    def now_ns(self) -> int:
        """ROS time in nanoseconds: the latest ``/clock`` under :meth:`use_sim_time`, else :meth:`clock_ns`."""
        return self.clock_ns() if self._sim_ns is None else self._sim_ns

    def use_sim_time(self, topic: str = "/clock") -> None:
        """Take ROS time from ``topic`` (rosgraph_msgs/msg/Clock), as a node with ``use_sim_time:=true``.

        A simulator (the mock driver with ``sim_time``) publishes it; until the first
        message arrives :meth:`now_ns` is 0, as in ROS.
        """
        if self._sim_ns is not None:
            return
        self._sim_ns = 0

        def on_clock(msg: Any) -> None:
            self._sim_ns = max(self._sim_ns or 0, int(msg.clock.sec) * 10**9 + int(msg.clock.nanosec))

        self.subscribe(topic, CLOCK, CLOCK_QOS, on_clock)

    @abstractmethod
    def spin_once(self, timeout_s: float = 0.0) -> int:
        """Run ready callbacks, waiting up to ``timeout_s`` for one; returns how many ran."""

    @abstractmethod
    def close(self) -> None: ...

    @property
    def closed(self) -> bool:
        return self._closed

    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> bool:
        """Spin until ``until()`` is true, the transport closes or ``timeout_s`` (wall) passes.

        Returns whether ``until`` became true (always False without one).  Another thread
        may close the transport meanwhile: that ends the spin, not with an error.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.closed:
            if until is not None and until():
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
            try:
                self.spin_once(0.05)
            except TransportClosed:
                if not self.closed:  # a callback's error about some other node
                    raise
        return False

    def __enter__(self) -> "Transport":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
