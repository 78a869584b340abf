"""``t42 model train``: a source model from a hand's recorded bags, as a transfer server starts from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from t42_transfer.cli import main
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import collect
from t42_transfer.models.checkpoint import UNIT_KEY, read_metadata
from t42_transfer.planning.workspace import Workspace
from t42_transfer.transfer.online import load_source


@pytest.fixture(scope="module")
def source_bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, TrajectorySet]:
    """A recorder's out_dir of two bags of the simulated source hand (as ``t42 sim collect`` writes them)."""
    data, _ = collect("source", 24, 60, seed=3, workers=1, progress=False)
    data = TrajectorySet(assign_start_times(data), hand=data.hand)
    out = tmp_path_factory.mktemp("recordings")
    write_bag(out / "episode_000", TrajectorySet(data.trajectories[:12], hand=data.hand))
    write_bag(out / "episode_001", TrajectorySet(data.trajectories[12:], hand=data.hand))
    return out, data


def one_step_error(model: torch.nn.Module, data: TrajectorySet) -> float:
    x, a, x_next = (torch.as_tensor(v, dtype=torch.float32) for v in data.transitions())
    with torch.no_grad():
        return float((model.rollout(x, a[:, None, :])[:, -1] - x_next).abs().mean())


def test_a_source_model_trained_on_bags_is_one_a_transfer_server_starts_from(
        source_bags, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_dir, data = source_bags
    model_file = tmp_path / "source.safetensors"
    assert main(["model", "train", str(out_dir), "--out", str(model_file), "--epochs", "30"]) == 0
    said = capsys.readouterr().out
    assert f"{len(data)} episodes ({data.num_transitions} transitions) of 2 bag(s), hand source" in said, said
    model, meta = load_source(model_file)  # what the transfer server does with its source_model
    assert meta["method"] == "source" and len(meta["data"]["bags"]) == 2
    assert meta[UNIT_KEY] == ACTION_UNIT_RAD  # bags read as they were recorded, in the suite's unit
    assert Workspace.from_metadata(meta).to_dict() == Workspace.from_trajectories(data).to_dict()
    hold_still = float(np.abs(data.transitions()[2] - data.transitions()[0]).mean())
    assert one_step_error(model, data) < 0.5 * hold_still  # it learned the hand, not the identity

    # The same bags named one by one train the same model: the data and the seed decide it, not the spelling.
    again = tmp_path / "again.safetensors"
    bags = sorted(out_dir.iterdir())
    assert main(["model", "train", *map(str, bags), "--out", str(again), "--epochs", "30"]) == 0
    assert read_metadata(again)["data"] == read_metadata(model_file)["data"]
    assert one_step_error(load_source(again)[0], data) == one_step_error(model, data)


def test_bad_inputs_are_one_line_errors_and_nothing_is_written(source_bags, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    out_dir, _ = source_bags
    empty = tmp_path / "empty"
    empty.mkdir()
    taken = tmp_path / "taken.safetensors"
    taken.write_bytes(b"")
    nested = tmp_path / "recordings"  # a suite under the namespace /left records into recordings/left
    nested.mkdir()
    (nested / "left").symlink_to(out_dir)
    other_hand, _ = collect("target", 3, 30, seed=1, workers=1, progress=False)
    other = write_bag(tmp_path / "target_bag", TrajectorySet(assign_start_times(other_hand), hand="target"))
    cases = [
        ([str(empty), "--out", str(tmp_path / "m.safetensors")], f"{empty}: holds no finished bag"),
        ([str(nested), "--out", str(tmp_path / "m.safetensors")], f"these folders in it do (a suite under a "
                                                                  f"namespace records there): {nested / 'left'}"),
        ([str(out_dir), str(other), "--out", str(tmp_path / "m.safetensors")],
         "the bags hold episodes of 2 hands (source, target): a source model is one hand's"),
        ([str(tmp_path / "missing"), "--out", str(tmp_path / "m.safetensors")], "does not exist"),
        ([str(out_dir), "--out", str(taken)], f"{taken}: exists already"),
    ]
    for argv, message in cases:
        assert main(["model", "train", *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    theirs = write_bag(tmp_path / "theirs", TrajectorySet(list(source_bags[1])[:12], hand="source"),
                       action_unit_rad=AUTHORS_ACTION_UNIT_RAD)  # declares the authors' unit
    assert main(["model", "train", str(out_dir / "episode_000"), str(theirs), "--out", str(tmp_path / "m.safetensors")]
                ) == 2
    assert "the bags declare different action units (0.00388, 0.025 rad): a model learns one; name it with " \
        "--action-unit-rad" in capsys.readouterr().err
    assert main(["model", "train", str(theirs), "--out", str(tmp_path / "theirs.safetensors"), "--epochs", "1"]) == 0
    assert read_metadata(tmp_path / "theirs.safetensors")[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD  # the bag's own
    capsys.readouterr()
    # Bags of the suite's unit read in the authors': each is skipped with why, then nothing is left to train on.
    assert main(["model", "train", str(out_dir), "--out", str(tmp_path / "m.safetensors"), "--action-unit-rad",
                 "0.00388"]) == 2
    *skipped, error = capsys.readouterr().err.strip().splitlines()
    assert len(skipped) == 2 and all("in units of 0.00388 rad a step, past 1.5" in line for line in skipped), skipped
    assert "no usable episode in 2 bag(s)" in error
    assert not (tmp_path / "m.safetensors").exists() and taken.read_bytes() == b""
