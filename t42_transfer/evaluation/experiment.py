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
import json
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import yaml

from t42_transfer.data.bag import assign_start_times, read_bag, write_bag
from t42_transfer.data.quality import handle_flagged, summarise
from t42_transfer.data.t42_real import load_t42_testpaths, real_data_dir, real_file
from t42_transfer.data.trajectory import (
    Trajectory,
    TrajectorySet,
    grasp_centre,
    same_action_sequence,
    split_by_fraction,
)
from t42_transfer.evaluation.cluster import check_reachable, check_scheduler, run_cells
from t42_transfer.evaluation.experiment_config import (
    DataSpec,
    ExperimentConfig,
    check_config,
    config_dict,
    sides,
)
from t42_transfer.evaluation.experiment_files import (
    Cell,
    cell_key,
    digest,
    failure_record,
    run_lock,
    stored_rows,
    warn_if_diverged,
    write_results,
)
from t42_transfer.evaluation.model_files import check_action_units, file_sha256, put_source_model
from t42_transfer.files import held_lock, write_atomic
from t42_transfer.hand.collect import POLICIES
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import load_model, read_metadata, save_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.training import ProgressBar, train_transition_model
from t42_transfer.transfer.methods import select_method, transfer

if TYPE_CHECKING:
    from t42_transfer.planning.workspace import Workspace

THRESHOLDS_MM = (4.0, 10.0)
"""Divergence is also reported at both thresholds in use (the paper's figure: 4 mm; the authors' scripts: 10 mm),
counted by the experiment's definition, since the threshold alone can flip a ranking."""
BASELINE = HoldStill.kind
"""The method name of the hold-still rows every run writes beside its cells'."""


# ------------------------------------------------------------------------------- data


def data_cache(run_dir: Path) -> Path:
    """Collected data sets live beside the runs (``<out>/data``), shared by every experiment there."""
    return Path(run_dir).parent / "data"


def load_data(spec: DataSpec, cache: Path, progress: bool = True) -> TrajectorySet:
    """The trajectories ``spec`` names, as stored; simulated sets are collected once and kept as bags in ``cache``
    (once also when experiments sharing ``cache`` need one at the same time: the later waits for the first).

    The spec's moves (mirror, negated actions) and its handling of flagged episodes are :func:`load_spec`'s.
    A source that is a model (``model``) has no trajectories.
    """
    if spec.model:
        return TrajectorySet()
    if spec.real:
        return load_t42_testpaths(real_data_dir() / real_file(spec.real, spec.real_object))
    if spec.bag:
        return read_bag(spec.bag, spec.unit_rad())
    if spec.hand:
        bag = cache / f"{spec.hand}_{digest(spec.describe())}"
        if bag.exists():  # (no lock: a cache others keep may be read-only)
            return read_bag(bag)
        cache.mkdir(parents=True, exist_ok=True)
        lock = cache / f".{bag.name}.lock"
        with held_lock(lock):  # another experiment collecting the same set: wait for it, then read its bag
            if bag.exists():
                data = read_bag(bag)
            else:
                from t42_transfer.hand.collect import collect

                collected, _ = collect(spec.hand, spec.episodes, spec.steps, seed=spec.seed,
                                       policy=POLICIES[spec.policy](), progress=progress)
                data = TrajectorySet(assign_start_times(collected), hand=collected.hand)
                with contextlib.suppress(FileExistsError):  # put there by a writer no lock held off: the same data
                    write_bag(bag, data, metadata={"experiment_spec": json.dumps(spec.describe())})
            lock.unlink(missing_ok=True)  # the bag is in place for good: whoever locks the file unlinked finds it
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


def load_side(cfg: ExperimentConfig, side: str, cache: Path, progress: bool = True) -> SideData:
    """The ``source``, ``target`` or ``test`` data of ``cfg``; a mirror about the grasp also reads the other side
    (the source's other side is the target; the target's and the test set's is the source)."""
    return load_spec(getattr(cfg, side), cache, getattr(cfg, "target" if side == "source" else "source"), progress)


