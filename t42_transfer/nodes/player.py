"""Bag player node: a rosbag2 bag's messages back onto their topics, like ``ros2 bag play``.

Each message goes out as the CDR bytes stored in the bag (``publish_raw``), on its
topic with its type, at its log-time offset from the bag's first message divided by
``rate``.  Timing runs on the transport's clock and timers, so the same code plays
in real time over Cyclone DDS and deterministically on the in-process bus with a
:class:`~t42_transfer.ros.inprocess.FakeClock`: a message is published on the first
timer tick (every ``tick_s``) at or after its due time.  Each topic's publisher
offers the QoS the bag recorded for it (reliability, durability, history, depth),
else ROS's default, unless ``params.qos`` names one.

Messages are read lazily through rosbags, so memory does not grow with the bag.
A bag without ``metadata.yaml`` or with a cut-off MCAP (a killed recorder) is
refused: ``t42 bag repair`` makes it playable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosHistory, QosReliability

from t42_transfer.data.errors import BagError
from t42_transfer.ros import qos as ros_qos
from t42_transfer.ros.naming import validate_name
from t42_transfer.ros.transport import Publisher, Transport


@dataclass(frozen=True)
class PlayerParams:
    """Parameters of :class:`BagPlayer`."""

    bag: str | Path
    """Bag directory (rosbag2, MCAP or sqlite3) to play."""
    rate: float = 1.0
    """Playback speed factor: 2.0 plays twice as fast."""
    loop: bool = False
    """Start again from the first message after the last (never done)."""
    start_paused: bool = False
    """Publish nothing until :meth:`BagPlayer.resume`."""
    topics: tuple[str, ...] | None = None
    """Play only these topics (all when None); each must be in the bag."""
    qos: Mapping[str, ros_qos.QoSProfile] = field(default_factory=dict)
    """Publisher QoS per topic, overriding what the bag recorded."""
    tick_s: float = 0.001
    """Timer period: the timing resolution of playback."""

    def __post_init__(self) -> None:
        if not (isinstance(self.rate, (int, float)) and self.rate > 0 and self.rate != float("inf")):
            raise ValueError(f"rate must be a positive finite number, got {self.rate!r}")
        if not self.tick_s > 0:
            raise ValueError(f"tick_s must be positive, got {self.tick_s!r}")
        if self.topics is not None:
            object.__setattr__(self, "topics", tuple(self.topics))
            for topic in self.topics:
                validate_name(topic)
        object.__setattr__(self, "qos", dict(self.qos))


def offered_qos(profiles: list[Any]) -> ros_qos.QoSProfile:
    """Our QoS profile for a bag connection's offered QoS (rosbags ``Qos`` list); DEFAULT when none."""
    if not profiles:
        return ros_qos.DEFAULT
    offered = profiles[0]
    keep_all = offered.history == QosHistory.KEEP_ALL
    return ros_qos.QoSProfile(
        ros_qos.Reliability.BEST_EFFORT if offered.reliability == QosReliability.BEST_EFFORT
        else ros_qos.Reliability.RELIABLE,
        ros_qos.Durability.TRANSIENT_LOCAL if offered.durability == QosDurability.TRANSIENT_LOCAL
        else ros_qos.Durability.VOLATILE,
        ros_qos.History.KEEP_ALL if keep_all else ros_qos.History.KEEP_LAST,
        max(int(offered.depth), 1) if not keep_all and offered.depth > 0 else ros_qos.DEFAULT.depth,
    )


