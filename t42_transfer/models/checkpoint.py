"""Model files: weights in safetensors plus JSON metadata in its header; loading never unpickles.

One file holds everything needed to rebuild and trust a model: its kind and
architecture, the transfer method and hyper-parameters that made it, the
normalisation (as buffers among the weights), fingerprints of the data it saw,
library versions, and a SHA-256 digest of its weights.  Saving is atomic: a crash
mid-save never leaves a half-written file under the final name.

Loading treats the file as untrusted and is total: it returns a model or raises
:class:`CheckpointError` (one line naming the file).  Everything is checked before
it is used, in this order: a regular file (a FIFO or directory is never opened);
a safetensors header of bounded size whose tensors fit the file's real size; metadata that
is a JSON object of bounded depth with fields of the right types; an architecture
whose ``from_config`` accepts it, built on the ``meta`` device so nothing is
allocated; the file's tensor names and shapes against that architecture; only then
the weights themselves, which must match their digest and be finite (each normalisation std above 0).  So a model
never takes more memory than its file justifies, and a new model kind's
``from_config`` must check its (untrusted) config the way ``TransitionModel``'s does.

Files saved before digests existed (no ``weights_sha256``) still load, with an
:class:`UnverifiedCheckpointWarning`: they were written by this project, and
refusing them would strand existing models; saving one again adds the digest.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import reprlib
import tempfile
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file
from torch import Tensor

from t42_transfer import __version__
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, STATE_NAMES, checked_action_unit
from t42_transfer.data.errors import DataFileError
from t42_transfer.files import not_regular_reason
from t42_transfer.models.dynamics import MODEL_KINDS, LatentDynamics

FORMAT = "t42_transfer.model/1"
_HEADER_KEY = "t42_transfer"
DIGEST_KEY = "weights_sha256"
UNIT_KEY = "action_unit_rad"
"""The actuator-angle step (rad) of an action of 1 in the data the model learnt from (``conventions``: the suite's
or the paper authors' unit)."""
UNIT_ASSUMED_KEY = "action_unit_assumed"
"""Set (true) in the metadata read of a file saved before the unit was stored: its ``action_unit_rad`` is then
assumed, the suite's, or the authors' for their imports (method ``authors_...``); a model trained on their data
(an experiment on their files) cannot be told apart, so checks against data take such a file as in the data's."""
MAX_HEADER_BYTES = 2**20
"""Largest safetensors header (tensor table and metadata JSON) read; saved files have a few kB, so parsing
a file's JSON never takes more than a few tens of MB however it is crafted."""
MAX_METADATA_DEPTH = 32
"""Deepest nesting of objects and lists in a file's metadata (saved files use under 10)."""
_FIELDS: dict[str, tuple[type | tuple[type, ...], bool]] = {
    "format": (str, True), "state_layout": (list, True), "kind": (str, True), "config": (dict, True),
    "method": (str, True), "hyperparameters": (dict, False), "data": (dict, False), "extra": (dict, False),
    "versions": (dict, False), DIGEST_KEY: (str, False), UNIT_KEY: ((int, float), False),
}
"""Metadata fields this project reads: their JSON type and whether a file must have them."""


class CheckpointError(DataFileError):
    """A model file that is missing, damaged, or not the model the caller asked for."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        super().__init__(path, " ".join(problem.split()))  # one line, whatever a library's message holds


class UnverifiedCheckpointWarning(UserWarning):
    """A model file without a weights digest (saved before digests existed) was loaded unverified."""


def weights_digest(tensors: Mapping[str, Tensor]) -> str:
    """SHA-256 of names, dtypes, shapes and bytes in name order: independent of how the file lays them out."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        tensor = tensors[name].detach().to("cpu").contiguous()
        digest.update(json.dumps([name, str(tensor.dtype), list(tensor.shape)]).encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def save_model(
    model: LatentDynamics,
    path: str | os.PathLike[str],
    *,
    method: str,
    hyperparameters: dict[str, Any] | None = None,
    data: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    action_unit_rad: float = ACTION_UNIT_RAD,
) -> Path:
    """Write ``model`` to ``path`` atomically; returns the path.  ``action_unit_rad`` is the unit of the actions it
    learnt from: the suite's for simulated hands and bags read as they are, the authors' for their data."""
    checked_action_unit(action_unit_rad)  # before anything is written
    target = Path(path)
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    metadata = {
        "format": FORMAT,
        "kind": model.kind,
        "config": model.config(),
        "method": method,
        "hyperparameters": hyperparameters or {},
        "data": data or {},
        "state_layout": list(STATE_NAMES),
        "latent_dim": model.latent_dim,
        UNIT_KEY: float(action_unit_rad),
        "versions": {"t42_transfer": __version__, "torch": torch.__version__, "numpy": np.__version__},
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        DIGEST_KEY: weights_digest(tensors),
        **({"extra": extra} if extra else {}),
    }
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent)
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata={_HEADER_KEY: json.dumps(metadata, default=str)})
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON metadata of a model file, checked for format, state layout and field types."""
    file = _regular_file(path)
    with _open(file) as f:
        return _metadata(file, f)


def load_model(
    path: str | os.PathLike[str], *, expect_method: str | None = None
) -> tuple[LatentDynamics, dict[str, Any]]:
    """Rebuild the model in ``path`` (evaluation mode) and return it with its metadata."""
    file = _regular_file(path)
    with _open(file) as f:
        meta = _metadata(file, f)
        if expect_method is not None and meta["method"] != expect_method:
            raise CheckpointError(file, f"holds a {reprlib.repr(meta['method'])} model, not {expect_method!r}")
        model = _architecture(file, meta)
        expected = model.state_dict()
        _check_names_and_shapes(file, f, expected)
        tensors = _read_tensors(file, f, expected)
    _check_weights(file, meta, tensors)
    model.load_state_dict(tensors, strict=True, assign=True)  # the meta-device model takes the loaded tensors
    return model.eval(), meta


def _regular_file(path: str | os.PathLike[str]) -> Path:
    """``path`` if it is a regular file; checked before opening, so a FIFO cannot block the reader."""
    file = Path(path)
    try:
        mode = file.stat().st_mode
    except FileNotFoundError:
        raise CheckpointError(file, "does not exist") from None
    except (OSError, ValueError) as err:
        raise CheckpointError(file, f"cannot be read ({getattr(err, 'strerror', None) or err})") from None
    reason = not_regular_reason(mode)
    if reason is not None:
        raise CheckpointError(file, reason)
    return file


def _open(file: Path) -> Any:
    """The file's safetensors reader; the header is bounded and its tensors already fit the file's size."""
    try:
        with open(file, "rb") as raw:
            head = raw.read(8)
        header_size = int.from_bytes(head, "little")  # a shorter file is safetensors' to report
        if header_size > MAX_HEADER_BYTES:
            if _is_pickle(head):
                raise CheckpointError(file, f"is a pickle (as the paper authors' models are), not a model file; "
                                      f"convert an authors' model first: t42 model import-authors {file} "
                                      f"OUT.safetensors")
            raise CheckpointError(file, f"is not a readable model file (truncated or corrupt: its header claims "
                                  f"{header_size} bytes, a model file's has under {MAX_HEADER_BYTES})")
        return safe_open(str(file), framework="pt")
    except (SafetensorError, OSError) as err:
        raise CheckpointError(file, f"is not a readable model file (truncated or corrupt: {err})") from None


def _is_pickle(head: bytes) -> bool:
    """Whether ``head`` opens a pickle of protocol 2 or later, as the authors' ``torch.save`` files do (so the user
    hears to convert it, not a header size); asked only of a size out of range: a 0x280-byte header starts 80 02."""
    return len(head) > 1 and head[:1] == pickle.PROTO and 2 <= head[1] <= pickle.HIGHEST_PROTOCOL


def _metadata(file: Path, f: Any) -> dict[str, Any]:
    header = f.metadata() or {}
    if _HEADER_KEY not in header:
        raise CheckpointError(file, "is a safetensors file without t42_transfer metadata")
    try:
        meta = json.loads(header[_HEADER_KEY])
    except RecursionError:
        raise CheckpointError(file, f"has metadata nested deeper than {MAX_METADATA_DEPTH} levels") from None
    except ValueError as err:  # also numbers too long for Python's int
        raise CheckpointError(file, f"has unreadable metadata ({err})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(file, f"has metadata that is not a JSON object but {type(meta).__name__}")
    if _depth(meta) > MAX_METADATA_DEPTH:
        raise CheckpointError(file, f"has metadata nested deeper than {MAX_METADATA_DEPTH} levels")
    if meta.get("format") != FORMAT:
        raise CheckpointError(file, f"has format {reprlib.repr(meta.get('format'))}; this version reads {FORMAT!r}")
    if meta.get("state_layout") != list(STATE_NAMES):
        raise CheckpointError(
            file, f"was trained on state layout {reprlib.repr(meta.get('state_layout'))}, not {list(STATE_NAMES)}"
        )
    for name, (kind, required) in _FIELDS.items():
        if (required or name in meta) and not isinstance(meta.get(name), kind):
            what = {str: "a string", list: "a list", dict: "an object"}.get(kind, "a number")
            raise CheckpointError(file, f"has metadata {name!r} that is not {what}: {reprlib.repr(meta.get(name))}")
    if UNIT_KEY not in meta:
        meta[UNIT_KEY] = AUTHORS_ACTION_UNIT_RAD if meta["method"].startswith("authors_") else ACTION_UNIT_RAD
        meta[UNIT_ASSUMED_KEY] = True
    try:
        checked_action_unit(meta[UNIT_KEY])
    except ValueError as err:
        raise CheckpointError(file, f"has metadata {UNIT_KEY!r}: {err}") from None
    return meta


def _depth(value: object) -> int:
    """Nesting depth of JSON ``value``, counted without recursion (so any depth json.loads returns is safe)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, depth)
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return deepest


