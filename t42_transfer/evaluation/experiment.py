"""The experiment runner: methods x amounts of target data x seeds, from one YAML config.

The source model is trained once on the whole source set; every cell transfers
it with one method to a subset of the target's training pool and scores the
result on held-out target episodes (divergence time, MSE, Lyapunov exponent,
and the quantities of the paper's bound).  Cells are cached by a hash of
everything they depend on, so an interrupted run resumes where it stopped and a
changed setting reruns only what it touches.  Every run also scores the
hold-still model (:class:`~t42_transfer.models.baselines.HoldStill`) on the same
test episodes, the baseline each method's numbers are read against.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

import numpy as np
import torch
import yaml

from t42_transfer.data.bag_io import assign_start_times, read_bag, write_bag
from t42_transfer.data.quality import HANDLING, handle_flagged, summarise
from t42_transfer.data.t42_real import REAL_HANDS, REAL_OBJECT, load_t42_testpaths, real_data_dir, real_file
from t42_transfer.data.trajectory import (
    Trajectory,
    TrajectorySet,
    grasp_centre,
    same_action_sequence,
    split_by_fraction,
)
from t42_transfer.evaluation.metrics import METRIC_DEFINITIONS
from t42_transfer.hand.collect import MAX_EPISODES, MAX_STEPS, MAX_WORKERS, POLICIES, check_collection
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import load_model, save_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
from t42_transfer.transfer.config import (
    DEFINITIONS,
    RECURRENT_FORMS,
    RESIDUAL_NORMALISATIONS,
    SOURCE_TRAINING,
    TRAJECTORY_LOSSES,
    AutoConfig,
    L2FineTuneConfig,
    NewModelConfig,
    RecurrentResidualConfig,
    ResidualConfig,
    TrajectoryFineTuneConfig,
    TransferConfig,
)
from t42_transfer.transfer.methods import METHODS, select_method, transfer
from t42_transfer.yaml_files import read_yaml

RESULT_COLUMNS = (
    "method", "amount", "seed", "train_episodes", "train_transitions", "test_rollouts", "divergence_mean",
    "divergence_median", "divergence_mean_4mm", "divergence_mean_10mm", "position_mse_mean", "lyapunov_mean",
    "lyapunov_median", "covering_radius", "train_error_normalised", "train_error_xy_mm", "seconds",
)
THRESHOLDS_MM = (4.0, 10.0)
"""Divergence is also reported at both thresholds in use (the paper's figure: 4 mm; the authors' scripts: 10 mm),
counted by the experiment's definition, since the threshold alone can flip a ranking."""
BASELINE = HoldStill.kind
"""The method name of the hold-still rows every run writes beside its cells'."""


@dataclass(frozen=True)
class DataSpec:
    """Where a hand's data comes from (a simulated hand, a bag, or a public real-hand file) and what is done to it."""

    hand: str | None = None
    episodes: int = 300
    steps: int = 1000
    seed: int = 0
    bag: str | None = None
    real: str | None = None
    """``A`` or ``B``: the public T42 test paths of that hand, of the object ``real_object``."""
    mirror_x: bool = False
    """Mirror x (the real hands are mirror images of each other), about ``mirror_about``."""
    real_object: str = REAL_OBJECT
    """The object of ``real``'s file (``testpaths_<object>[_red]_d_v0.pkl`` in ``$T42_REAL_DATA``): ``cyl35`` lies
    beside the project; the public repository also holds ``egg50`` and ``poly6`` for both hands."""
    mirror_about: str = "origin"
    """``origin``: x -> -x, about the camera's origin.  ``grasp``: about the axis halfway between this side's
    and the other side's grasp centres, with y shifted by their difference, so both grasps coincide."""
    negate_actions: bool = False
    """Negate every action: the authors' B -> A runs gave hand A its actions negated (the hands are mirrored)."""
    flagged: str = "keep"
    """Episodes with frozen tracking or jumps (:mod:`t42_transfer.data.quality`): ``keep`` them as they are,
    ``drop`` them, or ``split`` them at each flagged stretch.  Found stretches are recorded in any case."""
    exclude_test_sequences: bool = False
    """Source only: leave out of the source model's training every episode that ran the action sequence of one
    of the cell's test episodes (both real hands ran the same six), training a source per test set."""
    policy: str = "random"
    """``hand`` only: how the simulated hand is driven (:data:`t42_transfer.hand.collect.POLICIES`): ``random``,
    the paper's training data, or ``sustained``, test paths like the real hands' (long holds of discrete moves)."""

    def describe(self) -> dict:
        """The settings, without those still at defaults added after runs were cached (their keys stay valid)."""
        values = dataclasses.asdict(self)
        return {k: v for k, v in values.items() if k in _ORIGINAL_SPEC or v != _SPEC_DEFAULTS[k]}


