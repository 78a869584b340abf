"""Full ROS 2 message definitions (``ros2msg``: the type's fields, then each type it uses after a ``MSG:`` line),
as the recorder's bags hold them in MCAP schemas and Foxglove reads them.

:data:`msg_adapters.TYPESTORE` defines the standard messages and the suite's own (:mod:`msg_adapters.interfaces`),
the same text the bag writer stores.  The messages an action's topics carry (``t42/reach/_action/feedback``:
``t42_interfaces/action/Reach_FeedbackMessage``) are built from the package's ``.action`` file (beside the
``msg`` folder :mod:`msg_adapters.interfaces` reads) in a private copy of the store; their nested types are named
``package/msg/...`` in the text, as rosbags writes every nested name.
"""

from __future__ import annotations

import re
from functools import cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from msg_adapters.interfaces import msg_dir, register_interfaces
from msg_adapters.kit import TYPESTORE

_ACTIONS = get_typestore(Stores.ROS2_JAZZY)
"""The Jazzy store, the suite's messages and the action messages asked for so far."""
_ACTIONS_READY: list[bool] = []
_SECTIONS = {"Goal": 0, "Result": 1, "Feedback": 2}


def _action_text(package: str, action: str, part: str) -> str | None:
    """The ``.msg`` text of ``<action>_<part>``: a section of ``<action>.action`` or, for ``FeedbackMessage``, the
    message of the action's feedback topic; None when there is no such file or part."""
    folder = msg_dir(package)
    path = None if folder is None else folder.parent / "action" / f"{action}.action"
    if path is None or not path.is_file():
        return None
    if part == "FeedbackMessage":
        return f"unique_identifier_msgs/UUID goal_id\n{package}/msg/{action}_Feedback feedback\n"
    sections = re.split(r"^---[ \t]*$", path.read_text(), flags=re.M)
    return sections[_SECTIONS[part]] if part in _SECTIONS and len(sections) == 3 else None


def _register_action_message(package: str, name: str) -> str:
    """Put ``<package>/action/<name>`` (and the section its feedback message uses) into the private store as
    ``<package>/msg/<name>``; that name.  KeyError when no definition is found."""
    if not _ACTIONS_READY:
        register_interfaces(_ACTIONS, package)
        _ACTIONS_READY.append(True)
    action, _, part = name.rpartition("_")
    parts = [f"{action}_Feedback", name] if part == "FeedbackMessage" else [name]
    for each in parts:
        typename = f"{package}/msg/{each}"
        if typename in _ACTIONS.types:
            continue
        text = _action_text(package, action, each.rpartition("_")[2]) if action else None
        if text is None:
            raise KeyError(f"no definition of {package}/action/{name} (not a Jazzy message, nor in an installed "
                           f"{package}'s msg or action files)")
        _ACTIONS.register(get_types_from_msg(text, typename))
    return f"{package}/msg/{name}"


@cache
def message_definition(typename: str) -> str:
    """The full ``ros2msg`` definition of ``pkg/msg/Name`` (or an action topic's ``pkg/action/Name_...``); KeyError
    when no definition is known here."""
    if typename in TYPESTORE.types:
        return TYPESTORE.generate_msgdef(typename, ros_version=2)[0]
    package, kind, name = typename.split("/")
    if kind != "action":
        raise KeyError(f"no definition of {typename} (not a Jazzy message, nor one of the suite's)")
    return _ACTIONS.generate_msgdef(_register_action_message(package, name), ros_version=2)[0]
