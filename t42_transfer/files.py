"""The one check that a path a user names is a regular file, and its one message; writing a file whole.

A FIFO blocks ``open()``, a device never ends and a directory cannot be read as a
file, so every reader of user files checks the file's mode before it opens it (and
again with ``fstat`` after a non-blocking open, where a swap in between matters).
Readers raise their own error types (BagError, CheckpointError, ...) with the reason
given here, so the words a user reads are the same whatever the file.  Files a later
run trusts (an experiment's cells and results) are written whole or not at all
(:func:`write_atomic`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


def read_whole(path: str | os.PathLike[str], what: str, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path`` (a ``what``, for messages); ValueError naming the file on any problem.

    Opened non-blocking and checked with ``fstat`` before a byte is read (no race with a swap between a check and
    the open); a file over ``max_bytes`` is refused rather than read whole."""
    file = Path(path)
    try:
        fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as err:
        raise ValueError(f"{file}: cannot read the {what} ({err.strerror or err})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{file}: the {what} {not_regular_reason(info.st_mode)}")
        if info.st_size > max_bytes:
            raise ValueError(f"{file}: the {what} has {info.st_size} bytes; at most {max_bytes} are read")
        with os.fdopen(os.dup(fd), "rb") as stream:
            data = stream.read(max_bytes + 1)
    except OSError as err:
        raise ValueError(f"{file}: cannot read the {what} ({err.strerror or err})") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise ValueError(f"{file}: the {what} has more than {max_bytes} bytes")
    return data


JSON_MAX_BYTES = 1 << 28
"""Largest JSON result file read (256 MiB); a 100-goal benchmark's trials are about 1 MiB."""


def json_number(value: object) -> bool:
    """Whether a value read from JSON is a number (int or float, NaN included), not a bool (an int in Python)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def read_json(path: str | os.PathLike[str], what: str) -> Any:
    """The JSON document in ``path`` (a ``what`` this project wrote, read back); ValueError naming the file."""
    data = read_whole(path, what, JSON_MAX_BYTES)
    try:
        return json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: the {what} is not UTF-8 text (byte {err.start})") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: the {what} is not valid JSON: {err.msg} at line {err.lineno}, "
                         f"column {err.colno}") from None
    except RecursionError:
        raise ValueError(f"{path}: the {what} is nested too deeply to read") from None


def write_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Replace ``path`` with ``text``, whole or not at all.

    Written to a hidden file beside it (the same filesystem), synced and renamed over it, so a full disk or a kill
    mid-write leaves the old file or none, never a half file that a resume would trust.  An OSError names ``path``
    (the temporary file's name would tell a user nothing)."""
    file = Path(path)
    tmp = file.with_name(f".{file.name}.{os.getpid()}.{secrets.token_hex(4)}.partial")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies, as for open()
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, file)
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(file)) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


@contextlib.contextmanager
def held_lock(path: str | os.PathLike[str], busy: Callable[[int], Exception] | None = None) -> Iterator[int]:
    """Hold an advisory ``flock`` on ``path`` (made if missing), yielding its descriptor: the one locking step.

    For work two processes would otherwise do at once into one place (two experiments collecting the same data
    set, two runs into one directory); the kernel drops the lock when its holder exits, however it ends, so none
    is left stale.  Without ``busy`` it waits for another holder to let go; with it, it does not wait but raises
    ``busy(fd)`` (made while the lock file is still open, so it can say who holds it)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if busy is None else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if busy is None:
                raise
            raise busy(fd) from None
        yield fd
    finally:
        os.close(fd)
