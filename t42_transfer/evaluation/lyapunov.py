"""Finite-time Lyapunov exponents of learned dynamics, by Benettin's method (float64).

The paper explains transfer failures by the models' Lyapunov exponents
``lambda = lim 1/n sum ln |f'(x_i)|``; for a multi-dimensional map the exponents
are the growth rates of the Jacobian products along an orbit.  Benettin's method
carries an orthonormal frame ``Q`` along the orbit: each step replaces it by the
QR factors of ``J_t Q`` and accumulates ``ln |diag R|``; the averages are the
exponents, largest first.  Everything is batched over orbits: Jacobians come
from ``vmap(jacrev)`` and the frames from one batched Householder QR per step.

A model is analysed through its latent map ``latent_step``, so hidden state
(e.g. the residual sum of a cumulative residual model) is part of the system, as
in the paper's theorem.  Coordinates the map carries unchanged (the grasp state a
network reads, :meth:`~t42_transfer.models.dynamics.LatentDynamics.held_latents`)
are parameters, not state: the Jacobian is block triangular with an identity block
there, which only adds exponents of exactly 0 to the full spectrum (a frame started
in the state block stays there, so the maximal exponent is the same either way).
They are held at their orbit's values and left out.  Exponents are per 0.1 s step,
natural log.

Two settings make a finite-time estimate mean something.  ``burn_in`` steps move
the orbit onto its attractor and turn the frame toward the growing directions
before anything is averaged.  ``scales`` measure lengths in normalised
coordinates ``z / scales`` (e.g. the model's stored state std): asymptotically the
exponents do not depend on a fixed change of coordinates, but over a finite
orbit in raw units (millimetres beside load units a hundred times larger) the
starting frame and the transient are dominated by the large coordinates.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor
from torch.func import jacrev, vmap

from t42_transfer.conventions import STATE_DIM
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.metrics import model_device
from t42_transfer.models.dynamics import LatentDynamics

StepFn = Callable[[Tensor, Tensor], Tensor]
"""A map ``step(z[B, d], a[B, m]) -> z'[B, d]`` that treats batch rows independently."""


def _orthonormalise(m: Tensor) -> tuple[Tensor, Tensor]:
    """Reduced QR of a batch ``m[B, d, k]``: ``(Q[B, d, k], |diag R|[B, k])``.

    geqrf + householder_product is the same Householder QR as ``torch.linalg.qr``;
    on small matrices it avoided a fixed multi-millisecond per-call overhead that
    ``linalg.qr`` showed with several CPU threads, which dominated the step loop.
    """
    reflectors, tau = torch.geqrf(m)
    return torch.linalg.householder_product(reflectors, tau), reflectors.diagonal(dim1=-2, dim2=-1).abs()


def lyapunov_spectrum(
    step: StepFn,
    z0: Tensor,
    actions: Tensor,
    k: int | None = None,
    *,
    burn_in: int = 0,
    lengths: Tensor | None = None,
    scales: Tensor | np.ndarray | None = None,
) -> Tensor:
    """The ``k`` largest finite-time Lyapunov exponents (all when ``None``) of each orbit, ``[B, k]`` float64.

    Orbit ``b`` starts at ``z0[b]`` and follows ``actions[b, t]``; an autonomous map
    simply ignores its action input.  The first ``burn_in`` steps move the orbit
    and align the frame but are not averaged.  ``lengths[b]`` (optional) ends orbit
    ``b`` early, for padded batches; the exponent averages over its own steps.
    ``scales[d]`` (optional, positive) analyses the map in coordinates ``z / scales``:
    each Jacobian becomes ``diag(1 / scales) J diag(scales)``.
    ``step`` is called with float64 tensors and must not mix batch rows.
    """
    z = z0.to(torch.float64)
    actions = actions.to(device=z.device, dtype=torch.float64)
    if z.ndim != 2 or actions.ndim != 3 or actions.shape[0] != z.shape[0]:
        raise ValueError(f"need z0[B, d] and actions[B, T, m], got {tuple(z.shape)}, {tuple(actions.shape)}")
    batch, dim = z.shape
    k = dim if k is None else k
    if not 1 <= k <= dim:
        raise ValueError(f"k must be in 1..{dim}, got {k}")
    steps = (
        torch.full((batch,), actions.shape[1], device=z.device)
        if lengths is None
        else torch.as_tensor(lengths, device=z.device).long()
    )
    if steps.shape != (batch,) or int(steps.max()) > actions.shape[1] or int(steps.min()) <= burn_in:
        raise ValueError(f"every orbit needs more than burn_in={burn_in} and at most {actions.shape[1]} steps")
    if scales is not None:
        scales = torch.as_tensor(scales, dtype=torch.float64, device=z.device)
        if scales.shape != (dim,) or not bool(torch.all(torch.isfinite(scales) & (scales > 0))):
            raise ValueError(f"scales must be {dim} positive finite numbers, got {scales.tolist()}")
        similarity = scales[None, :] / scales[:, None]  # (1 / s_i) J_ij s_j

    def one(zi: Tensor, ai: Tensor) -> tuple[Tensor, Tensor]:
        out = step(zi[None], ai[None])[0]
        return out, out

    jacobian_and_next = vmap(jacrev(one, has_aux=True))
    frame = torch.eye(dim, k, dtype=torch.float64, device=z.device).expand(batch, dim, k)
    total = torch.zeros(batch, k, dtype=torch.float64, device=z.device)
    with torch.no_grad():  # torch.func still differentiates inside; this only stops parameter graphs
        for t in range(int(steps.max())):
            # Finished orbits run on through their padding (rows are independent); only their sums stop.
            jac, z = jacobian_and_next(z, actions[:, t])
            if scales is not None:
                jac = jac * similarity
            frame, stretch = _orthonormalise(jac @ frame)
            if t >= burn_in:
                total += torch.where((t < steps)[:, None], stretch.log(), 0.0)
    return total / (steps - burn_in)[:, None]


