"""rclpy QoS profiles of the interface's :class:`msg_adapters.names.Qos` (defined there, as data)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters.names import Qos


def profile(qos: Qos) -> QoSProfile:
    """A new rclpy profile of ``qos``: KEEP_LAST ``depth``, RELIABLE, TRANSIENT_LOCAL when latched.

    New on every call: rclpy's QoS overrides (``qos_overriding_options``) change the profile they are given in
    place, so a shared one would carry one subscription's override to every later user in the process."""
    durability = DurabilityPolicy.TRANSIENT_LOCAL if qos.latched else DurabilityPolicy.VOLATILE
    return QoSProfile(depth=qos.depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=durability)


def recording(depth: int) -> QoSProfile:
    """What a recorder subscribes with: RELIABLE and a deep queue, so bursts are not dropped."""
    return profile(Qos(depth))
