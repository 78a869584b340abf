"""Score saved models on a data set's paths: time before divergence at 4 and 10 mm and position MSE, beside
hold-still, per path and overall (``t42 evaluate``; no ROS).

Each path is rolled out open loop from its first true state with its recorded actions
(:mod:`t42_transfer.evaluation.metrics` counts divergence and MSE, by the ``paper``
definition unless ``authors`` is asked for).  A model is a project model file or one of the
paper authors' files, imported on the fly (:func:`~t42_transfer.evaluation.experiment.load_model_file`).

Dropout: with ``dropout_draws`` K, each path is rolled out K times with dropout on (fresh masks at every step
of every draw) and each number is the mean over the draws.  The authors saved their models in training mode
and their scripts never call ``.eval()``, so the paper's published numbers were taken with dropout on, one draw
per model and path; the K-draw mean estimates what those single draws scatter around.  Without it, dropout is
off (the deterministic model, what the README's reference figures were measured with).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.metrics import (
    METRIC_DEFINITIONS,
    _windows,
    divergence_time,
    model_device,
    position_mse_per_rollout,
)
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.dynamics import LatentDynamics

THRESHOLDS_MM = (4.0, 10.0)
"""The paper's figure (4 mm) and the authors' figure scripts (10 mm)."""
MAX_DROPOUT_DRAWS = 1000
MAX_BATCH_STATES = 4_000_000
"""Predicted states held at once (64 MB of float32): draws are rolled out in chunks under it."""


@dataclass(frozen=True)
class Scores:
    """One model's numbers on the paths: overall means and one entry per path."""

    path: str | None
    """The model file as given (None for hold-still)."""
    divergence_mean_4mm: float
    divergence_mean_10mm: float
    position_mse_mean: float
    per_path: list[dict[str, Any]]
    """``{"episode", "steps", "divergence_4mm", "divergence_10mm", "position_mse"}`` per path, in order."""

    def as_dict(self) -> dict[str, Any]:
        return {"path": self.path, "divergence_mean_4mm": self.divergence_mean_4mm,
                "divergence_mean_10mm": self.divergence_mean_10mm, "position_mse_mean": self.position_mse_mean,
                "per_path": self.per_path}


@dataclass(frozen=True)
class Evaluation:
    """What :func:`evaluate_models` found."""

    models: list[Scores]
    """In the mode asked for: dropout on (mean over the draws) with ``dropout_draws``, else off."""
    hold_still: Scores
    dropout_off: list[Scores] | None
    """With ``dropout_draws``, the same models with dropout off too (None otherwise)."""
    dropout_draws: int | None
    episodes: list[int]
    steps: int
    """Steps over all paths."""

    def as_json(self) -> dict[str, Any]:
        """``{"models": [...], "hold_still": {...}}``, each with the keys of :meth:`Scores.as_dict`; with
        ``dropout_draws``, ``models`` holds the dropout-on numbers and ``dropout_off`` (same keys) and
        ``dropout_draws`` are added, so both modes are kept."""
        out: dict[str, Any] = {"models": [m.as_dict() for m in self.models], "hold_still": self.hold_still.as_dict()}
        if self.dropout_off is not None:
            out["dropout_draws"] = self.dropout_draws
            out["dropout_off"] = [m.as_dict() for m in self.dropout_off]
        return out


@contextlib.contextmanager
def _dropout_on(model: LatentDynamics, seed: int) -> Iterator[None]:
    """Dropout on inside, the model's mode and the global torch generator restored after."""
    was_training = model.training
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model.train()
        try:
            yield
        finally:
            model.train(was_training)


def _rollouts(model: LatentDynamics, x0: np.ndarray, actions: np.ndarray, dropout: bool) -> np.ndarray:
    device = model_device(model)
    x0_t = torch.as_tensor(x0, dtype=torch.float32, device=device)
    actions_t = torch.as_tensor(actions, dtype=torch.float32, device=device)
    if not dropout:
        return model.rollout(x0_t, actions_t).cpu().numpy()
    with torch.no_grad():
        return model.rollout_with_grad(x0_t, actions_t).cpu().numpy()


