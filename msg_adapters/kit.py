"""Which message classes the builders make: rosbags' Jazzy typestore or rclpy's generated ones.

Both sides have the same fields, so every reader in :mod:`msg_adapters` takes
either; builders take a ``kit`` saying which to build.  The bag layer builds
rosbags objects (:data:`ROSBAGS`, no ROS runtime needed), nodes build rclpy
objects (:data:`RCLPY`).  The two differ only in how a primitive sequence and a
``byte`` are held (numpy arrays and ints in rosbags; ``array.array`` and
one-byte ``bytes`` in rclpy), which :meth:`MessageKit.floats` and
:meth:`MessageKit.byte` hide.
"""

from __future__ import annotations

import array
import importlib
from abc import ABC, abstractmethod
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from msg_adapters.interfaces import register_interfaces

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
"""rosbags' Jazzy typestore and the suite's own messages (``t42_interfaces/msg/...``,
:mod:`msg_adapters.interfaces`): what bags are read into and written from."""
INTERFACE_TYPES = register_interfaces(TYPESTORE)
"""The ``t42_interfaces`` message types :data:`TYPESTORE` holds (empty when their files were not found)."""


class MessageKit(ABC):
    """Makes message objects of one family by ROS type name (``geometry_msgs/msg/PoseStamped``)."""

    @abstractmethod
    def cls(self, typename: str) -> type: ...

    @abstractmethod
    def floats(self, values: np.ndarray) -> Any:
        """A float64 sequence field's value."""

    @abstractmethod
    def byte(self, value: int) -> Any:
        """A ``byte`` field's value."""

    def make(self, typename: str, **fields: Any) -> Any:
        return self.cls(typename)(**fields)


class RosbagsKit(MessageKit):
    def cls(self, typename: str) -> type:
        return TYPESTORE.types[typename]

    def floats(self, values: np.ndarray) -> Any:
        return np.ascontiguousarray(values, dtype=np.float64)

    def byte(self, value: int) -> Any:
        return int(value)


class RclpyKit(MessageKit):
    def cls(self, typename: str) -> type:
        return rclpy_class(typename)

    def floats(self, values: np.ndarray) -> Any:
        return array.array("d", np.ascontiguousarray(values, dtype=np.float64).tobytes())

    def byte(self, value: int) -> Any:
        return bytes([int(value)])


@cache
def rclpy_class(typename: str) -> type:
    """rclpy's generated class of ``pkg/msg/Name`` or ``pkg/srv/Name`` (imported on first use), or of an action's
    message as its topics name it (``pkg/action/Name_FeedbackMessage``: ``Name.Impl.FeedbackMessage``)."""
    package, kind, name = typename.split("/")
    module = importlib.import_module(f"{package}.{kind}")
    if kind == "action" and not hasattr(module, name) and "_" in name:
        action, _, part = name.rpartition("_")
        return getattr(getattr(module, action).Impl, part)
    return getattr(module, name)


def rclpy_message(data: bytes, typename: str, max_bytes: int) -> Any:
    """The rclpy message of a raw subscription's CDR ``data``; ValueError, unread, when it is over ``max_bytes``
    (deserializing a million-point trajectory held a driver for 15 s) or is no ``typename``."""
    if len(data) > max_bytes:
        raise ValueError(f"{len(data)} bytes, over the {max_bytes} any such message needs: refused unread")
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(data, rclpy_class(typename))
    except Exception as err:  # rclpy raises a bare RuntimeError-like error for bad CDR
        raise ValueError(f"not a {typename} ({type(err).__name__}: {err})") from None


