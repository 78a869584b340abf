"""Full ROS 2 message definitions (``ros2msg``: the type's fields, then each type it uses after a ``MSG:`` line),
as the recorder's bags hold them in MCAP schemas and Foxglove reads them.

The Jazzy typestore of rosbags defines the standard messages, the same text the bag writer stores; a type it lacks
(``t42_interfaces/msg/...``) is read from the ``share/<package>/msg/<Name>.msg`` (an action's messages from
``share/<package>/action/<Name>.action``) of an install prefix
(``AMENT_PREFIX_PATH``, then this Python's prefix: the venv where the bootstrap builds the interfaces) and added to
a private copy of the store.
"""

from __future__ import annotations

import os
import re
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


def _share_file(package: str, kind: str, filename: str) -> Path | None:
    for prefix in _prefixes():
        path = prefix / "share" / package / kind / filename
        if path.is_file():
            return path
    return None


_ACTION_SECTIONS = {"Goal": 0, "Result": 1, "Feedback": 2}


def _definition_text(typename: str) -> str | None:
    """The ``.msg`` text of ``pkg/msg/Name``: its file, or for an action's message (``Name_Feedback``,
    ``Name_FeedbackMessage``...: rosbags writes nested names as ``pkg/msg/...``) the section of ``Name.action``, or
    the message its feedback topic carries."""
    package, _, name = typename.split("/")
    path = _share_file(package, "msg", f"{name}.msg")
    if path is not None:
        return path.read_text()
    action, _, part = name.rpartition("_")
    path = _share_file(package, "action", f"{action}.action") if action else None
    if path is None:
        return None
    if part == "FeedbackMessage":
        return f"unique_identifier_msgs/UUID goal_id\n{package}/msg/{action}_Feedback feedback\n"
    sections = re.split(r"^---[ \t]*$", path.read_text(), flags=re.M)
    return sections[_ACTION_SECTIONS[part]] if part in _ACTION_SECTIONS and len(sections) == 3 else None


def _register(typename: str, seen: set[str]) -> None:
    """Add ``typename`` and the unknown types its fields use to the private store; KeyError when a file is missing."""
    if typename in _EXTRA.types or typename in seen:
        return
    seen.add(typename)
    text = _definition_text(typename)
    if text is None:
        raise KeyError(f"no definition of {typename} (not a Jazzy message, nor in share/<package>/ under "
                       "AMENT_PREFIX_PATH or this Python's prefix)")
    types = get_types_from_msg(text, typename)
    for _, fields in (v[:2] for v in types.values()):
        for _, desc in fields:
            for nested in _nested_names(desc):
                _register(nested, seen)
    _EXTRA.register(types)


def _nested_names(desc: object) -> list[str]:
    """Message type names inside a rosbags field description (a NAME node's ``package/msg/Type``, inside arrays too)."""
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
    """The full ``ros2msg`` definition of ``pkg/msg/Name`` (or an action topic's ``pkg/action/Name_...``); KeyError
    when no definition is known here."""
    if typename in TYPESTORE.types:
        return TYPESTORE.generate_msgdef(typename, ros_version=2)[0]
    package, _, name = typename.split("/")
    as_msg = f"{package}/msg/{name}"  # an action's messages too: the text names types only after "MSG:" lines
    _register(as_msg, set())
    return _EXTRA.generate_msgdef(as_msg, ros_version=2)[0]
