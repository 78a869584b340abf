"""Model files: exact round trip of every model kind, and a clear error for each bad file."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from t42_transfer.models import CumulativeResidualModel, Normalisation, RecurrentResidualModel, TransitionModel
from t42_transfer.models.checkpoint import CheckpointError, load_model, read_metadata, save_model


def _models() -> dict[str, torch.nn.Module]:
    torch.manual_seed(0)
    norm = Normalisation.identity()
    source, residual = TransitionModel(norm), TransitionModel(norm)
    with torch.no_grad():
        source.state_mean.copy_(torch.tensor([1.0, 2.0, 3.0, 4.0]))
    return {
        "direct": source,
        "grasp": TransitionModel(norm, grasp_input=True),
        "cumulative_residual": CumulativeResidualModel(source, residual, 0.3, 0.99),
        "recurrent_residual": RecurrentResidualModel(source, residual, 0.3),
    }


@pytest.mark.parametrize("name", list(_models()))
def test_round_trip_gives_the_same_predictions(name: str, tmp_path: Path) -> None:
    model = _models()[name]
    path = save_model(model, tmp_path / "m.safetensors", method=name, hyperparameters={"lr": 2.5e-5}, data={"target": "abc"})
    loaded, meta = load_model(path, expect_method=name)
    assert type(loaded) is type(model) and meta["method"] == name and meta["data"] == {"target": "abc"}
    assert meta["hyperparameters"] == {"lr": 2.5e-5} and "torch" in meta["versions"]
    x0, actions = torch.randn(3, 4), torch.rand(3, 9, 2) * 2 - 1
    assert torch.equal(loaded.rollout(x0, actions), model.rollout(x0, actions))
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"]  # no temporary files left


@pytest.fixture()
def saved(tmp_path: Path) -> Path:
    return save_model(_models()["direct"], tmp_path / "m.safetensors", method="direct")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="does not exist"):
        load_model(tmp_path / "none.safetensors")


@pytest.mark.parametrize("keep", [0, 7, 100, -50])
def test_truncated_file(saved: Path, keep: int) -> None:
    data = saved.read_bytes()
    saved.write_bytes(data[:keep] if keep >= 0 else data[:keep])
    with pytest.raises(CheckpointError, match="truncated or corrupt") as err:
        load_model(saved)
    assert str(saved) in str(err.value)


def test_garbage_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x80\x04\x95 this is a pickle, not a model")
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_model(bad)


def test_other_method_is_refused(saved: Path) -> None:
    with pytest.raises(CheckpointError, match="holds a 'direct' model, not 'cumulative_residual'"):
        load_model(saved, expect_method="cumulative_residual")


def _rewrite_metadata(path: Path, change) -> None:
    tensors = {}
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["t42_transfer"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    change(meta, tensors)
    save_file(tensors, str(path), metadata={"t42_transfer": json.dumps(meta)})


def test_other_state_layout_is_refused(saved: Path) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta.update(state_layout=["x", "y", "angle", "load1", "load2"]))
    with pytest.raises(CheckpointError, match="state layout"):
        load_model(saved)


def test_unknown_kind_and_format(saved: Path) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta.update(kind="gaussian_process"))
    with pytest.raises(CheckpointError, match="unknown kind 'gaussian_process'"):
        load_model(saved)
    _rewrite_metadata(saved, lambda meta, _: meta.update(format="t42_transfer.model/99"))
    with pytest.raises(CheckpointError, match="format"):
        read_metadata(saved)


def test_weights_that_do_not_fit_the_architecture(saved: Path) -> None:
    _rewrite_metadata(saved, lambda _, tensors: tensors.pop("net.0.weight"))
    with pytest.raises(CheckpointError, match="do not fit"):
        load_model(saved)


def test_safetensors_without_our_metadata(tmp_path: Path) -> None:
    path = tmp_path / "plain.safetensors"
    save_file({"w": torch.zeros(2)}, str(path))
    with pytest.raises(CheckpointError, match="without t42_transfer metadata"):
        load_model(path)


def test_header_length_lie_is_caught(saved: Path) -> None:
    data = bytearray(saved.read_bytes())
    data[:8] = struct.pack("<Q", 10**9)
    saved.write_bytes(bytes(data))
    with pytest.raises(CheckpointError):
        load_model(saved)
