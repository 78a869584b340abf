"""The paper authors' saved models are legacy torch pickles: read here without running any of their code.

The files (shared/data/authors_models/README.md) are ``torch.save`` output of the
legacy, pre-zip format: five pickles (a magic number, the format's protocol
number, a little sys-info dict, the saved object, the list of storage keys) and
then, per key, an 8-byte element count and the raw little-endian float32 data.
The saved object is a whole ``nn.Module`` of the authors' classes with their
source embedded, so ``torch.load`` would import and run code the file names.

Here they go through an unpickler of our own: Python's pure-Python unpickler with
an opcode whitelist, a bounded number of opcodes, and ``find_class`` admitting
only the exact globals the published files name (listed with ``pickletools``).
Every one of them becomes an inert marker; nothing the file names is imported or
called.  Module objects become :class:`ModuleObject` (a class name and a state dict
with string keys), storages become :class:`_Storage` (a key and a declared size
that the file's bytes must account for), tensors become :class:`TensorRef`
(contiguous views checked against their storage), and the weights are read as
plain float32 bytes after the pickles.  Anything else is refused with one line
naming the file (:class:`AuthorsModelError`).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import pickletools
import reprlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch

from t42_transfer.data.errors import DataFileError
from t42_transfer.files import not_regular_reason

LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
"""The number every legacy (pre-zip) ``torch.save`` file starts with."""
LEGACY_PROTOCOL = 1001
MAX_FILE_BYTES = 16 * 2**20
"""The published files have 90 kB to 571 kB."""
MAX_OPCODES = 100_000
"""The largest published file (cumulative residual) takes 2 993 opcodes."""
MAX_TEXT_CHARS = 200
"""Longest text quoted from a file in an error message."""


class AuthorsModelError(DataFileError):
    """An authors' model file that is missing, damaged, hostile, or of a family this project cannot represent."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        super().__init__(path, " ".join(problem.split()))  # one line, whatever a library's message holds


class Refused(Exception):
    """Something the published files never hold; the reader names the file."""


# --------------------------------------------------------------------------- inert stand-ins
@dataclass(frozen=True)
class _Global:
    """A global the file names, admitted by name only: never imported, never called."""

    name: str


@dataclass(frozen=True)
class _Storage:
    key: str
    numel: int


@dataclass(frozen=True)
class TensorRef:
    """A contiguous float32 tensor ``shape`` at ``offset`` elements into ``storage``."""

    storage: _Storage
    offset: int
    shape: tuple[int, ...]


class ModuleObject:
    """An instance of an admitted module class: the class's name and the state dict BUILD gave it."""

    __slots__ = ("cls", "state")

    def __init__(self, cls: _Global) -> None:
        self.cls = cls.name
        self.state: dict[str, Any] | None = None


_MODULE_CLASSES = frozenset({
    "common.TrajNet.TrajNet", "common.TrajNet.TimeIndepLatentDeltaNet", "common.TrajNet.LSTMStateTrajNet",
    "common.TrajNet.ResBlock", "torch.nn.modules.container.Sequential", "torch.nn.modules.activation.SELU",
    "torch.nn.modules.activation.Tanh", "torch.nn.modules.dropout.AlphaDropout", "torch.nn.modules.dropout.Dropout",
    "torch.nn.modules.linear.Linear", "torch.nn.modules.rnn.GRU",
})
"""Module classes the published files hold (instances are created empty and given a state dict, nothing else)."""
_ORDERED_DICT = _Global("collections.OrderedDict")
_BACKEND = _Global("torch.nn.backends.thnn._get_thnn_function_backend")
_FLOAT_STORAGE = _Global("torch.FloatStorage")
_FLOAT32 = _Global("torch.float32")
_REBUILD_TENSOR = _Global("torch._utils._rebuild_tensor_v2")
_REBUILD_PARAMETER = _Global("torch._utils._rebuild_parameter")
_GLOBALS = {g.name: g for g in (_ORDERED_DICT, _BACKEND, _FLOAT_STORAGE, _FLOAT32, _REBUILD_TENSOR,
                                _REBUILD_PARAMETER, *map(_Global, _MODULE_CLASSES))}
"""Every global the published files name (listed with pickletools over all 202 files), by dotted name."""
_BACKEND_VALUE = _Global("thnn backend")
"""What ``_get_thnn_function_backend()`` stands for: an attribute no rollout reads."""

