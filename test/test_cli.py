"""The ``t42`` command: help, sim -> bag -> trajectories round trip, bag tools, errors, the demo."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from t42_transfer.cli import main
from t42_transfer.data.bag import read_bag
from t42_transfer.hand.collect import collect

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "bags"


def test_help_lists_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    text = capsys.readouterr().out
    for command in ("demo", "sim", "bag"):
        assert command in text
    with pytest.raises(SystemExit) as exit_info:
        main(["sim", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    assert "collect" in text and "compare-real" in text


def test_sim_collect_round_trips_exactly_through_the_bag(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    argv = ["sim", "collect", "--hand", "target", "--episodes", "3", "--steps", "40", "--seed", "7", "--workers", "1"]
    assert main([*argv, "--quiet", "--out", str(out)]) == 0
    direct, _ = collect("target", 3, 40, seed=7, workers=1, progress=False)
    back = read_bag(out)
    assert len(back) == len(direct) == 3
    for got, want in zip(back, direct, strict=True):
        assert (got.states == want.states).all() and (got.actions == want.actions).all()
        assert (got.actuator_angles == want.actuator_angles).all()
        assert got.end_reason == want.end_reason and got.hand == "target"


def test_sim_collect_sustained_policy_holds_the_real_hands_moves(tmp_path: Path) -> None:
    from t42_transfer.conventions import REAL_HAND_ACTIONS
    from t42_transfer.hand.collect import SustainedPolicy

    out = tmp_path / "bag"
    argv = ["sim", "collect", "--episodes", "2", "--steps", "150", "--seed", "3", "--workers", "1", "--quiet"]
    assert main([*argv, "--policy", "sustained", "--hold-max", "130", "--out", str(out)]) == 0
    direct, _ = collect("source", 2, 150, seed=3, workers=1, policy=SustainedPolicy(hold_max=130), progress=False)
    back = read_bag(out)
    assert len(back) == len(direct) >= 1
    moves = {tuple(a) for a in np.array(REAL_HAND_ACTIONS, dtype=float)}
    for got, want in zip(back, direct, strict=True):
        assert (got.actions == want.actions).all()
        assert {tuple(a) for a in got.actions} <= moves
        assert len(got) < 120 or (got.actions[:120] == got.actions[0]).all()  # the first hold is 120-130 steps


def test_collect_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bag"
    out.mkdir()
    code = main(["sim", "collect", "--episodes", "1", "--steps", "20", "--workers", "1", "--quiet", "--out", str(out)])
    assert code == 2
    assert str(out) in capsys.readouterr().err


@pytest.mark.parametrize("fixture", ["source_small", "target_small"])
def test_bag_info_on_the_fixture_bags(fixture: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bag", "info", str(FIXTURES / fixture), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    data = read_bag(FIXTURES / fixture)
    assert info["episodes"] == len(data) > 0
    assert info["transitions"] == data.num_transitions
    assert info["hand"] == fixture.split("_")[0] == data.hand


def test_bag_info_on_a_folder_of_bags_gives_a_line_each_and_names_a_bad_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recorder's out_dir: one line per finished bag, the sums, and an unreadable bag named (exit 1)."""
    import shutil

    folder = tmp_path / "recordings"
    for fixture in ("source_small", "target_small"):
        shutil.copytree(FIXTURES / fixture, folder / fixture)
    (folder / "open_bag").mkdir()  # a bag being written: no metadata.yaml yet, not listed
    assert main(["bag", "info", str(folder)]) == 0
    lines = capsys.readouterr().out.splitlines()
    bags = ("source_small", "target_small")
    counts = [(len(d), d.num_transitions) for d in (read_bag(folder / f) for f in bags)]
    assert lines[:2] == [f"{name}: {e} episodes, {t} transitions, " + line.split(" transitions, ", 1)[1]
                         for name, (e, t), line in zip(bags, counts, lines[:2], strict=True)]
    assert lines[2] == (f"2 bags: {sum(e for e, _ in counts)} episodes, {sum(t for _, t in counts)} transitions "
                        "(t42 bag info BAG for one)")
    assert main(["bag", "info", str(folder), "--json", "--verify"]) == 0
    infos = json.loads(capsys.readouterr().out)
    assert [i["episodes"] for i in infos] == [e for e, _ in counts] and all(i["verify"] == [] for i in infos)
    assert main(["bag", "info", str(tmp_path)]) == 2  # a suite under a namespace records in a sub-folder: named
    assert f"holds no finished bag (a directory with a metadata.yaml); these folders in it do (a suite under a " \
           f"namespace records there): {folder}" in capsys.readouterr().err
    for data_file in (folder / "target_small").glob("*.mcap"):
        data_file.write_bytes(b"not an mcap file")
    assert main(["bag", "info", str(folder)]) == 1
    out = capsys.readouterr().out
    assert "target_small: unreadable: " in out and out.splitlines()[-1].startswith("2 bags: ")