def load_spec(spec: DataSpec, cache: Path, other: DataSpec | None = None, progress: bool = True) -> SideData:
    """The data ``spec`` names, moved as it says (negated actions, mirror) and with flagged episodes handled.

    ``other``: the data set a mirror about the grasp mirrors onto (required for ``mirror_about: grasp``).
    A source that is a model has no data: empty sets, and the model file named in the quality record.
    """
    if spec.model is not None:
        empty = TrajectorySet()
        return SideData(empty, empty, (), {"model": spec.model, "model_sha256": file_sha256(spec.model),
                                           "negate_actions": spec.negate_actions, "episodes": 0, "transitions": 0})
    raw = load_data(spec, cache, progress)
    if spec.paths is not None:
        beyond = [i for i in spec.paths if i >= len(raw)]
        if beyond:
            raise ValueError(f"paths: the data has {len(raw)} episodes (0 to {len(raw) - 1}), not {beyond[0]}")
        raw = raw.subset(spec.paths)
    if spec.negate_actions:
        raw = TrajectorySet((dataclasses.replace(t, actions=-t.actions) for t in raw), hand=raw.hand)
    if spec.mirror_x:
        if spec.mirror_about == "grasp":
            if other is None or other.model is not None:
                raise ValueError("mirror_about: grasp mirrors onto another data set's grasp: none is given")
            own, theirs = grasp_centre(raw), grasp_centre(load_data(other, cache))
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
    ran = [tested.raw[o] for t, o in zip(tested.data, tested.origins, strict=True) if any(t is u for u in test)]
    return tuple(i for i, s in enumerate(source.raw) if any(same_action_sequence(s, t) for t in ran))


# ------------------------------------------------------------------------------ cells