@dataclass(frozen=True)
class ExperimentConfig:
    name: str
    """The run directory's name under ``--out``: one plain path component."""
    source: DataSpec
    target: DataSpec
    methods: tuple[str, ...] = tuple(m for m in METHODS if m != "auto")
    split: str = "fraction"
    """``fraction``: amounts are fractions of the target pool, a fixed test split held out;
    ``paths``: amounts are numbers of target episodes, the others are the test set."""
    amounts: tuple[float, ...] = (0.005, 0.01, 0.02, 0.05, 0.1)
    seeds: int = 5
    test_fraction: float = 0.2
    definition: str = "paper"
    """Where the paper's text and its authors' code differ, which one this run follows (``paper`` or
    ``authors``): the transfer settings, the source training, the threshold and how divergence and MSE count."""
    epsilon_mm: float | None = None
    """None: the definition's (paper 4 mm, authors 10 mm)."""
    start_offsets: tuple[int, ...] = (0,)
    horizon: int | None = None
    lyapunov_steps: int = 100
    source_training: TrainConfig | None = None
    """None: the definition's; settings given in a file apply on top of it."""
    transfer: TransferConfig | None = None
    """None: ``TransferConfig.for_definition(definition)``; settings given in a file apply on top of it."""
    workers: int | None = None
    test: DataSpec | None = None
    """Test episodes of the target hand from their own data set (e.g. sustained-action paths) instead of the
    held-out target episodes; the training subsets stay those without it, so cells pair across test sets."""

    def __post_init__(self) -> None:
        # The run directory is ``out / name``: anything but one plain component could leave ``out``.
        if not (isinstance(self.name, str) and SAFE_NAME.fullmatch(self.name)):
            raise ValueError(f"name must be one plain path component (letters, digits, '.', '_', '-'; "
                             f"not starting with '.'; at most 100 characters), got {_show(self.name)}")
        for key, value in _definition_defaults(self.definition).items():
            if getattr(self, key) is None:
                object.__setattr__(self, key, value)


def _definition_defaults(definition: Any) -> dict[str, Any]:
    """The settings ``definition`` decides unless a config gives them (ValueError for an unknown definition)."""
    if not isinstance(definition, str) or definition not in DEFINITIONS:
        raise ValueError(f"definition must be one of {DEFINITIONS}, got {_show(definition)}")
    return {"epsilon_mm": METRIC_DEFINITIONS[definition].epsilon_mm, "source_training": SOURCE_TRAINING[definition],
            "transfer": TransferConfig.for_definition(definition)}


SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,99}")
SAFE_OBJECT = re.compile(r"[a-z][a-z0-9]{0,39}")
"""The public files' object names (cyl35, egg50, poly6, sqr30...): part of a file name, so nothing else."""
MIRRORS = ("origin", "grasp")
_ORIGINAL_SPEC = ("hand", "episodes", "steps", "seed", "bag", "real", "mirror_x")
_SPEC_DEFAULTS = {f.name: f.default for f in dataclasses.fields(DataSpec)}
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
_RESIDUAL_RULES: dict[str, _Rule] = {
    "alpha": _between(0, math.inf), "gamma": _between(0, 1, True), "val_fraction": _between(0, 1, False, True),
    "normalisation": (lambda v: v in RESIDUAL_NORMALISATIONS, f"one of {RESIDUAL_NORMALISATIONS}"),
}
RULES: dict[type, dict[str, _Rule]] = {
    ExperimentConfig: {
        "seeds": _between(1, MAX_SEEDS), "amounts": _between(0, MAX_EPISODES, True), "test_fraction": _FRACTION,
        "epsilon_mm": _POSITIVE, "start_offsets": _between(0, MAX_EVAL_STEPS), "horizon": _STEPS,
        "lyapunov_steps": _STEPS, "workers": _between(1, MAX_WORKERS),
        "split": (lambda v: v in SPLITS, f"one of {SPLITS}"),
        "methods": (lambda v: v in METHODS, f"one of {sorted(METHODS)}"),
        "definition": (lambda v: v in DEFINITIONS, f"one of {DEFINITIONS}"),
    },
    DataSpec: {"episodes": _between(1, MAX_EPISODES), "steps": _between(1, MAX_STEPS), "seed": _SEED,
               "real": (lambda v: v in REAL_HANDS, f"one of {sorted(REAL_HANDS)}"),
               "real_object": (lambda v: bool(SAFE_OBJECT.fullmatch(v)), "an object name such as cyl35 or egg50"),
               "mirror_about": (lambda v: v in MIRRORS, f"one of {MIRRORS}"),
               "flagged": (lambda v: v in HANDLING, f"one of {HANDLING}"),
               "policy": (lambda v: v in POLICIES, f"one of {sorted(POLICIES)}")},
    TrainConfig: {"lr": _POSITIVE, "epochs": _STEPS, "batch_size": _between(1, 2**31 - 1),
                  "weight_decay": _between(0, math.inf), "grad_clip": _POSITIVE, "patience": _between(0, MAX_EVAL_STEPS),
                  "seed": _SEED},
    NewModelConfig: {"val_fraction": _between(0, 1, False, True)},
    L2FineTuneConfig: {"l2": _between(0, math.inf)},
    TrajectoryFineTuneConfig: {"cutoff_mm2": _POSITIVE,
                               "loss": (lambda v: v in TRAJECTORY_LOSSES, f"one of {TRAJECTORY_LOSSES}")},
    ResidualConfig: _RESIDUAL_RULES,
    RecurrentResidualConfig: {**_RESIDUAL_RULES, "form": (lambda v: v in RECURRENT_FORMS, f"one of {RECURRENT_FORMS}")},
    AutoConfig: {"candidates": (lambda v: v in METHODS and v != "auto", "a method other than auto"),
                 "fallback": (lambda v: v in METHODS and v != "auto", "a method other than auto"),
                 "holdout_fraction": _FRACTION, "min_episodes": _between(2, MAX_EPISODES)},
}
"""What each setting must be beyond its type (every element of a list setting)."""


def _show(value: Any) -> str:
    text = reprlib.repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _typed(value: Any, hint: Any, where: str, base: Any = None) -> Any:
    """``value`` from YAML checked against a field's annotation (lists become tuples); ValueError otherwise.

    A mapping for a settings dataclass applies on top of ``base`` (its settings not given), if any.
    """
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (hint,) = [a for a in args if a is not type(None)]
        return _typed(value, hint, where, base)
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
        return _build(hint, value, f"{where}.", base)
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