class BagPlayer:
    """Plays one bag on ``transport``; see the module docstring."""

    def __init__(self, transport: Transport, params: PlayerParams) -> None:
        self.transport, self.params = transport, params
        self.published = 0
        """Messages published so far (over all loops)."""
        self.loops = 0
        """Completed passes through the bag."""
        path = Path(params.bag)
        if not path.exists():
            raise BagError(path, "does not exist")
        try:
            self._reader = AnyReader([path])
            self._reader.open()
        except Exception as err:  # rosbags raises many types for what is not a sound bag
            raise BagError(path, f"cannot be played ({type(err).__name__}: {err}); "
                                 "a bag left by a killed recorder needs `t42 bag repair` first") from None
        try:
            self._connections = self._select(path)
            self.publishers: dict[str, Publisher] = {}
            for conn in self._connections:
                if conn.topic not in self.publishers:
                    qos = params.qos.get(conn.topic) or offered_qos(conn.ext.offered_qos_profiles)
                    self.publishers[conn.topic] = transport.publisher(conn.topic, conn.msgtype, qos)
        except Exception:
            self._reader.close()
            raise
        self.first_log_ns = self._reader.start_time if self._reader.message_count else 0
        self._messages: Iterator[tuple[Any, int, bytes]] = iter(())
        self._next: tuple[Any, int, bytes] | None = None
        self._base_ns: int | None = None
        """Transport time at which the bag's first message is due (None until started)."""
        self._paused_at_ns: int | None = transport.now_ns() if params.start_paused else None
        self._closed = False
        self._restart()
        self._timer = transport.timer(params.tick_s, self._tick)
        if not params.start_paused:
            self._base_ns = transport.now_ns()

    def _select(self, path: Path) -> list[Any]:
        connections = list(self._reader.connections)
        if self.params.topics is None:
            return connections
        present = {c.topic for c in connections}
        missing = sorted(set(self.params.topics) - present)
        if missing:
            raise BagError(path, f"has no topic {', '.join(missing)}; it has {', '.join(sorted(present))}")
        return [c for c in connections if c.topic in self.params.topics]

    def _restart(self) -> None:
        self._messages = iter(self._reader.messages(connections=self._connections)) \
            if self._connections else iter(())
        self._next = next(self._messages, None)

    # ------------------------------------------------------------------ control
    @property
    def done(self) -> bool:
        """Every message published (never for ``loop``)."""
        return self._next is None

    @property
    def paused(self) -> bool:
        return self._paused_at_ns is not None

    def pause(self) -> None:
        if self._paused_at_ns is None:
            self._paused_at_ns = self.transport.now_ns()

    def resume(self) -> None:
        """Start or continue; paused time does not count."""
        if self._paused_at_ns is None:
            return
        now = self.transport.now_ns()
        self._base_ns = now if self._base_ns is None else self._base_ns + now - self._paused_at_ns
        self._paused_at_ns = None

    def close(self) -> None:
        """Stop publishing and close the bag (the transport's owner closes the transport)."""
        if not self._closed:
            self._closed = True
            self._timer.cancel()
            self._reader.close()

    # ------------------------------------------------------------------ playback
    def due_ns(self, log_ns: int) -> int:
        """Transport time at which the message logged at ``log_ns`` goes out (``resume``/start set the base)."""
        assert self._base_ns is not None
        return self._base_ns + round((log_ns - self.first_log_ns) / self.params.rate)

    def _tick(self) -> None:
        if self.paused or self._closed:
            return
        now = self.transport.now_ns()
        while self._next is not None:
            conn, log_ns, data = self._next
            if self.due_ns(log_ns) > now:
                return
            self.publishers[conn.topic].publish_raw(data)
            self.published += 1
            self._next = next(self._messages, None)
            if self._next is None and self.params.loop and self.published:
                self.loops += 1
                self._base_ns = self.due_ns(log_ns)  # the next pass's first message follows this last one
                self._restart()
                return  # the next pass starts on the next tick, so a zero-length bag cannot spin here
        self.close()


def matched_subscribers(publisher: Publisher) -> int | None:
    """Readers matched to ``publisher`` (Cyclone DDS writer or rclpy publisher); None where the backend cannot tell."""
    writer = getattr(publisher, "writer", None)  # CyclonePublisher's DataWriter
    if writer is not None and hasattr(writer, "get_matched_subscriptions"):
        return len(writer.get_matched_subscriptions())
    pub = getattr(publisher, "pub", None)  # RclpyPublisher's rclpy Publisher
    if pub is not None and hasattr(pub, "get_subscription_count"):
        return int(pub.get_subscription_count())
    return None


def wait_for_subscribers(player: BagPlayer, timeout_s: float) -> bool:
    """Spin until every topic of ``player`` has a matched reader, or ``timeout_s`` passes; whether all matched.

    Without this the first messages of a DDS playback go to no one: discovery
    takes a moment after the writers are created.  A backend that cannot count
    readers returns at once (False).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        counts = [matched_subscribers(p) for p in player.publishers.values()]
        if None in counts:
            return False
        if all(counts):
            return True
        if time.monotonic() >= deadline:
            return False
        player.transport.spin_once(0.02)


def play_bag(transport: Transport, bag: str | Path, rate: float = 1.0, timeout_s: float | None = None) -> int:
    """Play ``bag`` once on ``transport`` at ``rate``, spinning until done; returns the messages published."""
    player = BagPlayer(transport, PlayerParams(bag, rate))
    try:
        if not transport.spin(until=lambda: player.done, timeout_s=timeout_s):
            raise TimeoutError(f"playing {bag} did not finish within {timeout_s} s")
    finally:
        player.close()
    return player.published
