"""Fuzzing model files: mutated checkpoints never crash, hang, bomb or escape ``load_model`` (issue 11).

Seeds are small valid files (so mutations often land in the header JSON): a transition
model and a cumulative residual model with digests, and a transition model saved before
digests existed, whose mutated weights reach the shape, dtype and NaN checks instead of
the digest.  Every input is either loaded or refused with one line naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from fuzz_harness import DecoderWorker, fuzz, mutated
from hypothesis import strategies as st
from safetensors import safe_open
from safetensors.torch import save_file

from t42_transfer.models import CumulativeResidualModel, Normalisation, TransitionModel
from t42_transfer.models.checkpoint import DIGEST_KEY, save_model

TARGET = "t42_transfer.models.checkpoint:load_model"
ERRORS = "t42_transfer.data.errors:DataFileError"
MEM_MB = 256
"""The old loader took 2.4 GB for ``hidden: 30000``; a 1 kB file justifies far less than this."""


def _seeds(directory: Path) -> list[bytes]:
    torch.manual_seed(0)
    small = TransitionModel(Normalisation.identity(), hidden=4)
    residual = CumulativeResidualModel(small, TransitionModel(Normalisation.identity(), hidden=3), 0.3, 0.99)
    paths = [save_model(small, directory / "transition.safetensors", method="direct"),
             save_model(residual, directory / "residual.safetensors", method="cumulative_residual")]
    old = directory / "old.safetensors"  # as saved before digests existed
    with safe_open(str(paths[0]), framework="pt") as f:
        meta = json.loads(f.metadata()["t42_transfer"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    del meta[DIGEST_KEY]
    save_file(tensors, str(old), metadata={"t42_transfer": json.dumps(meta)})
    return [p.read_bytes() for p in (*paths, old)]


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> list[bytes]:
    return _seeds(tmp_path_factory.mktemp("seeds"))


@pytest.fixture(scope="module")
def worker(tmp_path_factory: pytest.TempPathFactory):
    with DecoderWorker(TARGET, errors=ERRORS, mem_mb=MEM_MB, keep_dir=tmp_path_factory.mktemp("escapes")) as w:
        yield w


def test_seeds_load(worker: DecoderWorker, seeds: list[bytes]) -> None:
    for data in seeds:
        assert worker.check_bytes(data, "model.safetensors").outcome == "accepted"


def _split(file: bytes) -> tuple[bytes, bytes]:
    """A safetensors file's header JSON and data section."""
    size = int.from_bytes(file[:8], "little")
    return file[8:8 + size], file[8 + size:]


def _pack(header: bytes, data: bytes) -> bytes:
    """A safetensors file of ``header`` (its length prefix right, padded as safetensors pads) and ``data``."""
    header += b" " * (-len(header) % 8)
    return len(header).to_bytes(8, "little") + header + data


def _with_metadata(file: bytes, text: str) -> bytes:
    """``file`` with its t42_transfer metadata text replaced, everything else kept."""
    header, data = _split(file)
    parsed = json.loads(header)
    parsed["__metadata__"]["t42_transfer"] = text
    return _pack(json.dumps(parsed).encode(), data)


def _header_edit(seed: bytes, edit) -> bytes:
    """``seed`` with its metadata replaced by ``edit(meta)`` (a JSON string), weights untouched."""
    return _with_metadata(seed, edit(json.loads(json.loads(_split(seed)[0])["__metadata__"]["t42_transfer"])))


def _with_config(**change: object):
    return lambda meta: json.dumps({**meta, "config": {**meta["config"], **change}})