def maximal_lyapunov(
    step: StepFn,
    z0: Tensor,
    actions: Tensor,
    *,
    burn_in: int = 0,
    lengths: Tensor | None = None,
    scales: Tensor | np.ndarray | None = None,
) -> Tensor:
    """The largest finite-time Lyapunov exponent of each orbit, ``[B]`` float64."""
    return lyapunov_spectrum(step, z0, actions, 1, burn_in=burn_in, lengths=lengths, scales=scales)[:, 0]


def state_scales(model: LatentDynamics) -> np.ndarray:
    """The state std a model stores (its first transition model's: the source's in a residual model), ``[4]``.

    Passed as ``scales`` it measures exponents in the units the network sees; use the
    source model's for every model of a comparison, so that all are measured alike.
    """
    from t42_transfer.models.network import TransitionModel

    for module in model.modules():
        if isinstance(module, TransitionModel):
            return module.state_std.detach().cpu().numpy().astype(np.float64)
    raise ValueError(f"{type(model).__name__} holds no transition model, so no stored normalisation")


def _latent_scales(scales: Tensor | np.ndarray, latent_dim: int) -> np.ndarray:
    """Per-latent scales: given per latent coordinate, or per hand-state coordinate and repeated.

    Every latent of the project's models is made of hand-state blocks (the state, the
    grasp state, the residual sum), so state scales repeat over them.
    """
    scales = np.asarray(scales, dtype=np.float64).reshape(-1)
    if len(scales) == STATE_DIM and latent_dim % STATE_DIM == 0:
        return np.tile(scales, latent_dim // STATE_DIM)
    if len(scales) != latent_dim:
        raise ValueError(f"scales must have {STATE_DIM} or {latent_dim} entries for this model, got {len(scales)}")
    return scales


def _starts_and_actions(
    data: TrajectorySet | tuple[Tensor | np.ndarray, Tensor | np.ndarray], steps: int | None
) -> tuple[Tensor, Tensor, Tensor | None]:
    """``(x0[B, 4], actions[B, T, 2], lengths or None)`` from episodes (zero-padded) or explicit arrays."""
    if steps is not None and steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    if isinstance(data, TrajectorySet):
        if not len(data):
            raise ValueError("no episodes to analyse")
        lengths = torch.tensor([min(len(ep), steps or len(ep)) for ep in data])
        actions = torch.zeros(len(data), int(lengths.max()), data[0].actions.shape[1], dtype=torch.float64)
        for row, (ep, n) in enumerate(zip(data, lengths.tolist(), strict=True)):
            actions[row, :n] = torch.tensor(ep.actions[:n])
        x0 = torch.as_tensor(np.stack([ep.states[0] for ep in data]))
        return x0, actions, lengths
    x0, actions = (v if isinstance(v, Tensor) else torch.tensor(v) for v in data)
    return x0, actions[:, :steps], None


def dynamic_coordinates(model: LatentDynamics) -> tuple[int, ...]:
    """The latent coordinates that change along an orbit: all but the model's held ones (parameters)."""
    held = set(model.held_latents())
    return tuple(i for i in range(model.latent_dim) if i not in held)


def _over_dynamic(step: StepFn, dynamic: tuple[int, ...], held: tuple[int, ...]) -> StepFn:
    """``step`` restricted to the ``dynamic`` coordinates; the ``held`` ones ride along as extra action columns."""
    order = torch.argsort(torch.tensor(dynamic + held))

    def restricted(zd: Tensor, extended: Tensor) -> Tensor:
        action, fixed = extended[:, : extended.shape[1] - len(held)], extended[:, extended.shape[1] - len(held):]
        z = torch.cat([zd, fixed], dim=1)[:, order]
        return step(z, action)[:, list(dynamic)]

    return restricted


def model_lyapunov_spectrum(
    model: LatentDynamics,
    data: TrajectorySet | tuple[Tensor | np.ndarray, Tensor | np.ndarray],
    k: int | None = None,
    *,
    steps: int | None = None,
    burn_in: int = 0,
    scales: Tensor | np.ndarray | None = None,
) -> Tensor:
    """Finite-time Lyapunov exponents ``[B, k]`` of ``model`` along its own open-loop orbits.

    Orbits start at ``initial_latent(x0)`` and follow the recorded actions: one
    per episode of a :class:`TrajectorySet` (from its first state, over its own
    length), or per row of ``(x0[B, 4], actions[B, T, 2])``; ``steps`` crops them,
    burn-in included (``steps - burn_in`` steps are averaged).  ``scales`` (see
    :func:`lyapunov_spectrum`) may be per hand-state coordinate (e.g.
    :func:`state_scales`), repeated over the latent's state blocks.
    The map is ``latent_step`` of a float64 copy in eval mode (dropout off), over
    the :func:`dynamic_coordinates` (the held ones stay at their start values); the
    caller's model is left untouched.  The full spectrum gives the source model's
    smallest exponent, which the paper uses to choose ``gamma``.
    """
    x0, actions, lengths = _starts_and_actions(data, steps)
    analysed = copy.deepcopy(model).to(torch.float64).eval().requires_grad_(False)
    device = model_device(analysed)
    x0, actions = x0.to(device=device, dtype=torch.float64), actions.to(device=device, dtype=torch.float64)
    with torch.no_grad():
        z0 = analysed.initial_latent(x0)
    if scales is not None:
        scales = _latent_scales(scales, z0.shape[1])
    dynamic, step = dynamic_coordinates(analysed), analysed.latent_step
    held = tuple(sorted(set(range(z0.shape[1])) - set(dynamic)))
    if held:
        step = _over_dynamic(step, dynamic, held)
        fixed = z0[:, list(held)][:, None, :].expand(-1, actions.shape[1], -1)
        actions, z0 = torch.cat([actions, fixed], dim=2), z0[:, list(dynamic)]
        scales = None if scales is None else scales[list(dynamic)]
    return lyapunov_spectrum(step, z0, actions, k, burn_in=burn_in, lengths=lengths, scales=scales)


def model_lyapunov(
    model: LatentDynamics,
    data: TrajectorySet | tuple[Tensor | np.ndarray, Tensor | np.ndarray],
    *,
    steps: int | None = None,
    burn_in: int = 0,
    scales: Tensor | np.ndarray | None = None,
) -> Tensor:
    """The maximal finite-time Lyapunov exponent ``[B]`` of each open-loop orbit of ``model`` (see above)."""
    return model_lyapunov_spectrum(model, data, 1, steps=steps, burn_in=burn_in, scales=scales)[:, 0]


GAMMA_RULE_STEPS = 200
"""Steps of each target orbit the source's spectrum is averaged over for :func:`lyapunov_gamma`."""


def lyapunov_gamma(source: LatentDynamics, data: TrajectorySet, steps: int = GAMMA_RULE_STEPS) -> float:
    """The cumulative residual's ``gamma`` by the paper's proof: ``min(1, e^lambda_min)``, ``lambda_min`` the
    smallest exponent of ``source``'s full spectrum along ``data``'s open-loop orbits (mean over orbits)."""
    if not len(data):
        raise ValueError("the gamma rule needs at least one episode to follow")
    spectrum = model_lyapunov_spectrum(source, data, steps=steps)  # in the frame's column order: take the minimum
    return float(min(1.0, np.exp(float(spectrum.min(dim=1).values.mean()))))
