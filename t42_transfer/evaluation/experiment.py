"""The experiment runner: methods x amounts of target data x seeds, from one YAML config.

The source model is trained once on the whole source set; every cell transfers
it with one method to a subset of the target's training pool and scores the
result on held-out target episodes (divergence time, MSE, Lyapunov exponent,
and the quantities of the paper's bound).  Cells are cached by a hash of
everything they depend on, so an interrupted run resumes where it stopped and a
changed setting reruns only what it touches.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import math
import multiprocessing
import os
import re
import reprlib
import time
import types
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

import numpy as np
import torch
import yaml

from t42_transfer.data.bag_io import assign_start_times, read_bag, write_bag
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
from t42_transfer.data.trajectory import Trajectory, TrajectorySet, split_by_fraction
from t42_transfer.hand.collect import MAX_EPISODES, MAX_STEPS, MAX_WORKERS, check_collection
from t42_transfer.models.checkpoint import load_model, save_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
from t42_transfer.transfer.config import (
    L2FineTuneConfig,
    NewModelConfig,
    ResidualConfig,
    TrajectoryFineTuneConfig,
    TransferConfig,
)
from t42_transfer.transfer.methods import METHODS, transfer
from t42_transfer.yaml_files import read_yaml

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
    """The run directory's name under ``--out``: one plain path component."""
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

    def __post_init__(self) -> None:
        # The run directory is ``out / name``: anything but one plain component could leave ``out``.
        if not (isinstance(self.name, str) and SAFE_NAME.fullmatch(self.name)):
            raise ValueError(f"name must be one plain path component (letters, digits, '.', '_', '-'; "
                             f"not starting with '.'; at most 100 characters), got {_show(self.name)}")


SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,99}")
MAX_SEEDS = 1000
MAX_CELLS = 100_000
MAX_EVAL_STEPS = 100_000
"""Bound of every step count of the evaluation (offsets, horizons, windows, epochs)."""
SEED_RANGE = (0, 2**32 - 1)
SPLITS = ("fraction", "paths")

_Rule = tuple[Callable[[Any], bool], str]


def _between(low: float, high: float, low_open: bool = False, high_open: bool = False) -> _Rule:
    def ok(v: Any) -> bool:
        return (low < v if low_open else low <= v) and (v < high if high_open else v <= high)
    return ok, (f"{'>' if low_open else '>='} {low}" if math.isinf(high) else
                f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}")


_STEPS, _SEED, _FRACTION, _POSITIVE = (_between(1, MAX_EVAL_STEPS), _between(*SEED_RANGE),
                                       _between(0, 1, True, True), _between(0, math.inf, True))
RULES: dict[type, dict[str, _Rule]] = {
    ExperimentConfig: {
        "seeds": _between(1, MAX_SEEDS), "amounts": _between(0, MAX_EPISODES, True), "test_fraction": _FRACTION,
        "epsilon_mm": _POSITIVE, "start_offsets": _between(0, MAX_EVAL_STEPS), "horizon": _STEPS,
        "lyapunov_steps": _STEPS, "workers": _between(1, MAX_WORKERS),
        "split": (lambda v: v in SPLITS, f"one of {SPLITS}"),
        "methods": (lambda v: v in METHODS, f"one of {sorted(METHODS)}"),
    },
    DataSpec: {"episodes": _between(1, MAX_EPISODES), "steps": _between(1, MAX_STEPS), "seed": _SEED,
               "real": (lambda v: v in REAL_FILES, f"one of {sorted(REAL_FILES)}")},
    TrainConfig: {"lr": _POSITIVE, "epochs": _STEPS, "batch_size": _between(1, 2**31 - 1),
                  "weight_decay": _between(0, math.inf), "grad_clip": _POSITIVE, "patience": _between(0, MAX_EVAL_STEPS),
                  "seed": _SEED},
    NewModelConfig: {"val_fraction": _FRACTION},
    L2FineTuneConfig: {"l2": _between(0, math.inf)},
    TrajectoryFineTuneConfig: {"horizon": _STEPS, "stride": _STEPS, "cutoff_mm2": _POSITIVE},
    ResidualConfig: {"alpha": _between(0, math.inf), "gamma": _between(0, 1, True), "val_fraction": _FRACTION},
}
"""What each setting must be beyond its type (every element of a list setting)."""


