"""The paper's upper bound on a learned model's Lyapunov exponent, term by term, beside the measured exponent.

The theorem: for a model ``f_hat`` of the true map ``f`` on the hand state (``N`` dimensions),

    lambda_f_hat <= lambda_f + lim 1/n sum_i log(1 + b N ||J_i^-1||),   b = 4 sqrt(6 r^2 c^2 + epsilon c) + 10 r c,

with ``r`` the covering radius of the training states over the region, ``epsilon`` the largest one-step training
error, ``c`` a Lipschitz constant of both maps' Jacobians and ``J_i`` the true map's Jacobian along the orbit.

What stands in for what, since the true map is not known (say so wherever a number is quoted):
- ``f`` is a *reference model* trained on dense data of the target hand (e.g. the authors' own hand-A model);
- the region is the test episodes' states, and the orbit is ``f_hat``'s own open-loop orbit along a test episode's
  actions: the theorem's ``J_i`` are ``f``'s Jacobians at ``f_hat``'s orbit points, whose product gives
  ``lambda_f`` here (Benettin's method, the same burn-in as the measured exponent);
- ``c`` is the largest Jacobian change per distance over sampled pairs of test states, for ``f_hat`` and for ``f``:
  a lower estimate of the supremum the theorem needs, so the ``b`` and the bound computed here are lower
  estimates too. A measured exponent above them would not disprove the theorem; one far below shows its slack.

Lengths are measured in normalised coordinates ``x / scales`` (one fixed ``scales`` for every model compared).
The maps are ``x -> x'`` on the hand state for one step at a recorded action, with the episode's start state (the
grasp input some networks read) held as the parameter it is, so only models whose dynamic latent is the hand state
itself qualify: a cumulative residual carries a hidden sum (the paper bounds it by another theorem).
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.func import jacrev, vmap

from t42_transfer.conventions import STATE_DIM
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.lyapunov import _orthonormalise, dynamic_coordinates, model_lyapunov_spectrum
from t42_transfer.evaluation.metrics import covering_radius, max_training_error
from t42_transfer.models.dynamics import LatentDynamics

PAIR_GAPS = (1, 3, 10, 30)
"""Step gaps of the state pairs within an episode that estimate ``c`` (near pairs matter most), beside random pairs."""


@dataclass(frozen=True)
class BoundTerms:
    """The theorem's terms for one model, in normalised coordinates, and the exponent measured along the same orbits."""

    r: float
    """Covering radius: the largest distance from a test state to its nearest training state."""
    epsilon: float
    """Largest one-step prediction error on the training transitions."""
    c_model: float
    """Largest Jacobian change per unit distance of ``f_hat`` over the sampled pairs."""
    c_reference: float
    """The same for the reference ``f``."""
    b: float
    """``4 sqrt(6 r^2 c^2 + epsilon c) + 10 r c`` with ``c = max(c_model, c_reference)``: the Jacobian gap bound."""
    inverse_norm: float
    """Mean over the orbit steps of ``||J_i^-1||`` (spectral norm, the reference's Jacobian)."""
    log_term: float
    """Mean over orbits of the mean over steps of ``log(1 + b N ||J_i^-1||)``."""
    reference_exponent: float
    """``lambda_f``: the largest exponent of the reference's Jacobians along the model's orbits (mean over orbits);
    both exponents here are the largest of the whole spectrum, so no starting direction can hide one."""
    bound: float
    """``reference_exponent + log_term``."""
    measured: float
    """``lambda_f_hat``: the model's own maximal exponent along the same orbits (mean over orbits)."""
    orbits: int
    steps: int
    burn_in: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def gap_bound(r: float, epsilon: float, c: float) -> float:
    """The theorem's ``b``: how far the model's Jacobian may stray from the true one, from ``r``, ``epsilon``, ``c``."""
    if min(r, epsilon, c) < 0 or not all(map(math.isfinite, (r, epsilon, c))):
        raise ValueError(f"r, epsilon and c must be finite and non-negative, got {r}, {epsilon}, {c}")
    return 4.0 * math.sqrt(6.0 * r * r * c * c + epsilon * c) + 10.0 * r * c


