"""Importer for the public real Model-T42 test paths (avishais/t42_autonomous_system).

The files are Python 2 pickles: ``[actions, states, name, success_flags]`` with
six paths per hand (see shared/data/t42_real/README.md).  Unpickling runs code
the file's author chose, and numpy builds whatever array a pickle describes (a
datetime array without its unit segfaults, a pickle of 71 bytes can ask for 1.9 GB),
so the files go through an unpickler that admits only what the real files hold:
lists, tuples, ints, strings and float64 arrays rebuilt the way numpy pickles
them, each dtype and shape checked before it is built, and no more array bytes
or objects than the file's size accounts for.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import pickle
import pickletools
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from numpy._core.multiarray import _reconstruct

from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD, DROPPED
from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.errors import PickleFileError
from t42_transfer.data.quality import scan, summarise, summary_lines
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.files import not_regular_reason

REAL_HANDS = {"A": "", "B": "_red"}
"""The two real hands, A ("blue") and B ("red"), mirror images of each other, and their files' name infix."""

REAL_OBJECT = "cyl35"
"""The object of the files beside the project (a 35 mm cylinder)."""


def real_file(hand: str, obj: str = REAL_OBJECT) -> str:
    """The public file name of ``obj``'s test paths on ``hand`` (``A`` or ``B``), as the public repository names it."""
    if hand not in REAL_HANDS:
        raise ValueError(f"the real hands are {sorted(REAL_HANDS)}, got {hand!r}")
    return f"testpaths_{obj}{REAL_HANDS[hand]}_d_v0.pkl"


REAL_FILES = {hand: real_file(hand) for hand in REAL_HANDS}
"""The files beside the project: the 35 mm cylinder on hands A and B."""

MAX_PICKLE_BYTES = 256 * 2**20
"""The real files are 2.6 MB each; a file this size would hold about a hundred times more paths."""

MAX_OPCODES = 100_000
"""The real files take 381 pickle opcodes; each builds at most one small object, so this bounds them all."""

MAX_NAME_CHARS = 200
"""The hand name goes into bag metadata and messages; the real ones are "cyl35" and "cyl35_red"."""


def real_data_dir() -> Path:
    """Where the public files are: ``$T42_REAL_DATA``, else ``shared/data/t42_real`` beside the checkout.

    They are not redistributed with the project, so callers must expect the folder to be missing.
    """
    default = Path(__file__).resolve().parents[3] / "shared" / "data" / "t42_real"
    return Path(os.environ.get("T42_REAL_DATA", default))


STATE_COLUMNS = (0, 1, 11, 12)
"""Object x, y (mm) and the two actuator loads among the files' 13 state columns."""

_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,  # as Python 2's numpy named it
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}
"""The only globals a pickled list of numpy arrays names."""

_OPCODES = frozenset(
    "PROTO FRAME STOP MARK NONE NEWTRUE NEWFALSE INT BININT BININT1 BININT2 "
    "STRING BINSTRING SHORT_BINSTRING BINBYTES SHORT_BINBYTES UNICODE BINUNICODE SHORT_BINUNICODE "
    "EMPTY_LIST APPEND APPENDS LIST EMPTY_TUPLE TUPLE TUPLE1 TUPLE2 TUPLE3 "
    "PUT BINPUT LONG_BINPUT MEMOIZE GET BINGET LONG_BINGET GLOBAL STACK_GLOBAL REDUCE BUILD".split()
)
"""What Python 2 (protocols 0-2) and Python 3 (protocols 3-4) write for such a list.

Left out, among others: dicts and sets (hashing a key of shared nested tuples takes
exponential time), object creation other than REDUCE, extensions and 8-byte lengths.
"""

_OPCODE_NAMES = {op.code.encode("latin-1")[0]: op.name for op in pickletools.opcodes}

_FLOAT32_MAX = float(np.finfo(np.float32).max)

_DTYPE_STATES = frozenset((3, order, None, None, None, -1, -1, 0) for order in "<>")
"""``np.dtype("f8").__reduce__()[2]`` little- and big-endian: the only dtype states set."""


