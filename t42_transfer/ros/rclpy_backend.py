"""rclpy backend of :class:`~t42_transfer.ros.transport.Transport`, for machines with ROS 2 Jazzy installed.

UNTESTED AGAINST A REAL ROS INSTALL: rclpy cannot be installed where this project
is developed.  It is written from the rclpy Jazzy API and its tests run it against
a fake ``rclpy`` that records calls (test/test_ros_backends.py), which shows the
wiring, not that ROS accepts it.

Messages stay rosbags typestore objects, as everywhere in this project; rclpy only
ever sees CDR bytes or its own generated classes:

* publishers send bytes (``Publisher.publish`` accepts serialised messages);
  subscriptions are ``raw=True`` and typed callbacks deserialise with
  :func:`~t42_transfer.ros.transport.deserialize`;
* services convert the rclpy request to bytes (``serialize_message``), to our
  request type, call the handler, serialise its response our way and
  ``deserialize_message`` it into the rclpy response; clients do the reverse.

Timers are the base class's :class:`PeriodicTimer` on the node clock, polled in
:meth:`RclpyTransport.spin_once` next to the executor, so timing behaves as on the
other backends.  :meth:`RclpyTransport.spin_once` takes one ready callback at a time
from a ``SingleThreadedExecutor`` (``wait_for_ready_callbacks``, as rclpy's own
executors do) and runs it in the spinning thread, except the handler of a service
registered with ``concurrent=True``: that service is in a ``ReentrantCallbackGroup``
(so a running request blocks neither the node's default group nor the next request)
and its handler task runs, and sends the response, in a daemon thread of its own,
as ``MultiThreadedExecutor`` would run it in its pool.  A ``MultiThreadedExecutor``
for the node would run every other callback in its pool too, outside ``spin_once``
and alongside our timers, which nodes written for the other backends do not expect.  ``rclpy.init`` runs once per process (the first
transport's ``domain_id`` wins, default ``ROS_DOMAIN_ID``) with
rclpy's signal handlers off (the runner owns SIGINT/SIGTERM); the last transport
to close shuts rclpy down again if it started it.  A client's :meth:`call` spins
the node's executor until the reply arrives: do not call it from a callback.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor, TimeoutException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy
from rclpy.qos import QoSProfile as RclpyQoSProfile
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.signals import SignalHandlerOptions
from rosidl_runtime_py.utilities import get_message, get_service

from t42_transfer.ros.naming import request_type, response_type, validate_name, validate_node_name
from t42_transfer.ros.qos import DEFAULT, Durability, History, QoSProfile, Reliability
from t42_transfer.ros.transport import Callback, Client, Publisher, Transport, deserialize, serialize

_RELIABILITY = {Reliability.RELIABLE: ReliabilityPolicy.RELIABLE, Reliability.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {Durability.VOLATILE: DurabilityPolicy.VOLATILE,
               Durability.TRANSIENT_LOCAL: DurabilityPolicy.TRANSIENT_LOCAL}
_HISTORY = {History.KEEP_LAST: HistoryPolicy.KEEP_LAST, History.KEEP_ALL: HistoryPolicy.KEEP_ALL}

_INIT_LOCK = threading.Lock()
_open_transports = 0
_we_initialised = False


def rclpy_qos(qos: QoSProfile) -> RclpyQoSProfile:
    """The rclpy QoS profile of one of ours."""
    return RclpyQoSProfile(history=_HISTORY[qos.history], depth=qos.depth,
                           reliability=_RELIABILITY[qos.reliability], durability=_DURABILITY[qos.durability])


def _acquire(domain_id: int | None) -> None:
    """Initialise rclpy for this process unless it already is."""
    global _open_transports, _we_initialised
    with _INIT_LOCK:
        if not rclpy.ok():
            rclpy.init(domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
            _we_initialised = True
        _open_transports += 1


def _release() -> None:
    global _open_transports, _we_initialised
    with _INIT_LOCK:
        _open_transports -= 1
        if _open_transports == 0 and _we_initialised:
            rclpy.try_shutdown()
            _we_initialised = False


class RclpyPublisher(Publisher):
    def __init__(self, node: "RclpyTransport", topic: str, msgtype: str, qos: QoSProfile) -> None:
        super().__init__(topic, msgtype, qos)
        self._node = node
        self.pub = node.node.create_publisher(get_message(msgtype), topic, rclpy_qos(qos))

    def publish_raw(self, data: bytes) -> None:
        self._node._check_open()
        self.pub.publish(bytes(data))


class RclpyClient(Client):
    def __init__(self, node: "RclpyTransport", name: str, srvtype: str) -> None:
        super().__init__(name, srvtype)
        self._node = node
        self._srv = get_service(srvtype)
        self.client = node.node.create_client(self._srv, name)

    def service_is_ready(self) -> bool:
        return bool(self.client.service_is_ready())

    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout_s
        if not self.client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError(f"no server for service {self.name} within {timeout_s} s")
        ros_request = deserialize_message(serialize(request_type(self.srvtype), request), self._srv.Request)
        future = self.client.call_async(ros_request)
        self._node._executor.spin_until_future_complete(future, timeout_sec=max(0.0, deadline - time.monotonic()))
        if not future.done():
            self.client.remove_pending_request(future)
            raise TimeoutError(f"no reply from service {self.name} within {timeout_s} s")
        return deserialize(response_type(self.srvtype), serialize_message(future.result()))


class RclpyTransport(Transport):
    """One ROS node = one rclpy ``Node`` with its own single-threaded executor."""

    def __init__(self, node_name: str, domain_id: int | None = None) -> None:
        super().__init__(validate_node_name(node_name))
        _acquire(domain_id)
        try:
            self.node = Node(node_name)
            self._executor = SingleThreadedExecutor()
            self._executor.add_node(self.node)
        except Exception:
            _release()
            raise
        self._ran = 0
        """Callbacks run or started so far (what :meth:`spin_once` counts)."""
        self._concurrent: list[Any] = []
        """The rclpy services whose handler tasks run in threads of their own."""

    def _counted(self, callback: Callable[..., Any]) -> Callable[..., Any]:
        def run(*args: Any) -> Any:
            self._ran += 1
            return callback(*args)
        return run

    def publisher(self, topic: str, msgtype: str, qos: QoSProfile = DEFAULT) -> RclpyPublisher:
        self._check_open()
        validate_name(topic)
        return RclpyPublisher(self, topic, msgtype, qos)

    def subscribe(self, topic: str, msgtype: str, qos: QoSProfile, callback: Callback,
                  raw: bool = False) -> None:
        self._check_open()
        validate_name(topic)

        def on_bytes(data: bytes) -> None:
            callback(data if raw else deserialize(msgtype, data))

        self.node.create_subscription(get_message(msgtype), topic, self._counted(on_bytes), rclpy_qos(qos), raw=True)

    def service(self, name: str, srvtype: str, handler: Callable[[Any], Any], concurrent: bool = False) -> None:
        """Serve ``name``; with ``concurrent=True`` each request runs in a thread of its own (module docstring)."""
        self._check_open()
        validate_name(name, "service")
        srv = get_service(srvtype)

        def on_request(ros_request: Any, ros_response: Any) -> Any:
            request = deserialize(request_type(srvtype), serialize_message(ros_request))
            response = handler(request)
            return deserialize_message(serialize(response_type(srvtype), response), srv.Response)

        if concurrent:  # counted when spin_once starts its thread
            self._concurrent.append(
                self.node.create_service(srv, name, on_request, callback_group=ReentrantCallbackGroup()))
        else:
            self.node.create_service(srv, name, self._counted(on_request))

    def client(self, name: str, srvtype: str) -> RclpyClient:
        self._check_open()
        validate_name(name, "service")
        return RclpyClient(self, name, srvtype)

    def clock_ns(self) -> int:
        """The node's ROS clock: rclpy itself follows ``/clock`` once ``use_sim_time`` is set."""
        return int(self.node.get_clock().now().nanoseconds)

    def use_sim_time(self, topic: str = "/clock") -> None:
        """rclpy's own sim time: the node's ``use_sim_time`` parameter (``topic`` must be /clock)."""
        from rclpy.parameter import Parameter

        if topic != "/clock":
            raise ValueError("rclpy takes sim time from /clock only")
        self.node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])

    def _run_due_timers(self) -> None:
        now = self.clock_ns()
        for timer in [t for t in self._timers if t.take_if_due(now)]:
            self._ran += 1
            timer.callback()

    def _step(self, timeout_s: float) -> None:
        """Run one ready callback here, or start a concurrent service's handler task in its own thread."""
        try:
            handler, entity, _ = self._executor.wait_for_ready_callbacks(timeout_sec=timeout_s)
        except (TimeoutException, ShutdownException, ExternalShutdownException):
            return
        if any(entity is srv for srv in self._concurrent):
            self._ran += 1
            threading.Thread(target=self._run_concurrent, args=(handler,), daemon=True,
                             name=f"{self.node_name} service").start()
            return
        handler()
        if handler.exception() is not None:
            raise handler.exception()

    def _run_concurrent(self, handler: Any) -> None:
        """Run a concurrent service's task (handler and response); its error is logged, as it cannot end a spin."""
        handler()
        error = handler.exception()
        if error is None:
            return
        if self.closed:
            self.logger.info("node closed while a service request was handled; no reply")
        else:
            self.logger.error("service handler failed; the request gets no reply", exc_info=error)

    def spin_once(self, timeout_s: float = 0.0) -> int:
        """Run ready callbacks (one executor step at a time) and due timers, waiting up to ``timeout_s``."""
        self._check_open()
        deadline = time.monotonic() + timeout_s
        start, wait = self._ran, 0.0
        while True:
            self._step(wait)
            self._run_due_timers()
            remaining = deadline - time.monotonic()
            if self._ran > start or remaining <= 0:
                return self._ran - start
            dues = [t.next_due_ns for t in self._timers if not t.cancelled]
            wait = min([remaining] + [max(0.0, (due - self.clock_ns()) / 1e9) for due in dues])

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()
        try:
            self._executor.remove_node(self.node)
            self._executor.shutdown()
            self.node.destroy_node()
        finally:
            _release()
