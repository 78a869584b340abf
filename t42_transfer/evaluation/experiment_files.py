"""The files of an experiment's run directory: named by the cells' keys, locked while a run writes, written whole,
read back with suspicion.

A resume trusts what ``cells/`` holds, so every file is written whole or not at all (:func:`write_atomic`), and a
cell read back is used only when it is whole and was computed on the data the run holds now: anything else is
run again, with a warning naming the file, instead of stopping every later resume.  A cell that raised leaves
``failed/<key>.json`` (:func:`failure_record`), until a resume redoes it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import traceback
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from t42_transfer.evaluation.experiment_config import ExperimentConfig
from t42_transfer.files import held_lock, read_json, write_atomic


def digest(obj: Any) -> str:
    """A short content hash of ``obj`` as JSON: the names of cached cells, sources and data sets."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Cell:
    """One cell of the grid: a method, an amount of target data, a seed."""

    method: str
    amount: float
    seed: int


_TRAINING_WHEN_ADDED = {"lr": 1e-4, "epochs": 30, "batch_size": 64, "weight_decay": 1e-3, "grad_clip": 10.0,
                        "patience": None, "seed": 0}
METHODS_ADDED_LATER = {
    "multistep_l2_finetune": {"train": _TRAINING_WHEN_ADDED, "l2": 1e-2, "horizon": 10},
    "anchored_finetune": {"train": _TRAINING_WHEN_ADDED, "anchor": 1.0, "state_noise": 1.0},
}
"""Methods whose settings joined the transfer config after runs were stored, with their settings when they joined:
hashed only when they differ from those (a later change of the defaults changes the keys, as it should)."""


def _method_config(cfg: ExperimentConfig) -> dict[str, Any]:
    """The transfer settings a cell's key hashes; a setting added later is left out at its default, so the cells
    of earlier runs keep their keys."""
    settings = dataclasses.asdict(cfg.transfer)
    for method in ("cumulative_residual", "recurrent_residual"):
        if settings[method]["gamma_rule"] == "fixed":
            del settings[method]["gamma_rule"]
    for method, when_added in METHODS_ADDED_LATER.items():
        if settings[method] == when_added:
            del settings[method]
    return settings


def cell_key(cfg: ExperimentConfig, cell: Cell, source_path: Path) -> str:
    """The name of ``cell``'s files (``cells/<key>.json``, ``models/<key>.safetensors``): a hash of everything it
    depends on by name and setting, so a resume finds it again (the data's content is checked apart: its row's
    draws, :func:`stored_rows`)."""
    depends = {
        "cell": dataclasses.asdict(cell), "target": cfg.target.describe(), "split": cfg.split,
        "test_fraction": cfg.test_fraction, "epsilon": cfg.epsilon_mm, "offsets": cfg.start_offsets,
        "horizon": cfg.horizon, "lyapunov_steps": cfg.lyapunov_steps,
        "method_config": _method_config(cfg), "source": source_path.name, "definition": cfg.definition,
    }
    if cfg.test is not None:  # absent otherwise: keys of runs without a test set stay valid
        depends["test"] = cfg.test.describe()
    return f"{cell.method}-{cell.amount}-{cell.seed}-{digest(depends)}"


RESULT_COLUMNS = (
    "method", "amount", "seed", "train_episodes", "train_transitions", "test_rollouts", "divergence_mean",
    "divergence_median", "divergence_mean_4mm", "divergence_mean_10mm", "position_mse_mean", "lyapunov_mean",
    "lyapunov_median", "covering_radius", "train_error_normalised", "train_error_xy_mm", "seconds",
)
"""The columns of ``results.csv``, and what every cell's row holds (``results.json`` keeps more)."""


@contextlib.contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold ``run_dir/.lock`` while a run writes there: a second run would interleave cells and results.

    The lock is :func:`held_lock`'s, not waited for: a run already there is refused, naming the pid it wrote.
    """

    def in_use(fd: int) -> ValueError:
        holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
        return ValueError(f"{run_dir}: in use by another run ({holder or 'its lock file is held'})")

    with held_lock(run_dir / ".lock", busy=in_use) as fd:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}\n".encode(), 0)
        yield


def stored_rows(files: Mapping[Any, Path], draws: Mapping[Any, Mapping[str, str]]) -> dict[Any, dict[str, Any]]:
    """The rows finished cells kept (``files``: each cell's file, made or not), leaving out, with a warning naming
    the files, those to run again: unreadable or incomplete (a write cut short by a full disk or a kill), or
    computed on other data than the run holds now (``draws``, what a row records of its data: a bag recorded again
    at the same path keeps the cell's key, which hashes the path, not the data).

    A draw a row lacks counts as matching, so that rows written before it was recorded (every committed run's)
    resume unchanged; ``train_draw`` is then filled in from the split, as results.json has it.
    """
    rows, changed = {}, {}
    for cell, path in files.items():
        if not path.exists():
            continue
        try:
            row = read_json(path, "cell")
            if not isinstance(row, dict):
                raise ValueError(f"{path}: the cell is not a JSON object")
        except ValueError as err:
            warnings.warn(f"{err}: the cell is run again", stacklevel=2)
            continue
        if missing := [c for c in RESULT_COLUMNS if c not in row]:
            warnings.warn(f"{path}: the cell lacks {', '.join(missing)}: it is run again", stacklevel=2)
            continue
        row.setdefault("train_draw", draws[cell]["train_draw"])
        if differ := tuple(k for k, v in draws[cell].items() if row.get(k, v) != v):  # a missing draw: matching
            changed.setdefault(differ, []).append(path.name)
            continue
        rows[cell] = row
    for differ, names in changed.items():
        warnings.warn(f"{len(names)} cell(s) in {next(iter(files.values())).parent} were computed on other data "
                      f"(their {', '.join(differ)} differ): run again: {', '.join(names)}", stacklevel=2)
    return rows


def failure_record(cell: Cell, err: BaseException) -> dict[str, Any]:
    """What ``failed/<key>.json`` keeps of a cell that raised: the cell, its error as the run's error names it
    (type and message) and the traceback, from the process that ran it (a pool's or Dask's worker)."""
    return {**dataclasses.asdict(cell), "error": repr(err), "traceback": "".join(traceback.format_exception(err))}


def warn_if_diverged(cell: str, row: Mapping[str, Any]) -> None:
    """A model whose predictions are no numbers (a fine-tuning that diverged) scores a divergence time that
    measures nothing: said at once, naming the cell, rather than left as a row that reads as a result."""
    bad = [k for k in RESULT_COLUMNS if isinstance(row.get(k), float) and not math.isfinite(row[k])]
    if bad:
        warnings.warn(f"{cell}: {', '.join(bad)} not finite: the transferred model predicts no numbers (its "
                      f"training diverged?), so its divergence time ({row['divergence_mean']:g}) measures nothing",
                      stacklevel=2)


def write_results(run_dir: Path, results: Mapping[str, Any]) -> None:
    """``results.json`` and its rows as ``results.csv`` (:data:`RESULT_COLUMNS`), each written whole."""
    write_atomic(run_dir / "results.json", json.dumps(results, indent=1))
    rows = results["rows"]
    lines = [",".join(RESULT_COLUMNS), *(",".join(str(row[c]) for c in RESULT_COLUMNS) for row in rows)]
    write_atomic(run_dir / "results.csv", "\n".join(lines) + "\n")
