"""Where cells run (:mod:`t42_transfer.evaluation.cluster`): rows kept as they come, failures named after the others
ran, Ctrl-C and a failed save stopping the workers, Dask keys of one run only; plain functions for cells, then the
``t42 experiment`` command on a tiny config (the fixture bags, a source trained for one epoch)."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from t42_transfer.cli import main
from t42_transfer.evaluation import experiment as exp
from t42_transfer.evaluation.cluster import CellsFailed, run_cells

BAGS = Path(__file__).resolve().parents[1] / "bags"


def _waits_for_the_others(task: tuple[str, Path]) -> dict:
    """Task ``slow`` finishes only once the others' rows were kept (a marker file), or after 5 s."""
    name, marker = task
    deadline = time.monotonic() + 5
    while name == "slow" and not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    return {"name": name}


def test_the_pool_keeps_each_row_as_it_comes_not_in_task_order(tmp_path: Path) -> None:
    marker = tmp_path / "others_kept"
    kept: list[str] = []

    def keep(task: tuple[str, Path], row: dict) -> None:
        kept.append(row["name"])
        if len(kept) == 2:
            marker.touch()

    run_cells(_waits_for_the_others, [("slow", marker), ("a", marker), ("b", marker)], keep, workers=2)
    assert sorted(kept[:2]) == ["a", "b"] and kept[2] == "slow"  # a kill before the slow one ends loses only it


def _fails_on_one(task: int) -> dict:
    if task == 1:
        raise ValueError("a numerical error")
    return {"task": task}


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_cell_is_named_once_the_others_ran_and_kept(workers: int) -> None:
    kept: list[int] = []
    with pytest.raises(CellsFailed) as failed:
        run_cells(_fails_on_one, [0, 1, 2, 3], lambda task, row: kept.append(row["task"]), workers=workers,
                  name=lambda task: f"cell number {task}")
    assert sorted(kept) == [0, 2, 3]
    assert failed.value.failed == ["cell number 1: ValueError('a numerical error')"]
    assert str(failed.value).startswith("1 of 4 cells failed (the others are kept; run again to redo these)")


def _sleeps(task: float) -> dict:
    time.sleep(task)
    return {"slept": task}


def _interrupt_handler(_: int) -> str:
    return repr(signal.getsignal(signal.SIGINT))


def test_pool_workers_leave_ctrl_c_to_the_parent() -> None:
    """Ctrl-C reaches the whole process group: a worker that took it would print a traceback of its own."""
    handlers: list[str] = []
    run_cells(_interrupt_handler, [0, 1], lambda task, row: handlers.append(row), workers=2)
    assert handlers == [repr(signal.SIG_IGN)] * 2


@pytest.mark.parametrize("parent_on_sigterm", [signal.SIG_DFL, lambda *_: None], ids=["default", "a handler"])
def test_ctrl_c_or_a_failed_save_stops_the_workers_at_once_and_keeps_what_came_back(parent_on_sigterm: Any) -> None:
    """Also when this process has a SIGTERM handler of its own (a server's "stop" flag), which a forked worker
    inherits: such a worker slept on through the pool's SIGTERM, and the run waited for its cell (a test that had
    left ``serve_bag``'s handler in the pytest worker showed it)."""
    kept: list[float] = []

    def keep(task: float, row: dict) -> None:
        if kept:
            raise KeyboardInterrupt  # as Ctrl-C would, while the 8 s cell still runs
        kept.append(row["slept"])

    previous = signal.signal(signal.SIGTERM, parent_on_sigterm)
    try:
        start = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            run_cells(_sleeps, [0.0, 0.0, 8.0], keep, workers=2)
        assert time.monotonic() - start < 4, "the run waited for the cell still running"
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert kept == [0.0] and multiprocessing.active_children() == []


def _who(task: tuple[str, int, float]) -> dict:
    run, index, pause = task
    time.sleep(pause)
    if run == "B" and index == 2:
        raise RuntimeError("out of memory")
    return {"run": run, "index": index}


