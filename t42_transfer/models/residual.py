"""Models that keep the source model and add a learned residual (Algorithm 2 and its recurrent twins).

The residual network ``g`` has the transition model's architecture and learns, one
step at a time, the source model's error on target data: ``x' - f_S(x, a)``.
The recurrent residual comes in the paper's form (:class:`AdjustedStateResidualModel`)
and the authors' code's (:class:`RecurrentResidualModel`); see docs/transfer_methods.md.
"""

from __future__ import annotations

import reprlib
import sys

import torch
from torch import Tensor

from t42_transfer.conventions import STATE_DIM
from t42_transfer.models.dynamics import MODEL_KINDS, LatentDynamics
from t42_transfer.models.network import TransitionModel, config_number


def _spec(model: LatentDynamics) -> dict:
    return {"kind": model.kind, "config": model.config()}


def _build(spec: object, role: str, kinds: dict[str, type[LatentDynamics]] = MODEL_KINDS) -> LatentDynamics:
    """The model ``spec`` describes, checked first: specs come from model files."""
    kind = spec.get("kind") if isinstance(spec, dict) else None
    if not isinstance(kind, str) or kind not in kinds or not isinstance(spec.get("config"), dict):
        raise ValueError(f"{role} must be {{kind: one of {sorted(kinds)}, config: {{...}}}}, not {reprlib.repr(spec)}")
    return kinds[kind].from_config(spec["config"])


def _weight(config: dict, key: str) -> float:
    """A required finite float (``alpha``, ``gamma``)."""
    return float(config_number(config, key, None, -sys.float_info.max, sys.float_info.max))


class CumulativeResidualModel(LatentDynamics):
    """Algorithm 2: the frozen source rolls out ``x``; ``y' = gamma y + alpha g(x, a)``; shows ``x + y``.

    ``g`` never sees its own output, so the model's Lyapunov exponents are the
    source's and ``ln gamma`` (the paper's theorem; checked numerically in the tests).
    """

    kind = "cumulative_residual"

    def __init__(self, source: LatentDynamics, residual: TransitionModel, alpha: float, gamma: float) -> None:
        super().__init__()
        self.source = source
        self.residual = residual
        self.alpha = float(alpha)
        self.gamma = float(gamma)
        self.latent_dim = source.latent_dim + STATE_DIM  # y: a sum of hand-state changes
        for p in self.source.parameters():
            p.requires_grad_(False)

    def initial_latent(self, x0: Tensor) -> Tensor:
        return torch.cat([self.source.initial_latent(x0), torch.zeros_like(x0)], dim=-1)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        zs, y = z[:, : self.source.latent_dim], z[:, self.source.latent_dim :]
        x = self.source.observe(zs)
        y_next = self.gamma * y + self.alpha * self.residual.delta(x, action)
        return torch.cat([self.source.latent_step(zs, action), y_next], dim=-1)

    def observe(self, z: Tensor) -> Tensor:
        zs, y = z[:, : self.source.latent_dim], z[:, self.source.latent_dim :]
        return self.source.observe(zs) + y

    def held_latents(self) -> tuple[int, ...]:
        return self.source.held_latents()  # the residual sum y changes every step

    def config(self) -> dict:
        return {"source": _spec(self.source), "residual": _spec(self.residual), "alpha": self.alpha,
                "gamma": self.gamma}

    @classmethod
    def from_config(cls, config: dict) -> CumulativeResidualModel:
        residual = _build(config.get("residual"), "residual", {TransitionModel.kind: TransitionModel})
        return cls(_build(config.get("source"), "source"), residual, _weight(config, "alpha"), _weight(config, "gamma"))


class RecurrentResidualModel(LatentDynamics):
    """The authors' recurrent residual: ``x' = f_S(x, a) + alpha g(x, a)`` inside the loop (g feeds back).

    With ``g`` scaled like the source (its normalisation: the source's states, no
    mean change, the source's change std) this is the authors' code exactly:
    ``x' = x + denorm_S(net_S(u) + alpha res(u))`` for the source-normalised input ``u``
    (TrajNet.forward: ``out = model(x) + res(x) * coeff``).
    """

    kind = "recurrent_residual"

    def __init__(self, source: LatentDynamics, residual: TransitionModel, alpha: float) -> None:
        super().__init__()
        self.source = source
        self.residual = residual
        self.alpha = float(alpha)
        self.latent_dim = source.latent_dim
        for p in self.source.parameters():
            p.requires_grad_(False)

    def initial_latent(self, x0: Tensor) -> Tensor:
        return self.source.initial_latent(x0)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        x = self.source.observe(z)
        correction = self.alpha * self.residual.delta(x, action)
        z_next = self.source.latent_step(z, action)
        pad = z_next.shape[-1] - correction.shape[-1]
        return z_next + torch.nn.functional.pad(correction, (0, pad))

    def observe(self, z: Tensor) -> Tensor:
        return self.source.observe(z)

    def held_latents(self) -> tuple[int, ...]:
        return self.source.held_latents()

    def config(self) -> dict:
        return {"source": _spec(self.source), "residual": _spec(self.residual), "alpha": self.alpha}

    @classmethod
    def from_config(cls, config: dict) -> RecurrentResidualModel:
        residual = _build(config.get("residual"), "residual", {TransitionModel.kind: TransitionModel})
        return cls(_build(config.get("source"), "source"), residual, _weight(config, "alpha"))


class AdjustedStateResidualModel(CumulativeResidualModel):
    """The paper's recurrent residual: Algorithm 2 with the adjusted state as an additional input of ``g``.

    The source rolls out ``x`` on its own; ``y' = gamma y + alpha g(x, a, x + y)``;
    shows ``x + y`` (``y`` here is the paper's ``alpha y``, so ``x + y`` is its adjusted
    state ``x + alpha y``).  ``g`` is a transition model with a second state input
    (its ``grasp`` slot), which carries the adjusted state: that is the feedback.
    """

    kind = "adjusted_state_residual"

    def __init__(self, source: LatentDynamics, residual: TransitionModel, alpha: float, gamma: float) -> None:
        if not residual.grasp_input:
            raise ValueError("the adjusted-state residual needs a residual net with a second state input")
        super().__init__(source, residual, alpha, gamma)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        zs, y = z[:, : self.source.latent_dim], z[:, self.source.latent_dim :]
        x = self.source.observe(zs)
        y_next = self.gamma * y + self.alpha * self.residual.delta(x, action, x + y)
        return torch.cat([self.source.latent_step(zs, action), y_next], dim=-1)
