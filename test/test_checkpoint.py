"""Model files: exact round trip of every model kind, and a clear error for each bad file."""

from __future__ import annotations

import json
import os
import struct
import warnings
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD
from t42_transfer.models import CumulativeResidualModel, Normalisation, RecurrentResidualModel, TransitionModel
from t42_transfer.models.checkpoint import (
    DIGEST_KEY,
    UNIT_ASSUMED_KEY,
    UNIT_KEY,
    CheckpointError,
    UnverifiedCheckpointWarning,
    load_model,
    read_metadata,
    save_model,
    weights_digest,
)


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
    path = save_model(model, tmp_path / "m.safetensors", method=name, hyperparameters={"lr": 2.5e-5},
                      data={"target": "abc"})
    loaded, meta = load_model(path, expect_method=name)
    assert type(loaded) is type(model) and meta["method"] == name and meta["data"] == {"target": "abc"}
    assert meta["hyperparameters"] == {"lr": 2.5e-5} and "torch" in meta["versions"]
    assert meta[DIGEST_KEY] == weights_digest(model.state_dict())
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
    _refused(bad, "is a pickle .*convert an authors' model first: t42 model import-authors")
    bad.write_bytes(b"\x00\xff this is garbage, not a model")
    _refused(bad, "truncated or corrupt")


def test_a_safetensors_header_that_starts_as_a_pickle_still_loads(tmp_path: Path) -> None:
    """A header of 0x280, 0x380, 0x480 or 0x580 bytes starts 80 02 to 80 05, as a pickle does: only a size out of
    range is taken for one."""
    for pad in range(0, 800, 8):  # safetensors pads its header to 8 bytes
        path = save_model(TransitionModel(Normalisation.identity()), tmp_path / "m.safetensors", method="direct",
                          extra={"p": "x" * pad})
        if path.read_bytes()[0] == 0x80 and 2 <= path.read_bytes()[1] <= 5:
            break
    else:
        pytest.fail("no padding gave a header size that starts as a pickle")
    load_model(path)


def test_other_method_is_refused(saved: Path) -> None:
    with pytest.raises(CheckpointError, match="holds a 'direct' model, not 'cumulative_residual'"):
        load_model(saved, expect_method="cumulative_residual")


def _rewrite_metadata(path: Path, change, *, redigest: bool = False) -> None:
    """Apply ``change(meta, tensors)`` to a saved file; ``redigest``: as a forger would, digest the new weights."""
    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["t42_transfer"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    change(meta, tensors)
    if redigest:
        meta[DIGEST_KEY] = weights_digest(tensors)
    _write_raw(path, tensors, json.dumps(meta))


def _write_raw(path: Path, tensors: dict[str, torch.Tensor], metadata_text: str) -> None:
    save_file(tensors, str(path), metadata={"t42_transfer": metadata_text})


def _refused(path: Path, match: str) -> CheckpointError:
    """``load_model`` refuses ``path`` with one line naming the file and matching ``match``."""
    with pytest.raises(CheckpointError, match=match) as err:
        load_model(path)
    assert "\n" not in str(err.value) and str(err.value).startswith(f"{path}: ")
    return err.value


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


def test_header_size_is_bounded(saved: Path) -> None:
    """A header within the file but over 1 MiB (JSON that would take hundreds of MB to parse) is not read."""
    _rewrite_metadata(saved, lambda meta, _: meta["data"].update(padding=[{}] * 300_000))
    _refused(saved, r"its header claims \d+ bytes, a model file's has under 1048576")


# --------------------------------------------------------------------------- crafted files (issue 11)
def test_sizes_out_of_bounds_are_refused_before_building(saved: Path) -> None:
    """``hidden: 30000`` allocated 2.4 GB; ``-1`` and ``1e6`` ended in torch tracebacks."""
    for hidden, match in [(30000, r"hidden must lie in \[1, 4096\], not 30000"), (-1, "hidden must lie in"),
                          (1e6, "hidden must be an integer, not 1000000.0"), ("128", "hidden must be an integer"),
                          (10**400, "hidden must lie in"), (True, "hidden must be an integer")]:
        _rewrite_metadata(saved, lambda meta, _, hidden=hidden: meta["config"].update(hidden=hidden))
        _refused(saved, "cannot build .*" + match)


def test_sizes_in_bounds_must_match_the_weights_in_the_file(saved: Path) -> None:
    """A plausible size the file's weights do not have is refused before any weight is read."""
    _rewrite_metadata(saved, lambda meta, _: meta["config"].update(hidden=4096))
    _refused(saved, r"do not fit .*net\.0\.weight is \[128, 6\], not \[4096, 6\]")


@pytest.mark.parametrize("text,match", [
    ("[1, 2]", "not a JSON object but list"),
    ('"model"', "not a JSON object but str"),
    ("null", "not a JSON object but NoneType"),
    ("[" * 100_000 + "]" * 100_000, "nested deeper than 32"),
    ('{"x": ' + "[" * 100 + "]" * 100 + "}", "nested deeper than 32"),
    ('{"hidden": ' + "9" * 5000 + "}", "unreadable metadata"),
    ("{not json", "unreadable metadata"),
])
def test_metadata_that_is_not_an_object_or_too_deep(saved: Path, text: str, match: str) -> None:
    with safe_open(str(saved), framework="pt") as f:
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    _write_raw(saved, tensors, text)
    _refused(saved, match)
    with pytest.raises(CheckpointError, match=match):
        read_metadata(saved)


@pytest.mark.parametrize("field,value,match", [
    ("kind", ["transition"], "'kind' that is not a string"),
    ("config", [1], "'config' that is not an object"),
    ("method", {"a": 1}, "'method' that is not a string"),
    ("data", "abc", "'data' that is not an object"),
    ("extra", 3, "'extra' that is not an object"),
    (DIGEST_KEY, 5, "'weights_sha256' that is not a string"),
    ("state_layout", "x", "state layout"),
    ("format", None, "format None"),
])
def test_wrong_typed_fields(saved: Path, field: str, value: object, match: str) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta.update({field: value}))
    _refused(saved, match)