class _Refused(Exception):
    """Something the real files never hold; the loader names the file."""


def _text(value: str) -> str:
    """Text from the file for a one-line message: as it is when short and printable, else a cut repr."""
    return value if value.isprintable() and len(value) <= 80 else repr(value[:80])


def _is_placeholder(args: Any) -> bool:
    """``(ndarray, (0,), 'b')``: numpy pickles every array as this empty placeholder plus its state."""
    return (
        type(args) is tuple
        and len(args) == 3
        and args[0] is np.ndarray
        and type(args[1]) is tuple
        and len(args[1]) == 1
        and type(args[1][0]) is int
        and args[1][0] == 0
        and type(args[2]) in (str, bytes)
        and args[2] in ("b", b"b")
    )


def _float64(args: Any) -> np.dtype:
    """``np.dtype("f8", align, copy)``: the one dtype the real files name
    (a datetime one without its unit segfaults)."""
    if not (type(args) is tuple and len(args) == 3 and type(args[0]) is str):
        raise _Refused("a dtype must be given as (name, align, copy)")
    if args[0] != "f8":
        raise _Refused(f"refused dtype {args[0][:20]!r}: only float64 ('f8') arrays are allowed")
    if not all(type(flag) in (int, bool) and flag in (0, 1) for flag in args[1:]):
        raise _Refused("a dtype's align and copy flags must be 0 or 1")
    return np.dtype("f8", align=bool(args[1]), copy=bool(args[2]))


class _RestrictedUnpickler(pickle._Unpickler):
    """Python's own unpickler with an opcode whitelist and every object numpy builds checked first.

    The pure-Python unpickler, not the C one: its memo is a dict (the C one grows a list to
    any index a PUT names) and it never reserves a declared length before reading it.
    """

    def __init__(self, data: bytes) -> None:
        super().__init__(io.BytesIO(data), encoding="latin1")
        self._opcodes_left = MAX_OPCODES
        self._array_bytes_left = len(data)

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _GLOBALS[(module, name)]
        except KeyError:
            raise _Refused(
                f"refused to load global {_text(module)}.{_text(name)}: "
                "only numpy arrays, lists and scalars are allowed"
            ) from None

    def _reduce(self) -> None:
        args = self.stack.pop()
        func = self.stack[-1]
        if func is _reconstruct and _is_placeholder(args):
            self.stack[-1] = _reconstruct(np.ndarray, (0,), b"b")
        elif func is np.dtype:
            self.stack[-1] = _float64(args)
        else:
            what = "numpy.ndarray" if func is np.ndarray else getattr(func, "__name__", type(func).__name__)
            raise _Refused(f"refused to call {what}: arrays are rebuilt only from an empty placeholder and their bytes")

    def _build(self) -> None:
        state = self.stack.pop()
        inst = self.stack[-1]
        if isinstance(inst, np.dtype):
            if not (
                type(state) is tuple
                and all(v is None or type(v) in (int, str) for v in state)
                and state in _DTYPE_STATES
            ):
                raise _Refused("refused a dtype state other than a plain float64's")
        elif type(inst) is np.ndarray:
            self._check_array_state(state)
        else:
            raise _Refused(f"refused to set the state of a {type(inst).__name__}")
        inst.__setstate__(state)

    def _check_array_state(self, state: Any) -> None:
        """Shape, dtype and byte count agree, and all arrays together hold no more bytes than the file."""
        if not (type(state) is tuple and len(state) == 5):
            raise _Refused("an array's state must be (version, shape, dtype, fortran, data)")
        version, shape, dtype, fortran, raw = state
        if not (type(version) is int and version == 1 and type(fortran) in (int, bool) and fortran in (0, 1)):
            raise _Refused("an array's state has an unknown version or order flag")
        if not (isinstance(dtype, np.dtype) and dtype.kind == "f" and dtype.itemsize == 8):
            raise _Refused(f"refused an array of dtype {type(dtype).__name__}: only float64 arrays are allowed")
        if not (type(shape) is tuple and len(shape) <= 2 and all(type(n) is int and n >= 0 for n in shape)):
            raise _Refused("an array's shape must be at most two non-negative sizes")
        if any(n > self._array_bytes_left for n in shape):
            raise _Refused("an array dimension is larger than the file's bytes could fill")
        if type(raw) not in (bytes, str) or len(raw) != math.prod(shape) * dtype.itemsize:
            raise _Refused(f"an array of shape {shape} needs {math.prod(shape) * dtype.itemsize} bytes of data")
        self._array_bytes_left -= len(raw)
        if self._array_bytes_left < 0:
            raise _Refused("its arrays hold more bytes than the file")