def _analysed(model: LatentDynamics) -> LatentDynamics:
    """A float64 copy in eval mode (dropout off) whose dynamic latent is the hand state; ValueError otherwise."""
    if dynamic_coordinates(model) != tuple(range(STATE_DIM)):
        raise ValueError(f"{type(model).__name__} carries hidden state beyond the hand state in its latent; "
                         "the bound's maps take hand states to hand states")
    return copy.deepcopy(model).to(torch.float64).eval().requires_grad_(False)


def state_jacobians(model: LatentDynamics, states: Tensor, starts: Tensor, actions: Tensor,
                    scales: Tensor) -> Tensor:
    """``[B, N, N]``: the one-step map's Jacobian ``d x' / d x`` at each row, in coordinates ``x / scales``."""
    z = model.episode_latent(states, starts)

    def step(state: Tensor, rest: Tensor, action: Tensor) -> Tensor:
        latent = torch.cat([state, rest])[None]
        return model.latent_step(latent, action[None])[0, :STATE_DIM]

    with torch.no_grad():
        jac = vmap(jacrev(step))(z[:, :STATE_DIM], z[:, STATE_DIM:], actions)
    return jac * (scales[None, :] / scales[:, None])


def _episode_arrays(data: TrajectorySet) -> tuple[list[Tensor], list[Tensor]]:
    return ([torch.tensor(t.states, dtype=torch.float64) for t in data],
            [torch.tensor(t.actions, dtype=torch.float64) for t in data])