def test_two_runs_on_one_dask_scheduler_get_their_own_rows() -> None:
    """Both runs name their cells alike (cell 0, 1, 2): the second, started while the first runs, gets its own."""
    from distributed import LocalCluster

    rows: dict[str, list[dict]] = {"A": [], "B": []}
    failed: dict[str, CellsFailed] = {}

    def run(name: str, pause: float) -> None:
        try:
            run_cells(_who, [(name, i, pause) for i in range(3)], lambda task, row: rows[name].append(row),
                      scheduler=cluster.scheduler_address, name=lambda task: f"cell {task[1]}")
        except CellsFailed as err:
            failed[name] = err

    with LocalCluster(n_workers=2, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        first = threading.Thread(target=run, args=("A", 1.0))
        first.start()
        time.sleep(0.3)
        run("B", 0.0)
        first.join(timeout=30)
    assert sorted((r["run"], r["index"]) for r in rows["A"]) == [("A", 0), ("A", 1), ("A", 2)]
    assert sorted((r["run"], r["index"]) for r in rows["B"]) == [("B", 0), ("B", 1)]
    assert list(failed) == ["B"] and failed["B"].failed == ["cell 2: RuntimeError('out of memory')"]


def _config(tmp_path: Path, methods: str, transfer: str) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(f"""
name: tiny
source: {{bag: {BAGS / 'source_small'}}}
target: {{bag: {BAGS / 'target_small'}}}
methods: {methods}
split: paths
amounts: [1]
seeds: 1
lyapunov_steps: 10
source_training: {{epochs: 1}}
transfer: {transfer}
""")
    return path


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_cell_ends_the_run_in_one_error_naming_it_with_every_other_cell_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], workers: int) -> None:
    transfer = exp.transfer

    def fails_for_one(method: str, *args, **kwargs):  # type: ignore[no-untyped-def]
        if method == "cumulative_residual":
            raise RuntimeError("out of memory")
        return transfer(method, *args, **kwargs)

    monkeypatch.setattr(exp, "transfer", fails_for_one)  # the pool's forked workers have it too
    config = _config(tmp_path, "[direct, cumulative_residual, naive_finetune]",
                     "{naive_finetune: {train: {epochs: 1}}}")
    args = ["experiment", str(config), "--out", str(tmp_path), "--workers", str(workers), "--quiet", "--no-report"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("t42: error:") == 1
    assert ("1 of 3 cells failed (the others are kept; run again to redo these): cumulative_residual at amount 1, "
            "seed 0: RuntimeError('out of memory')") in err
    kept = sorted(p.name.split("-")[0] for p in (tmp_path / "tiny" / "cells").iterdir())
    assert kept == ["direct", "naive_finetune"]  # naive_finetune: the cell after the failed one ran too


@pytest.mark.slow
def test_ctrl_c_during_a_pool_run_ends_in_one_line_with_the_finished_cells_kept(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group (the pool's workers too), while a long cell still runs."""
    config = _config(tmp_path, "[naive_finetune, direct, cumulative_residual]",
                     "{naive_finetune: {train: {epochs: 100000, patience: null}}}")
    cells = tmp_path / "tiny" / "cells"
    run = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "experiment", str(config),
                            "--out", str(tmp_path), "--workers", "2", "--no-report"],
                           stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while (not cells.is_dir() or len(list(cells.glob("*.json"))) < 2) and time.monotonic() < deadline:
            time.sleep(0.1)
        os.killpg(run.pid, signal.SIGINT)
        _, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
    assert run.returncode == 130 and "Traceback" not in err, err
    assert err.replace("\r", "\n").strip().splitlines()[-1] == (
        f"t42: interrupted: the cells that finished are kept in {cells}; the same command resumes the run")
    assert sorted(p.name.split("-")[0] for p in cells.iterdir()) == ["cumulative_residual", "direct"]
