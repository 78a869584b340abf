"""rclpy QoS profiles of the interface's :class:`msg_adapters.names.Qos` (defined there, as data)."""

from __future__ import annotations

from functools import cache

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters.names import Qos


@cache
def profile(qos: Qos) -> QoSProfile:
    """The rclpy profile of ``qos``: KEEP_LAST ``depth``, RELIABLE, TRANSIENT_LOCAL when latched."""
    durability = DurabilityPolicy.TRANSIENT_LOCAL if qos.latched else DurabilityPolicy.VOLATILE
    return QoSProfile(depth=qos.depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=durability)


def recording(depth: int) -> QoSProfile:
    """What a recorder subscribes with: RELIABLE and a deep queue, so bursts are not dropped."""
    return profile(Qos(depth))
