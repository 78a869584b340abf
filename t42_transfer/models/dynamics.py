"""The one model contract: every transfer method's model is a latent Markov system.

A model advances a latent state ``z`` with ``z' = latent_step(z, a)`` and shows the
hand state ``x = observe(z)``.  For a plain transition model ``z`` is the hand
state itself; a cumulative residual model carries the source model's state and
the residual sum, so ``z`` is 8-D.  Writing every model this way gives one
``rollout`` for metrics, planner and nodes, and one differentiable map for the
Lyapunov analysis, which must see the hidden state to be honest.

Shapes (float32 unless the caller passes float64):
``rollout(x0[B, 4], actions[B, T, 2]) -> states[B, T + 1, 4]``, millimetres and
raw load units, ``states[:, 0] == x0``.
"""

from __future__ import annotations

import abc

import torch
from torch import Tensor, nn

from t42_transfer.conventions import ACTION_DIM, STATE_DIM

MODEL_KINDS: dict[str, type[LatentDynamics]] = {}
"""Every concrete model class by its ``kind``: checkpoints rebuild models through it."""


class LatentDynamics(nn.Module, abc.ABC):
    """Base of every model; subclasses define the latent map, this class rolls it out.

    A subclass sets a unique ``kind`` and implements ``config()`` (JSON-able
    constructor arguments) and ``from_config()``; ``from_config`` may use
    placeholder normalisation because ``load_state_dict`` restores the buffers.
    """

    kind: str = ""
    latent_dim: int = STATE_DIM

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if cls.kind:
            if cls.kind in MODEL_KINDS and MODEL_KINDS[cls.kind] is not cls:
                raise TypeError(f"model kind {cls.kind!r} defined twice")
            MODEL_KINDS[cls.kind] = cls

    @abc.abstractmethod
    def config(self) -> dict:
        """JSON-able arguments that rebuild this model's architecture with :meth:`from_config`."""

    @classmethod
    @abc.abstractmethod
    def from_config(cls, config: dict) -> LatentDynamics:
        """An untrained model of the architecture ``config`` describes."""

    @abc.abstractmethod
    def initial_latent(self, x0: Tensor) -> Tensor:
        """Latent state ``[B, latent_dim]`` of hand states ``x0[B, 4]``."""

    @abc.abstractmethod
    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        """One 0.1 s step: ``z[B, latent_dim], action[B, 2] -> z'[B, latent_dim]`` (differentiable)."""

    @abc.abstractmethod
    def observe(self, z: Tensor) -> Tensor:
        """Hand state ``[B, 4]`` shown by latent ``z``."""

    def episode_latent(self, states: Tensor, starts: Tensor) -> Tensor:
        """Latent ``[B, latent_dim]`` of hand states ``states[B, 4]`` met in episodes that began at ``starts[B, 4]``:
        the episode's parameters (the grasp state some networks read) are the start's, not the state's, as a rollout
        from ``starts`` carries them.  A one-step prediction from a mid-episode state needs this, not
        :meth:`initial_latent`, which takes the state for its own start.  The latent's first four coordinates are the
        hand state (residual sums start at 0); a model whose latent is otherwise overrides this."""
        z = self.initial_latent(starts).clone()
        z[:, :STATE_DIM] = states
        return z

    def held_latents(self) -> tuple[int, ...]:
        """Latent coordinates ``latent_step`` carries unchanged: parameters of the episode (the grasp state some
        networks read), not state. Their directions are neutral by construction, so dynamics analyses leave them out."""
        return ()

    def rollout_with_grad(self, x0: Tensor, actions: Tensor) -> Tensor:
        """Open-loop prediction in the model's current mode (dropout on while training), keeping the autograd
        graph: dropout-on evaluation (``t42 evaluate --dropout-draws``), the planner's dropout members and its gradient
        polish."""
        _check_shapes(x0, actions)
        z = self.initial_latent(x0)
        states = [self.observe(z)]
        for t in range(actions.shape[1]):
            z = self.latent_step(z, actions[:, t])
            states.append(self.observe(z))
        return torch.stack(states, dim=1)

    @torch.no_grad()
    def rollout(self, x0: Tensor, actions: Tensor) -> Tensor:
        """Open-loop prediction in evaluation mode (dropout off), no gradients."""
        was_training = self.training
        self.eval()
        try:
            return self.rollout_with_grad(x0, actions)
        finally:
            self.train(was_training)


def _check_shapes(x0: Tensor, actions: Tensor) -> None:
    if x0.ndim != 2 or x0.shape[1] != STATE_DIM:
        raise ValueError(f"x0 must be [B, {STATE_DIM}], got {tuple(x0.shape)}")
    if actions.ndim != 3 or actions.shape[2] != ACTION_DIM or actions.shape[0] != x0.shape[0]:
        raise ValueError(f"actions must be [B={x0.shape[0]}, T, {ACTION_DIM}], got {tuple(actions.shape)}")
