"""IDL message definitions as rosbag2 stores them, put in the form rosbags 0.11 reads.

rosbag2 stores the definition of a type defined in ``.idl`` (a vendor's package; an MCAP ``ros2idl`` schema, a
sqlite3 ``message_definitions`` row) as each type's IDL after a line of 80 '=' and ``IDL: <type>``, the type's own
first, then every type it uses; each type that uses another ``#include``s it, and vendor IDL often has include guards
(``#ifndef``/``#define``/``#endif``).  rosbags' IDL parser takes no preprocessor line: it refuses the definition
("Could not parse"), and its ``AnyReader`` the whole bag with it.  The included types' IDL is in the definition
itself, so the directives are made comments: :func:`rosbags_idl` is the one place that does it, for reading every
bag (:mod:`.db3`) and for repairing one (:mod:`.repair`).
"""

from __future__ import annotations

import re
from typing import Any

from rosbags.typesys import TypesysError, get_types_from_idl

SEPARATOR = "=" * 80 + "\n"
"""What separates the definitions of a type and its dependencies in a stored definition (rosbag2's, and rosbags')."""
_DIRECTIVE = re.compile(r"^([ \t]*)#", re.MULTILINE)
"""A preprocessor line of IDL (``#include``, an include guard)."""
_SHOWN = 40
"""At most this much of a header line that is not ``IDL: <type>`` is quoted in the error."""


def rosbags_idl(text: str, msgtype: str) -> str:
    """``text``, a stored IDL definition of ``msgtype``, as rosbags reads and writes one: each type's IDL after the
    separator and ``IDL: <type>`` (rosbags' writer tells IDL from msg by that header; a definition stored without one
    is ``msgtype``'s IDL alone), every preprocessor line kept as a comment."""
    text = text if text.startswith(f"{SEPARATOR}IDL: ") else f"{SEPARATOR}IDL: {msgtype}\n{text}"
    return _DIRECTIVE.sub(r"\1// #", text)


def idl_types(text: str) -> dict[str, Any]:
    """The types a definition from :func:`rosbags_idl` defines, each type's IDL parsed as rosbags' ``AnyReader``
    parses it; rosbags raises what it cannot parse, and a TypesysError is raised here for a type's IDL without its
    ``IDL: <type>`` line (``AnyReader`` fails an assertion or an unpacking on it)."""
    types: dict[str, Any] = {}
    for part in text.split(SEPARATOR)[1:]:
        header, newline, idl = part.partition("\n")
        if not (newline and header.startswith("IDL: ")):
            raise TypesysError(f"Could not parse: no 'IDL: <type>' line at {header[:_SHOWN]!r}")
        types.update(get_types_from_idl(idl))
    return types
