"""Open-loop accuracy of dynamics models, and the data quantities of the paper's Lyapunov bound.

Definitions used everywhere (states are ``(x mm, y mm, load1, load2)``; a rollout
of ``T`` steps has ``T + 1`` states and step 0 is the true start state, so its
error is zero by construction):

* **x,y error** at step ``k``: Euclidean distance (mm) between the predicted and
  the true object position.
* **divergence time** (the paper's ``t(x, eps)``): the number of steps predicted
  before the x,y error first exceeds ``eps``; that is ``(first k in 1..T with
  error > eps) - 1``, or ``T`` when it never does (such a rollout is censored at
  its length; :func:`evaluate_model` counts them).  A non-finite error counts as
  exceeding, so a model that blows up to NaN diverges.
* **position MSE**: mean over steps ``1..T`` of the squared x,y distance
  ``dx^2 + dy^2`` (mm^2), so its square root is an RMS distance comparable to ``eps``.

Those are the paper's definitions.  The authors' figure scripts counted and
averaged differently (:data:`METRIC_DEFINITIONS`): 10 mm, the first crossing
step itself (one more; ``T + 1`` when censored), and the MSE averaged over x and y
(half of ``dx^2 + dy^2``).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from t42_transfer.conventions import ACTION_DIM, STATE_DIM
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.models.dynamics import LatentDynamics

ArrayLike = np.ndarray | Tensor

DEFAULT_EPSILON_MM = 4.0
"""The paper's divergence threshold."""


@dataclass(frozen=True)
class MetricDefinition:
    """How divergence time and position MSE are counted under one definition."""

    epsilon_mm: float
    """Divergence threshold on the Euclidean x,y error."""
    count_crossing_step: bool
    """True: the first step past the threshold counts (the authors' count, one more than the paper's)."""
    mse_per_coordinate: bool
    """True: the MSE averages over x and y, ``(dx^2 + dy^2) / 2`` (the authors'); False: ``dx^2 + dy^2``."""


METRIC_DEFINITIONS = {
    # Paper: the caption of its divergence figure (4 mm) and t(x, eps) = max n with d < eps, read as its
    # prose says ("the number of time-steps before ... differs by more than a given threshold").
    "paper": MetricDefinition(DEFAULT_EPSILON_MM, count_crossing_step=False, mse_per_coordinate=False),
    # Authors: lc_bounds.py / learning_curve.py (threshold 10, duration = index of the first crossing in a
    # state list that starts with x0) and mse_bounds.py (torch MSELoss over x and y).
    "authors": MetricDefinition(10.0, count_crossing_step=True, mse_per_coordinate=True),
}


