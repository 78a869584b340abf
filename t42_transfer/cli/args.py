"""The checks every ``t42`` command shares: one-line errors, bounded numbers, paths checked before work starts.

Numbers are checked by the parser (finite, in range, with bounds where a number sizes an
allocation) and paths before any work starts, so a typo is refused in a second instead of
after a long run or an 800 GB allocation.  A regular file is checked by
:mod:`t42_transfer.files`, with the message every reader gives.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import stat
from collections.abc import Callable
from pathlib import Path

from t42_transfer.files import not_regular_reason

SEED_MAX = 2**32 - 1
ROS_NAMESPACE = re.compile(r"/?|/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*/?")

# ------------------------------------------------------------------ arguments


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one ``t42: error:`` line (exit 2), like every other error."""

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("t42").strip()
        self.exit(2, f"t42: error: {command + ': ' if command else ''}{message} (see {self.prog} --help)\n")


def int_arg(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in ``[low, high]``."""
    wanted = f"an integer from {low} to {high}" if high is not None else f"an integer >= {low}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}")
        return value

    return parse


def float_arg(low: float = -math.inf, high: float = math.inf, low_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number in ``[low, high]`` (``(low, high]`` with ``low_open``)."""
    bounds = [f"{'>' if low_open else '>='} {low:g}"] if low > -math.inf else []
    bounds += [f"<= {high:g}"] if high < math.inf else []
    wanted = " ".join(["a finite number", " and ".join(bounds)]).strip()

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value > low if low_open else value >= low) and value <= high):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}")
        return value

    return parse


def _stat(path: Path) -> os.stat_result | None:
    """``path``'s status (following links); None when nothing is there; ValueError for any other failure."""
    try:
        return path.stat()
    except FileNotFoundError:
        return None
    except OSError as err:
        raise ValueError(f"{path}: {err.strerror or err}") from None


def _existing(path: Path, is_kind: Callable[[int], bool], kind: str) -> Path:
    """``path`` when it exists and ``is_kind(st_mode)``; ValueError naming it otherwise."""
    info = _stat(path)
    if info is None:
        raise ValueError(f"{path}: does not exist")
    if not is_kind(info.st_mode):
        raise ValueError(f"{path}: not {kind}")
    return path


def existing_file(path: Path) -> Path:
    """``path`` when it is a regular file (a FIFO would block the reader)."""
    info = _stat(path)
    if info is None:
        raise ValueError(f"{path}: does not exist")
    reason = not_regular_reason(info.st_mode)
    if reason is not None:
        raise ValueError(f"{path}: {reason}")
    return path


def existing_dir(path: Path) -> Path:
    return _existing(path, stat.S_ISDIR, "a directory")


def output_dir(path: Path) -> Path:
    """``path`` when it is a directory, or can be made one (its nearest existing ancestor is a directory), and
    can be written: said before the work, not when its result is saved (a model trained for an hour)."""
    for at in (path, *path.absolute().parents):
        info = _stat(at)
        if info is not None:
            if not stat.S_ISDIR(info.st_mode):
                raise ValueError(f"{path}: {'' if at == path else f'{at} '}is not a directory")
            if not os.access(at, os.W_OK | os.X_OK):  # (a read-only file system included)
                raise ValueError(f"{path}: {'' if at == path else f'{at} '}cannot be written (permission denied)")
            break
    return path


def new_output(path: Path) -> Path:
    """``path`` when nothing is there yet and its directory can be made; outputs are never overwritten."""
    if os.path.lexists(path):
        raise ValueError(f"{path}: exists already; choose a new path")
    return output_dir(path)


def os_error(err: OSError) -> str:
    """An OSError as ``<file>: <problem>``."""
    return f"{err.filename}: {err.strerror}" if err.filename is not None and err.strerror else str(err)


def namespace_arg(text: str) -> str:
    if not ROS_NAMESPACE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected a ROS namespace such as /left (letters, digits, _ and /; "
                                         f"no token starting with a digit), got {text[:40]!r}")
    return text


def bags_in(paths: list[Path]) -> list[Path]:
    """Each path a bag (a directory holding ``metadata.yaml``) or a directory of finished bags (a recorder's
    ``out_dir``), in order, a bag named twice once; ValueError naming the sub-folders that hold bags when a
    directory holds none itself (a suite under a namespace records into one)."""
    from t42_transfer.data.bag import list_bags

    bags: dict[Path, Path] = {}  # by resolved path
    for path in paths:
        existing_dir(path)
        found = [path] if (path / "metadata.yaml").is_file() else list_bags(path)
        if not found:
            nested = sorted(str(d) for d in path.iterdir() if d.is_dir() and list_bags(d))
            hint = f"; these folders in it do (a suite under a namespace records there): {', '.join(nested)}" \
                if nested else ""
            raise ValueError(f"{path}: holds no finished bag (a directory with a metadata.yaml){hint}")
        bags.update((bag.resolve(), bag) for bag in found)
    return list(bags.values())