def test_bad_bag_is_a_clear_error_not_a_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "metadata.yaml").write_text("this: [is not a bag")
    assert main(["bag", "info", str(junk)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("t42: error: ") and str(junk) in err and "Traceback" not in err


@pytest.mark.realdata
def test_import_t42(t42_real_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "real_a"
    assert main(["bag", "import-t42", str(t42_real_dir / "testpaths_cyl35_d_v0.pkl"), str(bag)]) == 0
    assert "6 paths" in capsys.readouterr().out
    assert read_bag(bag).hand == "cyl35"


@pytest.mark.slow
@pytest.mark.realdata
def test_compare_real_writes_table_and_figure(t42_real_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "docs"
    assert main(["sim", "compare-real", "--real-dir", str(t42_real_dir), "--out-dir", str(out)]) == 0
    summary = json.loads((out / "sim_vs_real.json").read_text())
    names = [r["name"] for r in summary["paths"]]
    assert names == ["real A", "real B", "sim source (same actions)", "sim target (same actions)"]
    held = {(r["name"], tuple(r["action"])) for r in summary["held_moves"]}
    assert ("real A", (-1.0, 1.0)) in held and ("sim source (same actions)", (-1.0, 1.0)) in held
    assert (out / "sim_vs_real_paths.png").stat().st_size > 10_000
    assert (out / "sim_vs_real_held_moves.png").stat().st_size > 10_000
    onsets = {(r["name"], tuple(r["action"])): r for r in summary["onsets"]}
    real, sim = onsets[("real A", (-1.0, 1.0))], onsets[("sim source (same actions)", (-1.0, 1.0))]
    assert real["threshold_mm"] == 2.0 and real["window"] == 20 and real["runs"] >= 1
    assert real["onset_steps"] > sim["onset_steps"]  # the real hands wait tens of steps; these hands do not
    assert (out / "sim_vs_real_onsets.png").stat().st_size > 10_000




def test_bag_info_reports_frozen_tracking_and_jumps(
    tmp_path: Path, make_set, capsys: pytest.CaptureFixture[str]
) -> None:
    import dataclasses

    from t42_transfer.data.bag import write_bag

    data = make_set([80, 80], seed=4, hand="h")
    states = data[1].states.copy()
    states[30:, 1] -= 10.0  # transition 29 jumps about 10 mm
    bag = write_bag(tmp_path / "bag", type(data)([data[0], dataclasses.replace(data[1], states=states)], hand="h"))
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "quality: 1 of 2 episodes with frozen tracking, jumps or late steps" in out
    assert "  episode 1: jump of " in out and "mm at step 29" in out
    assert main(["bag", "info", str(bag), "--json"]) == 0
    quality = json.loads(capsys.readouterr().out)["quality"]
    assert quality["flagged_episodes"] == 1 and quality["findings"]["1"][0]["start"] == 29
    assert main(["bag", "info", str(FIXTURES / "target_small")]) == 0
    assert "quality: 0 of 4 episodes" in capsys.readouterr().out


@pytest.mark.realdata
def test_import_names_the_flagged_stretches(
    t42_real_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "real_b"
    assert main(["bag", "import-t42", str(t42_real_dir / "testpaths_cyl35_red_d_v0.pkl"), str(bag)]) == 0
    assert "flagged stretches: path 0: frozen tracking at steps 0-198" in capsys.readouterr().out
    assert main(["bag", "info", str(bag)]) == 0
    assert "  episode 0: frozen tracking at steps 0-198 (199 steps, loads ranged 102); jump of 26.3 mm at step 198" \
        in capsys.readouterr().out


def test_a_reader_that_goes_away_ends_the_command_quietly() -> None:
    """``t42 bag info BAG --json | head``: the pipe closes before the output is written; no error line, as with
    any Unix tool (it said ``t42: error: [Errno 32] Broken pipe``)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # stdout to a pipe buffered, as in a shell
    proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "bag", "info", str(FIXTURES / "source_small"),
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # long before the interpreter has started and read the bag
    with proc.stderr:
        err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and err == "", err