def _as_numpy(value: ArrayLike) -> np.ndarray:
    """A float64 copy (writable, unlike Trajectory arrays, so torch can wrap it without warnings)."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    return np.array(value, dtype=np.float64)


def xy_error(predicted: ArrayLike, true: ArrayLike) -> np.ndarray:
    """Per-step x,y distance (mm), ``[B, T + 1]``, of rollouts ``[B, T + 1, 4]`` (or one ``[T + 1, 4]``)."""
    pred, ref = _as_numpy(predicted), _as_numpy(true)
    if pred.shape != ref.shape:
        raise ValueError(f"predicted {pred.shape} and true {ref.shape} differ in shape")
    if pred.ndim == 2:
        pred, ref = pred[None], ref[None]
    if pred.ndim != 3 or pred.shape[2] != STATE_DIM or pred.shape[1] < 2:
        raise ValueError(f"rollouts must be [B, T + 1, {STATE_DIM}] with T >= 1, got {pred.shape}")
    return np.linalg.norm(pred[..., :2] - ref[..., :2], axis=-1)


def _steps(lengths: ArrayLike | Sequence[int] | None, batch: int, horizon: int) -> np.ndarray:
    """Valid steps per rollout: all ``horizon`` steps, or ``lengths`` (1..horizon) for padded batches."""
    if lengths is None:
        return np.full(batch, horizon, dtype=np.int64)
    steps = np.asarray(lengths.detach().cpu() if isinstance(lengths, Tensor) else lengths, dtype=np.int64)
    if steps.shape != (batch,) or steps.min(initial=1) < 1 or steps.max(initial=1) > horizon:
        raise ValueError(f"lengths must be {batch} integers in 1..{horizon}, got {steps}")
    return steps


def divergence_time(
    predicted: ArrayLike,
    true: ArrayLike,
    epsilon_mm: float = DEFAULT_EPSILON_MM,
    lengths: ArrayLike | Sequence[int] | None = None,
    count_crossing_step: bool = False,
) -> np.ndarray:
    """Steps before the x,y error first exceeds ``epsilon_mm`` (int64 ``[B]``; see the module docstring).

    ``lengths`` marks padded batches: rollout ``b`` only has steps ``1..lengths[b]``.
    ``count_crossing_step`` counts the crossing step too (the authors' count: one more, censored ``T + 1``).
    """
    err = xy_error(predicted, true)
    steps = _steps(lengths, err.shape[0], err.shape[1] - 1)
    k = np.arange(err.shape[1])
    exceeded = ~(err <= epsilon_mm) & (k >= 1) & (k <= steps[:, None])
    return np.where(exceeded.any(axis=1), exceeded.argmax(axis=1), steps + 1) - (0 if count_crossing_step else 1)


def position_mse_per_rollout(
    predicted: ArrayLike, true: ArrayLike, lengths: ArrayLike | Sequence[int] | None = None,
    per_coordinate: bool = False,
) -> np.ndarray:
    """Mean squared x,y distance over steps ``1..T`` (mm^2) of each rollout, ``[B]``; halved ``per_coordinate``."""
    err = xy_error(predicted, true)
    steps = _steps(lengths, err.shape[0], err.shape[1] - 1)
    k = np.arange(err.shape[1])
    valid = (k >= 1) & (k <= steps[:, None])
    return np.where(valid, err**2, 0.0).sum(axis=1) / steps / (2.0 if per_coordinate else 1.0)


def position_mse(
    predicted: ArrayLike, true: ArrayLike, lengths: ArrayLike | Sequence[int] | None = None,
    per_coordinate: bool = False,
) -> float:
    """Position MSE (mm^2) averaged over rollouts, each weighted equally."""
    return float(position_mse_per_rollout(predicted, true, lengths, per_coordinate).mean())


def model_device(model: LatentDynamics) -> torch.device:
    """Where the model's weights live (CPU for a model without any), so inputs can follow them."""
    first = next(itertools.chain(model.parameters(), model.buffers()), None)
    return first.device if first is not None else torch.device("cpu")


class _Windows(NamedTuple):
    """Padded open-loop test windows: ``actions``/``true`` are zero past each window's ``steps``."""

    x0: np.ndarray
    actions: np.ndarray
    true: np.ndarray
    steps: np.ndarray
    episode: np.ndarray
    offset: np.ndarray


def _windows(episodes: TrajectorySet, start_offsets: Sequence[int], horizon: int | None) -> _Windows:
    if horizon is not None and horizon < 1:
        raise ValueError(f"horizon must be at least 1, got {horizon}")
    if any(int(o) < 0 for o in start_offsets):
        raise ValueError(f"start offsets must be non-negative, got {tuple(start_offsets)}")
    picked = [
        (i, int(o), min(len(ep) - int(o), horizon or len(ep)))
        for i, ep in enumerate(episodes)
        for o in start_offsets
        if int(o) < len(ep)
    ]
    if not picked:
        raise ValueError("no episode is longer than any start offset: nothing to evaluate")
    longest = max(n for _, _, n in picked)
    actions = np.zeros((len(picked), longest, ACTION_DIM), np.float32)
    true = np.zeros((len(picked), longest + 1, STATE_DIM), np.float32)
    for row, (i, o, n) in enumerate(picked):
        actions[row, :n] = episodes[i].actions[o : o + n]
        true[row, : n + 1] = episodes[i].states[o : o + n + 1]
    episode, offset, steps = (np.array(col, dtype=np.int64) for col in zip(*picked, strict=True))
    return _Windows(true[:, 0].copy(), actions, true, steps, episode, offset)


def evaluate_model(
    model: LatentDynamics,
    episodes: TrajectorySet,
    epsilon_mm: float | None = None,
    start_offsets: Sequence[int] = (0,),
    horizon: int | None = None,
    definition: str = "paper",
) -> dict:
    """Roll ``model`` out open loop over test episodes and score it against the true states.

    One rollout per episode and start offset (offsets at or past an episode's end
    are skipped), starting from the true state there and following the recorded
    actions for the rest of the episode, or ``horizon`` steps at most.  All
    rollouts run as one padded float32 batch; padding is masked out of the scores.

    Returns summary floats ``divergence_mean``, ``divergence_median``,
    ``position_mse_mean`` (rollouts weighted equally), counts ``num_rollouts``,
    ``num_episodes``, ``never_diverged`` (rollouts censored at their length),
    ``epsilon_mm``, ``definition``, and per-rollout arrays ``divergence_steps``, ``position_mse``,
    ``steps``, ``episode`` (index into ``episodes``) and ``offset``.

    ``definition`` (``paper`` or ``authors``, :data:`METRIC_DEFINITIONS`) sets how
    divergence is counted and the MSE averaged, and the threshold unless
    ``epsilon_mm`` is given.
    """
    if definition not in METRIC_DEFINITIONS:
        raise ValueError(f"definition must be one of {tuple(METRIC_DEFINITIONS)}, got {definition!r}")
    how = METRIC_DEFINITIONS[definition]
    epsilon_mm = how.epsilon_mm if epsilon_mm is None else epsilon_mm
    win = _windows(episodes, start_offsets, horizon)
    device = model_device(model)
    predicted = model.rollout(
        torch.as_tensor(win.x0, dtype=torch.float32, device=device),
        torch.as_tensor(win.actions, dtype=torch.float32, device=device),
    )
    divergence = divergence_time(predicted, win.true, epsilon_mm, win.steps, how.count_crossing_step)
    mse = position_mse_per_rollout(predicted, win.true, win.steps, how.mse_per_coordinate)
    return {
        "epsilon_mm": float(epsilon_mm),
        "definition": definition,
        "num_rollouts": len(win.steps),
        "num_episodes": len(np.unique(win.episode)),
        "never_diverged": int((divergence == win.steps + int(how.count_crossing_step)).sum()),
        "divergence_mean": float(divergence.mean()),
        "divergence_median": float(np.median(divergence)),
        "position_mse_mean": float(mse.mean()),
        "divergence_steps": divergence,
        "position_mse": mse,
        "steps": win.steps,
        "episode": win.episode,
        "offset": win.offset,
    }


def covering_radius(data_points: ArrayLike, query_points: ArrayLike, max_pairs: int = 1 << 22) -> float:
    """The paper's ``r``: largest distance from a query point to its nearest data point (Euclidean).

    Distances are computed in float64 in blocks of at most ``max_pairs`` pairs
    (32 MiB at the default), so memory stays bounded for any set sizes.  The
    metric is the caller's: scale the columns first (e.g. by :func:`model_state_scale`)
    to measure ``r`` in the same units as :func:`max_training_error`.
    """
    data = torch.as_tensor(_as_numpy(data_points))
    query = torch.as_tensor(_as_numpy(query_points))
    if data.ndim != 2 or query.ndim != 2 or data.shape[1] != query.shape[1] or not len(data) or not len(query):
        shapes = f"{tuple(data.shape)}, {tuple(query.shape)}"
        raise ValueError(f"need non-empty [N, d] data and [M, d] queries, got {shapes}")
    if not (torch.isfinite(data).all() and torch.isfinite(query).all()):
        raise ValueError("covering_radius needs finite points")
    query_block = max(1, min(len(query), 1024))
    data_block = max(1, max_pairs // query_block)
    radius = 0.0
    for q in query.split(query_block):
        nearest = torch.full((len(q),), torch.inf, dtype=torch.float64)
        for d in data.split(data_block):
            nearest = torch.minimum(nearest, torch.cdist(q, d).amin(dim=1))
        radius = max(radius, float(nearest.max()))
    return radius


def model_state_scale(model: LatentDynamics) -> np.ndarray:
    """Per-component state scale: the model's input normalisation ``state_std``, the bound's unit."""
    scale = getattr(model, "state_std", None)
    if scale is None:
        raise ValueError(f"{type(model).__name__} has no state_std: pass state_scale explicitly")
    return _as_numpy(scale)


class TrainingError(NamedTuple):
    """The paper's ``epsilon`` in two metrics (maxima taken separately, possibly at different transitions)."""

    normalised: float
    """Max Euclidean 4-D next-state error with each component divided by the state scale."""
    xy_mm: float
    """Max Euclidean x,y next-state error in millimetres."""


def max_training_error(
    model: LatentDynamics,
    transitions: tuple[ArrayLike, ArrayLike, ArrayLike],
    state_scale: ArrayLike | None = None,
    chunk: int = 65536,
    starts: ArrayLike | None = None,
    dtype: torch.dtype = torch.float32,
) -> TrainingError:
    """The paper's ``epsilon``: the largest one-step prediction error on ``(x, a, x_next)`` data.

    A one-step prediction is ``observe(latent_step(episode_latent(x, start), a))``,
    dropout off; ``starts`` are the transitions' episodes' first states
    (:meth:`TrajectorySet.start_states`), which a start-state model reads as its
    rollouts do (default: each ``x`` its own start).  The normalised metric divides
    each state component by ``state_scale`` (default: the model's ``state_std``) so
    that millimetres and load units weigh alike.  ``dtype`` is what the inputs are fed as: the model's own
    (the bound's float64 copies, :func:`t42_transfer.evaluation.lyapunov_bound.training_error`, need float64).
    """
    x, a, x_next = (_as_numpy(v) for v in transitions)
    if not (len(x) == len(a) == len(x_next)) or not len(x):
        raise ValueError(f"need equally many (x, a, x_next), got {len(x)}, {len(a)}, {len(x_next)}")
    first = x if starts is None else _as_numpy(starts)
    if first.shape != x.shape:
        raise ValueError(f"need a start state per transition, got {first.shape} for {x.shape}")
    scale = model_state_scale(model) if state_scale is None else _as_numpy(state_scale)
    device = model_device(model)
    worst_norm, worst_xy = 0.0, 0.0
    was_training = model.training
    model.eval()
    try:
        for start in range(0, len(x), chunk):
            rows = slice(start, start + chunk)
            tensors = (torch.as_tensor(v[rows], dtype=dtype, device=device) for v in (x, first, a))
            with torch.no_grad():
                states, firsts, actions = tensors
                pred = model.observe(model.latent_step(model.episode_latent(states, firsts), actions))
            diff = _as_numpy(pred) - x_next[rows]
            # np.maximum, not max(): a NaN prediction must show up in the result, not vanish.
            worst_norm = np.maximum(worst_norm, np.linalg.norm(diff / scale, axis=1).max())
            worst_xy = np.maximum(worst_xy, np.linalg.norm(diff[:, :2], axis=1).max())
    finally:
        model.train(was_training)
    return TrainingError(float(worst_norm), float(worst_xy))