def target_split(
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

    error = max_training_error(model, train.transitions(), _bound_scale(train, test), starts=train.start_states())
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
            train, test = target_split(cfg, target, Cell(BASELINE, amount, seed), test_set)
            key = test.fingerprint()
            if key not in scored:
                scored[key] = _test_scores(model, test, cfg)
            paired = next(r for c, r in cell_rows.items() if (c.amount, c.seed) == (amount, seed))
            rows.append({
                "method": BASELINE, "amount": amount, "seed": seed, "train_episodes": len(train),
                "train_transitions": train.num_transitions, "train_draw": train.fingerprint()[:16], **scored[key],
                "covering_radius": paired["covering_radius"],
                **_training_error(model, train, test), "seconds": time.perf_counter() - start,
            })
    return rows


_WORKER: dict[str, Any] = {}


def _data_id(target: TrajectorySet, test: TrajectorySet | None) -> str:
    """What a run's target (and test) data hold, by content: the bag at a path can be recorded again."""
    return digest([target.fingerprint(), None if test is None else test.fingerprint()])


def _worker_data(cfg: ExperimentConfig, run_dir: Path, data_id: str | None) -> tuple[TrajectorySet, Any]:
    """The target (and test) data, read once per process and run, and kept while the run's ``data_id`` (None:
    unchecked) stays: ValueError when this process reads other data than the run holds (changed since)."""
    data_key = digest({"data": [dataclasses.asdict(getattr(cfg, side)) for side in sides(cfg)], "run": str(run_dir),
                        "id": data_id})
    if _WORKER.get("data_key") != data_key:
        test_side = load_test(cfg, data_cache(run_dir))
        target, test = load_side(cfg, "target", data_cache(run_dir)).data, None if test_side is None else test_side.data
        if data_id is not None and _data_id(target, test) != data_id:
            raise ValueError("the target data read for the cell differ from the run's: changed at their path since "
                             "the run started, or another copy on this worker's host")
        _WORKER.update(target=target, test=test, data_key=data_key)
    return _WORKER["target"], _WORKER["test"]


def _run_cell(args: tuple[Any, ...]) -> dict[str, Any]:
    """One cell's row, computed on whichever process runs it.  ``args``: the config, the cell, the run directory,
    its source model file, the planning workspace and (optional) what the run's data hold (``data``:
    :func:`_data_id`; ``source_data``: the source model's identity, recorded in the row as ``test_draw`` is)."""
    cfg, cell, run_dir, source_path, workspace, *more = args
    expect: dict[str, str] = more[0] if more else {}
    torch.set_num_threads(1)
    sources = _WORKER.setdefault("sources", {})  # one per test set when the source leaves test sequences out
    source_id = (source_path, expect.get("source_data"))  # a source trained again on new data is read again
    if source_id not in sources:
        sources[source_id] = load_model(source_path)[0]
    target, tests = _worker_data(cfg, run_dir, expect.get("data"))
    source = sources[source_id]
    train, test = target_split(cfg, target, cell, tests)
    start = time.perf_counter()
    row = {
        "method": cell.method, "amount": cell.amount, "seed": cell.seed,
        "train_episodes": len(train), "train_transitions": train.num_transitions,
        "train_draw": train.fingerprint()[:16],  # seeds that drew the same episodes are one cell (stats.one_per_draw)
    }
    if expect:  # what a resume compares with the data it holds then
        row.update(test_draw=test.fingerprint()[:16], source_data=expect["source_data"])
    if cell.method == "auto":  # keep which candidate the held-out evidence picked (results.json only)
        selection = select_method(source, train, cfg.transfer, seed=cell.seed)
        model, row["auto_picked"] = selection.model.eval(), selection.best
    else:
        model = transfer(cell.method, source, train, cfg.transfer, seed=cell.seed)
    row.update(_score(model, train, test, cfg))
    row["seconds"] = time.perf_counter() - start
    save_model(model, run_dir / "models" / f"{cell_key(cfg, cell, source_path)}.safetensors", method=cell.method,
               hyperparameters=dataclasses.asdict(cfg.transfer), data={"target_train": train.fingerprint()},
               extra={"workspace": workspace}, action_unit_rad=cfg.target.unit_rad())
    return row


def load_test(cfg: ExperimentConfig, cache: Path, progress: bool = True) -> SideData | None:
    """The config's own test set, if it names one."""
    return None if cfg.test is None else load_side(cfg, "test", cache, progress)


def cell_excluded(
    cfg: ExperimentConfig, cell: Cell, source: SideData, target: SideData, test: SideData | None = None
) -> tuple[int, ...]:
    """The source episodes left out of the source model of ``cell``: those that ran one of its test sequences.

    ``test``: :func:`load_test`'s, when the config names a test set.
    """
    episodes = target_split(cfg, target.data, cell, None if test is None else test.data)[1]
    return excluded_sources(cfg, source, target if test is None else test, episodes)


def _cells(cfg: ExperimentConfig) -> list[Cell]:
    return [Cell(m, a, s) for m in cfg.methods for a in cfg.amounts for s in range(cfg.seeds)]


def cell_model_file(cfg: ExperimentConfig, run_dir: Path, cell: Cell, source: SideData, target: SideData,
                    test: SideData | None = None) -> Path:
    """Where a run keeps the model ``cell`` trained (``run_dir/models/<cell key>.safetensors``), made or not."""
    source_path = source_model_path(cfg, run_dir, cell_excluded(cfg, cell, source, target, test))
    return run_dir / "models" / f"{cell_key(cfg, cell, source_path)}.safetensors"


def source_model_path(cfg: ExperimentConfig, run_dir: Path, excluded: tuple[int, ...] = ()) -> Path:
    """Where the source model trained without the source episodes ``excluded`` is kept (shared by experiments).

    A source that is a model is kept there too, named by its file's sha256 (and the negation of its actions).
    """
    if cfg.source.model is not None:
        model = {"model_sha256": file_sha256(cfg.source.model), "negate_actions": cfg.source.negate_actions}
        return Path(run_dir).parent / "sources" / f"source-{digest(model)}.safetensors"
    depends: dict[str, Any] = {"source": cfg.source.describe(), "train": dataclasses.asdict(cfg.source_training)}
    if cfg.source.mirror_about == "grasp":  # mirrored onto the target's grasp
        depends["onto"] = cfg.target.describe()
    if excluded:
        depends["excluded"] = list(excluded)
    return Path(run_dir).parent / "sources" / f"source-{digest(depends)}.safetensors"


def source_training_data(side: SideData, excluded: tuple[int, ...] = ()) -> TrajectorySet:
    """What a source model is trained on: the source data without the episodes ``excluded`` (of ``side.raw``)."""
    return TrajectorySet((t for t, o in zip(side.data, side.origins, strict=True) if o not in excluded),
                         hand=side.data.hand)


def train_source(cfg: ExperimentConfig, run_dir: Path, progress: bool = True, excluded: tuple[int, ...] = (),
                 again: bool = False) -> Path:
    """The source model of this experiment, trained once and cached by its data and settings.

    ``excluded``: episodes of the source data as loaded (:attr:`SideData.raw`) left out of training.
    ``again``: train it anew over the one kept (trained on data since changed at the same path).
    A source that is a model is not trained: it is imported or copied as it is.
    """
    path = source_model_path(cfg, run_dir, excluded)
    if path.exists() and not again:
        return path
    if cfg.source.model is not None:
        put_source_model(cfg.source, path)
        return path
    data = source_training_data(load_side(cfg, "source", data_cache(run_dir)), excluded)
    if not len(data):
        raise ValueError(f"no source episode is left to train on once episodes {list(excluded)} are excluded")
    # Minibatches of 64 gain nothing from a second thread, and idle OpenMP threads
    # spinning against other processes cost up to 10x on a busy 2-core machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model, report = train_transition_model(data, cfg.source_training,
                                               on_epoch=ProgressBar() if progress else None, phase="source model")
    finally:
        torch.set_num_threads(threads)
    save_model(
        model, path, method="source", hyperparameters=dataclasses.asdict(cfg.source_training),
        data={"source": data.fingerprint(), "transitions": data.num_transitions},
        extra={"epochs_run": report.epochs_run, "best_epoch": report.best_epoch, "val_loss": report.val_loss,
               "validation": report.validation, "excluded_source_episodes": list(excluded)},
        action_unit_rad=cfg.source.unit_rad(),
    )
    return path