def _show(value: Any) -> str:
    text = reprlib.repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _typed(value: Any, hint: Any, where: str) -> Any:
    """``value`` from YAML checked against a field's annotation (lists become tuples); ValueError otherwise."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (hint,) = [a for a in args if a is not type(None)]
        return _typed(value, hint, where)
    if origin is tuple:
        many = len(args) == 2 and args[1] is Ellipsis
        if not isinstance(value, list) or not value or (not many and len(value) != len(args)):
            size = "a non-empty list" if many else f"a list of {len(args)}"
            raise ValueError(f"{where} must be {size}, got {_show(value)}")
        hints = args[:1] * len(value) if many else args
        return tuple(_typed(v, h, f"{where}[{i}]") for i, (v, h) in enumerate(zip(value, hints)))
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ValueError(f"{where} must be a mapping of {hint.__name__} settings, got {_show(value)}")
        return _build(hint, value, f"{where}.")
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:  # ints are floats here; NaN and inf never are
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and (
            isinstance(value, int) or math.isfinite(value))
    else:
        ok = isinstance(value, hint)
    if not ok:
        kind = {float: "a finite number", int: "an integer", bool: "true or false", str: "a string"}.get(hint, hint)
        raise ValueError(f"{where} must be {kind}, got {_show(value)}")
    return value


def _build(cls: type, values: dict[Any, Any], prefix: str = "") -> Any:
    """A (nested) frozen dataclass from a YAML mapping: unknown keys, wrong types and values out of range refused."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(str(k) for k in values if k not in fields)
    if unknown:
        kind = "experiment" if cls is ExperimentConfig else cls.__name__
        inside = f" in {prefix[:-1]}" if prefix else ""
        raise ValueError(f"unknown {kind} settings {_show(unknown)}{inside}; known: {sorted(fields)}")
    hints, rules = get_type_hints(cls), RULES.get(cls, {})
    kwargs = {}
    for key, value in values.items():
        where = f"{prefix}{key}"
        kwargs[key] = _typed(value, hints[key], where)
        if key in rules and kwargs[key] is not None:
            ok, wanted = rules[key]
            for item in kwargs[key] if isinstance(kwargs[key], tuple) else (kwargs[key],):
                if not ok(item):
                    raise ValueError(f"{where} must be {wanted}, got {_show(item)}")
    return cls(**kwargs)


def load_config(path: str | os.PathLike[str]) -> ExperimentConfig:
    """Read an experiment YAML; ValueError naming the file and the offending setting, before anything runs."""
    file = Path(path)
    raw = read_yaml(file, "experiment config")
    if not isinstance(raw, dict) or "name" not in raw or "source" not in raw or "target" not in raw:
        raise ValueError(f"{file}: an experiment config needs name, source and target")
    try:
        cfg = _build(ExperimentConfig, raw)
        check_config(cfg)
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None
    return cfg


def check_config(cfg: ExperimentConfig) -> None:
    """ValueError unless ``cfg`` keeps every rule of a config file, also when built in code.

    Beyond each setting's type and range: one data source per side, no repeated or too many
    cells, amounts that fit the split.
    """
    _build(ExperimentConfig, _config_dict(cfg))
    for side in ("source", "target"):
        spec: DataSpec = getattr(cfg, side)
        given = [k for k in ("hand", "bag", "real") if getattr(spec, k) is not None]
        if len(given) != 1:
            raise ValueError(f"{side} needs exactly one of hand, bag or real, got {given or 'none'}")
        if spec.hand is not None:
            check_collection(spec.hand, spec.episodes, spec.steps)
    for key in ("methods", "amounts"):
        values = getattr(cfg, key)
        if len(set(values)) != len(values):
            raise ValueError(f"{key} repeat an entry: {_show(values)}")
    cells = len(cfg.methods) * len(cfg.amounts) * cfg.seeds
    if cells > MAX_CELLS:
        raise ValueError(f"{cells} cells (methods x amounts x seeds) is over {MAX_CELLS}")
    if cfg.split == "fraction" and max(cfg.amounts) > 1:
        raise ValueError(f"amounts are fractions of the target pool with split: fraction, got {max(cfg.amounts)}")
    if cfg.split == "paths" and not all(float(a).is_integer() for a in cfg.amounts):
        raise ValueError(f"amounts are numbers of episodes with split: paths, got {_show(cfg.amounts)}")


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------- data


def data_cache(run_dir: Path) -> Path:
    """Collected data sets live beside the runs (``<out>/data``), shared by every experiment there."""
    return Path(run_dir).parent / "data"


def load_data(spec: DataSpec, cache: Path) -> TrajectorySet:
    """The trajectories ``spec`` names; simulated sets are collected once and kept as bags in ``cache``."""
    if spec.real:
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
    """Run (or resume) every cell; write ``results.json`` and ``results.csv`` in ``out / cfg.name``.

    The config is checked first and the run directory locked: a bad setting or a run directory in
    use is refused before anything is written.
    """
    check_config(cfg)
    for side in ("source", "target"):
        _check_input(getattr(cfg, side), side)
    run_dir = Path(out) / cfg.name
    target = load_data(cfg.target, data_cache(run_dir))
    if len(target) < 2:
        raise ValueError(f"the target set has {len(target)} episodes; need at least 2")
    if cfg.split == "paths" and max(cfg.amounts) >= len(target):
        raise ValueError(f"amounts up to {max(cfg.amounts)} episodes with split: paths, but the target set has "
                         f"{len(target)}: some must stay for testing")
    (run_dir / "cells").mkdir(parents=True, exist_ok=True)
    with _run_lock(run_dir):
        return _run(cfg, run_dir, progress)


def _check_input(spec: DataSpec, side: str) -> None:
    """A missing bag or real-hand file is refused before the run writes anything."""
    if spec.bag is not None and not Path(spec.bag).is_dir():
        raise ValueError(f"{side}.bag: {spec.bag}: no bag directory there")
    if spec.real is not None and not (real_data_dir() / REAL_FILES[spec.real]).is_file():
        raise ValueError(f"{side}.real: {real_data_dir() / REAL_FILES[spec.real]}: no such file (see $T42_REAL_DATA)")


@contextlib.contextmanager
def _run_lock(run_dir: Path) -> Iterator[None]:
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


def _run(cfg: ExperimentConfig, run_dir: Path, progress: bool) -> list[dict[str, Any]]:
    from tqdm.auto import tqdm

    (run_dir / "config.yaml").write_text(yaml.safe_dump(_config_dict(cfg), sort_keys=False))
    source_path = train_source(cfg, run_dir, progress)
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
