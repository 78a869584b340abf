"""Action-sequence samplers for the Monte Carlo planner: ``[K, T, 2]`` in ``[-1, 1]``.

- ``uniform``: every step i.i.d. uniform in ``[-1, 1]^2``; dense near the start,
  but sums of independent steps rarely travel far.
- ``discrete``: every step one of the real hand's eight moves.  The real set
  ``{[1,1], [-1,-1], [-1,1], [1,-1], [+-1.5,0], [0,+-1.5]}`` reaches 1.5, beyond the
  planner's ``[-1, 1]``; it is scaled by ``1 / ACTION_LIMIT`` (not clipped), which
  keeps its directions and relative sizes: a planned move ``a`` is the real
  hand's move ``1.5 a``.
- ``piecewise``: uniform actions held for random durations (``hold_steps``
  inclusive); a held action drives the servos steadily, which reaches far goals.
- ``gaussian``: every step i.i.d. normal with mean 0 and std ``std``, clipped to
  the box: with std 1 about a third of the steps sit on a bound, the bang-bang
  moves a cross-entropy search starts from (the textbook CEM's initial draw).
"""

from __future__ import annotations

import torch
from torch import Tensor

from t42_transfer.conventions import ACTION_DIM, ACTION_LIMIT, RANDOM_POLICY_LIMIT, REAL_HAND_ACTIONS

SAMPLERS = ("uniform", "discrete", "piecewise", "gaussian")
DISCRETE_ACTIONS = torch.tensor(REAL_HAND_ACTIONS) / ACTION_LIMIT
"""The real hand's moves scaled into ``[-1, 1]``, ``[8, 2]``."""
SAMPLE_BLOCK = 4096
"""Sequences drawn per block: bounds the sampler's temporaries at any K; fixed, so the samples
depend only on the generator, not on how the planner chunks its rollouts."""


def sample_actions(
    sampler: str, count: int, horizon: int, generator: torch.Generator, hold_steps: tuple[int, int] = (5, 40),
    std: float = 1.0,
) -> Tensor:
    """``count`` sequences of ``horizon`` actions, float32 ``[count, horizon, 2]``."""
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
    out = torch.empty(count, horizon, ACTION_DIM)
    for start in range(0, count, SAMPLE_BLOCK):
        block = out[start : start + SAMPLE_BLOCK]
        if sampler == "uniform":
            block.uniform_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT, generator=generator)
        elif sampler == "gaussian":
            block.normal_(0.0, std, generator=generator).clamp_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT)
        elif sampler == "discrete":
            block.copy_(DISCRETE_ACTIONS[torch.randint(len(DISCRETE_ACTIONS), block.shape[:2], generator=generator)])
        else:
            block.copy_(_piecewise(len(block), horizon, generator, hold_steps))
    return out


def project(sampler: str, actions: Tensor) -> Tensor:
    """The nearest actions the sampler could have drawn: clipped to the box, or snapped to the discrete set."""
    if sampler == "discrete":
        nearest = torch.cdist(actions.reshape(-1, ACTION_DIM), DISCRETE_ACTIONS.to(actions.dtype)).argmin(-1)
        return DISCRETE_ACTIONS.to(actions.dtype)[nearest].reshape(actions.shape)
    return actions.clamp(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT)


def _piecewise(count: int, horizon: int, generator: torch.Generator, hold_steps: tuple[int, int]) -> Tensor:
    low, high = hold_steps
    if not 1 <= low <= high:
        raise ValueError(f"hold_steps must satisfy 1 <= low <= high, got {hold_steps}")
    # Enough segments to cover the horizon even if all are short; the segment
    # crossing the horizon is cut there, and later ones get length 0.
    segments = -(-horizon // low)
    durations = torch.randint(low, high + 1, (count, segments), generator=generator)
    values = torch.empty(count, segments, ACTION_DIM).uniform_(
        -RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT, generator=generator
    )
    ends = durations.cumsum(1).clamp_max_(horizon)
    lengths = torch.diff(ends, dim=1, prepend=torch.zeros(count, 1, dtype=ends.dtype))
    held = values.view(-1, ACTION_DIM).repeat_interleave(lengths.view(-1), dim=0, output_size=count * horizon)
    return held.view(count, horizon, ACTION_DIM)