_OPCODES = frozenset(
    "PROTO STOP MARK NONE NEWTRUE NEWFALSE LONG1 BININT1 BININT2 BINFLOAT BINUNICODE "
    "EMPTY_LIST APPEND APPENDS EMPTY_DICT SETITEM SETITEMS EMPTY_TUPLE TUPLE TUPLE1 TUPLE2 TUPLE3 "
    "BINPUT LONG_BINPUT BINGET LONG_BINGET GLOBAL REDUCE NEWOBJ BUILD BINPERSID".split()
)
"""Every opcode the published files use (protocol 2), no more."""
_OPCODE_NAMES = {op.code.encode("latin-1")[0]: op.name for op in pickletools.opcodes}


def quoted(value: object) -> str:
    """Text from the file for a one-line message (reprlib: a crafted nesting cannot make it long or slow)."""
    text = value if type(value) is str else reprlib.repr(value)
    return text if text.isprintable() and len(text) <= MAX_TEXT_CHARS else repr(text[:MAX_TEXT_CHARS])


@dataclass
class _Budget:
    """What the file may still spend, over all its pickles: opcodes, and storage bytes it can account for."""

    opcodes_left: int
    bytes_left: int


class _Unpickler(pickle._Unpickler):
    """The pure-Python unpickler (its memo is a dict; it never reserves a declared length) with every object
    creation replaced by inert stand-ins."""

    def __init__(self, stream: io.BytesIO, budget: _Budget, storages: dict[str, _Storage]) -> None:
        super().__init__(stream, encoding="utf-8")
        self._budget = budget
        self._storages = storages

    def find_class(self, module: str, name: str) -> _Global:
        try:
            return _GLOBALS[f"{module}.{name}"]
        except KeyError:
            raise Refused(f"refused to load global {quoted(module)}.{quoted(name)}: not one the authors' "
                           "model files use") from None

    def persistent_load(self, pid: Any) -> Any:
        if type(pid) is tuple and len(pid) == 4 and pid[0] == "module":
            # ('module', class, source file name, class source): torch only compared the source; we ignore it
            if not (isinstance(pid[1], _Global) and pid[1].name in _MODULE_CLASSES):
                raise Refused("a module record names no admitted module class")
            return pid[1]
        if type(pid) is tuple and len(pid) == 6 and pid[0] == "storage":
            _, kind, key, location, numel, view = pid
            if kind is not _FLOAT_STORAGE:
                raise Refused("refused a storage other than torch.FloatStorage")
            if not (type(key) is str and key.isprintable() and len(key) <= 40 and type(location) is str
                    and location.startswith(("cpu", "cuda")) and len(location) <= 20 and view is None):
                raise Refused("a storage record must be ('storage', FloatStorage, key, location, size, None)")
            if not (type(numel) is int and 0 <= numel):
                raise Refused("a storage's size must be a non-negative integer")
            known = self._storages.get(key)
            if known is None:
                self._budget.bytes_left -= 4 * numel
                if self._budget.bytes_left < 0:
                    raise Refused("its storages claim more bytes than the file holds")
                known = self._storages[key] = _Storage(key, numel)
            elif known.numel != numel:
                raise Refused(f"storage {key} is declared with two sizes")
            return known
        raise Refused(f"refused persistent id {quoted(pid)[:60]}")

    # -- handlers replacing the base class's ---------------------------------------------
    def _reduce(self) -> None:
        args = self.stack.pop()
        func = self.stack[-1]
        if func in (_ORDERED_DICT, _BACKEND) and args == ():
            self.stack[-1] = {} if func is _ORDERED_DICT else _BACKEND_VALUE
        elif func is _REBUILD_TENSOR:
            self.stack[-1] = _tensor(args)
        elif func is _REBUILD_PARAMETER:
            if not (type(args) is tuple and len(args) == 3 and isinstance(args[0], TensorRef)
                    and type(args[1]) is bool and args[2] == {}):
                raise Refused("a parameter must be (tensor, requires_grad, {})")
            self.stack[-1] = args[0]
        else:
            raise Refused(f"refused to call {quoted(getattr(func, 'name', type(func).__name__))}")

    def _newobj(self) -> None:
        args = self.stack.pop()
        cls = self.stack.pop()
        if not (isinstance(cls, _Global) and cls.name in _MODULE_CLASSES and args == ()):
            raise Refused(f"refused to create {quoted(getattr(cls, 'name', type(cls).__name__))}")
        self.append(ModuleObject(cls))

    def _build(self) -> None:
        state = self.stack.pop()
        inst = self.stack[-1]
        if not (isinstance(inst, ModuleObject) and inst.state is None and type(state) is dict):
            raise Refused("refused to set the state of anything but a new module object from a dict")
        inst.state = state

    def _setitem(self) -> None:
        value = self.stack.pop()
        key = self.stack.pop()
        self._set(self.stack[-1], [(key, value)])

    def _setitems(self) -> None:
        items = self.pop_mark()
        self._set(self.stack[-1], list(zip(items[::2], items[1::2], strict=False)))

    @staticmethod
    def _set(target: Any, items: list[tuple[Any, Any]]) -> None:
        """Only string keys (hashing a crafted key of shared nested tuples takes exponential time)."""
        if type(target) is not dict or any(type(key) is not str for key, _ in items):
            raise Refused("refused a dict that is not a plain dict with string keys")
        target.update(items)

    def _append(self) -> None:
        value = self.stack.pop()
        self._extend(self.stack[-1], [value])

    def _appends(self) -> None:
        items = self.pop_mark()
        self._extend(self.stack[-1], items)

    @staticmethod
    def _extend(target: Any, items: list[Any]) -> None:
        if type(target) is not list:
            raise Refused("refused to append to anything but a list")
        target.extend(items)


