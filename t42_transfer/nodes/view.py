"""View node (``t42 view``): the live graph in Foxglove, over a Foxglove WebSocket server (foxglove-sdk).

What a Foxglove client (the app's "Foxglove WebSocket" connection, ``ws://127.0.0.1:8765``) gets:

* every topic of the graph (looked at every ``discovery_period_s``) as a channel named as the graph names it
  (``/hand/object_pose``), ``message_encoding`` ``cdr`` and a ``ros2msg`` schema of the full definition (as the
  recorder's bags hold it, :func:`msg_adapters.schemas.message_definition`); messages are the CDR bytes the node
  received (a raw subscription), unchanged, logged at the graph's time.  A topic is read from the graph only
  while a client subscribes to its channel (camera images cost nothing when nobody watches them), with a QoS
  that matches the publishers then: TRANSIENT_LOCAL when they all are (so a late client sees ``hand/status``
  and the model announcements), BEST_EFFORT when one is.  A topic whose type is not installed here, or has no
  definition, is left out with one warning;
* ``/clock`` as the server's time (the Time capability), so the app's clock is the driver's sim time;
* ``view/markers`` (visualization_msgs/MarkerArray, also published on the graph for RViz, latched): the scene of
  :mod:`t42_transfer.view.scene` from ``hand/joint_states``, ``hand/object_pose``, ``t42/goal`` and
  ``t42/planned_path`` (the plan's predicted path, published with each accepted plan) and
  ``t42/plan_candidates`` (the planner's lowest-cost candidates, with its parameter ``candidates`` above 0),
  drawn with the links of
  ``hand`` and a tolerance circle of ``tolerance_m``, red with the planner's status word when ``t42/plan_result``
  says it refused that goal; at most ``marker_rate_hz``, when something changed;
* Parameters: every node's parameters, as ``/namespace/node.parameter``, read and set through the nodes'
  parameter services (:mod:`t42_transfer.nodes.view_params`); a node refuses a bad value as it would refuse
  ``ros2 param set``;
* ClientPublish: a client may advertise a channel on one of ``client_topics`` (default ``t42/goal``, as
  Foxglove's Publish panel does) in ``cdr`` with a type installed here; its messages go onto the graph unchanged.
  Other topics and encodings are refused with a warning (a viewer must not drive the servos), and so is a message
  that does not read as its channel's type (checked before it is published, so no reader gets bad CDR).

The server listens on ``host`` (127.0.0.1 by default: this machine only) and ``port`` (0: any free port; the node
logs the one it got, :attr:`View.port`).  Each node has its own foxglove Context, so two views in one process
do not share channels.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import foxglove
import numpy as np
from foxglove.websocket import Capability, ChannelView, Client, ClientChannel
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from t42_interfaces.msg import PlanCandidates
from t42_interfaces.msg import PlanResult as PlanResultMsg
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.markers import scene_markers
from msg_adapters.plan_result import plan_result
from msg_adapters.planning import candidates_xy_mm
from msg_adapters.schemas import message_definition
from t42_transfer.conventions import MM_PER_M
from t42_transfer.hand.params import variant
from t42_transfer.nodes.view_params import GraphParameters
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.qos import profile
from t42_transfer.view.scene import DEFAULT_TOLERANCE_MM, build_scene
from t42_transfer.view.server import start_server

LEFT_OUT = ("/parameter_events",)
"""Graph topics never offered (every node's parameter changes: noise in a viewer)."""
CDR = "cdr"
CLIENT_MAX_BYTES = 65_536
"""A client's message larger than this is refused unread (a goal is under 100 bytes)."""


@dataclass(frozen=True)
class ViewParams:
    """The view node's ROS parameters."""

    host: str = param("127.0.0.1", "address the Foxglove WebSocket server listens on (127.0.0.1: this machine "
                                   "only; 0.0.0.0: every interface)", read_only=True)
    port: int = param(8765, "port of the Foxglove WebSocket server (0: any free port)", read_only=True,
                      min=0, max=65535)
    hand: str = param("target", "hand whose link lengths draw the fingers (source, target, family-<seed>...)",
                      read_only=True)
    tolerance_m: float = param(DEFAULT_TOLERANCE_MM / MM_PER_M, "radius of the goal's circle (m): the planner's "
                                                                "tolerance", min=1e-6, max=1.0,
                               renamed_from="tolerance_mm")
    marker_rate_hz: float = param(10.0, "markers are drawn at most this often (Hz, steady time)", read_only=True,
                                  min=0.1, max=100.0)
    discovery_period_s: float = param(1.0, "how often the graph is looked at for new topics (s)", read_only=True,
                                      min=0.05, max=60.0)
    client_topics: tuple[str, ...] = param((names.GOAL,), "topics a Foxglove client may publish on (relative or "
                                           "absolute names)", read_only=True)

    def __post_init__(self) -> None:
        variant(self.hand)  # ValueError naming the bad hand
        if not (math.isfinite(self.tolerance_m) and self.tolerance_m > 0):
            raise ValueError(f"tolerance_m must be a positive number, got {self.tolerance_m!r}")


_DECODERS: dict[str, Any] = {
    "joints": ma.joint_state_arrays, "pose": ma.object_xy_mm, "goal": ma.goal_xy_mm, "path": ma.path_xy_mm,
    "candidates": candidates_xy_mm,
}
"""How the scene reads each input (ValueError for one it cannot draw)."""


class _Listener(foxglove.websocket.ServerListener):
    """The server's callbacks (its own threads) handed to the node."""

    def __init__(self, view: View) -> None:
        self.view = view

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.view.client_subscribed(client.id, channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self.view.client_unsubscribed(client.id, channel.topic)

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        self.view.client_advertised(client, channel)

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        self.view.client_unadvertised(client, client_channel_id)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        self.view.client_message(client, client_channel_id, data)

    def on_get_parameters(self, client: Client, param_names: list[str],
                          request_id: str | None = None) -> list[foxglove.Parameter]:
        return self.view.graph_parameters.get(param_names)

    def on_set_parameters(self, client: Client, parameters: list[foxglove.Parameter],
                          request_id: str | None = None) -> list[foxglove.Parameter]:
        self.view.log.info(f"client {client.id} sets {', '.join(p.name for p in parameters)}")
        return self.view.graph_parameters.set(parameters)


def subscription_qos(publishers: list[Any]) -> QoSProfile:
    """A reader that matches every one of ``publishers`` (rclpy TopicEndpointInfo) and gets what they keep."""
    latched = bool(publishers) and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                       for p in publishers)
    best_effort = any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers)
    return QoSProfile(depth=100 if latched else 10,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
                      reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE)


