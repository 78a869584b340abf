"""Importer for the public real Model-T42 test paths (avishais/t42_autonomous_system).

The files are Python 2 pickles: ``[actions, states, name, success_flags]`` with
six paths per hand (see shared/data/t42_real/README.md).  Unpickling runs code
the file's author chose, so they are loaded through an unpickler that admits only
numpy arrays, lists and plain scalars.
"""

from __future__ import annotations

import hashlib
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np
from numpy._core.multiarray import _reconstruct

from t42_transfer.data.bag_io import assign_start_times, write_bag
from t42_transfer.data.errors import PickleFileError
from t42_transfer.data.trajectory import Trajectory, TrajectorySet

REAL_FILES = {"A": "testpaths_cyl35_d_v0.pkl", "B": "testpaths_cyl35_red_d_v0.pkl"}
"""The two real hands' files: A ("blue") and B ("red"), mirror images of each other."""


def real_data_dir() -> Path:
    """Where the public files are: ``$T42_REAL_DATA``, else ``shared/data/t42_real`` beside the checkout.

    They are not redistributed with the project, so callers must expect the folder to be missing.
    """
    default = Path(__file__).resolve().parents[3] / "shared" / "data" / "t42_real"
    return Path(os.environ.get("T42_REAL_DATA", default))


STATE_COLUMNS = (0, 1, 11, 12)
"""Object x, y (mm) and the two actuator loads among the files' 13 state columns."""

_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    **{(module, t.__name__): t for module in ("builtins", "__builtin__") for t in (list, float, bool, str)},
}


class _RestrictedUnpickler(pickle.Unpickler):
    """Resolves only the globals a pickled list of float arrays needs."""

    def __init__(self, file: Any, path: Path) -> None:
        super().__init__(file, encoding="latin1")
        self._path = path

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise PickleFileError(
                self._path, f"refused to load global {module}.{name}: only numpy arrays, lists and scalars are allowed"
            ) from None


def _load_pickle(path: Path) -> Any:
    try:
        with path.open("rb") as file:
            return _RestrictedUnpickler(file, path).load()
    except PickleFileError:
        raise
    except OSError as err:
        raise PickleFileError(path, f"cannot be read ({err.strerror or err})") from None
    except Exception as err:  # a malformed pickle raises whatever its opcodes trip over
        raise PickleFileError(path, f"is not a readable pickle ({type(err).__name__}: {err})") from None


def _float_table(path: Path, what: str, value: Any, min_cols: int) -> np.ndarray:
    if not (isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] >= min_cols):
        shape = getattr(value, "shape", type(value).__name__)
        raise PickleFileError(path, f"{what} must be a 2-D array with at least {min_cols} columns, got {shape}")
    if not np.issubdtype(value.dtype, np.floating):
        raise PickleFileError(path, f"{what} has dtype {value.dtype}, expected floats")
    return value


def load_t42_testpaths(path: str | Path) -> TrajectorySet:
    """The six test paths of one real hand as episodes: state (x, y, load1, load2), hand = the file's name.

    The files hold one or more actions than states per path (the last ones were
    never observed), so each episode takes the first ``len(states) - 1``.  A path
    whose success flag is False dropped the object.
    """
    file = Path(path)
    content = _load_pickle(file)
    if not (isinstance(content, list) and len(content) == 4):
        raise PickleFileError(file, "expected a list [actions, states, name, success_flags]")
    actions, states, name, flags = content
    if not (isinstance(actions, list) and isinstance(states, list) and isinstance(flags, list)):
        raise PickleFileError(file, "actions, states and success flags must be lists")
    if not isinstance(name, str):
        raise PickleFileError(file, f"the hand name must be a string, got {type(name).__name__}")
    if not len(actions) == len(states) == len(flags):
        raise PickleFileError(
            file, f"{len(actions)} action arrays, {len(states)} state arrays and {len(flags)} flags differ in number"
        )
    episodes = []
    for i, (acts, obs, ok) in enumerate(zip(actions, states, flags)):
        obs = _float_table(file, f"path {i} states", obs, max(STATE_COLUMNS) + 1)
        acts = _float_table(file, f"path {i} actions", acts, 2)
        if len(acts) < len(obs) - 1:
            raise PickleFileError(file, f"path {i} has {len(obs)} states but only {len(acts)} actions")
        if not isinstance(ok, bool):
            raise PickleFileError(file, f"path {i}'s success flag is {type(ok).__name__}, expected bool")
        try:
            episodes.append(
                Trajectory(
                    states=obs[:, STATE_COLUMNS],
                    actions=acts[: len(obs) - 1, :2],
                    end_reason="length" if ok else "dropped",
                    hand=name,
                )
            )
        except ValueError as err:
            raise PickleFileError(file, f"path {i}: {err}") from None
    return TrajectorySet(assign_start_times(episodes), hand=name)


def import_t42_to_bag(pickle_path: str | Path, bag_path: str | Path) -> Path:
    """Write one hand's test paths as a bag, recording the source file's name and sha256."""
    source = Path(pickle_path)
    data = load_t42_testpaths(source)
    digest = hashlib.sha256(source.read_bytes()).hexdigest()
    return write_bag(bag_path, data, metadata={"source": source.name, "source_sha256": digest})