class _Dispatch(dict):
    """Opcode -> handler; an opcode not in it is refused by name (the base class would raise a bare KeyError)."""

    def __missing__(self, code: int) -> NoReturn:
        raise _Refused(f"refused pickle opcode {_OPCODE_NAMES.get(code, hex(code))}: the real files do not use it")


def _counted(op: Callable[[_RestrictedUnpickler], None]) -> Callable[[_RestrictedUnpickler], None]:
    """``op`` spending one of the file's MAX_OPCODES: shared references cannot multiply the objects built."""

    def run(unpickler: _RestrictedUnpickler) -> None:
        unpickler._opcodes_left -= 1
        if unpickler._opcodes_left < 0:
            raise _Refused(f"holds more than {MAX_OPCODES} pickle opcodes")
        op(unpickler)

    return run


_HANDLERS = {"REDUCE": _RestrictedUnpickler._reduce, "BUILD": _RestrictedUnpickler._build}
_RestrictedUnpickler.dispatch = _Dispatch(
    (code, _counted(_HANDLERS.get(_OPCODE_NAMES[code], op)))
    for code, op in pickle._Unpickler.dispatch.items()
    if _OPCODE_NAMES[code] in _OPCODES
)


def _require_regular(path: Path, mode: int) -> None:
    reason = not_regular_reason(mode)
    if reason is not None:
        raise PickleFileError(path, reason)


def _read_regular(path: Path) -> bytes:
    """The file's bytes; anything but a regular file is refused before it is opened (opening a FIFO blocks)."""
    try:
        _require_regular(path, path.stat().st_mode)
        # O_NONBLOCK: should the path have become a FIFO since the stat, the open still returns at once
        with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as file:
            info = os.fstat(file.fileno())
            _require_regular(path, info.st_mode)
            if info.st_size > MAX_PICKLE_BYTES:
                raise PickleFileError(
                    path, f"is {info.st_size} bytes, more than a test-path pickle's {MAX_PICKLE_BYTES}"
                )
            return file.read(info.st_size)  # read(n) reserves n bytes: the size the stat gave, not the limit
    except OSError as err:
        raise PickleFileError(path, f"cannot be read ({err.strerror or err})") from None


def _unpickle(path: Path, data: bytes) -> Any:
    try:
        return _RestrictedUnpickler(data).load()
    except _Refused as err:
        raise PickleFileError(path, str(err)) from None
    except MemoryError:  # the bounds above should make this unreachable: not a verdict on the file
        raise
    except Exception as err:  # a malformed pickle raises whatever its opcodes trip over
        detail = f"{type(err).__name__}: {err}".replace("\n", " ")[:300] if str(err) else type(err).__name__
        raise PickleFileError(path, f"is not a readable pickle ({detail})") from None


def _float_table(path: Path, what: str, value: Any, min_cols: int) -> np.ndarray:
    if not (isinstance(value, np.ndarray) and value.ndim == 2 and value.shape[1] >= min_cols):
        shape = value.shape if isinstance(value, np.ndarray) else type(value).__name__
        raise PickleFileError(path, f"{what} must be a 2-D array with at least {min_cols} columns, got {shape}")
    return value


