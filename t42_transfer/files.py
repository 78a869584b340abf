"""The one check that a path a user names is a regular file, and its one message.

A FIFO blocks ``open()``, a device never ends and a directory cannot be read as a
file, so every reader of user files checks the file's mode before it opens it (and
again with ``fstat`` after a non-blocking open, where a swap in between matters).
Readers raise their own error types (BagError, CheckpointError, ...) with the reason
given here, so the words a user reads are the same whatever the file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a device"),
    (stat.S_ISBLK, "a device"),
)


class NotRegularFile(ValueError):
    """``path`` exists but is not a regular file; ``reason`` is the text after the path."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words (``"a FIFO"``); ``"a regular file"`` for one."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def not_regular_reason(mode: int) -> str | None:
    """None for a regular file; otherwise the one message every reader gives (``"is a FIFO, not a regular file"``)."""
    return None if stat.S_ISREG(mode) else f"is {file_kind(mode)}, not a regular file"


def require_regular(path: str | os.PathLike[str], mode: int) -> None:
    """NotRegularFile unless ``mode`` (of ``path``, from ``stat`` or ``fstat``) is a regular file's."""
    reason = not_regular_reason(mode)
    if reason is not None:
        raise NotRegularFile(Path(path), reason)


def regular_file(path: str | os.PathLike[str]) -> os.stat_result:
    """``path``'s status (links followed) when it is a regular file, checked before anything opens it.

    FileNotFoundError when nothing is there, NotRegularFile for a FIFO, directory, socket
    or device, OSError for any other failure of ``stat``.
    """
    info = Path(path).stat()
    require_regular(path, info.st_mode)
    return info