@dataclass
class _Offered:
    """A graph topic offered to clients, read from the graph while one of them subscribes."""

    channel: foxglove.Channel
    msg_class: type
    clients: set[int] = field(default_factory=set)
    reader: Any = None
    """The raw subscription while a client subscribes, else None."""


class View(Node):
    """The Foxglove live view of the graph; see the module docstring."""

    params_class = ViewParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("view", **node_kwargs)
        self._params = LiveParams(self, self.params_class)
        p = self.params
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        self.hand = variant(p.hand)
        self._lock = threading.Lock()
        self._channels: dict[str, _Offered] = {}
        """Offered graph topic -> its Foxglove channel and reader."""
        self._skipped: set[str] = set()
        self._client_pubs: dict[tuple[int, int], Any] = {}
        """(client id, client channel id) -> the rclpy publisher its messages go out on, and their type."""
        self._let_go: list[Any] = []
        """Graph readers and client publishers no client needs, for the executor's thread to destroy: destroyed on
        the server's threads, one could go while the executor was putting its wait set together (InvalidHandle)."""
        self._destroy_let_go = self.create_guard_condition(self._destroy_what_was_let_go)
        self._clock_ns: int | None = None
        self._inputs: dict[str, Any] = {}
        self._refused = ""
        """The planner's status word when it refused the goal drawn, else empty."""
        self._dirty = False
        self._allowed = {self.resolve_topic_name(t) for t in p.client_topics}
        self.graph_parameters = GraphParameters(self)
        self._foxglove = foxglove.Context()
        self.server = start_server(
            f"t42 view {self.get_fully_qualified_name()}", p.host, p.port,
            capabilities=[Capability.ClientPublish, Capability.Time, Capability.Parameters], supported_encodings=[CDR],
            server_listener=_Listener(self), context=self._foxglove)
        self.port = self.server.port
        self._marker_pub = self.create_publisher(MarkerArray, names.VIEW_MARKERS, profile(names.LATCHED))
        # Best effort, as rclpy's own time source reads /clock: it matches a best-effort clock publisher too.
        self.create_subscription(Clock, names.CLOCK, self._on_clock,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(JointState, names.JOINT_STATES, lambda m: self._input("joints", m), 10)
        self.create_subscription(PoseStamped, names.OBJECT_POSE, lambda m: self._input("pose", m), 10)
        self.create_subscription(PointStamped, names.GOAL, lambda m: self._input("goal", m), 10)
        # Volatile, though the planner latches these two: a transient-local reader would not match a volatile
        # publisher (a bag played, another planner), and a view drawing nothing is worse than one a plan late.
        self.create_subscription(PathMsg, names.PLANNED_PATH, lambda m: self._input("path", m), 10)
        self.create_subscription(PlanCandidates, names.PLAN_CANDIDATES, lambda m: self._input("candidates", m), 10)
        self.create_subscription(PlanResultMsg, names.PLAN_RESULT, self._on_plan_result, profile(names.EVENT_READER))
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / p.marker_rate_hz, self._draw, clock=steady)
        self.create_timer(p.discovery_period_s, self.discover, clock=steady)
        self.log.info(f"Foxglove WebSocket server on ws://{p.host}:{self.port} (open it in Foxglove: "
                      "Open connection -> Foxglove WebSocket)")
        self.discover()

    @property
    def params(self) -> ViewParams:
        return self._params.value

    @property
    def offered(self) -> list[str]:
        """Graph topics offered to clients so far."""
        with self._lock:
            return sorted(self._channels)

    @property
    def reading(self) -> list[str]:
        """Graph topics read now (a client subscribes to their channels)."""
        with self._lock:
            return sorted(t for t, offered in self._channels.items() if offered.reader is not None)

    # ------------------------------------------------------------------ graph topics -> channels
    def now_ns(self) -> int:
        """The graph's time: the newest /clock when there is one, else the wall clock."""
        return self._clock_ns if self._clock_ns is not None else time.time_ns()

    def _on_clock(self, msg: Clock) -> None:
        self._clock_ns = ma.stamp_to_ns(msg.clock)
        self.server.broadcast_time(self._clock_ns)

    def discover(self) -> None:
        """Offer every graph topic not offered yet."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._channels or topic in self._skipped or topic in LEFT_OUT or not types:
                continue
            try:
                self._offer(topic, types[0])
            except (ImportError, AttributeError, KeyError, ValueError) as err:
                self._skipped.add(topic)
                self.log.warning(f"{topic} ({types[0]}) is not offered: {err}")

    def _offer(self, topic: str, typename: str) -> None:
        msg_class = ma.rclpy_class(typename)
        schema = foxglove.Schema(name=typename, encoding="ros2msg", data=message_definition(typename).encode())
        channel = foxglove.Channel(topic, schema=schema, message_encoding=CDR, context=self._foxglove)
        with self._lock:
            self._channels[topic] = _Offered(channel, msg_class)
        self.log.debug(f"offering {topic} ({typename})")

    def client_subscribed(self, client_id: int, topic: str) -> None:
        """A client's first subscription to a channel subscribes to its topic on the graph (a raw reader whose QoS
        matches the publishers there now)."""
        with self._lock:
            offered = self._channels.get(topic)
            if offered is None:
                return
            offered.clients.add(client_id)
            let_go = next((e for e in self._let_go if not isinstance(e, Publisher) and e.topic_name == topic), None)
            if offered.reader is None and let_go is not None:  # back before it was destroyed: read on with it
                self._let_go.remove(let_go)
                offered.reader = let_go
            elif offered.reader is None:
                channel = offered.channel
                qos = subscription_qos(self.get_publishers_info_by_topic(topic))
                offered.reader = self.create_subscription(
                    offered.msg_class, topic, lambda data: channel.log(data, log_time=self.now_ns()), qos, raw=True)
        self.log.info(f"client {client_id} subscribed to {topic}")

    def client_unsubscribed(self, client_id: int, topic: str) -> None:
        """The last client gone from a channel ends the graph subscription (nothing is read for no one)."""
        with self._lock:
            offered = self._channels.get(topic)
            if offered is None:
                return
            offered.clients.discard(client_id)
            if offered.clients or offered.reader is None:
                return
            self._let_go.append(offered.reader)
            offered.reader = None
        self._wake_destroyer()

    # ------------------------------------------------------------------ markers
    def _input(self, key: str, msg: Any) -> None:
        """Keep ``msg`` as the newest ``key`` to draw, unless it cannot be drawn (another frame, NaN): then the last
        good one stays, so one bad message does not blank the whole scene."""
        try:
            _DECODERS[key](msg)
        except ValueError as err:
            self.per_message.warning(f"{key} not drawn, the last one kept: {err}")
            return
        self._inputs[key] = msg
        if key == "goal":
            self._refused = ""  # until the planner says otherwise
        self._dirty = True

    def _on_plan_result(self, msg: Any) -> None:
        """The planner's word on the goal drawn: refused (with its status) or not.  ``superseded`` is no refusal
        of the goal drawn (a newer one, perhaps the same point sent again, replaced it)."""
        goal = self._inputs.get("goal")
        try:
            result = plan_result(msg)
            drawn = None if goal is None else ma.goal_xy_mm(goal)
        except ValueError as err:
            self.per_message.warning(f"plan result not used: {err}")
            return
        if drawn is None or result.goal_mm is None or result.status == names.SUPERSEDED:
            return
        if np.allclose(drawn, result.goal_mm, rtol=0.0, atol=1e-3):
            self._refused = "" if result.accepted else result.status
            self._dirty = True

    def scene(self) -> Any:
        """The scene of the newest inputs; ValueError for one that cannot be drawn (another frame, NaN)."""
        joints, pose, goal, path, candidates = (self._inputs.get(k) for k in ("joints", "pose", "goal", "path",
                                                                               "candidates"))
        return build_scene(self.hand, actuator_angles=None if joints is None else ma.joint_state_arrays(joints)[1],
                           object_xy_mm=None if pose is None else ma.object_xy_mm(pose),
                           goal_xy_mm=None if goal is None else ma.goal_xy_mm(goal),
                           tolerance_mm=self.params.tolerance_m * MM_PER_M,
                           path_xy_mm=None if path is None else ma.path_xy_mm(path), goal_refused=self._refused,
                           candidates=() if candidates is None else candidates_xy_mm(candidates))

    def _draw(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        try:
            scene = self.scene()
        except ValueError as err:
            self.per_message.warning(f"scene not drawn: {err}")
            return
        joints = self._inputs.get("joints")
        stamp = ma.stamp_to_ns(joints.header.stamp) if joints is not None else self.now_ns()
        self._marker_pub.publish(scene_markers(scene, stamp, ma.RCLPY))

    # ------------------------------------------------------------------ ClientPublish
    def client_advertised(self, client: Client, channel: ClientChannel) -> None:
        topic = self.resolve_topic_name(channel.topic)
        if topic not in self._allowed:
            self.log.warning(f"client {client.id} may not publish on {channel.topic}: only on "
                             f"{sorted(self._allowed)} (client_topics)")
            return
        if channel.encoding != CDR:
            self.log.warning(f"client {client.id} publishes {channel.topic} in {channel.encoding!r}: only cdr here")
            return
        try:
            msg_class = ma.rclpy_class(channel.schema_name)
        except (ImportError, AttributeError, ValueError):
            self.log.warning(f"client {client.id} publishes {channel.topic} as {channel.schema_name!r}, "
                             "not a message type installed here")
            return
        on_graph = dict(self.get_topic_names_and_types()).get(topic, [])
        if on_graph and channel.schema_name not in on_graph:  # (rcl would refuse the publisher with its own words)
            self.log.warning(f"client {client.id} publishes {channel.topic} as {channel.schema_name}; the graph's "
                             f"type is {', '.join(on_graph)}")
            return
        with self._lock:
            self._client_pubs[(client.id, channel.id)] = (self.create_publisher(msg_class, topic, 10),
                                                          channel.schema_name)
        self.log.info(f"client {client.id} publishes on {topic} ({channel.schema_name})")

    def client_unadvertised(self, client: Client, client_channel_id: int) -> None:
        with self._lock:
            entry = self._client_pubs.pop((client.id, client_channel_id), None)
            if entry is None:
                return
            self._let_go.append(entry[0])
        self._wake_destroyer()

    def _wake_destroyer(self) -> None:
        try:
            self._destroy_let_go.trigger()
        except InvalidHandle:  # the node destroyed: its entities went with it
            pass

    def _destroy_what_was_let_go(self) -> None:
        with self._lock:
            let_go, self._let_go = self._let_go, []
        for entity in let_go:
            if isinstance(entity, Publisher):
                self.destroy_publisher(entity)
            else:
                self.destroy_subscription(entity)

    def client_message(self, client: Client, client_channel_id: int, data: bytes) -> None:
        with self._lock:
            entry = self._client_pubs.get((client.id, client_channel_id))
        if entry is None:
            self.per_message.warning(f"client {client.id}: a message on a channel it may not publish on")
            return
        publisher, typename = entry
        try:  # what reaches the graph must read as its type: a bad CDR could stop a reader's node
            ma.rclpy_message(bytes(data), typename, CLIENT_MAX_BYTES)
        except ValueError as err:
            self.per_message.warning(f"client {client.id} on {publisher.topic_name}: {err}; not published")
            return
        publisher.publish(bytes(data))

    def close(self) -> None:
        self.server.stop()