def run_experiment(cfg: ExperimentConfig, out: Path, progress: bool = True,
                   scheduler: str | None = None) -> list[dict[str, Any]]:
    """Run (or resume) every cell; write its rows and the hold-still rows to ``results.json`` and ``results.csv``
    in ``out / cfg.name``, and return them.  ``scheduler`` runs the cells on Dask (:mod:`.cluster`: ``local:N``
    or a scheduler's address) instead of ``cfg.workers`` local processes; the numbers are the same.

    The config is checked first and the run directory locked: a bad setting or a run directory in
    use is refused before anything is written.
    """
    check_config(cfg)
    if scheduler is not None:
        check_reachable(check_scheduler(scheduler))
    for side in sides(cfg):
        _check_input(getattr(cfg, side), side)
    check_action_units(cfg)  # and a source file that is no model, before anything is written
    run_dir = Path(out) / cfg.name
    target = load_side(cfg, "target", data_cache(run_dir), progress)  # collected here when simulated
    test = load_test(cfg, data_cache(run_dir), progress)
    if len(target.data) < 2:
        raise ValueError(f"the target set has {len(target.data)} episodes; need at least 2")
    if test is not None and not len(test.data):
        raise ValueError("the test set has no episodes")
    if cfg.split == "paths" and max(cfg.amounts) >= len(target.data) + (test is not None):
        raise ValueError(f"amounts up to {max(cfg.amounts)} episodes with split: paths, but the target set has "
                         f"{len(target.data)}" + ("" if test is not None else ": some must stay for testing"))
    _check_methods_fit(cfg, target.data, None if test is None else test.data)
    if cfg.source.exclude_test_sequences or cfg.source.paths is not None:  # (a path the file lacks: refused here)
        source = load_side(cfg, "source", data_cache(run_dir), progress)
    if cfg.source.exclude_test_sequences:
        for cell in _cells(cfg):
            if not set(source.origins) - set(cell_excluded(cfg, cell, source, target, test)):
                raise ValueError(f"every source episode ran a test sequence of {cell}: none is left to train on")
    (run_dir / "cells").mkdir(parents=True, exist_ok=True)
    with run_lock(run_dir):
        return _run(cfg, run_dir.absolute(), progress, scheduler)  # absolute: workers elsewhere see the same path


