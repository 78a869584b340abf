"""The experiment runner: methods x amounts of target data x seeds, from one YAML config.

The source model is trained once on the whole source set; every cell transfers
it with one method to a subset of the target's training pool and scores the
result on held-out target episodes (divergence time, MSE, Lyapunov exponent,
and the quantities of the paper's bound).  Cells are cached by a hash of
everything they depend on, so an interrupted run resumes where it stopped and a
changed setting reruns only what it touches.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from t42_transfer.data.bag_io import assign_start_times, read_bag, write_bag
from t42_transfer.data.trajectory import Trajectory, TrajectorySet, split_by_fraction
from t42_transfer.models.checkpoint import load_model, save_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.methods import METHODS, transfer

RESULT_COLUMNS = (
    "method", "amount", "seed", "train_episodes", "train_transitions", "test_rollouts", "divergence_mean",
    "divergence_median", "position_mse_mean", "lyapunov_mean", "lyapunov_median", "covering_radius",
    "train_error_normalised", "train_error_xy_mm", "seconds",
)


@dataclass(frozen=True)
class DataSpec:
    """Where a hand's data comes from: a simulated hand, a bag, or a public real-hand file."""

    hand: str | None = None
    episodes: int = 300
    steps: int = 1000
    seed: int = 0
    bag: str | None = None
    real: str | None = None
    """``A`` or ``B``: the public T42 test paths of that hand."""
    mirror_x: bool = False
    """Negate x (the real hands are mirror images of each other)."""

    def describe(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ExperimentConfig:
    name: str
    source: DataSpec
    target: DataSpec
    methods: tuple[str, ...] = tuple(METHODS)
    split: str = "fraction"
    """``fraction``: amounts are fractions of the target pool, a fixed test split held out;
    ``paths``: amounts are numbers of target episodes, the others are the test set."""
    amounts: tuple[float, ...] = (0.005, 0.01, 0.02, 0.05, 0.1)
    seeds: int = 5
    test_fraction: float = 0.2
    epsilon_mm: float = 4.0
    start_offsets: tuple[int, ...] = (0,)
    horizon: int | None = None
    lyapunov_steps: int = 100
    source_training: TrainConfig = TrainConfig()
    transfer: TransferConfig = field(default_factory=TransferConfig)
    workers: int | None = None


def _build(cls: type, values: dict[str, Any]) -> Any:
    """A (nested) frozen dataclass from a dict, refusing unknown keys with their names."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ValueError(f"unknown {cls.__name__} settings {unknown}; known: {sorted(fields)}")
    kwargs = {}
    for key, value in values.items():
        default = getattr(cls(), key)
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            kwargs[key] = _build(type(default), value)
        elif isinstance(value, list):
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def load_config(path: str | os.PathLike[str]) -> ExperimentConfig:
    """Read an experiment YAML; errors name the file and the offending setting."""
    file = Path(path)
    try:
        raw = yaml.safe_load(file.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"{file}: cannot read the experiment config ({err})") from None
    if not isinstance(raw, dict) or "name" not in raw or "source" not in raw or "target" not in raw:
        raise ValueError(f"{file}: an experiment config needs name, source and target")
    try:
        raw = dict(raw)
        raw["source"], raw["target"] = _build(DataSpec, raw["source"]), _build(DataSpec, raw["target"])
        cfg = _build_experiment(raw)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{file}: {err}") from None
    unknown = sorted(set(cfg.methods) - set(METHODS))
    if unknown:
        raise ValueError(f"{file}: unknown methods {unknown}; known: {sorted(METHODS)}")
    return cfg


def _build_experiment(raw: dict[str, Any]) -> ExperimentConfig:
    fields = {f.name for f in dataclasses.fields(ExperimentConfig)}
    unknown = sorted(set(raw) - fields)
    if unknown:
        raise ValueError(f"unknown experiment settings {unknown}; known: {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for key, value in raw.items():
        if key == "source_training":
            kwargs[key] = _build(TrainConfig, value)
        elif key == "transfer":
            kwargs[key] = _build(TransferConfig, value)
        elif isinstance(value, list):
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return ExperimentConfig(**kwargs)


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------- data


def data_cache(run_dir: Path) -> Path:
    """Collected data sets live beside the runs (``<out>/data``), shared by every experiment there."""
    return Path(run_dir).parent / "data"


def load_data(spec: DataSpec, cache: Path) -> TrajectorySet:
    """The trajectories ``spec`` names; simulated sets are collected once and kept as bags in ``cache``."""
    if spec.real:
        from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir

        data = load_t42_testpaths(real_data_dir() / REAL_FILES[spec.real])
    elif spec.bag:
        data = read_bag(spec.bag)
    elif spec.hand:
        bag = cache / f"{spec.hand}_{_digest(spec.describe())}"
        if bag.exists():
            data = read_bag(bag)
        else:
            from t42_transfer.hand.collect import collect

            collected, _ = collect(spec.hand, spec.episodes, spec.steps, seed=spec.seed)
            data = TrajectorySet(assign_start_times(collected), hand=collected.hand)
            write_bag(bag, data, metadata={"experiment_spec": json.dumps(spec.describe())})
    else:
        raise ValueError("a data spec needs one of hand, bag or real")
    if spec.mirror_x:
        data = TrajectorySet((_mirror(t) for t in data), hand=data.hand)
    return data


def _mirror(traj: Trajectory) -> Trajectory:
    """The same episode seen in a mirror: x negated (the real hands A and B are mirror images)."""
    states = traj.states.copy()
    states[:, 0] = -states[:, 0]
    return dataclasses.replace(traj, states=states)


# ------------------------------------------------------------------------------ cells


@dataclass(frozen=True)
class Cell:
    method: str
    amount: float
    seed: int


def _target_split(cfg: ExperimentConfig, target: TrajectorySet, cell: Cell) -> tuple[TrajectorySet, TrajectorySet]:
    """(training subset, test episodes) of a cell."""
    if cfg.split == "fraction":
        test, pool = split_by_fraction(target, cfg.test_fraction, seed=12345)
        train, _ = split_by_fraction(pool, float(cell.amount), seed=cell.seed)
        return train, test
    if cfg.split == "paths":
        k = int(cell.amount)
        if not 1 <= k < len(target):
            raise ValueError(f"paths split needs 1 <= k < {len(target)} target episodes, got {k}")
        order = np.random.default_rng(cell.seed).permutation(len(target))
        return target.subset(sorted(order[:k])), target.subset(sorted(order[k:]))
    raise ValueError(f"split must be 'fraction' or 'paths', got {cfg.split!r}")


def _score(model: LatentDynamics, train: TrajectorySet, test: TrajectorySet, cfg: ExperimentConfig) -> dict[str, Any]:
    from t42_transfer.evaluation.lyapunov import model_lyapunov
    from t42_transfer.evaluation.metrics import covering_radius, evaluate_model, max_training_error

    scores = evaluate_model(model, test, cfg.epsilon_mm, cfg.start_offsets, cfg.horizon)
    lyap = model_lyapunov(model, test, steps=cfg.lyapunov_steps).numpy()
    train_states = np.concatenate([t.states for t in train])
    test_states = np.concatenate([t.states for t in test])
    # One scale for both quantities of the bound: the spread of the target states.
    scale = np.concatenate([train_states, test_states]).std(0) + 1e-9
    error = max_training_error(model, train.transitions(), state_scale=scale)
    return {
        "test_rollouts": scores["num_rollouts"],
        "divergence_mean": scores["divergence_mean"],
        "divergence_median": scores["divergence_median"],
        "position_mse_mean": scores["position_mse_mean"],
        "lyapunov_mean": float(np.mean(lyap)),
        "lyapunov_median": float(np.median(lyap)),
        "covering_radius": covering_radius(train_states / scale, test_states / scale),
        "train_error_normalised": error.normalised,
        "train_error_xy_mm": error.xy_mm,
    }


_WORKER: dict[str, Any] = {}


def _run_cell(args: tuple[ExperimentConfig, Cell, Path, Path, dict[str, Any]]) -> dict[str, Any]:
    cfg, cell, run_dir, source_path, workspace = args
    torch.set_num_threads(1)
    if "source" not in _WORKER:
        _WORKER["source"] = load_model(source_path)[0]
        _WORKER["target"] = load_data(cfg.target, data_cache(run_dir))
    source, target = _WORKER["source"], _WORKER["target"]
    train, test = _target_split(cfg, target, cell)
    start = time.perf_counter()
    model = transfer(cell.method, source, train, cfg.transfer, seed=cell.seed)
    row = {
        "method": cell.method, "amount": cell.amount, "seed": cell.seed,
        "train_episodes": len(train), "train_transitions": train.num_transitions,
    }
    row.update(_score(model, train, test, cfg))
    row["seconds"] = time.perf_counter() - start
    save_model(model, run_dir / "models" / f"{_cell_key(cfg, cell, source_path)}.safetensors", method=cell.method,
               hyperparameters=dataclasses.asdict(cfg.transfer), data={"target_train": train.fingerprint()},
               extra={"workspace": workspace})
    return row


def _cell_key(cfg: ExperimentConfig, cell: Cell, source_path: Path) -> str:
    depends = {
        "cell": dataclasses.asdict(cell), "target": cfg.target.describe(), "split": cfg.split,
        "test_fraction": cfg.test_fraction, "epsilon": cfg.epsilon_mm, "offsets": cfg.start_offsets,
        "horizon": cfg.horizon, "lyapunov_steps": cfg.lyapunov_steps,
        "method_config": dataclasses.asdict(cfg.transfer), "source": source_path.name,
    }
    return f"{cell.method}-{cell.amount}-{cell.seed}-{_digest(depends)}"


def train_source(cfg: ExperimentConfig, run_dir: Path, progress: bool = True) -> Path:
    """The source model of this experiment, trained once and cached by its data and settings."""
    key = _digest({"source": cfg.source.describe(), "train": dataclasses.asdict(cfg.source_training)})
    path = Path(run_dir).parent / "sources" / f"source-{key}.safetensors"  # shared by experiments with equal source
    if path.exists():
        return path
    data = load_data(cfg.source, data_cache(run_dir))
    # Minibatches of 64 gain nothing from a second thread, and idle OpenMP threads
    # spinning against other processes cost up to 10x on a busy 2-core machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model, report = train_transition_model(data, cfg.source_training, on_epoch=ProgressBar() if progress else None, phase="source model")
    finally:
        torch.set_num_threads(threads)
    save_model(
        model, path, method="source", hyperparameters=dataclasses.asdict(cfg.source_training),
        data={"source": data.fingerprint(), "transitions": data.num_transitions},
        extra={"epochs_run": report.epochs_run, "best_epoch": report.best_epoch, "val_loss": report.val_loss},
    )
    return path


def run_experiment(cfg: ExperimentConfig, out: Path, progress: bool = True) -> list[dict[str, Any]]:
    """Run (or resume) every cell; write ``results.json`` and ``results.csv`` in ``out / cfg.name``."""
    from tqdm.auto import tqdm

    run_dir = Path(out) / cfg.name
    (run_dir / "cells").mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(_config_dict(cfg), sort_keys=False))
    source_path = train_source(cfg, run_dir, progress)
    target = load_data(cfg.target, data_cache(run_dir))
    if len(target) < 2:
        raise ValueError(f"the target set has {len(target)} episodes; need at least 2")
    cells = [Cell(m, a, s) for m in cfg.methods for a in cfg.amounts for s in range(cfg.seeds)]
    rows: dict[Cell, dict[str, Any]] = {}
    todo = []
    for cell in cells:
        done = run_dir / "cells" / f"{_cell_key(cfg, cell, source_path)}.json"
        if done.exists():
            rows[cell] = json.loads(done.read_text())
        else:
            todo.append(cell)
    workers = cfg.workers or os.cpu_count() or 1
    bar = tqdm(total=len(cells), initial=len(cells) - len(todo), desc=cfg.name, unit="cell", disable=not progress)
    # The planner keeps predictions inside the states these models were trained on.
    from t42_transfer.planning.workspace import Workspace

    workspace = Workspace.from_trajectories(load_data(cfg.source, data_cache(run_dir))).to_dict() if todo else {}
    tasks = [(cfg, c, run_dir, source_path, workspace) for c in todo]

    def keep(cell: Cell, row: dict[str, Any]) -> None:
        rows[cell] = row
        (run_dir / "cells" / f"{_cell_key(cfg, cell, source_path)}.json").write_text(json.dumps(row, indent=1))
        bar.update()

    if workers == 1 or len(todo) <= 1:
        for task in tasks:
            keep(task[1], _run_cell(task))
    else:
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            for task, row in zip(tasks, pool.map(_run_cell, tasks)):
                keep(task[1], row)
    bar.close()
    ordered = [rows[c] for c in cells]
    (run_dir / "results.json").write_text(json.dumps({"config": _config_dict(cfg), "rows": ordered}, indent=1))
    with open(run_dir / "results.csv", "w") as f:
        f.write(",".join(RESULT_COLUMNS) + "\n")
        for row in ordered:
            f.write(",".join(str(row[c]) for c in RESULT_COLUMNS) + "\n")
    return ordered


def _config_dict(cfg: ExperimentConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