@pytest.mark.parametrize("change,match", [
    ({"grasp_input": "yes"}, "grasp_input must be true or false"),
    ({"dropout": float("nan")}, "dropout must lie in"),
    ({"dropout": 1.5}, "dropout must lie in"),
    ({"depth": 3}, r"has no arguments \['depth'\]"),
])
def test_wrong_typed_transition_config(saved: Path, change: dict, match: str) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta["config"].update(change))
    _refused(saved, match)


@pytest.fixture()
def residual_file(tmp_path: Path) -> Path:
    return save_model(_models()["cumulative_residual"], tmp_path / "r.safetensors", method="cumulative_residual")


@pytest.mark.parametrize("change,match", [
    (lambda c: c.update(alpha="0.3"), "alpha must be a number, not '0.3'"),
    (lambda c: c.update(gamma=float("inf")), "gamma must lie in"),
    (lambda c: c.pop("alpha"), "alpha must be a number, not None"),
    (lambda c: c.update(source=[1]), "source must be"),
    (lambda c: c["source"].update(kind=["transition"]), "source must be"),
    (lambda c: c["source"].update(config="x"), "source must be"),
    (lambda c: c["residual"].update(kind="cumulative_residual"), "residual must be {kind: one of \\['transition'\\]"),
    (lambda c: c["source"]["config"].update(hidden=30000), "hidden must lie in"),
])
def test_wrong_typed_residual_config(residual_file: Path, change, match: str) -> None:
    _rewrite_metadata(residual_file, lambda meta, _: change(meta["config"]))
    _refused(residual_file, match)


def test_residual_nesting_is_bounded(residual_file: Path) -> None:
    def nest(meta: dict, _: dict) -> None:
        for _ in range(20):
            meta["config"] = {**meta["config"], "source": {"kind": meta["kind"], "config": meta["config"]}}
    _rewrite_metadata(residual_file, nest)
    _refused(residual_file, "nested deeper than 32")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("redigest", [True, False])
def test_non_finite_weights_are_refused(saved: Path, bad: float, redigest: bool) -> None:
    """With a forged digest the NaN check refuses it; without one (an old file), too."""
    def poison(meta: dict, tensors: dict) -> None:
        tensors["net.3.weight"][5, 7] = bad
        if not redigest:
            del meta[DIGEST_KEY]
    _rewrite_metadata(saved, poison, redigest=redigest)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnverifiedCheckpointWarning)
        _refused(saved, r"non-finite weights \(NaN or infinity\) in net\.3\.weight")


@pytest.mark.parametrize("name", ["state_std", "delta_std"])
@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_a_std_that_is_not_positive_is_refused(saved: Path, name: str, bad: float) -> None:
    """A model divides by its stds: a zero one made every prediction NaN (evaluate exited 0 with NaN MSE)."""
    _rewrite_metadata(saved, lambda _, tensors: tensors[name].__setitem__(2, bad), redigest=True)
    _refused(saved, rf"normalisation std that is not positive in {name} \(smallest {bad:g}\)$")


def test_a_sub_models_std_is_checked_too(residual_file: Path) -> None:
    _rewrite_metadata(residual_file, lambda _, tensors: tensors["residual.delta_std"].zero_(), redigest=True)
    _refused(residual_file, r"not positive in residual\.delta_std")