def _architecture(file: Path, meta: dict[str, Any]) -> LatentDynamics:
    """The declared model, built on the ``meta`` device: checked by ``from_config``, nothing allocated."""
    kind = meta["kind"]
    if kind not in MODEL_KINDS:
        raise CheckpointError(file, f"holds a model of unknown kind {reprlib.repr(kind)}; known: {sorted(MODEL_KINDS)}")
    try:
        with torch.device("meta"):
            return MODEL_KINDS[kind].from_config(meta["config"])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(file, f"has an architecture this version cannot build ({err})") from None


def _check_names_and_shapes(file: Path, f: Any, expected: Mapping[str, Tensor]) -> None:
    """The file holds exactly the architecture's tensors, each of its shape: checked before reading any."""
    names = set(f.keys())
    if names != set(expected):
        missing, unexpected = sorted(set(expected) - names), sorted(names - set(expected))
        raise CheckpointError(
            file, f"weights do not fit its declared architecture (missing {reprlib.repr(missing)}, "
            f"unexpected {reprlib.repr(unexpected)})"
        )
    for name, tensor in expected.items():
        shape = list(f.get_slice(name).get_shape())
        if shape != list(tensor.shape):
            raise CheckpointError(
                file, f"weights do not fit its declared architecture ({name} is {shape}, not {list(tensor.shape)})"
            )


