"""Where a bag keeps the hand's topics: by name under one namespace, or as its recorder wrote them down.

The hand's topics are known by their names (``/hand/object_pose``, ``/left/hand/object_pose``). A recorder
whose topics were remapped (``-r hand/object_pose:=pose``) records them under other names, which no suffix
finds, so it writes down in the bag's custom data (:data:`HAND_TOPICS_KEY`) which recorded topic holds each
hand topic, and a reader takes that over the names.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path

import msg_adapters as ma
from t42_transfer.data.errors import BagError

HAND_TOPICS_KEY = "t42_transfer.hand_topics"
"""Custom-data key: JSON ``{hand topic: recorded topic}``, e.g. ``{"/hand/object_pose": "/pose", ...}``."""
HAND_ROLES = (*ma.HAND_TOPICS, ma.HAND_STATUS_TOPIC)
"""The hand topics a bag may hold, each under its own name at the root: the keys of the mapping."""
_MAX_NAME_CHARS = 256


def hand_namespace(path: str | Path, topics: Iterable[str]) -> str:
    """The one namespace the hand topics among ``topics`` lie under ("" for the root); BagError for several.

    A hand topic is found by suffix: ``/hand/object_pose`` or ``<ns>/hand/object_pose``.
    """
    found: dict[str, list[str]] = {}
    for name in topics:
        for hand in ma.HAND_TOPICS:
            if name.endswith(hand):
                found.setdefault(name[: -len(hand)], []).append(name)
    if len(found) > 1:
        listed = "; ".join(f"{ns or '/'} ({', '.join(sorted(names))})" for ns, names in sorted(found.items()))
        raise BagError(path, f"holds hand topics under {len(found)} namespaces: {listed}; "
                             "a bag must hold one hand's topics (filter it to one namespace)")
    return next(iter(found), "")


def recorded_topics_custom(resolved: Mapping[str, str]) -> dict[str, str]:
    """Custom data for a bag whose hand topics were recorded as ``resolved`` (hand topic -> recorded name)."""
    unknown = sorted(set(resolved) - set(HAND_ROLES))
    if unknown:
        raise ValueError(f"not hand topics: {', '.join(unknown)} (hand topics: {', '.join(HAND_ROLES)})")
    return {HAND_TOPICS_KEY: json.dumps(dict(sorted(resolved.items())))}


def written_names(custom: Mapping[str, str]) -> set[str]:
    """The recorded names a bag's custom data gives its hand topics (none if it gives none, or is unreadable):
    what a loader keeps messages of besides the names found by suffix."""
    try:
        mapping = json.loads(custom.get(HAND_TOPICS_KEY, "{}"))
    except ValueError:
        return set()
    return {v for v in mapping.values() if isinstance(v, str)} if isinstance(mapping, dict) else set()


def hand_topic_names(path: str | Path, custom: Mapping[str, str], topics: Iterable[str]) -> dict[str, str]:
    """Hand topic -> the name a bag holds it under: as its custom data writes it down, else found by suffix."""
    text = custom.get(HAND_TOPICS_KEY)
    if text is None:
        namespace = hand_namespace(path, topics)
        return {role: namespace + role for role in HAND_ROLES}
    where = f"its custom data {HAND_TOPICS_KEY}"
    try:
        mapping = json.loads(text)
    except ValueError as err:
        raise BagError(path, f"{where} is not JSON ({err})") from None
    if not isinstance(mapping, dict):
        raise BagError(path, f"{where} must map hand topics to recorded topics, got {type(mapping).__name__}")
    unknown = sorted(str(k) for k in mapping if k not in HAND_ROLES)
    if unknown:
        raise BagError(path, f"{where} names {', '.join(unknown)}, not hand topics ({', '.join(HAND_ROLES)})")
    for role, name in mapping.items():
        if not (isinstance(name, str) and name.startswith("/") and len(name) <= _MAX_NAME_CHARS):
            raise BagError(path, f"{where} gives {role} the name {str(name)[:80]!r}: a topic name must start with "
                                 f"'/' and be at most {_MAX_NAME_CHARS} characters")
    missing = [role for role in ma.HAND_TOPICS if role not in mapping]
    if missing:
        raise BagError(path, f"{where} gives no name for {', '.join(missing)}")
    shared = {name: sorted(r for r, n in mapping.items() if n == name) for name in set(mapping.values())}
    for name, roles in sorted(shared.items()):
        if len(roles) > 1:
            raise BagError(path, f"{where} gives {' and '.join(roles)} the same topic {name}: one topic holds one")
    return {role: mapping.get(role, role) for role in HAND_ROLES}
