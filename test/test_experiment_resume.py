"""What an experiment run keeps, and what a resume trusts of it: cells written whole, a cell cut short or computed on
data since changed run again (with a warning naming it), one collection of a data set two experiments share, a
diverged cell said at once.  Tiny configs on the fixture bags: one cheap method, one amount, a source trained for
one epoch."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from t42_transfer.data.bag import assign_start_times, read_bag, write_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation import experiment as exp
from t42_transfer.evaluation.cluster import CellsFailed
from t42_transfer.evaluation.experiment import run_experiment
from t42_transfer.evaluation.experiment_config import DataSpec, ExperimentConfig, load_config

BAGS = Path(__file__).resolve().parents[1] / "bags"


def _config(tmp_path: Path, *, methods: str = "[direct]", seeds: int = 2, target: Path = BAGS / "target_small",
            source: Path = BAGS / "source_small", transfer: str = "{}") -> ExperimentConfig:
    path = tmp_path / "tiny.yaml"
    path.write_text(f"""
name: tiny
source: {{bag: {source}}}
target: {{bag: {target}}}
methods: {methods}
split: paths
amounts: [1]
seeds: {seeds}
lyapunov_steps: 10
source_training: {{epochs: 1}}
transfer: {transfer}
workers: 1
""")
    return load_config(path)


def _untimed(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "seconds"} for row in rows]


def test_a_cell_file_cut_short_or_lacking_columns_is_run_again_with_a_warning_naming_it(tmp_path: Path) -> None:
    cfg = _config(tmp_path)
    rows = run_experiment(cfg, tmp_path / "runs", progress=False)
    cut, partial = sorted((tmp_path / "runs" / "tiny" / "cells").glob("*.json"))
    cut.write_text("")  # the disk filled while it was written, or the run was killed then
    row = json.loads(partial.read_text())
    del row["divergence_mean"]
    partial.write_text(json.dumps(row))
    with pytest.warns(UserWarning) as caught:
        again = run_experiment(cfg, tmp_path / "runs", progress=False)
    said = [str(w.message) for w in caught]
    assert any(m.startswith(f"{cut}: the cell is not valid JSON") and "run again" in m for m in said), said
    assert f"{partial}: the cell lacks divergence_mean: it is run again" in said
    assert _untimed(again) == _untimed(rows)


def test_cells_are_written_whole_and_a_failed_write_names_the_file(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = _config(tmp_path, seeds=1)
    run_experiment(cfg, tmp_path, progress=False)
    cells, results = tmp_path / "tiny" / "cells", (tmp_path / "tiny" / "results.json").read_text()
    kept = sorted(cells.iterdir())
    fsync = os.fsync

    def full_disk(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").startswith(f"{cells}/"):
            raise OSError(errno.ENOSPC, "No space left on device")
        fsync(fd)

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError) as failed:  # the second seed's cell is new: its file cannot be written
        run_experiment(_config(tmp_path, seeds=2), tmp_path, progress=False)
    assert failed.value.errno == errno.ENOSPC
    assert Path(failed.value.filename).parent == cells and failed.value.filename.endswith(".json")
    assert sorted(cells.iterdir()) == kept  # no half file, no temporary file left
    assert (tmp_path / "tiny" / "results.json").read_text() == results


def test_a_bag_recorded_again_at_the_same_path_reruns_its_cells_and_trains_the_source_again(tmp_path: Path) -> None:
    target, source = tmp_path / "target", tmp_path / "source"
    shutil.copytree(BAGS / "target_small", target)
    shutil.copytree(BAGS / "source_small", source)
    cfg = _config(tmp_path, seeds=1, target=target, source=source)
    first = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert all(len(r["test_draw"]) == len(r["source_data"]) == 16 for r in first if r["method"] == "direct")

    shutil.rmtree(target)
    shutil.copytree(BAGS / "source_small", target)  # the same path, other episodes: another hand's, here
    with pytest.warns(UserWarning, match=r"1 cell\(s\) in .*/cells were computed on other data \(their train_draw, "
                                         r"test_draw differ\): run again"):
        resumed = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert _untimed(resumed) == _untimed(run_experiment(cfg, tmp_path / "fresh", progress=False)) != _untimed(first)

    shutil.rmtree(source)
    shutil.copytree(BAGS / "target_small", source)
    with pytest.warns(UserWarning, match=r"source-\w+\.safetensors: the source model was trained on other data than "
                                         rf"the source \(bag {source}\) holds now"):
        resumed = run_experiment(cfg, tmp_path / "runs", progress=False)
    assert _untimed(resumed) == _untimed(run_experiment(cfg, tmp_path / "fresh_source", progress=False))


def test_cells_kept_from_before_the_data_were_recorded_in_them_resume_as_they_are(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = _config(tmp_path)
    rows = run_experiment(cfg, tmp_path, progress=False)
    for cell in (tmp_path / "tiny" / "cells").glob("*.json"):  # as the committed runs' cells are
        row = json.loads(cell.read_text())
        for key in ("test_draw", "source_data"):
            del row[key]
        cell.write_text(json.dumps(row))
    monkeypatch.setattr(exp, "transfer", lambda *a, **k: pytest.fail("a kept cell was run again"))
    again = run_experiment(cfg, tmp_path, progress=False)
    old = [{k: v for k, v in r.items() if k not in ("test_draw", "source_data")} if r["method"] == "direct" else r
           for r in rows]
    assert _untimed(again) == _untimed(old)


def test_two_experiments_collecting_the_same_data_set_collect_it_once(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    from t42_transfer.hand import collect as collection

    calls: list[str] = []

    def slow_collect(hand: str, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(hand)
        time.sleep(0.3)
        return read_bag(BAGS / "target_small"), None

    monkeypatch.setattr(collection, "collect", slow_collect)
    spec, cache = DataSpec(hand="target", episodes=4, steps=100, seed=1), tmp_path / "data"
    loaded: list[TrajectorySet] = []
    both = [threading.Thread(target=lambda: loaded.append(exp.load_data(spec, cache))) for _ in range(2)]
    for thread in both:
        thread.start()
    for thread in both:
        thread.join(timeout=30)
    assert calls == ["target"] and len(loaded) == 2 and loaded[0].fingerprint() == loaded[1].fingerprint()
    (bag,) = cache.iterdir()  # the bag alone: no lock file, no half bag left

    def another_host_writes_it_first(hand: str, *args, **kwargs):  # type: ignore[no-untyped-def]
        data = read_bag(BAGS / "target_small")
        write_bag(other, TrajectorySet(assign_start_times(data), hand=data.hand))
        return data, None

    other = cache / f"{spec.hand}_{exp.digest(DataSpec(hand='target', seed=2).describe())}"
    monkeypatch.setattr(collection, "collect", another_host_writes_it_first)
    assert len(exp.load_data(DataSpec(hand="target", seed=2), cache)) == 4


def test_a_diverged_fine_tune_is_named_in_a_warning(tmp_path: Path) -> None:
    cfg = _config(tmp_path, methods="[naive_finetune]", seeds=1,
                  transfer="{naive_finetune: {train: {epochs: 2, lr: 1.0e+30, patience: null}}}")
    with pytest.warns(UserWarning, match=r"naive_finetune at amount 1, seed 0: position_mse_mean, .* not finite: the "
                                         r"transferred model predicts no numbers"):
        run_experiment(cfg, tmp_path, progress=False)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failed_cell_keeps_its_traceback_in_the_run_directory_until_it_is_redone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int) -> None:
    """The run's error names each failed cell with its error's type and message; its record in ``failed/`` adds
    the traceback, from the process that ran it (a pool worker's too), and goes once a resume redid the cell."""
    cfg = dataclasses.replace(_config(tmp_path), workers=workers)
    transfer = exp.transfer

    def fails_for_seed_1(method, source, train, settings, seed):  # type: ignore[no-untyped-def]
        if seed == 1:
            raise RuntimeError("out of memory")
        return transfer(method, source, train, settings, seed=seed)

    monkeypatch.setattr(exp, "transfer", fails_for_seed_1)  # the pool's forked workers have it too
    with pytest.raises(CellsFailed, match=r"direct at amount 1, seed 1: RuntimeError\('out of memory'\)"):
        run_experiment(cfg, tmp_path / "runs", progress=False)
    run_dir = tmp_path / "runs" / "tiny"
    (kept,) = (run_dir / "cells").iterdir()
    (failed,) = (run_dir / "failed").iterdir()
    assert kept.name.startswith("direct-1-0-") and failed.name.startswith("direct-1-1-")
    record = json.loads(failed.read_text())
    assert {k: record[k] for k in ("method", "amount", "seed", "error")} == {
        "method": "direct", "amount": 1, "seed": 1, "error": "RuntimeError('out of memory')"}
    assert "in fails_for_seed_1" in record["traceback"] and "in _run_cell" in record["traceback"]
    assert record["traceback"].rstrip().endswith("RuntimeError: out of memory")
    monkeypatch.setattr(exp, "transfer", transfer)
    run_experiment(cfg, tmp_path / "runs", progress=False)
    assert (run_dir / "cells" / failed.name).is_file() and list((run_dir / "failed").iterdir()) == []