def _read_tensors(file: Path, f: Any, expected: Mapping[str, Tensor]) -> dict[str, Tensor]:
    tensors = {}
    for name, tensor in expected.items():
        try:
            tensors[name] = f.get_tensor(name)
        except (SafetensorError, OSError, RuntimeError, TypeError, ValueError) as err:
            raise CheckpointError(file, f"has unreadable weights {name} (truncated or corrupt: {err})") from None
        if tensors[name].dtype != tensor.dtype:
            raise CheckpointError(file, f"holds {name} as {tensors[name].dtype}, not {tensor.dtype}")
    return tensors


def _check_weights(file: Path, meta: dict[str, Any], tensors: Mapping[str, Tensor]) -> None:
    """Weights that match their digest (or a warning for files saved before digests), finite, and every
    normalisation std (``state_std``, ``delta_std``, in any sub-model) above 0: a model divides by it."""
    if DIGEST_KEY not in meta:
        warnings.warn(f"{file}: has no weights digest (saved before digests existed); loaded unverified",
                      UnverifiedCheckpointWarning, stacklevel=3)
    elif weights_digest(tensors) != meta[DIGEST_KEY]:
        raise CheckpointError(file, "has weights that do not match their digest (corrupt or altered)")
    for name, tensor in tensors.items():
        if (tensor.is_floating_point() or tensor.is_complex()) and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(file, f"holds non-finite weights (NaN or infinity) in {name}")
        if name.rpartition(".")[2].endswith("_std") and not bool((tensor > 0).all()):  # a division by it: NaN
            raise CheckpointError(file, f"holds a normalisation std that is not positive in {name} "
                                  f"(smallest {tensor.min().item():g})")