DEEP = "[" * 50_000 + "]" * 50_000
CRAFTED = {
    "hidden 30000": (_with_config(hidden=30000), "hidden must lie in [1, 4096], not 30000"),
    "hidden -1": (_with_config(hidden=-1), "hidden must lie in [1, 4096], not -1"),
    "hidden 1e6": (_with_config(hidden=1e6), "hidden must be an integer, not 1000000.0"),
    "not an object": (lambda meta: json.dumps([meta]), "not a JSON object but list"),
    "list kind": (lambda meta: json.dumps({**meta, "kind": [meta["kind"]]}), "'kind' that is not a string"),
    "deep nesting": (lambda meta: json.dumps(meta).replace('"data": {}', '"data": ' + DEEP), "nested deeper"),
    "unknown kind": (lambda meta: json.dumps({**meta, "kind": "gaussian_process"}), "unknown kind"),
}
"""The issue's crafted checkpoints: metadata edit and what the refusal must say."""


@pytest.mark.parametrize("case", list(CRAFTED))
def test_crafted_cases_are_refused_in_bounded_memory(worker: DecoderWorker, seeds: list[bytes], case: str) -> None:
    """Through the guarded worker: refused for the right reason, within ``MEM_MB``, in one line."""
    edit, reason = CRAFTED[case]
    verdict = worker.check_bytes(_header_edit(seeds[0], edit), "model.safetensors")
    assert verdict.outcome == "refused" and reason in verdict.detail


def test_nan_weights_are_refused(worker: DecoderWorker, seeds: list[bytes]) -> None:
    old = bytearray(seeds[2])  # no digest: the NaN check itself must refuse it
    old[-4:] = b"\x00\x00\xc0\x7f"  # a float32 NaN in the last weight
    verdict = worker.check_bytes(bytes(old), "model.safetensors")
    assert verdict.outcome == "refused" and "non-finite" in verdict.detail


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8)
    | st.sampled_from([30000, -1, 0, 1e6, 10**400, 4096, "transition", "cumulative_residual", {}, []]),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)
"""Values a careless or hostile writer might put anywhere in the metadata (NaN and infinity included)."""


def _slots(value: object) -> list[tuple[dict | list, str | int]]:
    """Every (container, key) in JSON ``value``: the places a field can be replaced."""
    slots, stack = [], [value]
    while stack:
        item = stack.pop()
        keys = item.keys() if isinstance(item, dict) else range(len(item)) if isinstance(item, list) else ()
        for key in keys:
            slots.append((item, key))
            stack.append(item[key])
    return slots


@st.composite
def mutated_checkpoints(draw: st.DrawFn, seeds: list[bytes]) -> bytes:
    """A seed mutated in one part: whole-file bytes, or (framing kept valid, so the mutation reaches deeper
    checks) the safetensors header JSON, the metadata text inside it, one metadata value (replaced by any JSON
    value, or removed), or the data section (its length kept)."""
    seed = draw(st.sampled_from(seeds))
    header, data = _split(seed)
    part = draw(st.sampled_from(("file", "header", "metadata", "value", "data")))
    if part == "file":
        return draw(mutated(seed))
    if part == "value":
        meta = json.loads(json.loads(header)["__metadata__"]["t42_transfer"])
        container, key = draw(st.sampled_from(_slots(meta)))
        if isinstance(container, dict) and draw(st.booleans()):
            del container[key]
        else:
            container[key] = draw(JSON_VALUES)
        return _with_metadata(seed, json.dumps(meta))
    if part == "header":
        return _pack(draw(mutated(header)), data)
    if part == "metadata":
        text = json.loads(header)["__metadata__"]["t42_transfer"].encode()
        return _with_metadata(seed, draw(mutated(text)).decode("utf-8", "replace"))
    return _pack(header, draw(mutated(data))[:len(data)].ljust(len(data), b"\0"))


def _fuzz(worker: DecoderWorker, seeds: list[bytes], examples: int) -> dict[str, int]:
    counts = fuzz(worker, mutated_checkpoints(seeds), "model.safetensors", examples)
    assert sum(counts.values()) >= examples
    return counts


def test_mutated_checkpoints_fast_slice(worker: DecoderWorker, seeds: list[bytes]) -> None:
    _fuzz(worker, seeds, 40)


@pytest.mark.slow
def test_mutated_checkpoints(worker: DecoderWorker, seeds: list[bytes]) -> None:
    counts = _fuzz(worker, seeds, 2000)
    assert counts["refused"] > 0
