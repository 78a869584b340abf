"""Where a suite keeps its files (bags, models, transfer state): apart per namespace.

Two suites started from one working directory under ``/left`` and ``/right`` must not read each other's data,
so a relative directory is taken under the node's namespace (``recordings`` -> ``recordings/left``).  An absolute
directory is the user's explicit choice and is taken as given.  Nothing here needs rclpy.
"""

from __future__ import annotations

from pathlib import Path


def in_namespace(path: str | Path, namespace: str) -> Path:
    """``path`` for a node in ``namespace``: a relative path under the namespace's own folder, an absolute one as
    given."""
    path, ns = Path(path), namespace.strip("/")
    return path if path.is_absolute() or not ns else path / ns


def file_in_namespace(path: str | Path, namespace: str) -> Path:
    """A file ``path`` for a node in ``namespace``: its directory taken :func:`in_namespace`."""
    path = Path(path)
    return in_namespace(path.parent, namespace) / path.name if not path.is_absolute() else path