def _float32(path: Path, what: str, values: np.ndarray) -> np.ndarray:
    """``values`` as the float32 a Trajectory holds; a NaN, inf or float64 beyond float32's range is refused first."""
    bad = ~(np.abs(values) <= _FLOAT32_MAX)
    if bad.any():
        raise PickleFileError(path, f"{what} has a non-finite float32 value at row {int(np.argwhere(bad)[0, 0])}")
    return values.astype(np.float32)


def _testpaths(file: Path, data: bytes) -> TrajectorySet:
    content = _unpickle(file, data)
    if not (isinstance(content, list) and len(content) == 4):
        raise PickleFileError(file, "expected a list [actions, states, name, success_flags]")
    actions, states, name, flags = content
    if not (isinstance(actions, list) and isinstance(states, list) and isinstance(flags, list)):
        raise PickleFileError(file, "actions, states and success flags must be lists")
    if not (isinstance(name, str) and name.isprintable() and len(name) <= MAX_NAME_CHARS):
        raise PickleFileError(file, f"the hand name must be printable text of at most {MAX_NAME_CHARS} characters")
    if not len(actions) == len(states) == len(flags):
        raise PickleFileError(
            file, f"{len(actions)} action arrays, {len(states)} state arrays and {len(flags)} flags differ in number"
        )
    episodes, array_bytes = [], 0
    for i, (acts, obs, ok) in enumerate(zip(actions, states, flags, strict=True)):
        obs = _float_table(file, f"path {i} states", obs, max(STATE_COLUMNS) + 1)
        acts = _float_table(file, f"path {i} actions", acts, 2)
        if len(acts) < len(obs) - 1:
            raise PickleFileError(file, f"path {i} has {len(obs)} states but only {len(acts)} actions")
        if not isinstance(ok, bool):
            raise PickleFileError(file, f"path {i}'s success flag is {type(ok).__name__}, expected bool")
        array_bytes += obs.nbytes + acts.nbytes
        if array_bytes > len(data):  # one array named by many paths would be copied for each
            raise PickleFileError(file, f"paths 0..{i} refer to more array bytes than the file holds")
        try:
            episodes.append(
                Trajectory(
                    states=_float32(file, f"path {i} states", obs[:, STATE_COLUMNS]),
                    actions=_float32(file, f"path {i} actions", acts[: len(obs) - 1, :2]),
                    end_reason="length" if ok else DROPPED,
                    hand=name,
                )
            )
        except ValueError as err:
            raise PickleFileError(file, f"path {i}: {err}") from None
    return TrajectorySet(assign_start_times(episodes), hand=name)


def load_t42_testpaths(path: str | Path) -> TrajectorySet:
    """The six test paths of one real hand as episodes: state (x, y, load1, load2), hand = the file's name.

    The files hold one or more actions than states per path (the last ones were
    never observed), so each episode takes the first ``len(states) - 1``.  A path
    whose success flag is False dropped the object.
    """
    file = Path(path)
    return _testpaths(file, _read_regular(file))


def quality_lines(paths: TrajectorySet) -> list[str]:
    """What :mod:`~t42_transfer.data.quality` finds in one file's paths, a line per flagged path ("none" if clean).

    Hand B's cylinder file, for one: its path 0 lost tracking for its first 199 steps and then jumped 26.3 mm.
    """
    return summary_lines(scan(paths), unit="path")


def import_t42_to_bag(pickle_path: str | Path, bag_path: str | Path) -> Path:
    """Write one hand's test paths as a bag, recording the source file's name, the sha256 of the bytes read
    and what the quality scan found (``data_quality``, JSON), so the bag carries its flagged stretches along.
    The actions are the authors' (``AUTHORS_ACTION_UNIT_RAD``): the bag holds the steps their driver took, declares
    that unit and is read back in it."""
    source = Path(pickle_path)
    data = _read_regular(source)
    paths = _testpaths(source, data)
    quality = json.dumps(summarise(paths, scan(paths)), separators=(",", ":"))
    return write_bag(
        bag_path,
        paths,
        metadata={"source": source.name, "source_sha256": hashlib.sha256(data).hexdigest(), "data_quality": quality},
        action_unit_rad=AUTHORS_ACTION_UNIT_RAD,
    )
