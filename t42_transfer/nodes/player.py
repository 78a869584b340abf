"""Bag player node: a rosbag2 bag's messages back onto their topics, like ``ros2 bag play``.

Each message goes out as the CDR bytes stored in the bag (``Publisher.publish(bytes)``,
nothing is decoded), on its topic as named in the bag (absolute: a bag recorded
under ``/left`` plays on ``/left/hand/...``; remap it by its absolute name to move it,
``t42 bag play --remap OLD:=NEW``) with its type, at
its log-time offset from the bag's first message divided by ``rate``.  Each topic's
publisher offers the QoS the bag recorded for it (reliability, durability, history,
depth), else ROS's default.

Playback runs in its own thread on steady time (a player does not follow
``use_sim_time``: it is the clock), so timing does not depend on the executor; the
``rate`` parameter may change while playing and the current bag time carries on
from where it is.  With ``clock_hz > 0`` the node publishes ``/clock``
(rosgraph_msgs/msg/Clock) that often with the bag's current time, as ``ros2 bag
play --clock`` does, so nodes run with ``use_sim_time:=true`` live in the bag's
time (it stands still while paused and jumps back on each loop).

Messages are read lazily through rosbags, so memory does not grow with the bag.
A missing path, a directory that is no bag, a FIFO or directory where a bag file belongs, or a
bag without ``metadata.yaml`` or with a cut-off MCAP (a killed recorder) is refused with a
:class:`BagError` naming it (``t42 bag repair`` makes the last playable).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosgraph_msgs.msg import Clock

from msg_adapters import RCLPY, names, ns_to_stamp, rclpy_class
from t42_transfer.data.bag.playback import Timeline, open_bag
from t42_transfer.data.errors import BagError
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param

DEFAULT_QOS = QoSProfile(depth=10)
"""ROS's default (RELIABLE, VOLATILE, KEEP_LAST 10), for a topic whose bag recorded no offered QoS."""


