"""Full ROS 2 message definitions (``ros2msg``: the type's fields, then each type it uses after a ``MSG:`` line),
as the recorder's bags hold them in MCAP schemas and Foxglove reads them.

The Jazzy typestore of rosbags defines the standard messages, the same text the bag writer stores; a type it lacks
(``t42_interfaces/msg/...``) is read from the ``share/<package>/msg/<Name>.msg`` of an install prefix
(``AMENT_PREFIX_PATH``, then this Python's prefix: the venv where the bootstrap builds the interfaces) and added to
a private copy of the store.
"""

from __future__ import annotations

import os
import sys
from functools import cache
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from msg_adapters.kit import TYPESTORE

_EXTRA = get_typestore(Stores.ROS2_JAZZY)
"""The Jazzy store plus the installed interface packages' types, as they are asked for."""


def _prefixes() -> list[Path]:
    listed = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return [*listed, Path(sys.prefix)]


def _msg_file(typename: str) -> Path | None:
    package, kind, name = typename.split("/")
    for prefix in _prefixes():
        path = prefix / "share" / package / kind / f"{name}.msg"
        if path.is_file():
            return path
    return None


def _register(typename: str, seen: set[str]) -> None:
    """Add ``typename`` and the unknown types its fields use to the private store; KeyError when a file is missing."""
    if typename in _EXTRA.types or typename in seen:
        return
    seen.add(typename)
    path = _msg_file(typename)
    if path is None:
        raise KeyError(f"no definition of {typename} (not a Jazzy message, no share/.../{typename.split('/')[-1]}.msg "
                       "in AMENT_PREFIX_PATH or this Python's prefix)")
    types = get_types_from_msg(path.read_text(), typename)
    for _, fields in (v[:2] for v in types.values()):
        for _, desc in fields:
            for nested in _nested_names(desc):
                _register(nested, seen)
    _EXTRA.register(types)


def _nested_names(desc: object) -> list[str]:
    """Message type names inside a rosbags field description (``(Nodetype.NAME, 'pkg/msg/T')``, arrays of them)."""
    found: list[str] = []
    if isinstance(desc, tuple):
        for part in desc:
            if isinstance(part, str) and part.count("/") == 2:
                found.append(part)
            else:
                found.extend(_nested_names(part))
    return found


@cache
def message_definition(typename: str) -> str:
    """The full ``ros2msg`` definition of ``pkg/msg/Name``; KeyError when no definition is known here."""
    if typename in TYPESTORE.types:
        return TYPESTORE.generate_msgdef(typename)[0]
    _register(typename, set())
    return _EXTRA.generate_msgdef(typename)[0]