def test_weights_of_another_dtype_are_refused(saved: Path) -> None:
    _rewrite_metadata(saved, lambda _, tensors: tensors.update(state_std=tensors["state_std"].double()), redigest=True)
    _refused(saved, "holds state_std as torch.float64, not torch.float32")


def test_weights_that_do_not_match_their_digest(saved: Path) -> None:
    _rewrite_metadata(saved, lambda _, tensors: tensors["net.0.bias"].add_(1e-3))
    _refused(saved, "do not match their digest")
    data = bytearray(saved.read_bytes())  # one bit of the data section
    data[-5] ^= 0x01
    saved.write_bytes(bytes(data))
    _refused(saved, "do not match their digest")


def test_file_saved_before_digests_loads_with_a_warning(saved: Path, tmp_path: Path) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta.pop(DIGEST_KEY))
    with pytest.warns(UnverifiedCheckpointWarning, match=f"{saved}: has no weights digest"):
        model, meta = load_model(saved)
    assert DIGEST_KEY not in meta and DIGEST_KEY not in read_metadata(saved)
    resaved = save_model(model, tmp_path / "again.safetensors", method=meta["method"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnverifiedCheckpointWarning)
        assert load_model(resaved)[1][DIGEST_KEY] == weights_digest(model.state_dict())


def test_digest_covers_names_dtypes_and_shapes() -> None:
    weights = {"a": torch.arange(6.0).reshape(2, 3)}
    digests = {weights_digest(w) for w in (weights, {"b": weights["a"]}, {"a": weights["a"].reshape(3, 2)},
                                           {"a": weights["a"].double()}, {"a": weights["a"].T.contiguous().T})}
    assert len(digests) == 4  # the last is the first's values laid out differently: the same digest


def test_fifo_and_directory_are_refused_before_opening(tmp_path: Path) -> None:
    fifo = tmp_path / "model.safetensors"
    os.mkfifo(fifo)  # opening it for reading would block forever
    for path, kind in ((fifo, "a FIFO"), (tmp_path, "a directory")):
        for reader in (load_model, read_metadata):
            with pytest.raises(CheckpointError, match=f"is {kind}, not a regular file"):  # files.py's words
                reader(path)


def test_path_through_a_file_is_refused(saved: Path) -> None:
    with pytest.raises(CheckpointError, match=f"{saved}/x: cannot be read"):
        load_model(saved / "x")


def test_loaded_model_lives_on_the_cpu_and_trains(residual_file: Path) -> None:
    """Loading builds on the meta device and assigns the file's tensors: nothing is left on meta."""
    model, _ = load_model(residual_file)
    tensors = list(model.parameters()) + list(model.buffers())
    assert all(t.device.type == "cpu" for t in tensors)
    assert not any(p.requires_grad for p in model.source.parameters())
    assert all(p.requires_grad for p in model.residual.parameters())


def test_the_actions_unit_is_saved_and_files_without_it_get_the_unit_they_were_trained_in(saved: Path,
                                                                                            tmp_path: Path) -> None:
    assert read_metadata(saved)[UNIT_KEY] == ACTION_UNIT_RAD and UNIT_ASSUMED_KEY not in read_metadata(saved)
    model, _ = load_model(saved)
    authors = save_model(model, tmp_path / "authors.safetensors", method="direct", action_unit_rad=0.00388)
    assert load_model(authors)[1][UNIT_KEY] == 0.00388
    _rewrite_metadata(saved, lambda meta, _: meta.pop(UNIT_KEY))
    meta = load_model(saved)[1]
    assert meta[UNIT_KEY] == ACTION_UNIT_RAD and meta[UNIT_ASSUMED_KEY] is True  # saved before units: assumed
    _rewrite_metadata(saved, lambda meta, _: meta.update(method="authors_B"))
    assert read_metadata(saved)[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD  # an authors' import of then: theirs


@pytest.mark.parametrize("value, match", [("0.025", "'action_unit_rad' that is not a number"),
                                          (0, r"action unit must be a number of rad in \(0, 0.1\], got 0"),
                                          (0.5, "got 0.5"), (True, "got True"), (-0.025, "got -0.025")])
def test_a_bad_actions_unit_is_refused(saved: Path, tmp_path: Path, value: object, match: str) -> None:
    _rewrite_metadata(saved, lambda meta, _: meta.update({UNIT_KEY: value}))
    _refused(saved, match)
    if not isinstance(value, str):
        with pytest.raises(ValueError, match=match):
            save_model(TransitionModel(Normalisation.identity()), tmp_path / "new.safetensors", method="direct",
                       action_unit_rad=value)
        assert list(tmp_path.glob("new*")) == []
