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
- ``gaussian``: every step normal with mean 0 and std ``std``, clipped to
  the box: with std 1 about a third of the steps sit on a bound, the bang-bang
  moves a cross-entropy search starts from (the textbook CEM's initial draw).
  With ``beta`` > 0 the steps are not independent but coloured noise
  (:func:`colored_noise`), as in iCEM (Pinneri et al., 2020).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from t42_transfer.conventions import ACTION_DIM, ACTION_LIMIT, RANDOM_POLICY_LIMIT, REAL_HAND_ACTIONS

SAMPLERS = ("uniform", "discrete", "piecewise", "gaussian")
DISCRETE_ACTIONS = torch.tensor(REAL_HAND_ACTIONS) / ACTION_LIMIT
"""The real hand's moves scaled into ``[-1, 1]``, ``[8, 2]``."""
SAMPLE_BLOCK = 4096
"""Sequences drawn per block: bounds the sampler's temporaries at any K; fixed, so the samples
depend only on the generator, not on how the planner chunks its rollouts."""


def stream_generator(seed: int, stream: int) -> torch.Generator:
    """A torch generator of its own for one use of a plan's ``seed`` (``stream`` tells the uses apart), so that
    drawing for that use leaves the plan's other draws as they were.  SeedSequence takes no negative numbers;
    torch's seeds may be."""
    entropy = np.random.SeedSequence([int(seed) % (1 << 64), stream]).generate_state(1)[0]
    return torch.Generator().manual_seed(int(entropy))


def colored_noise(count: int, horizon: int, beta: float, generator: torch.Generator) -> Tensor:
    """``[count, horizon, 2]`` stationary Gaussian noise, unit variance per step, whose power spectrum along time
    falls as ``1 / f**beta``: 0 is white (i.i.d. steps; ``randn`` itself), 1 pink, 2 brown.  A coloured sequence
    wanders slowly, like an action held and changed gradually, where white noise flips sign every other step.

    White noise filtered in the frequency domain (circularly), the filter scaled so each step's variance is
    exactly 1; the zero frequency gets the lowest nonzero frequency's gain, so the mean stays finite."""
    if beta == 0 or horizon < 2 or count == 0:  # (the FFT takes no empty batch)
        return torch.randn(count, horizon, ACTION_DIM, generator=generator)
    white = torch.randn(count, ACTION_DIM, horizon, generator=generator)
    freqs = torch.fft.rfftfreq(horizon, dtype=torch.float64)
    freqs[0] = freqs[1]
    gain = freqs ** (-beta / 2)
    # Parseval: a step's variance is the mean of |gain|^2 over the full spectrum (the rfft's inner bins twice).
    weights = torch.full_like(gain, 2.0)
    weights[0] = 1.0
    if horizon % 2 == 0:
        weights[-1] = 1.0
    gain = gain / torch.sqrt((weights * gain**2).sum() / horizon)
    colored = torch.fft.irfft(torch.fft.rfft(white.double(), dim=-1) * gain, n=horizon, dim=-1)
    return colored.float().transpose(1, 2).contiguous()


def sample_actions(
    sampler: str, count: int, horizon: int, generator: torch.Generator, hold_steps: tuple[int, int] = (5, 40),
    std: float = 1.0, beta: float = 0.0,
) -> Tensor:
    """``count`` sequences of ``horizon`` actions, float32 ``[count, horizon, 2]``; ``beta``: the gaussian
    sampler's colour (:func:`colored_noise`; 0: i.i.d. steps)."""
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
    out = torch.empty(count, horizon, ACTION_DIM)
    for start in range(0, count, SAMPLE_BLOCK):
        block = out[start : start + SAMPLE_BLOCK]
        if sampler == "uniform":
            block.uniform_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT, generator=generator)
        elif sampler == "gaussian" and beta == 0:
            block.normal_(0.0, std, generator=generator).clamp_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT)
        elif sampler == "gaussian":
            noise = colored_noise(len(block), horizon, beta, generator)
            block.copy_(noise.mul_(std).clamp_(-RANDOM_POLICY_LIMIT, RANDOM_POLICY_LIMIT))
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
