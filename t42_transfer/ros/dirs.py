"""Where a suite keeps its files (bags, models, transfer state): apart per namespace.

Two suites started from one working directory under ``/left`` and ``/right`` must not read each other's data,
so a relative directory is taken under the node's namespace (``recordings`` -> ``recordings/left``).  An absolute
directory is the user's explicit choice and is taken as given; a node that uses a directory claims it for its
namespace (a hidden file beside it, ``.<name>.t42_namespace``, so the directory holds only what the suite wrote
there), and a node of another namespace refuses it unless told to share (``share_dirs``).  Nothing here needs rclpy.
"""

from __future__ import annotations

import os
from pathlib import Path

CLAIM = ".{name}.t42_namespace"
"""The file beside a suite's directory ``name`` that names the namespace whose files it holds."""


def claim_file(directory: str | Path) -> Path:
    """Where the claim on ``directory`` is kept."""
    directory = Path(directory).absolute()
    return directory.parent / CLAIM.format(name=directory.name)


def in_namespace(path: str | Path, namespace: str) -> Path:
    """``path`` for a node in ``namespace``: a relative path under the namespace's own folder, an absolute one as
    given."""
    path, ns = Path(path), namespace.strip("/")
    return path if path.is_absolute() or not ns else path / ns


def file_in_namespace(path: str | Path, namespace: str) -> Path:
    """A file ``path`` for a node in ``namespace``: its directory taken :func:`in_namespace`."""
    path = Path(path)
    return in_namespace(path.parent, namespace) / path.name if not path.is_absolute() else path


def claim(directory: str | Path, namespace: str, share: bool = False) -> None:
    """Claim an existing ``directory`` for ``namespace`` (ValueError when another namespace holds it); nothing
    for a directory not made yet (its maker claims it) or with ``share`` (two suites share it on purpose)."""
    directory, owner = Path(directory), "/" + namespace.strip("/")
    if share or not directory.is_dir():
        return
    marker = claim_file(directory)
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)  # atomic: two starting suites, one wins
    except FileExistsError:
        held = marker.read_text(errors="replace").strip()
        if held != owner:
            raise ValueError(f"{directory} holds the files of the suite under {held} ({marker}); a suite under "
                             f"{owner} takes its own (a relative directory is taken per namespace), or set "
                             "share_dirs:=true to share this one on purpose") from None
        return
    except OSError:  # a read-only parent: nothing can be claimed there
        return
    with os.fdopen(fd, "w") as out:
        out.write(owner + "\n")


def claim_made(directory: str | Path, namespace: str, share: bool = False) -> None:
    """:func:`claim` a directory its user may just have made (a transfer server's first save makes its model
    directory after the start's claim found none); one another namespace took meanwhile is not an error here: the
    next use, claiming it again, refuses it in one line."""
    try:
        claim(directory, namespace, share)
    except ValueError:
        pass
