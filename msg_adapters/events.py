"""Recorder events <-> plain Python: ``t42_interfaces/msg/BagClosed`` (``recorder/bag_closed``).

A closed bag is described by :class:`BagClosedEvent` (its path, episodes, messages, the log times of its first
and last message in ns, and why it was closed); :func:`bag_closed_msg` builds the message (rclpy's class: the
type comes from ``t42_interfaces``, which rosbags' Jazzy typestore does not hold) and :func:`bag_closed_event`
reads one back.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from msg_adapters.hand import ns_to_stamp, stamp_to_ns
from msg_adapters.kit import RCLPY, MessageKit

BAG_CLOSED_MSG = "t42_interfaces/msg/BagClosed"

STOP = "stop"
"""The reason of the bag a ``~/stop`` closed: the last bag of a recording."""
WRITE_FAILED = "write_failed"
"""The reason of a bag closed because writing to it failed (a full disk) and its summary could still be written."""
SHUTDOWN = "shutdown"
"""The reason of the bag open when the recorder closed (the node shut down)."""
SNAPSHOT = "snapshot"
"""The reason of a snapshot bag (the last seconds kept in memory, written on a trigger): its steps may be in the
continuous bags too, so a reader that collects training data skips it."""


class BagClosedEvent(NamedTuple):
    """A bag the recorder closed and finalised (``metadata.yaml`` written)."""

    path: str
    episodes: int
    """Episodes in it as :func:`t42_transfer.data.bag.read_bag` reads them (0 when it reads none)."""
    messages: int
    start_ns: int
    """Log time (receive time) of its first message; 0 for a bag that holds none."""
    end_ns: int
    """Log time of its last message."""
    reason: str
    """``stop``, ``split`` (a service), the ``hand/status`` word that split it in episode mode (``reset``,
    ``dropped``...), :data:`WRITE_FAILED`, :data:`SHUTDOWN` or :data:`SNAPSHOT`."""


def bag_closed_msg(event: BagClosedEvent, kit: MessageKit = RCLPY) -> Any:
    """The ``BagClosed`` message of ``event``; ValueError for a negative count or a stamp out of range."""
    if event.episodes < 0 or event.messages < 0:
        raise ValueError(f"counts must be non-negative, got {event.episodes} episodes, {event.messages} messages")
    if event.episodes >= 2**32:
        raise ValueError(f"episodes {event.episodes} does not fit a uint32")
    return kit.make(BAG_CLOSED_MSG, path=str(event.path), episodes=int(event.episodes), messages=int(event.messages),
                    start=ns_to_stamp(event.start_ns, kit), end=ns_to_stamp(event.end_ns, kit),
                    reason=str(event.reason))


def bag_closed_event(msg: Any) -> BagClosedEvent:
    """The :class:`BagClosedEvent` a ``BagClosed`` message carries."""
    return BagClosedEvent(str(msg.path), int(msg.episodes), int(msg.messages), stamp_to_ns(msg.start),
                          stamp_to_ns(msg.end), str(msg.reason))