def _build(cls: type, values: dict[Any, Any], prefix: str = "", base: Any = None) -> Any:
    """A (nested) frozen dataclass from a YAML mapping: unknown keys, wrong types and values out of range refused.

    Settings not given are ``base``'s (an instance of ``cls``) or the defaults; an experiment's transfer and
    source-training settings apply on top of its definition's.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(str(k) for k in values if k not in fields)
    if unknown:
        kind = "experiment" if cls is ExperimentConfig else cls.__name__
        inside = f" in {prefix[:-1]}" if prefix else ""
        raise ValueError(f"unknown {kind} settings {_show(unknown)}{inside}; known: {sorted(fields)}")
    hints, rules = get_type_hints(cls), RULES.get(cls, {})
    bases = _definition_defaults(values.get("definition", "paper")) if cls is ExperimentConfig else (
        {} if base is None else {f: getattr(base, f) for f in fields})
    kwargs = {}
    for key, value in values.items():
        where = f"{prefix}{key}"
        kwargs[key] = _typed(value, hints[key], where, bases.get(key))
        if key in rules and kwargs[key] is not None:
            ok, wanted = rules[key]
            for item in kwargs[key] if isinstance(kwargs[key], tuple) else (kwargs[key],):
                if not ok(item):
                    raise ValueError(f"{where} must be {wanted}, got {_show(item)}")
    return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)


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
    for side in sides(cfg):
        spec: DataSpec = getattr(cfg, side)
        given = [k for k in ("hand", "bag", "real") if getattr(spec, k) is not None]
        if len(given) != 1:
            raise ValueError(f"{side} needs exactly one of hand, bag or real, got {given or 'none'}")
        if spec.hand is not None:
            check_collection(spec.hand, spec.episodes, spec.steps, hold_max=POLICIES[spec.policy]().hold_max)
        elif spec.policy != _SPEC_DEFAULTS["policy"]:
            raise ValueError(f"{side}.policy drives a simulated hand: it needs {side}.hand")
        if spec.real_object != REAL_OBJECT and spec.real is None:
            raise ValueError(f"{side}.real_object names the object of a real-hand file: it needs {side}.real")
        if spec.mirror_about != "origin" and not spec.mirror_x:
            raise ValueError(f"{side}.mirror_about: {spec.mirror_about} needs {side}.mirror_x: true")
    for side in sides(cfg)[1:]:
        spec = getattr(cfg, side)
        if cfg.source.mirror_x and spec.mirror_x and "grasp" in (cfg.source.mirror_about, spec.mirror_about):
            raise ValueError("mirror_about: grasp mirrors one side onto the other: mirror_x on one side only")
        if spec.exclude_test_sequences:
            raise ValueError(f"{side}.exclude_test_sequences: only the source's training leaves test sequences out")
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


def sides(cfg: ExperimentConfig) -> tuple[str, ...]:
    """The data sets ``cfg`` names: source, target, and test when it has its own."""
    return ("source", "target") if cfg.test is None else ("source", "target", "test")


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------- data


def data_cache(run_dir: Path) -> Path:
    """Collected data sets live beside the runs (``<out>/data``), shared by every experiment there."""
    return Path(run_dir).parent / "data"


def load_data(spec: DataSpec, cache: Path) -> TrajectorySet:
    """The trajectories ``spec`` names, as stored; simulated sets are collected once and kept as bags in ``cache``.

    The spec's moves (mirror, negated actions) and its handling of flagged episodes are :func:`load_side`'s.
    """
    if spec.real:
        return load_t42_testpaths(real_data_dir() / real_file(spec.real, spec.real_object))
    if spec.bag:
        return read_bag(spec.bag)
    if spec.hand:
        bag = cache / f"{spec.hand}_{_digest(spec.describe())}"
        if bag.exists():
            return read_bag(bag)
        from t42_transfer.hand.collect import collect

        collected, _ = collect(spec.hand, spec.episodes, spec.steps, seed=spec.seed, policy=POLICIES[spec.policy]())
        data = TrajectorySet(assign_start_times(collected), hand=collected.hand)
        write_bag(bag, data, metadata={"experiment_spec": json.dumps(spec.describe())})
        return data
    raise ValueError("a data spec needs one of hand, bag or real")


@dataclass(frozen=True)
class SideData:
    """One side of an experiment: its data as the spec moves it, and what the experiment uses of it."""

    raw: TrajectorySet
    """Mirrored and negated as the spec says, before flagged episodes are handled."""
    data: TrajectorySet
    """What the experiment trains and tests on: ``raw`` with flagged episodes kept, dropped or split."""
    origins: tuple[int, ...]
    """The episode of ``raw`` each episode of ``data`` comes from."""
    quality: dict[str, Any]
    """What the quality scan found in ``raw`` and what was kept: the run records it."""


def load_side(cfg: ExperimentConfig, side: str, cache: Path) -> SideData:
    """The ``source``, ``target`` or ``test`` data of ``cfg``; a mirror about the grasp also reads the other side
    (the source's other side is the target; the target's and the test set's is the source)."""
    spec: DataSpec = getattr(cfg, side)
    raw = load_data(spec, cache)
    if spec.negate_actions:
        raw = TrajectorySet((dataclasses.replace(t, actions=-t.actions) for t in raw), hand=raw.hand)
    if spec.mirror_x:
        if spec.mirror_about == "grasp":
            other = load_data(getattr(cfg, "target" if side == "source" else "source"), cache)
            own, theirs = grasp_centre(raw), grasp_centre(other)
            axis, shift = (own[0] + theirs[0]) / 2, theirs[1] - own[1]
        else:
            axis, shift = 0.0, 0.0
        raw = TrajectorySet((_mirror(t, axis, shift) for t in raw), hand=raw.hand)
    handled = handle_flagged(raw, spec.flagged)
    quality = {**summarise(raw, handled.findings), "flagged": spec.flagged, "kept_episodes": len(handled.data),
               "kept_transitions": handled.data.num_transitions}
    return SideData(raw, handled.data, handled.origins, quality)


def _mirror(traj: Trajectory, axis: float = 0.0, shift_y: float = 0.0) -> Trajectory:
    """The same episode seen in a mirror about the line x = ``axis``, moved ``shift_y`` along y."""
    states = traj.states.astype(np.float64)
    states[:, 0] = 2 * axis - states[:, 0]
    states[:, 1] += shift_y
    return dataclasses.replace(traj, states=states)


def excluded_sources(cfg: ExperimentConfig, source: SideData, tested: SideData, test: TrajectorySet) -> tuple[int, ...]:
    """Episodes of ``source.raw`` that ran the action sequence of a test episode (empty unless the source asks).

    ``tested``: the side the test episodes come from (the target, or the config's own test set).  A test
    episode split off a longer one is compared through the episode it came from.
    """
    if not cfg.source.exclude_test_sequences:
        return ()
    ran = [tested.raw[o] for t, o in zip(tested.data, tested.origins) if any(t is u for u in test)]
    return tuple(i for i, s in enumerate(source.raw) if any(same_action_sequence(s, t) for t in ran))


# ------------------------------------------------------------------------------ cells


@dataclass(frozen=True)
class Cell:
    method: str
    amount: float
    seed: int


def _target_split(
    cfg: ExperimentConfig, target: TrajectorySet, cell: Cell, test: TrajectorySet | None = None
) -> tuple[TrajectorySet, TrajectorySet]:
    """(training subset, test episodes) of a cell.

    ``test``: the episodes of ``cfg.test`` (required when the config names one); they replace the held-out
    target episodes, and the training subset is the one the cell has without them.
    """
    if (cfg.test is None) != (test is None):
        raise ValueError("pass the test set's episodes exactly when the config names a test set")
    if cfg.split == "fraction":
        held_out, pool = split_by_fraction(target, cfg.test_fraction, seed=12345)
        train, _ = split_by_fraction(pool, float(cell.amount), seed=cell.seed)
        return train, held_out if test is None else test
    if cfg.split == "paths":
        k, limit = int(cell.amount), len(target) + (test is not None)  # with a test set, all may train
        if not 1 <= k < limit:
            raise ValueError(f"paths split needs 1 <= k < {limit} with {len(target)} target episodes, got {k}")
        order = np.random.default_rng(cell.seed).permutation(len(target))
        return target.subset(sorted(order[:k])), target.subset(sorted(order[k:])) if test is None else test
    raise ValueError(f"split must be 'fraction' or 'paths', got {cfg.split!r}")


def _test_scores(model: LatentDynamics, test: TrajectorySet, cfg: ExperimentConfig) -> dict[str, Any]:
    """``model``'s open-loop scores on the test episodes: divergence, MSE, Lyapunov exponents."""
    from t42_transfer.evaluation.lyapunov import model_lyapunov
    from t42_transfer.evaluation.metrics import evaluate_model

    scores = evaluate_model(model, test, cfg.epsilon_mm, cfg.start_offsets, cfg.horizon, cfg.definition)
    at = {eps: scores if eps == scores["epsilon_mm"] else
          evaluate_model(model, test, eps, cfg.start_offsets, cfg.horizon, cfg.definition) for eps in THRESHOLDS_MM}
    lyap = model_lyapunov(model, test, steps=cfg.lyapunov_steps).numpy()
    return {
        "test_rollouts": scores["num_rollouts"],
        "divergence_mean": scores["divergence_mean"],
        "divergence_median": scores["divergence_median"],
        **{f"divergence_mean_{eps:g}mm": at[eps]["divergence_mean"] for eps in THRESHOLDS_MM},
        "position_mse_mean": scores["position_mse_mean"],
        "lyapunov_mean": float(np.mean(lyap)),
        "lyapunov_median": float(np.median(lyap)),
    }


def _states(data: TrajectorySet) -> np.ndarray:
    return np.concatenate([t.states for t in data])


def _bound_scale(train: TrajectorySet, test: TrajectorySet) -> np.ndarray:
    """One scale for both quantities of the bound: the spread of the target states."""
    return np.concatenate([_states(train), _states(test)]).std(0) + 1e-9


def _training_error(model: LatentDynamics, train: TrajectorySet, test: TrajectorySet) -> dict[str, float]:
    from t42_transfer.evaluation.metrics import max_training_error

    error = max_training_error(model, train.transitions(), state_scale=_bound_scale(train, test))
    return {"train_error_normalised": error.normalised, "train_error_xy_mm": error.xy_mm}


def _score(model: LatentDynamics, train: TrajectorySet, test: TrajectorySet, cfg: ExperimentConfig) -> dict[str, Any]:
    from t42_transfer.evaluation.metrics import covering_radius

    scale = _bound_scale(train, test)
    radius = covering_radius(_states(train) / scale, _states(test) / scale)
    return {**_test_scores(model, test, cfg), "covering_radius": radius, **_training_error(model, train, test)}


def baseline_rows(
    cfg: ExperimentConfig, target: TrajectorySet, test_set: TrajectorySet | None, cell_rows: dict[Cell, dict[str, Any]]
) -> list[dict[str, Any]]:
    """The hold-still model's rows, one per amount and seed (paired with the cells'), nothing trained.

    Its test scores are computed once per distinct test set (once in all with ``split: fraction`` or a
    config's own test set); the covering radius, a property of a cell's data alone, is that of the cells
    at the same amount and seed (``cell_rows``).
    """
    model, scored, rows = HoldStill(), {}, []
    for amount in cfg.amounts:
        for seed in range(cfg.seeds):
            start = time.perf_counter()
            train, test = _target_split(cfg, target, Cell(BASELINE, amount, seed), test_set)
            key = test.fingerprint()
            if key not in scored:
                scored[key] = _test_scores(model, test, cfg)
            paired = next(r for c, r in cell_rows.items() if (c.amount, c.seed) == (amount, seed))
            rows.append({
                "method": BASELINE, "amount": amount, "seed": seed, "train_episodes": len(train),
                "train_transitions": train.num_transitions, **scored[key], "covering_radius": paired["covering_radius"],
                **_training_error(model, train, test), "seconds": time.perf_counter() - start,
            })
    return rows


_WORKER: dict[str, Any] = {}


def _run_cell(args: tuple[ExperimentConfig, Cell, Path, Path, dict[str, Any]]) -> dict[str, Any]:
    cfg, cell, run_dir, source_path, workspace = args
    torch.set_num_threads(1)
    sources = _WORKER.setdefault("sources", {})  # one per test set when the source leaves test sequences out
    if source_path not in sources:
        sources[source_path] = load_model(source_path)[0]
    data_key = _digest({"data": [dataclasses.asdict(getattr(cfg, side)) for side in sides(cfg)], "run": str(run_dir)})
    if _WORKER.get("data_key") != data_key:
        test_side = load_test(cfg, data_cache(run_dir))
        _WORKER["target"] = load_side(cfg, "target", data_cache(run_dir)).data
        _WORKER["test"] = None if test_side is None else test_side.data
        _WORKER["data_key"] = data_key
    source, target = sources[source_path], _WORKER["target"]
    train, test = _target_split(cfg, target, cell, _WORKER["test"])
    start = time.perf_counter()
    row = {
        "method": cell.method, "amount": cell.amount, "seed": cell.seed,
        "train_episodes": len(train), "train_transitions": train.num_transitions,
    }
    if cell.method == "auto":  # keep which candidate the held-out evidence picked (results.json only)
        selection = select_method(source, train, cfg.transfer, seed=cell.seed)
        model, row["auto_picked"] = selection.model.eval(), selection.best
    else:
        model = transfer(cell.method, source, train, cfg.transfer, seed=cell.seed)
    row.update(_score(model, train, test, cfg))
    row["seconds"] = time.perf_counter() - start
    save_model(model, run_dir / "models" / f"{_cell_key(cfg, cell, source_path)}.safetensors", method=cell.method,
               hyperparameters=dataclasses.asdict(cfg.transfer), data={"target_train": train.fingerprint()},
               extra={"workspace": workspace})
    return row


def load_test(cfg: ExperimentConfig, cache: Path) -> SideData | None:
    """The config's own test set, if it names one."""
    return None if cfg.test is None else load_side(cfg, "test", cache)


def cell_excluded(
    cfg: ExperimentConfig, cell: Cell, source: SideData, target: SideData, test: SideData | None = None
) -> tuple[int, ...]:
    """The source episodes left out of the source model of ``cell``: those that ran one of its test sequences.

    ``test``: :func:`load_test`'s, when the config names a test set.
    """
    episodes = _target_split(cfg, target.data, cell, None if test is None else test.data)[1]
    return excluded_sources(cfg, source, target if test is None else test, episodes)


def _cells(cfg: ExperimentConfig) -> list[Cell]:
    return [Cell(m, a, s) for m in cfg.methods for a in cfg.amounts for s in range(cfg.seeds)]


def _cell_key(cfg: ExperimentConfig, cell: Cell, source_path: Path) -> str:
    depends = {
        "cell": dataclasses.asdict(cell), "target": cfg.target.describe(), "split": cfg.split,
        "test_fraction": cfg.test_fraction, "epsilon": cfg.epsilon_mm, "offsets": cfg.start_offsets,
        "horizon": cfg.horizon, "lyapunov_steps": cfg.lyapunov_steps,
        "method_config": dataclasses.asdict(cfg.transfer), "source": source_path.name, "definition": cfg.definition,
    }
    if cfg.test is not None:  # absent otherwise: keys of runs without a test set stay valid
        depends["test"] = cfg.test.describe()
    return f"{cell.method}-{cell.amount}-{cell.seed}-{_digest(depends)}"


def source_model_path(cfg: ExperimentConfig, run_dir: Path, excluded: tuple[int, ...] = ()) -> Path:
    """Where the source model trained without the source episodes ``excluded`` is kept (shared by experiments)."""
    depends: dict[str, Any] = {"source": cfg.source.describe(), "train": dataclasses.asdict(cfg.source_training)}
    if cfg.source.mirror_about == "grasp":  # mirrored onto the target's grasp
        depends["onto"] = cfg.target.describe()
    if excluded:
        depends["excluded"] = list(excluded)
    return Path(run_dir).parent / "sources" / f"source-{_digest(depends)}.safetensors"


def train_source(cfg: ExperimentConfig, run_dir: Path, progress: bool = True, excluded: tuple[int, ...] = ()) -> Path:
    """The source model of this experiment, trained once and cached by its data and settings.

    ``excluded``: episodes of the source data as loaded (:attr:`SideData.raw`) left out of training.
    """
    path = source_model_path(cfg, run_dir, excluded)
    if path.exists():
        return path
    side = load_side(cfg, "source", data_cache(run_dir))
    data = TrajectorySet((t for t, o in zip(side.data, side.origins) if o not in excluded), hand=side.data.hand)
    if not len(data):
        raise ValueError(f"no source episode is left to train on once episodes {list(excluded)} are excluded")
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
        extra={"epochs_run": report.epochs_run, "best_epoch": report.best_epoch, "val_loss": report.val_loss,
               "validation": report.validation, "excluded_source_episodes": list(excluded)},
    )
    return path