def _check_methods_fit(cfg: ExperimentConfig, target: TrajectorySet, test: TrajectorySet | None) -> None:
    """Every method can run on every cell's training data (counts only, nothing trained): a method that cannot,
    at some amount, is refused before the first cell instead of failing after the others ran."""
    from t42_transfer.transfer.methods import data_problem

    for cell in _cells(cfg):
        train = target_split(cfg, target, cell, test)[0]
        if (why := data_problem(cell.method, len(train), train.num_transitions, cfg.transfer)) is not None:
            raise ValueError(f"{cell.method} at amount {cell.amount:g} (seed {cell.seed}, {len(train)} training "
                             f"episode(s)): {why}")


def _check_input(spec: DataSpec, side: str) -> None:
    """A missing bag or real-hand file is refused before the run writes anything."""
    if spec.bag is not None and not Path(spec.bag).is_dir():
        raise ValueError(f"{side}.bag: {spec.bag}: no bag directory there")
    if spec.real is not None and not (real_data_dir() / real_file(spec.real, spec.real_object)).is_file():
        raise ValueError(f"{side}.real: {real_data_dir() / real_file(spec.real, spec.real_object)}: no such file "
                         f"(see $T42_REAL_DATA)")


def _workspace(cfg: ExperimentConfig, source: TrajectorySet, target: TrajectorySet, source_file: Path) -> Workspace:
    """The states the cells' models are trusted in: the source data's; for a source that is a model, the
    workspace its file stores, else the target data's (the one hand's states the run has)."""
    from t42_transfer.planning.workspace import Workspace

    if cfg.source.model is None:
        return Workspace.from_trajectories(source)
    return Workspace.from_metadata(load_model(source_file)[1], source_file) or Workspace.from_trajectories(target)


Exclusions = tuple[int, ...]


def _source_ids(cfg: ExperimentConfig, run_dir: Path, source: SideData,
                exclusions: set[Exclusions]) -> tuple[dict[Exclusions, str], set[Exclusions]]:
    """What each source model of the run is made of (the fingerprint of its training data; for a source that is a
    model, its file's sha256), and those kept but trained on other data, with a warning: a bag recorded again at
    the same path, which the file's name (it hashes the spec's path) cannot tell.  Those are trained again."""
    if cfg.source.model is not None:  # kept under its file's sha256: never stale
        return dict.fromkeys(exclusions, file_sha256(cfg.source.model)), set()
    made_of = {e: source_training_data(source, e).fingerprint() for e in exclusions}
    stale = set()
    for excluded, fingerprint in made_of.items():
        path = source_model_path(cfg, run_dir, excluded)
        if path.exists() and read_metadata(path).get("data", {}).get("source", fingerprint) != fingerprint:
            where = next(f"{k} {v}" for k in ("bag", "real", "hand") if (v := getattr(cfg.source, k)) is not None)
            warnings.warn(f"{path}: the source model was trained on other data than the source ({where}) holds "
                          f"now: it is trained again and its cells are run again", stacklevel=3)
            stale.add(excluded)
    return made_of, stale