def jacobian_lipschitz(model: LatentDynamics, data: TrajectorySet, scales: np.ndarray, pairs: int = 2000,
                       seed: int = 0) -> float:
    """The largest ``||J(p) - J(q)|| / ||p - q||`` (normalised) over pairs of states of one episode at ``p``'s
    action: pairs ``PAIR_GAPS`` steps apart and random ones, ``pairs`` in all at most. A lower estimate of ``c``."""
    analysed, s = _analysed(model), torch.as_tensor(np.asarray(scales, np.float64))
    rng = np.random.default_rng(seed)
    states, actions = _episode_arrays(data)
    first, second, starts, acts = [], [], [], []
    per_episode = max(1, pairs // max(1, len(data)))
    for x, a in zip(states, actions, strict=True):
        n = len(a)
        candidates = [(i, i + g) for g in PAIR_GAPS for i in range(n - g)] or [(0, 0)]
        picks = rng.choice(len(candidates), size=min(per_episode // 2, len(candidates)), replace=False)
        chosen = [candidates[k] for k in picks]
        if n > 1:
            chosen += [tuple(rng.choice(n, size=2, replace=False)) for _ in range(per_episode - len(chosen))]
        for i, j in chosen:
            first.append(x[i])
            second.append(x[j])
            starts.append(x[0])
            acts.append(a[i])
    if not first:
        raise ValueError("no state pairs: the episodes are too short")
    p, q, x0, a = (torch.stack(v) for v in (first, second, starts, acts))
    distance = torch.linalg.vector_norm((p - q) / s, dim=1)
    keep = distance > 1e-9
    if not bool(keep.any()):
        raise ValueError("every sampled pair is one point twice")
    change = state_jacobians(analysed, p[keep], x0[keep], a[keep], s) - state_jacobians(analysed, q[keep], x0[keep],
                                                                                        a[keep], s)
    return float((torch.linalg.matrix_norm(change, ord=2) / distance[keep]).max())


def training_error(model: LatentDynamics, train: TrajectorySet, scales: np.ndarray) -> float:
    """The theorem's ``epsilon``: :func:`max_training_error`'s normalised metric, each transition predicted from
    its true state with its episode's start state held (the grasp input), run on the bound's float64 copy so that a
    model of its own paths scores zero to float64 precision."""
    error = max_training_error(_analysed(model), train.transitions(), np.asarray(scales, np.float64),
                               starts=train.start_states(), dtype=torch.float64)
    return error.normalised


def orbit_terms(model: LatentDynamics, reference: LatentDynamics, test: TrajectorySet, scales: np.ndarray,
                b: float, steps: int, burn_in: int) -> tuple[float, float, float]:
    """Along ``model``'s open-loop orbit of each test episode (``steps`` at most, the first ``burn_in`` not averaged):
    ``(mean ||J_i^-1||, mean log(1 + b N ||J_i^-1||), lambda_f)`` of the reference's Jacobians, means over orbits."""
    analysed, ref, s = _analysed(model), _analysed(reference), torch.as_tensor(np.asarray(scales, np.float64))
    norms, logs, exponents = [], [], []
    for x, a in zip(*_episode_arrays(test), strict=True):
        n = min(len(a), steps)
        if n <= burn_in:
            continue
        orbit = analysed.rollout(x[:1], a[None, :n])[0, :n]  # the points the steps leave from
        jac = state_jacobians(ref, orbit, x[:1].expand(n, -1), a[:n], s)
        inverse = 1.0 / torch.linalg.svdvals(jac)[:, -1]
        norms.append(float(inverse[burn_in:].mean()))
        logs.append(float(torch.log1p(b * STATE_DIM * inverse[burn_in:]).mean()))
        frame, total = torch.eye(STATE_DIM, dtype=torch.float64), torch.zeros(STATE_DIM, dtype=torch.float64)
        for t in range(n):  # the whole spectrum: its largest exponent does not hang on a starting direction
            frame, stretch = _orthonormalise(jac[t] @ frame)
            if t >= burn_in:
                total += stretch.log()
        exponents.append(float(total.max()) / (n - burn_in))
    if not norms:
        raise ValueError(f"no test episode is longer than the burn-in ({burn_in} steps)")
    return float(np.mean(norms)), float(np.mean(logs)), float(np.mean(exponents))


def bound_terms(model: LatentDynamics, reference: LatentDynamics, train: TrajectorySet, test: TrajectorySet,
                scales: np.ndarray, *, steps: int = 300, burn_in: int = 50, pairs: int = 2000) -> BoundTerms:
    """Every term of the theorem for ``model`` trained on ``train``, over ``test``'s region and orbits."""
    s = np.asarray(scales, np.float64)
    train_states = np.concatenate([t.states for t in train]) / s
    test_states = np.concatenate([t.states for t in test]) / s
    r = covering_radius(train_states, test_states)
    epsilon = training_error(model, train, s)
    c_model, c_reference = (jacobian_lipschitz(m, test, s, pairs) for m in (model, reference))
    b = gap_bound(r, epsilon, max(c_model, c_reference))
    inverse_norm, log_term, reference_exponent = orbit_terms(model, reference, test, s, b, steps, burn_in)
    measured, orbits = measured_exponent(model, test, s, steps=steps, burn_in=burn_in)
    return BoundTerms(r, epsilon, c_model, c_reference, b, inverse_norm, log_term, reference_exponent,
                      reference_exponent + log_term, measured, orbits, steps, burn_in)


def measured_exponent(model: LatentDynamics, test: TrajectorySet, scales: np.ndarray, *, steps: int = 300,
                      burn_in: int = 50) -> tuple[float, int]:
    """``(lambda_f_hat, orbits)``: the largest exponent of ``model``'s whole spectrum along its open-loop orbits of
    the test episodes longer than ``burn_in`` (mean over them); any model, hidden state included."""
    kept = TrajectorySet([t for t in test if min(len(t), steps) > burn_in], hand=test.hand)
    if not len(kept):
        raise ValueError(f"no test episode is longer than the burn-in ({burn_in} steps)")
    spectrum = model_lyapunov_spectrum(model, kept, steps=steps, burn_in=burn_in, scales=scales)
    return float(spectrum.max(dim=1).values.mean()), len(kept)