def _tensor(args: Any) -> TensorRef:
    """``_rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks)``: contiguous and inside
    its storage, or refused."""
    if not (type(args) is tuple and len(args) == 6 and isinstance(args[0], _Storage)):
        raise Refused("a tensor must be (storage, offset, size, stride, requires_grad, hooks)")
    storage, offset, shape, stride, requires_grad, hooks = args
    if not (type(shape) is tuple and type(stride) is tuple and len(shape) == len(stride) <= 4
            and all(type(n) is int and n >= 0 for n in (offset, *shape, *stride))):
        raise Refused("a tensor's offset, size and stride must be non-negative integers (at most 4 dimensions)")
    contiguous, step = [], 1
    for n in reversed(shape):
        contiguous.insert(0, step)
        step *= n
    if list(stride) != contiguous and step > 0:
        raise Refused(f"refused a tensor with stride {stride}: only contiguous tensors are used")
    if offset + step > storage.numel:
        raise Refused(f"a tensor of size {shape} at {offset} does not fit its storage of {storage.numel}")
    if type(requires_grad) is not bool or hooks != {}:
        raise Refused("a tensor's requires_grad must be a bool and its hooks empty")
    return TensorRef(storage, offset, shape)


class _Dispatch(dict):
    """Opcode -> handler; an opcode not in it is refused by name."""

    def __missing__(self, code: int) -> NoReturn:
        raise Refused(f"refused pickle opcode {_OPCODE_NAMES.get(code, hex(code))}: the authors' files do not use it")


def _counted(op: Callable[[_Unpickler], None]) -> Callable[[_Unpickler], None]:
    def run(unpickler: _Unpickler) -> None:
        unpickler._budget.opcodes_left -= 1
        if unpickler._budget.opcodes_left < 0:
            raise Refused(f"holds more than {MAX_OPCODES} pickle opcodes")
        op(unpickler)

    return run


_HANDLERS = {"REDUCE": _Unpickler._reduce, "NEWOBJ": _Unpickler._newobj, "BUILD": _Unpickler._build,
             "SETITEM": _Unpickler._setitem, "SETITEMS": _Unpickler._setitems, "APPEND": _Unpickler._append,
             "APPENDS": _Unpickler._appends}
_Unpickler.dispatch = _Dispatch(
    (code, _counted(_HANDLERS.get(_OPCODE_NAMES[code], op)))
    for code, op in pickle._Unpickler.dispatch.items()
    if _OPCODE_NAMES[code] in _OPCODES
)


# --------------------------------------------------------------------------- the legacy container
@dataclass(frozen=True)
class LegacyFile:
    """A legacy torch file's saved object (a tree of :class:`ModuleObject`, dicts, lists, tuples and tensors)."""

    root: Any
    tensors: dict[TensorRef, torch.Tensor]
    sha256: str

    def tensor(self, ref: Any, what: str, shape: tuple[int, ...]) -> torch.Tensor:
        if not isinstance(ref, TensorRef):
            raise Refused(f"{what} is {type(ref).__name__}, not a tensor")
        if ref.shape != shape:
            raise Refused(f"{what} has shape {ref.shape}, not {shape}")
        return self.tensors[ref]