@dataclass(frozen=True)
class PlayerParams:
    """The player's ROS parameters."""

    bag: Path = param(description="bag directory (rosbag2, MCAP or sqlite3) to play", read_only=True)
    rate: float = param(1.0, "playback speed factor: 2.0 plays twice as fast (may change while playing)",
                        min=1e-6, max=1e6)
    loop: bool = param(False, "start again from the first message after the last (never finishes)")
    topics: tuple[str, ...] | None = param(None, "play only these topics, as named in the bag (unset: all)",
                                           read_only=True)
    clock_hz: float = param(0.0, "publish /clock with the bag's time this often (Hz), as ros2 bag play --clock; "
                                 "0: no /clock", read_only=True, min=0.0, max=10_000.0)
    start_paused: bool = param(False, "publish nothing until resume() (the CLI waits for subscribers first)",
                               read_only=True)

    def __post_init__(self) -> None:
        if not (isinstance(self.rate, (int, float)) and math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate must be a positive finite number, got {self.rate!r}")
        if not (isinstance(self.clock_hz, (int, float)) and math.isfinite(self.clock_hz) and self.clock_hz >= 0):
            raise ValueError(f"clock_hz must be a finite number >= 0, got {self.clock_hz!r}")
        if self.topics is not None:
            if not self.topics:
                raise ValueError("topics must name at least one topic (unset plays all)")
            relative = [t for t in self.topics if not t.startswith("/")]
            if relative:
                raise ValueError(f"topics are named as in the bag (absolute, e.g. /hand/object_pose), got {relative}")


def offered_qos(profiles: list[Any]) -> QoSProfile:
    """rclpy's QoS for a bag connection's offered QoS (rosbags ``Qos`` list); ROS's default when none."""
    if not profiles:
        return DEFAULT_QOS
    offered = profiles[0]
    keep_all = offered.history == QosHistory.KEEP_ALL
    return QoSProfile(
        reliability=ReliabilityPolicy.BEST_EFFORT if offered.reliability == QosReliability.BEST_EFFORT
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if offered.durability == QosDurability.TRANSIENT_LOCAL
        else DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        depth=max(int(offered.depth), 1) if not keep_all and offered.depth > 0 else DEFAULT_QOS.depth,
    )


class BagPlayer(Node):
    """Plays one bag; see the module docstring."""

    params_class = PlayerParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("bag_player", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        p = self.params
        self.log = self.get_logger()
        self.published = 0
        """Messages published so far (over all loops)."""
        self.loops = 0
        """Completed passes through the bag."""
        self._reader = open_bag(p.bag)
        try:
            self._connections = self._select(Path(p.bag))
            self.topic_publishers = {}
            """Publisher by bag topic."""
            unplayable: dict[str, str] = {}
            for conn in self._connections:
                if conn.topic not in self.topic_publishers and conn.topic not in unplayable:
                    try:
                        msg_class = rclpy_class(conn.msgtype)
                    except (ImportError, AttributeError, ValueError):
                        if p.topics is not None:  # asked for by name: refused
                            raise BagError(p.bag, f"topic {conn.topic} has type {conn.msgtype}, "
                                                  "whose message package is not installed here") from None
                        unplayable[conn.topic] = conn.msgtype
                        continue
                    self.topic_publishers[conn.topic] = self.create_publisher(
                        msg_class, conn.topic, offered_qos(conn.ext.offered_qos_profiles))
            self._connections = self._playable(Path(p.bag), unplayable)
        except Exception:
            self._reader.close()
            raise
        self.first_log_ns = self._reader.start_time if self._reader.message_count else 0
        self._cond = threading.Condition()
        self._timeline = Timeline(self.first_log_ns, p.rate, paused=p.start_paused)
        self._stop = False
        self._finished = False
        self._closed = False
        self._clock_pub = None
        if p.clock_hz > 0:
            self._clock_pub = self.create_publisher(Clock, names.CLOCK, 10)
            # its own group: /clock keeps its pace whatever else the node's callbacks do
            self.create_timer(1.0 / p.clock_hz, self._publish_clock, callback_group=ReentrantCallbackGroup(),
                              clock=RosClock(clock_type=ClockType.STEADY_TIME))
        self._thread = threading.Thread(target=self._play, name=f"{self.get_name()}_playback", daemon=True)
        self._thread.start()

    def _select(self, path: Path) -> list[Any]:
        connections = list(self._reader.connections)
        wanted = self.params.topics
        if wanted is None:
            return connections
        present = {c.topic for c in connections}
        missing = sorted(set(wanted) - present)
        if missing:
            raise BagError(path, f"has no topic {', '.join(missing)}; it has {', '.join(sorted(present))}")
        return [c for c in connections if c.topic in wanted]

    def _playable(self, path: Path, unplayable: dict[str, str]) -> list[Any]:
        """The connections left once topics of types not installed here are set aside with a warning, as
        ``ros2 bag play`` ignores them (a ``ros2 bag record -a`` bag holds /tf, and pip's ROS has no tf2_msgs)."""
        if not unplayable:
            return self._connections
        said = ", ".join(f"{topic} ({kind})" for topic, kind in sorted(unplayable.items()))
        left = [c for c in self._connections if c.topic not in unplayable]
        if not left:
            raise BagError(path, f"no topic can be played: the message packages of {said} are not installed here")
        self.log.warning(f"not playing {said}: the message package is not installed here")
        return left

    # ------------------------------------------------------------------ control
    @property
    def params(self) -> PlayerParams:
        return self._params.value

    @property
    def finished(self) -> bool:
        """Every message published (never with ``loop``), or playback failed; the runner then ends."""
        return self._finished

    @property
    def paused(self) -> bool:
        return self._timeline.paused

    def bag_now_ns(self) -> int:
        """The bag time playing now (what ``/clock`` says)."""
        with self._cond:
            return self._timeline.bag_now()

    def pause(self) -> None:
        with self._cond:
            self._timeline.pause()
            self._cond.notify_all()

    def resume(self) -> None:
        """Start or continue; paused time does not count."""
        with self._cond:
            self._timeline.resume()
            self._cond.notify_all()

    def wait_for_subscribers(self, timeout_s: float, settle_s: float = 0.0) -> bool:
        """Wait until every topic has a matched subscriber, or ``timeout_s`` passes; whether all matched.

        Without this the first messages of a playback go to no one: discovery
        takes a moment (seconds between processes) after the publishers are made.
        Each side matches the other on its own, so a subscriber in another process
        may not accept data yet when this side sees it: ``settle_s`` more gives it time.
        """
        deadline = time.monotonic() + timeout_s
        while not all(pub.get_subscription_count() for pub in self.topic_publishers.values()):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        time.sleep(settle_s)
        return True

    def wait_for_acks(self, timeout_s: float) -> bool:
        """Wait until RELIABLE subscribers acknowledged everything published (before the publishers go away)."""
        deadline = time.monotonic() + timeout_s
        return all(pub.wait_for_all_acked(Duration(nanoseconds=max(0, round((deadline - time.monotonic()) * 1e9))))
                   for pub in self.topic_publishers.values())

    def close(self) -> None:
        """Stop publishing and close the bag (the owner destroys the node)."""
        with self._cond:
            if self._closed:
                return
            self._closed = self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=5.0)
        try:
            self._reader.close()
        except Exception as err:  # close() never raises
            self.log.error(f"closing {self.params.bag} failed: {err!r}")

    # ------------------------------------------------------------------ playback
    def _wait_until_due(self, log_ns: int) -> bool:
        """Block until the message logged at ``log_ns`` is due; False when playback stops first."""
        with self._cond:
            while not self._stop:
                delay_ns = self._timeline.due_ns(log_ns) - time.monotonic_ns()
                if delay_ns <= 0:
                    return True
                self._cond.wait(timeout=None if math.isinf(delay_ns) else delay_ns / 1e9)
        return False

    def _play(self) -> None:
        try:
            while self._connections:
                last_ns = None
                for conn, log_ns, data in self._reader.messages(connections=self._connections):
                    if not self._wait_until_due(log_ns):
                        return
                    self.topic_publishers[conn.topic].publish(bytes(data))
                    self.published += 1
                    last_ns = log_ns
                if not self.params.loop or last_ns is None:
                    break
                with self._cond:
                    self.loops += 1  # the next pass's first message follows this pass's last one
                    self._timeline.restart(self.first_log_ns, self._timeline.due_ns(last_ns))
            self.log.info(f"played {self.params.bag}: {self.published} messages")
        except Exception as err:  # a playback thread must not die silently
            self.log.error(f"playback of {self.params.bag} failed: {err!r}")
        finally:
            self._finished = True

    def _publish_clock(self) -> None:
        if self._clock_pub is not None and not self._closed:
            self._clock_pub.publish(Clock(clock=ns_to_stamp(max(self.bag_now_ns(), 0), RCLPY)))

    def _on_params(self, old: PlayerParams, new: PlayerParams) -> None:
        if new.rate != old.rate:
            with self._cond:
                self._timeline.set_rate(new.rate)
                self._cond.notify_all()
            self.log.info(f"rate {old.rate} -> {new.rate}")
