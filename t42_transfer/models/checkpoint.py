"""Model files: weights in safetensors plus JSON metadata in its header; loading never unpickles.

One file holds everything needed to rebuild and trust a model: its kind and
architecture, the transfer method and hyper-parameters that made it, the
normalisation (as buffers among the weights), fingerprints of the data it saw,
and library versions.  Saving is atomic: a crash mid-save never leaves a
half-written file under the final name.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from t42_transfer import __version__
from t42_transfer.conventions import STATE_NAMES
from t42_transfer.data.errors import DataFileError
from t42_transfer.models.dynamics import MODEL_KINDS, LatentDynamics

FORMAT = "t42_transfer.model/1"
_HEADER_KEY = "t42_transfer"


class CheckpointError(DataFileError):
    """A model file that is missing, damaged, or not the model the caller asked for."""


def save_model(
    model: LatentDynamics,
    path: str | os.PathLike[str],
    *,
    method: str,
    hyperparameters: dict[str, Any] | None = None,
    data: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``model`` to ``path`` atomically; returns the path."""
    target = Path(path)
    metadata = {
        "format": FORMAT,
        "kind": model.kind,
        "config": model.config(),
        "method": method,
        "hyperparameters": hyperparameters or {},
        "data": data or {},
        "state_layout": list(STATE_NAMES),
        "latent_dim": model.latent_dim,
        "versions": {"t42_transfer": __version__, "torch": torch.__version__, "numpy": np.__version__},
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **({"extra": extra} if extra else {}),
    }
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
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
    """The JSON metadata of a model file, checked for format and state layout."""
    from safetensors import safe_open

    file = Path(path)
    if not file.is_file():
        raise CheckpointError(file, "does not exist" if not file.exists() else "is not a file")
    try:
        with safe_open(str(file), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(file, f"is not a readable model file (truncated or corrupt: {err})") from None
    if _HEADER_KEY not in header:
        raise CheckpointError(file, "is a safetensors file without t42_transfer metadata")
    try:
        meta = json.loads(header[_HEADER_KEY])
    except json.JSONDecodeError as err:
        raise CheckpointError(file, f"has unreadable metadata ({err})") from None
    if meta.get("format") != FORMAT:
        raise CheckpointError(file, f"has format {meta.get('format')!r}; this version reads {FORMAT!r}")
    if meta.get("state_layout") != list(STATE_NAMES):
        raise CheckpointError(
            file, f"was trained on state layout {meta.get('state_layout')}, not {list(STATE_NAMES)}"
        )
    return meta


def load_model(
    path: str | os.PathLike[str], *, expect_method: str | None = None
) -> tuple[LatentDynamics, dict[str, Any]]:
    """Rebuild the model in ``path`` (evaluation mode) and return it with its metadata."""
    file = Path(path)
    meta = read_metadata(file)
    if expect_method is not None and meta.get("method") != expect_method:
        raise CheckpointError(file, f"holds a {meta.get('method')!r} model, not {expect_method!r}")
    kind = meta.get("kind")
    if kind not in MODEL_KINDS:
        raise CheckpointError(file, f"holds a model of unknown kind {kind!r}; known: {sorted(MODEL_KINDS)}")
    try:
        model = MODEL_KINDS[kind].from_config(meta["config"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(file, f"has an architecture this version cannot build ({err})") from None
    try:
        tensors = load_file(str(file))
    except (SafetensorError, OSError) as err:
        raise CheckpointError(file, f"has unreadable weights (truncated or corrupt: {err})") from None
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as err:
        first = str(err).splitlines()[0]
        raise CheckpointError(file, f"weights do not fit its declared architecture ({first})") from None
    return model.eval(), meta
