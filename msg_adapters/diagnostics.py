"""diagnostic_msgs <-> plain Python: how nodes report progress on ``/diagnostics``.

A node's status is one ``DiagnosticStatus`` (name, level, message, key-values)
inside a stamped ``DiagnosticArray``, the form ``rqt_robot_monitor`` and the
diagnostic aggregator read.  Key-value values are strings on the wire, so
:func:`diagnostic_array` writes numbers with ``str`` (floats round-trip exactly)
and :func:`status_report` hands back strings for the caller to parse.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from msg_adapters.hand import ns_to_stamp
from msg_adapters.kit import ROSBAGS, MessageKit, byte_value

DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

LEVELS: dict[str, int] = {"OK": 0, "WARN": 1, "ERROR": 2, "STALE": 3}
"""``DiagnosticStatus`` level names and their byte values."""
PERIOD_S = 1.0
"""How often a node says its status even when nothing changed (diagnostic_updater's 1 Hz): a monitor started
later, on a topic that keeps no history, still hears a failure within a second."""


def _text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def diagnostic_array(
    name: str,
    level: str,
    message: str,
    values: Mapping[str, object],
    stamp_ns: int,
    hardware_id: str = "",
    kit: MessageKit = ROSBAGS,
) -> Any:
    """A ``DiagnosticArray`` holding one status; ``level`` is a :data:`LEVELS` name, ``values`` become key-values."""
    if level not in LEVELS:
        raise ValueError(f"level must be one of {sorted(LEVELS)}, got {level!r}")
    status = kit.make(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=kit.byte(LEVELS[level]),
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[kit.make("diagnostic_msgs/msg/KeyValue", key=str(k), value=_text(v)) for k, v in values.items()],
    )
    header = kit.make("std_msgs/msg/Header", stamp=ns_to_stamp(stamp_ns, kit), frame_id="")
    return kit.make(DIAGNOSTIC_ARRAY, header=header, status=[status])


def level_name(level: int | bytes) -> str:
    """The :data:`LEVELS` name of a status level byte (an int in rosbags, one-byte ``bytes`` in rclpy)."""
    for name, value in LEVELS.items():
        if value == byte_value(level):
            return name
    raise ValueError(f"unknown diagnostic level {level!r}")


class DiagnosticReport(NamedTuple):
    """One status read back: level name, message and key-values."""

    level: str
    message: str
    values: dict[str, str]


def status_report(array: Any, name: str) -> DiagnosticReport:
    """The status called ``name`` in a ``DiagnosticArray``; KeyError when it holds none (another node's report)."""
    for status in array.status:
        if status.name == name:
            return DiagnosticReport(level_name(status.level), status.message,
                                    {kv.key: kv.value for kv in status.values})
    raise KeyError(f"no diagnostic status named {name!r}")
