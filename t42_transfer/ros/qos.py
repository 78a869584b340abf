"""QoS profiles with the ROS 2 presets nodes use; backends map them to their own."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class Reliability(str, Enum):
    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class Durability(str, Enum):
    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


class History(str, Enum):
    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"


@dataclass(frozen=True)
class QoSProfile:
    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10

    def __post_init__(self) -> None:
        for field, enum in (("reliability", Reliability), ("durability", Durability), ("history", History)):
            object.__setattr__(self, field, enum(getattr(self, field)))
        if self.history is History.KEEP_LAST and (not isinstance(self.depth, int) or self.depth < 1):
            raise ValueError(f"KEEP_LAST depth must be an int >= 1, got {self.depth!r}")

    def compatible_with(self, requested: "QoSProfile") -> bool:
        """DDS request/offered matching: may this (offered) writer feed a reader asking ``requested``?"""
        reliable_ok = self.reliability is Reliability.RELIABLE or requested.reliability is Reliability.BEST_EFFORT
        durable_ok = (
            self.durability is Durability.TRANSIENT_LOCAL or requested.durability is Durability.VOLATILE
        )
        return reliable_ok and durable_ok


DEFAULT = QoSProfile(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 10)
"""rclcpp/rclpy default: KEEP_LAST 10, RELIABLE, VOLATILE."""
SENSOR_DATA = QoSProfile(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 5)
"""rmw_qos_profile_sensor_data: KEEP_LAST 5, BEST_EFFORT, VOLATILE."""
TRANSIENT_LOCAL = QoSProfile(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)
"""Latched: KEEP_LAST 1, RELIABLE, TRANSIENT_LOCAL (late joiners get the last message)."""
SERVICES_DEFAULT = DEFAULT
"""rmw_qos_profile_services_default equals the default profile."""
CLOCK = QoSProfile(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 1)
"""rclcpp's ClockQoS for ``/clock``: only the latest time matters."""
