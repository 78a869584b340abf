"""Reading a YAML file the user names (experiment configs, ROS params files) without trusting it.

Only a regular file is read: a FIFO or a device would block ``open()`` or never end, so
the file is opened non-blocking and checked with ``fstat`` before a byte is read (no race
with a swap between check and open).  Configs are small; a file over :data:`MAX_BYTES` is
refused instead of read whole.  YAML's own messages span several lines (the offending line
and a caret): errors here are one line naming the file, the problem and its position.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from t42_transfer.files import read_whole

MAX_BYTES = 1 << 20
"""Largest config read (1 MiB); the shipped ones are under 2 kB."""


class _UniqueKeys(yaml.SafeLoader):
    """SafeLoader refusing a key given twice in one mapping (PyYAML keeps the last without a word: a setting
    written twice, its first value silently dropped); a ``<<`` merge's keys may still be overridden."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value if isinstance(node, yaml.MappingNode) else ():
            if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
                continue
            key = self.construct_object(key_node)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


class _NoAliases(_UniqueKeys):
    """SafeLoader refusing ``*alias`` nodes (for files rcl parses too: it does not support them)."""

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "aliases are not supported", self.peek_event().start_mark)
        return super().compose_node(parent, index)


def read_yaml(path: str | os.PathLike[str], what: str, aliases: bool = True) -> Any:
    """The document in ``path`` (a ``what``, for messages); ValueError naming the file on any problem."""
    file = Path(path)
    data = read_whole(file, what, MAX_BYTES)
    try:
        return yaml.load(data.decode("utf-8"), _UniqueKeys if aliases else _NoAliases)
    except UnicodeDecodeError as err:
        raise ValueError(f"{file}: the {what} is not UTF-8 text (byte {err.start})") from None
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ValueError(
            f"{file}: the {what} is not valid YAML: {_one_line(err.problem or err.context)}{where}"
        ) from None
    except (yaml.YAMLError, ValueError, OverflowError, RecursionError) as err:
        # ValueError/OverflowError: a scalar PyYAML cannot convert (a 13th month, a 5000-digit int);
        # RecursionError: nesting deeper than the composer's recursion.
        raise ValueError(f"{file}: the {what} is not valid YAML: {_one_line(str(err)) or type(err).__name__}") from None


def _one_line(text: str | None) -> str:
    return " ".join(str(text or "").split())[:200]
