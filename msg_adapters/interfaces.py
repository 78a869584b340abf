"""The suite's own messages (``t42_interfaces/msg/...``) in rosbags' Jazzy typestore, read from their ``.msg`` files.

:data:`msg_adapters.TYPESTORE` holds them beside the standard messages, so a bag writer stores their full
``ros2msg`` definitions in the MCAP schema (rosbags, mcap-ros2-support and Foxglove then decode them without this
package) and the bag layer decodes them without rclpy.  The files are read from ``share/t42_interfaces/msg`` of an
install prefix (``AMENT_PREFIX_PATH``, then this Python's prefix: the venv the bootstrap builds the package into),
so the definitions are those of the installed package rclpy publishes; a checkout where it is not built yet falls
back to the repository's ``interfaces/t42_interfaces/msg``.  Imports nothing of :mod:`t42_transfer`.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Any

from rosbags.typesys import get_types_from_msg

PACKAGE = "t42_interfaces"
REPOSITORY_INTERFACES = Path(__file__).resolve().parents[1] / "interfaces"
"""The repository's interface packages (``interfaces/<package>/msg``): the fallback of an unbuilt checkout."""


def msg_dirs(package: str = PACKAGE) -> list[Path]:
    """Where ``package``'s ``.msg`` files may be, in the order they are looked for."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return [*(prefix / "share" / package / "msg" for prefix in [*prefixes, Path(sys.prefix)]),
            REPOSITORY_INTERFACES / package / "msg"]


def msg_dir(package: str = PACKAGE) -> Path | None:
    """The first of :func:`msg_dirs` that holds a ``.msg`` file (None: none does)."""
    return next((d for d in msg_dirs(package) if d.is_dir() and any(d.glob("*.msg"))), None)


def interface_types(package: str = PACKAGE) -> dict[str, Any]:
    """rosbags type descriptions of every ``<package>/msg/<Name>`` found; ValueError naming a file that does not
    parse."""
    directory = msg_dir(package)
    types: dict[str, Any] = {}
    for file in sorted(directory.glob("*.msg")) if directory is not None else ():
        try:
            types.update(get_types_from_msg(file.read_text(), f"{package}/msg/{file.stem}"))
        except Exception as err:  # the parser raises its own errors
            raise ValueError(f"{file}: not a message definition rosbags reads ({type(err).__name__}: {err})") from None
    return types


def register_interfaces(typestore: Any, package: str = PACKAGE) -> tuple[str, ...]:
    """Add ``package``'s messages to ``typestore``; the type names added.  A package not found adds none, and a file
    that does not parse is a warning, not an error: every standard message still works."""
    try:
        types = interface_types(package)
    except (OSError, ValueError) as err:
        warnings.warn(f"{package} messages not registered for bags: {err}", stacklevel=2)
        return ()
    new = {name: desc for name, desc in types.items() if name not in typestore.types}
    typestore.register(new)
    return tuple(sorted(new))