def score_model(
    model: LatentDynamics,
    episodes: TrajectorySet,
    path: str | None = None,
    *,
    dropout_draws: int | None = None,
    seed: int = 0,
    definition: str = "paper",
    indices: Sequence[int] | None = None,
    on_chunk: Callable[[], None] | None = None,
) -> Scores:
    """``model``'s scores on every episode of ``episodes`` (one open-loop rollout each, from its first state).

    ``dropout_draws``: K rollouts per path with dropout on, averaged (seeded by ``seed``); None: dropout off.
    ``indices``: the episodes' numbers to report (default 0, 1, ...).  ``on_chunk``: called after each batch.
    """
    if definition not in METRIC_DEFINITIONS:
        raise ValueError(f"definition must be one of {tuple(METRIC_DEFINITIONS)}, got {definition!r}")
    if dropout_draws is not None and not 1 <= dropout_draws <= MAX_DROPOUT_DRAWS:
        raise ValueError(f"dropout draws must be 1 to {MAX_DROPOUT_DRAWS}, got {dropout_draws}")
    how = METRIC_DEFINITIONS[definition]
    win = _windows(episodes, (0,), None)
    paths, draws = len(win.steps), dropout_draws or 1
    per_draw = {eps: np.zeros((draws, paths)) for eps in THRESHOLDS_MM}
    mse = np.zeros((draws, paths))
    chunk = max(1, MAX_BATCH_STATES // (paths * win.true.shape[1]))
    with _dropout_on(model, seed) if dropout_draws else contextlib.nullcontext():
        for first in range(0, draws, chunk):
            n = min(chunk, draws - first)
            rows = slice(first, first + n)
            predicted = _rollouts(model, np.tile(win.x0, (n, 1)), np.tile(win.actions, (n, 1, 1)),
                                  dropout_draws is not None)
            true, steps = np.tile(win.true, (n, 1, 1)), np.tile(win.steps, n)
            for eps in THRESHOLDS_MM:
                per_draw[eps][rows] = divergence_time(predicted, true, eps, steps,
                                                      how.count_crossing_step).reshape(n, paths)
            mse[rows] = position_mse_per_rollout(predicted, true, steps, how.mse_per_coordinate).reshape(n, paths)
            if on_chunk is not None:
                on_chunk()
    numbers = list(range(paths)) if indices is None else [int(i) for i in indices]
    if len(numbers) != paths:
        raise ValueError(f"{len(numbers)} path numbers for {paths} paths")
    div4, div10, mse_path = per_draw[4.0].mean(0), per_draw[10.0].mean(0), mse.mean(0)
    per_path = [{"episode": numbers[p], "steps": int(win.steps[p]), "divergence_4mm": float(div4[p]),
                 "divergence_10mm": float(div10[p]), "position_mse": float(mse_path[p])} for p in range(paths)]
    return Scores(path, float(div4.mean()), float(div10.mean()), float(mse_path.mean()), per_path)


def chunks_per_model(episodes: TrajectorySet, dropout_draws: int | None) -> int:
    """How many batches :func:`score_model` rolls out (for a progress bar)."""
    longest = max(len(t) for t in episodes) + 1
    chunk = max(1, MAX_BATCH_STATES // (len(episodes) * longest))
    return -(-(dropout_draws or 1) // chunk)


def evaluate_models(
    models: Sequence[tuple[str, LatentDynamics]],
    episodes: TrajectorySet,
    *,
    indices: Sequence[int] | None = None,
    dropout_draws: int | None = None,
    seed: int = 0,
    definition: str = "paper",
    progress: bool = False,
) -> Evaluation:
    """Score each ``(name, model)`` and hold-still on ``episodes``; with ``dropout_draws``, in both modes.

    ``indices``: the episodes' numbers in their data set (reported per path).  ``progress``: a tqdm bar.
    """
    from t42_transfer.progress import progress_bar

    if not len(episodes):
        raise ValueError("no paths to evaluate")
    modes = [dropout_draws] if dropout_draws is None else [dropout_draws, None]
    total = sum(chunks_per_model(episodes, mode) for mode in modes) * len(models) + 1
    options = {"seed": seed, "definition": definition, "indices": indices}
    with progress_bar(total=total, desc="evaluate", unit="batch", disable=not progress, leave=False) as bar:
        scored = {mode: [score_model(model, episodes, name, dropout_draws=mode, on_chunk=bar.update, **options)
                         for name, model in models] for mode in modes}
        hold = score_model(HoldStill(), episodes, None, on_chunk=bar.update, **options)
    return Evaluation(scored[dropout_draws], hold, None if dropout_draws is None else scored[None], dropout_draws,
                      list(range(len(episodes))) if indices is None else [int(i) for i in indices],
                      episodes.num_transitions)


def table(evaluation: Evaluation, names: Sequence[str] | None = None) -> str:
    """The evaluation as a plain-text table: each model's overall numbers, then one line per path."""
    draws = evaluation.dropout_draws
    on = f"dropout on ({draws} draws)" if draws else "dropout off"
    rows: list[tuple[str, str, Scores]] = []
    for i, scores in enumerate(evaluation.models):
        name = names[i] if names else str(scores.path)
        if evaluation.dropout_off is not None:
            rows.append((name, "dropout off", evaluation.dropout_off[i]))
        rows.append((name, on, scores))
    rows.append(("hold still", "", evaluation.hold_still))
    width = max(len(name) for name, _, _ in rows) + 2
    lines = [f"{'model':<{width}}{'mode':<24}{'div 4mm':>10}{'div 10mm':>10}{'MSE mm^2':>12}"]
    for name, mode, s in rows:
        lines.append(f"{name:<{width}}{mode:<24}{s.divergence_mean_4mm:>10.2f}{s.divergence_mean_10mm:>10.2f}"
                     f"{s.position_mse_mean:>12.3f}")
        for p in s.per_path:
            label = f"  path {p['episode']} ({p['steps']} steps)"
            lines.append(f"{label:<{width + 24}}{p['divergence_4mm']:>10.2f}{p['divergence_10mm']:>10.2f}"
                         f"{p['position_mse']:>12.3f}")
    return "\n".join(lines)