def _read_regular(path: Path) -> bytes:
    try:
        reason = not_regular_reason(path.stat().st_mode)
        if reason is None:
            with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as file:
                info = os.fstat(file.fileno())
                reason = not_regular_reason(info.st_mode)
                if reason is None:
                    if info.st_size > MAX_FILE_BYTES:
                        raise AuthorsModelError(path, f"is {info.st_size} bytes, more than an authors' model file's "
                                                f"{MAX_FILE_BYTES}")
                    return file.read(info.st_size)
    except FileNotFoundError:
        raise AuthorsModelError(path, "does not exist") from None
    except OSError as err:
        raise AuthorsModelError(path, f"cannot be read ({err.strerror or err})") from None
    raise AuthorsModelError(path, reason)


def _walk(value: Any) -> list[TensorRef]:
    """Every tensor reference in the tree, without recursion (a crafted file may nest deeply)."""
    found, stack, seen = [], [value], set()
    while stack:
        item = stack.pop()
        if id(item) in seen:
            continue
        seen.add(id(item))
        if isinstance(item, TensorRef):
            found.append(item)
        elif isinstance(item, ModuleObject):
            stack.append(item.state)
        elif type(item) is dict:
            stack.extend(item.values())
        elif type(item) in (list, tuple):
            stack.extend(item)
    return found


def read_legacy(data: bytes) -> tuple[Any, dict[TensorRef, torch.Tensor]]:
    """The saved object and its tensors from a legacy torch file's bytes; :class:`Refused` (or any error a
    malformed pickle trips) otherwise."""
    stream, budget, storages = io.BytesIO(data), _Budget(MAX_OPCODES, len(data)), {}

    def load() -> Any:
        return _Unpickler(stream, budget, storages).load()

    if load() != LEGACY_MAGIC:
        raise Refused("is not a legacy torch file (no magic number)")
    if load() != LEGACY_PROTOCOL:
        raise Refused("has a legacy torch protocol other than 1001")
    info = load()
    if not (type(info) is dict and info.get("little_endian") is True):
        raise Refused("was not saved little-endian")
    root = load()
    keys = load()
    if not (type(keys) is list and all(type(k) is str for k in keys) and len(set(keys)) == len(keys)
            and set(keys) == set(storages)):
        raise Refused("its storage key list does not match the storages its object uses")
    arrays = {}
    for key in keys:
        count = int.from_bytes(stream.read(8), "little", signed=True)
        if count != storages[key].numel:
            raise Refused(f"storage {key} holds {count} elements, not the {storages[key].numel} declared")
        raw = stream.read(4 * count)
        if len(raw) != 4 * count:
            raise Refused(f"is truncated (storage {key} needs {4 * count} bytes, {len(raw)} left)")
        arrays[key] = np.frombuffer(raw, dtype="<f4")
    if stream.read(1):
        raise Refused("has bytes after its last storage")
    tensors = {}
    for ref in _walk(root):
        flat = arrays[ref.storage.key][ref.offset:ref.offset + int(np.prod(ref.shape, dtype=np.int64))]
        values = torch.from_numpy(flat.astype(np.float32).reshape(ref.shape))
        if not bool(torch.isfinite(values).all()):
            raise Refused("holds non-finite weights (NaN or infinity)")
        tensors[ref] = values
    return root, tensors


def load_legacy(path: str | os.PathLike[str]) -> LegacyFile:
    """Read an authors' legacy torch file without running its code; :class:`AuthorsModelError` otherwise."""
    file = Path(path)
    data = _read_regular(file)
    try:
        root, tensors = read_legacy(data)
    except Refused as err:
        raise AuthorsModelError(file, str(err)) from None
    except MemoryError:
        raise
    except Exception as err:  # a malformed pickle raises whatever its opcodes trip over
        detail = f"{type(err).__name__}: {err}"[:300] if str(err) else type(err).__name__
        raise AuthorsModelError(file, f"is not a readable legacy torch file ({detail})") from None
    return LegacyFile(root, tensors, hashlib.sha256(data).hexdigest())