def run_experiment(cfg: ExperimentConfig, out: Path, progress: bool = True) -> list[dict[str, Any]]:
    """Run (or resume) every cell; write its rows and the hold-still rows to ``results.json`` and ``results.csv``
    in ``out / cfg.name``, and return them.

    The config is checked first and the run directory locked: a bad setting or a run directory in
    use is refused before anything is written.
    """
    check_config(cfg)
    for side in sides(cfg):
        _check_input(getattr(cfg, side), side)
    run_dir = Path(out) / cfg.name
    target = load_side(cfg, "target", data_cache(run_dir))
    test = load_test(cfg, data_cache(run_dir))
    if len(target.data) < 2:
        raise ValueError(f"the target set has {len(target.data)} episodes; need at least 2")
    if test is not None and not len(test.data):
        raise ValueError("the test set has no episodes")
    if cfg.split == "paths" and max(cfg.amounts) >= len(target.data) + (test is not None):
        raise ValueError(f"amounts up to {max(cfg.amounts)} episodes with split: paths, but the target set has "
                         f"{len(target.data)}" + ("" if test is not None else ": some must stay for testing"))
    if cfg.source.exclude_test_sequences:
        source = load_side(cfg, "source", data_cache(run_dir))
        for cell in _cells(cfg):
            if not set(source.origins) - set(cell_excluded(cfg, cell, source, target, test)):
                raise ValueError(f"every source episode ran a test sequence of {cell}: none is left to train on")
    (run_dir / "cells").mkdir(parents=True, exist_ok=True)
    with _run_lock(run_dir):
        return _run(cfg, run_dir, progress)


