"""The paper's transition model: an MLP predicting the normalised state change.

``Linear(in, 128) -> SELU -> AlphaDropout(0.1) -> Linear(128, 128) -> Tanh ->
Dropout(0.1) -> Linear(128, 4)``; the saturating tanh keeps it from predicting
arbitrarily large moves.  Inputs are the z-normalised state and the raw action
(and, optionally, the episode's grasp state as the authors' code had); the output
is de-normalised and added to the state.  The normalisation is stored in buffers,
so it travels with the weights.
"""

from __future__ import annotations

import reprlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from t42_transfer.conventions import ACTION_DIM, STATE_DIM
from t42_transfer.models.dynamics import LatentDynamics

HIDDEN = 128
DROPOUT = 0.1
MAX_HIDDEN = 4096
"""Widest hidden layer ``from_config`` builds (64 MB of weights): a model file cannot ask for more."""
_MIN_STD = 1e-6


@dataclass(frozen=True)
class Normalisation:
    """Mean and std of states and of one-step state changes (actions are left as they are)."""

    state_mean: np.ndarray
    state_std: np.ndarray
    delta_mean: np.ndarray
    delta_std: np.ndarray

    @classmethod
    def from_transitions(cls, x: np.ndarray, x_next: np.ndarray) -> Normalisation:
        if len(x) < 2:
            raise ValueError(f"need at least 2 transitions to normalise, got {len(x)}")
        delta = x_next - x
        return cls(
            state_mean=x.mean(0).astype(np.float32),
            state_std=np.maximum(x.std(0), _MIN_STD).astype(np.float32),
            delta_mean=delta.mean(0).astype(np.float32),
            delta_std=np.maximum(delta.std(0), _MIN_STD).astype(np.float32),
        )

    @classmethod
    def identity(cls) -> Normalisation:
        zeros, ones = np.zeros(STATE_DIM, np.float32), np.ones(STATE_DIM, np.float32)
        return cls(zeros, ones, zeros, ones)


def mlp(inputs: int, outputs: int = STATE_DIM, hidden: int = HIDDEN, dropout: float = DROPOUT) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inputs, hidden),
        nn.SELU(),
        nn.AlphaDropout(dropout),
        nn.Linear(hidden, hidden),
        nn.Tanh(),
        nn.Dropout(dropout),
        nn.Linear(hidden, outputs),
    )


class TransitionModel(LatentDynamics):
    """``x' = x + denorm(net(norm(x), a))``; with ``grasp_input`` the latent also carries the grasp state."""

    kind = "transition"

    def __init__(
        self, norm: Normalisation, grasp_input: bool = False, hidden: int = HIDDEN, dropout: float = DROPOUT
    ) -> None:
        super().__init__()
        self.grasp_input = grasp_input
        self.hidden = hidden
        self.dropout = dropout
        self.latent_dim = 2 * STATE_DIM if grasp_input else STATE_DIM
        inputs = STATE_DIM + ACTION_DIM + (STATE_DIM if grasp_input else 0)
        self.net = mlp(inputs, STATE_DIM, hidden, dropout)
        for name in ("state_mean", "state_std", "delta_mean", "delta_std"):
            self.register_buffer(name, torch.as_tensor(np.asarray(getattr(norm, name), np.float32)).clone())

    # -- normalisation ------------------------------------------------------------
    @property
    def norm(self) -> Normalisation:
        return Normalisation(*(getattr(self, n).detach().cpu().numpy()
                               for n in ("state_mean", "state_std", "delta_mean", "delta_std")))

    def features(self, x: Tensor, a: Tensor, grasp: Tensor | None = None) -> Tensor:
        parts = [(x - self.state_mean) / self.state_std, a]
        if self.grasp_input:
            if grasp is None:
                raise ValueError("this model takes the grasp state as input")
            parts.append((grasp - self.state_mean) / self.state_std)
        return torch.cat(parts, dim=-1)

    def normalised_delta(self, x: Tensor, a: Tensor, grasp: Tensor | None = None) -> Tensor:
        """The network's raw output: the predicted state change, z-normalised (the training target)."""
        return self.net(self.features(x, a, grasp))

    def delta(self, x: Tensor, a: Tensor, grasp: Tensor | None = None) -> Tensor:
        return self.normalised_delta(x, a, grasp) * self.delta_std + self.delta_mean

    def normalise_delta(self, delta: Tensor) -> Tensor:
        return (delta - self.delta_mean) / self.delta_std

    # -- the contract ---------------------------------------------------------------
    def initial_latent(self, x0: Tensor) -> Tensor:
        return torch.cat([x0, x0], dim=-1) if self.grasp_input else x0

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        if self.grasp_input:
            x, grasp = z[:, :STATE_DIM], z[:, STATE_DIM:]
            return torch.cat([x + self.delta(x, action, grasp), grasp], dim=-1)
        return z + self.delta(z, action)

    def observe(self, z: Tensor) -> Tensor:
        return z[:, :STATE_DIM]

    def held_latents(self) -> tuple[int, ...]:
        return tuple(range(STATE_DIM, 2 * STATE_DIM)) if self.grasp_input else ()

    def config(self) -> dict:
        return {"grasp_input": self.grasp_input, "hidden": self.hidden, "dropout": self.dropout}

    @classmethod
    def from_config(cls, config: dict) -> TransitionModel:
        """Checks types and bounds first: the config comes from a model file, and ``hidden`` sizes the weights."""
        unknown = set(config) - {"grasp_input", "hidden", "dropout"}
        if unknown:
            raise ValueError(f"{cls.kind} has no arguments {reprlib.repr(sorted(unknown))}")
        grasp_input = config.get("grasp_input", False)
        if not isinstance(grasp_input, bool):
            raise TypeError(f"{cls.kind} grasp_input must be true or false, not {reprlib.repr(grasp_input)}")
        hidden = config_number(config, "hidden", HIDDEN, 1, MAX_HIDDEN, integer=True)
        dropout = config_number(config, "dropout", DROPOUT, 0.0, 1.0)
        return cls(Normalisation.identity(), grasp_input, int(hidden), dropout)


def config_number(
    config: dict, key: str, default: float | None, low: float, high: float, *, integer: bool = False
) -> float:
    """``config[key]`` (or ``default``; None: required) if it is a number in ``[low, high]`` (an integer if asked)."""
    value = config.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
        raise TypeError(f"{key} must be {'an integer' if integer else 'a number'}, not {reprlib.repr(value)}")
    if not low <= value <= high:  # also refuses NaN and infinity
        raise ValueError(f"{key} must lie in [{low}, {high}], not {reprlib.repr(value)}")
    return value
