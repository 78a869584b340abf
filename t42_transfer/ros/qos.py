"""The QoS profiles the nodes use beyond rclpy's default (KEEP_LAST 10, RELIABLE, VOLATILE)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""A late joiner still gets the last message (driver status, model announcements, plan results)."""


def recording(depth: int) -> QoSProfile:
    """What a recorder subscribes with: RELIABLE and a deep queue, so bursts are not dropped."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
