"""The QoS profiles the nodes use beyond rclpy's default (KEEP_LAST 10, RELIABLE, VOLATILE)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""A late joiner still gets the last message (driver status, model announcements, plan results)."""


EVENTS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""A stream of events (``hand/status``): none may be lost in a burst, which a depth of 1 allows (a
reliable KEEP_LAST 1 writer replaces an unacknowledged sample), and a late joiner gets the recent ones."""

EVENT_READER = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
"""Reading events as they happen: deep, so none is lost in a burst; VOLATILE, so it matches any reliable
writer (a TRANSIENT_LOCAL reader would not match a real driver that publishes its status VOLATILE)."""


def recording(depth: int) -> QoSProfile:
    """What a recorder subscribes with: RELIABLE and a deep queue, so bursts are not dropped."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
