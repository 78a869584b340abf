"""Residual models whose residual net also reads the episode's start state, as the authors' models do.

The authors' networks all take 10 inputs: state, action, and the episode's start
state (shared/data/authors_models/README.md).  The project's residual classes call
the residual net with state and action only, so the authors' residual families
need these two subclasses: the source is a transition model with the start state
in its latent (``grasp_input``), and the residual net gets it from there.
"""

from __future__ import annotations

import torch

from t42_transfer.conventions import STATE_DIM
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import TransitionModel
from t42_transfer.models.residual import CumulativeResidualModel, RecurrentResidualModel, _build, _weight


def _start_state_pair(source: LatentDynamics, residual: TransitionModel, kind: str) -> None:
    if not (isinstance(source, TransitionModel) and source.grasp_input and residual.grasp_input):
        raise ValueError(f"{kind} needs a source and a residual that both take the start state")


class StartStateCumulativeResidualModel(CumulativeResidualModel):
    """Algorithm 2 (:class:`CumulativeResidualModel`) whose residual net also reads the episode's start state.

    Why a class of its own: the authors' decoder ``g`` takes the same 10 inputs as
    their source (state, action, start state), and the base class calls ``g`` with
    state and action only.  Here the source is a transition model with the start
    state in its latent (``grasp_input``), and ``g`` gets it from there:
    ``y' = gamma y + alpha g(x, a, x_start)``.

    Alignment: the authors' rollout (LatentDeltaNet.run_traj) adds the residual of
    the step ``i -> i+1`` to state ``i`` (their ``states[0]`` is not the start
    state); this model keeps the paper's alignment, ``states[i] = x_i + y_i`` with
    ``y_0 = 0``, so the two differ by one step of the residual sum.
    """

    kind = "start_state_cumulative_residual"

    def __init__(self, source: LatentDynamics, residual: TransitionModel, alpha: float, gamma: float) -> None:
        _start_state_pair(source, residual, self.kind)
        super().__init__(source, residual, alpha, gamma)

    def latent_step(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        zs, y = z[:, : self.source.latent_dim], z[:, self.source.latent_dim :]
        x, start = zs[:, :STATE_DIM], zs[:, STATE_DIM:]
        y_next = self.gamma * y + self.alpha * self.residual.delta(x, action, start)
        return torch.cat([self.source.latent_step(zs, action), y_next], dim=-1)

    @classmethod
    def from_config(cls, config: dict) -> StartStateCumulativeResidualModel:
        residual = _build(config.get("residual"), "residual", {TransitionModel.kind: TransitionModel})
        source = _build(config.get("source"), "source", {TransitionModel.kind: TransitionModel})
        return cls(source, residual, _weight(config, "alpha"), _weight(config, "gamma"))


class StartStateRecurrentResidualModel(RecurrentResidualModel):
    """The authors' recurrent residual (:class:`RecurrentResidualModel`) whose residual net reads the start state.

    Why a class of its own: the authors' ``res`` takes the same 10 inputs as
    ``net_S`` (TrajNet.forward: ``out = model(u) + res(u) * coeff``), and the base
    class calls ``g`` with state and action only.
    """

    kind = "start_state_recurrent_residual"

    def __init__(self, source: LatentDynamics, residual: TransitionModel, alpha: float) -> None:
        _start_state_pair(source, residual, self.kind)
        super().__init__(source, residual, alpha)

    def latent_step(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x, start = z[:, :STATE_DIM], z[:, STATE_DIM:]
        correction = self.alpha * self.residual.delta(x, action, start)
        return self.source.latent_step(z, action) + torch.cat([correction, torch.zeros_like(start)], dim=-1)

    @classmethod
    def from_config(cls, config: dict) -> StartStateRecurrentResidualModel:
        residual = _build(config.get("residual"), "residual", {TransitionModel.kind: TransitionModel})
        source = _build(config.get("source"), "source", {TransitionModel.kind: TransitionModel})
        return cls(source, residual, _weight(config, "alpha"))
