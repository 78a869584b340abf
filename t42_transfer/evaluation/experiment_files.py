"""The files of an experiment's run directory: named by the cells' keys, locked while a run writes."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from t42_transfer.evaluation.experiment_config import ExperimentConfig


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
    depends on by name and setting, so a resume finds it again."""
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

    An advisory ``flock``: the kernel drops it when the holder exits, however it ends, so no stale lock.
    """
    path = run_dir / ".lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
            raise ValueError(f"{run_dir}: in use by another run ({holder or 'its lock file is held'})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)
