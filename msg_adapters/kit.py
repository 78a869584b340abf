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


def byte_value(value: Any) -> int:
    """A ``byte`` field as an int, from either family."""
    return value[0] if isinstance(value, (bytes, bytearray)) else int(value)


ROSBAGS: MessageKit = RosbagsKit()
RCLPY: MessageKit = RclpyKit()