def _draws(cfg: ExperimentConfig, cells: list[Cell], target: SideData, test: SideData | None,
           source_ids: dict[Cell, str]) -> dict[Cell, dict[str, str]]:
    """What each cell's row records of the data it runs on now: its training draw, its test episodes, its source."""
    splits: dict[tuple[float, int], tuple[str, str]] = {}  # the split depends on the amount and seed alone
    for cell in cells:
        if (cell.amount, cell.seed) not in splits:
            train, tested = target_split(cfg, target.data, cell, None if test is None else test.data)
            splits[cell.amount, cell.seed] = (train.fingerprint()[:16], tested.fingerprint()[:16])
    return {c: dict(zip(("train_draw", "test_draw"), splits[c.amount, c.seed], strict=True),
                    source_data=source_ids[c][:16]) for c in cells}


def _run(cfg: ExperimentConfig, run_dir: Path, progress: bool, scheduler: str | None) -> list[dict[str, Any]]:
    from t42_transfer.progress import progress_bar

    write_atomic(run_dir / "config.yaml", yaml.safe_dump(config_dict(cfg), sort_keys=False))
    cache = data_cache(run_dir)
    source, target = load_side(cfg, "source", cache, progress), load_side(cfg, "target", cache, progress)
    test = load_test(cfg, cache, progress)
    quality = {"source": source.quality, "target": target.quality}
    if test is not None:
        quality["test"] = test.quality
    write_atomic(run_dir / "data_quality.json", json.dumps(quality, indent=1))
    cells = _cells(cfg)
    excluded = {c: cell_excluded(cfg, c, source, target, test) for c in cells}
    sources = {c: source_model_path(cfg, run_dir, excluded[c]) for c in cells}
    files = {c: run_dir / "cells" / f"{cell_key(cfg, c, sources[c])}.json" for c in cells}
    made_of, stale = _source_ids(cfg, run_dir, source, set(excluded.values()))
    draws = _draws(cfg, cells, target, test, {c: made_of[excluded[c]] for c in cells})
    rows = stored_rows({c: files[c] for c in cells if excluded[c] not in stale}, draws)
    todo = [c for c in cells if c not in rows]
    for left_out in sorted({excluded[c] for c in todo}):
        train_source(cfg, run_dir, progress, left_out, again=left_out in stale)
    workers = cfg.workers or os.cpu_count() or 1
    bar = progress_bar(total=len(cells), initial=len(cells) - len(todo), desc=cfg.name, unit="cell",
                       disable=not progress)
    # The planner keeps predictions inside the states these models were trained on.
    workspace = _workspace(cfg, source.data, target.data, sources[todo[0]]).to_dict() if todo else {}
    data_id = _data_id(target.data, None if test is None else test.data)
    tasks = [(cfg, c, run_dir, sources[c], workspace, {"data": data_id, "source_data": draws[c]["source_data"]})
             for c in todo]

    def name(task: tuple[Any, ...]) -> str:
        return f"{task[1].method} at amount {task[1].amount:g}, seed {task[1].seed}"

    def keep(task: tuple[Any, ...], row: dict[str, Any]) -> None:
        rows[task[1]] = row
        write_atomic(files[task[1]], json.dumps(row, indent=1))
        (run_dir / "failed" / files[task[1]].name).unlink(missing_ok=True)  # an earlier run's failure, redone now
        bar.update()
        warn_if_diverged(name(task), row)

    def failed(task: tuple[Any, ...], err: BaseException) -> None:
        (run_dir / "failed").mkdir(exist_ok=True)
        write_atomic(run_dir / "failed" / files[task[1]].name, json.dumps(failure_record(task[1], err), indent=1))

    try:
        run_cells(_run_cell, tasks, keep, workers, scheduler, bar, name, key=lambda task: files[task[1]].stem,
                  on_fail=failed)
    finally:
        bar.close()
    ordered = [rows[c] for c in cells] + baseline_rows(cfg, target.data, None if test is None else test.data, rows)
    results: dict[str, Any] = {"config": config_dict(cfg), "rows": ordered, "data_quality": quality}
    if cfg.source.exclude_test_sequences:
        results["excluded_source_episodes"] = {f"{c.method}-{c.amount}-{c.seed}": list(excluded[c]) for c in cells}
    write_results(run_dir, results)
    return ordered
