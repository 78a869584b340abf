"""diagnostic_msgs <-> plain Python: how nodes report progress on ``/diagnostics``.

A node's status is one ``DiagnosticStatus`` (name, level, message, key-values)
inside a stamped ``DiagnosticArray``, the form ``rqt_robot_monitor`` and the
diagnostic aggregator read.  Key-value values are strings on the wire, so
:func:`diagnostic_array` writes numbers with ``str`` (floats round-trip exactly)
and :func:`status_report` hands back strings for the caller to parse.
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple

from msg_adapters.hand import TYPESTORE, ns_to_stamp

DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTICS_TOPIC = "/diagnostics"

_T = TYPESTORE.types
_Status = _T["diagnostic_msgs/msg/DiagnosticStatus"]
_KeyValue = _T["diagnostic_msgs/msg/KeyValue"]

LEVELS: dict[str, int] = {"OK": _Status.OK, "WARN": _Status.WARN, "ERROR": _Status.ERROR, "STALE": _Status.STALE}
"""``DiagnosticStatus`` level names and their byte values."""


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
) -> Any:
    """A ``DiagnosticArray`` holding one status; ``level`` is a :data:`LEVELS` name, ``values`` become key-values."""
    if level not in LEVELS:
        raise ValueError(f"level must be one of {sorted(LEVELS)}, got {level!r}")
    status = _Status(
        level=LEVELS[level],
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[_KeyValue(key=str(k), value=_text(v)) for k, v in values.items()],
    )
    header = _T["std_msgs/msg/Header"](stamp=ns_to_stamp(stamp_ns), frame_id="")
    return _T[DIAGNOSTIC_ARRAY](header=header, status=[status])


def level_name(level: int) -> str:
    """The :data:`LEVELS` name of a status level byte."""
    for name, value in LEVELS.items():
        if value == int(level):
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
            return DiagnosticReport(level_name(status.level), status.message, {kv.key: kv.value for kv in status.values})
    raise KeyError(f"no diagnostic status named {name!r}")