def _check_input(spec: DataSpec, side: str) -> None:
    """A missing bag or real-hand file is refused before the run writes anything."""
    if spec.bag is not None and not Path(spec.bag).is_dir():
        raise ValueError(f"{side}.bag: {spec.bag}: no bag directory there")
    if spec.real is not None and not (real_data_dir() / real_file(spec.real, spec.real_object)).is_file():
        raise ValueError(f"{side}.real: {real_data_dir() / real_file(spec.real, spec.real_object)}: no such file "
                         f"(see $T42_REAL_DATA)")


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
    cache = data_cache(run_dir)
    source, target, test = load_side(cfg, "source", cache), load_side(cfg, "target", cache), load_test(cfg, cache)
    quality = {"source": source.quality, "target": target.quality}
    if test is not None:
        quality["test"] = test.quality
    (run_dir / "data_quality.json").write_text(json.dumps(quality, indent=1))
    cells = _cells(cfg)
    excluded = {c: cell_excluded(cfg, c, source, target, test) for c in cells}
    sources = {c: source_model_path(cfg, run_dir, excluded[c]) for c in cells}
    rows: dict[Cell, dict[str, Any]] = {}
    todo = []
    for cell in cells:
        done = run_dir / "cells" / f"{_cell_key(cfg, cell, sources[cell])}.json"
        if done.exists():
            rows[cell] = json.loads(done.read_text())
        else:
            todo.append(cell)
    for left_out in sorted({excluded[c] for c in todo}):
        train_source(cfg, run_dir, progress, left_out)
    workers = cfg.workers or os.cpu_count() or 1
    bar = tqdm(total=len(cells), initial=len(cells) - len(todo), desc=cfg.name, unit="cell", disable=not progress)
    # The planner keeps predictions inside the states these models were trained on.
    from t42_transfer.planning.workspace import Workspace

    workspace = Workspace.from_trajectories(source.data).to_dict() if todo else {}
    tasks = [(cfg, c, run_dir, sources[c], workspace) for c in todo]

    def keep(cell: Cell, row: dict[str, Any]) -> None:
        rows[cell] = row
        (run_dir / "cells" / f"{_cell_key(cfg, cell, sources[cell])}.json").write_text(json.dumps(row, indent=1))
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
    ordered = [rows[c] for c in cells] + baseline_rows(cfg, target.data, None if test is None else test.data, rows)
    results: dict[str, Any] = {"config": _config_dict(cfg), "rows": ordered, "data_quality": quality}
    if cfg.source.exclude_test_sequences:
        results["excluded_source_episodes"] = {f"{c.method}-{c.amount}-{c.seed}": list(excluded[c]) for c in cells}
    (run_dir / "results.json").write_text(json.dumps(results, indent=1))
    with open(run_dir / "results.csv", "w") as f:
        f.write(",".join(RESULT_COLUMNS) + "\n")
        for row in ordered:
            f.write(",".join(str(row[c]) for c in RESULT_COLUMNS) + "\n")
    return ordered


def _config_dict(cfg: ExperimentConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