def message_fields(msg: Any) -> Any:
    """An rclpy message as plain data (dicts by field, lists, numbers, strings): what ``ros2 topic echo`` prints,
    for YAML or JSON."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: message_fields(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (bytes, bytearray)):
        return list(msg)
    if isinstance(msg, (list, tuple, array.array, np.ndarray)):
        return [message_fields(v) for v in (msg.tolist() if isinstance(msg, (array.array, np.ndarray)) else msg)]
    if isinstance(msg, np.generic):
        return msg.item()
    return msg


def message_from_fields(cls: type, data: Any, where: str = "") -> Any:
    """An rclpy message of ``cls`` from plain data (as :func:`message_fields` gives it, or YAML): unset fields keep
    their defaults; ValueError naming the field for an unknown field or a value of the wrong type."""
    msg = cls()
    if data is None:
        return msg
    fields = cls.get_fields_and_field_types()
    if not isinstance(data, dict):
        raise ValueError(f"{where or cls.__name__}: expected a mapping of {', '.join(fields)}, got {data!r}")
    for name, value in data.items():
        at = f"{where}.{name}" if where else str(name)
        if name not in fields:
            raise ValueError(f"{at}: no such field (it has {', '.join(fields) or 'none'})")
        kind = fields[name]
        element, many = _message_type(kind), kind.startswith("sequence<") or kind.endswith("]")
        try:
            if element is None:
                inner = kind.removeprefix("sequence<").split(">")[0].split(",")[0].split("[")[0]
                if many and not isinstance(value, list):
                    raise ValueError(f"{at}: expected a list, got {value!r}")
                setattr(msg, name, [_primitive(inner, v, f"{at}[{k}]") for k, v in enumerate(value)] if many
                        else _primitive(inner, value, at))
            elif many:
                if not isinstance(value, list):
                    raise ValueError(f"{at}: expected a list, got {value!r}")
                setattr(msg, name, [message_from_fields(element, v, f"{at}[{k}]") for k, v in enumerate(value)])
            else:
                setattr(msg, name, message_from_fields(element, value, at))
        except (AssertionError, TypeError) as err:  # rclpy's setters check types with asserts
            raise ValueError(f"{at}: {value!r} is no {fields[name]} ({err or 'wrong type'})") from None
    return msg


INTEGER_RANGES = {
    **{f"int{bits}": (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) for bits in (8, 16, 32, 64)},
    **{f"uint{bits}": (0, 2 ** bits - 1) for bits in (8, 16, 32, 64)},
    "octet": (0, 255), "char": (0, 255),
}
"""[low, high] of each integer field type, as ``get_fields_and_field_types`` names it."""


def _primitive(kind: str, value: Any, at: str) -> Any:
    """``value`` checked against a primitive field type (rclpy's own checks are off by default in Jazzy, and
    serialization says only "bad argument type"; an integer out of its type's range was sent wrapped, 300 as a
    uint8's 44, or failed unnamed); a whole number for a float or double as a float."""
    base = kind.split("<=")[0]
    whole = isinstance(value, int) and not isinstance(value, bool)
    if base in ("string", "wstring"):
        ok = isinstance(value, str)
    elif base == "boolean":
        ok = isinstance(value, bool)
    elif base in ("float", "double"):
        ok, value = whole or isinstance(value, float), float(value) if whole else value
    else:  # the integer types, byte, char, octet
        ok = whole
    if not ok:
        raise ValueError(f"{at}: {value!r} is no {kind}")
    low, high = INTEGER_RANGES.get(base, (None, None))
    if low is not None and not low <= value <= high:
        raise ValueError(f"{at}: {value} is out of range for {base} [{low}, {high}]")
    return value


def _message_type(field_type: str) -> type | None:
    """The message class of a field's (element) type, ``sequence<pkg/Name, 5>`` or ``pkg/Name[3]`` included;
    None for a primitive."""
    inner = field_type.removeprefix("sequence<").split(">")[0].split(",")[0].split("[")[0]
    if "/" not in inner:
        return None
    package, name = inner.split("/")
    return rclpy_class(f"{package}/msg/{name}")


def byte_value(value: Any) -> int:
    """A ``byte`` field as an int, from either family."""
    return value[0] if isinstance(value, (bytes, bytearray)) else int(value)


ROSBAGS: MessageKit = RosbagsKit()
RCLPY: MessageKit = RclpyKit()
