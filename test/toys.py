"""Toy dynamics models shared by the tests: exact, cheap systems whose right answers are known."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from t42_transfer.hand.sim import StepInfo
from t42_transfer.models import LatentDynamics


class StateIsLatent(LatentDynamics):
    """A model whose latent is the observed state: subclasses give only ``latent_step``."""

    def config(self) -> dict:
        return {}

    @classmethod
    def from_config(cls, config: dict) -> StateIsLatent:
        return cls(**config)

    def initial_latent(self, x0: Tensor) -> Tensor:
        return x0

    def observe(self, z: Tensor) -> Tensor:
        return z


class Toy(StateIsLatent):
    """``(x, y) += gain * a + drift``, loads grow apart by ``load_rate`` per step, NaN once ``x > nan_beyond``.

    It has a ``kind``, so it can be saved and loaded as a checkpoint (the planner node's model).
    """

    kind = "test_toy"

    def __init__(
        self,
        gain: float = 1.0,
        drift: tuple[float, float] = (0.0, 0.0),
        load_rate: float = 0.0,
        nan_beyond: float | None = math.inf,
    ) -> None:
        super().__init__()
        self.gain, self.drift, self.load_rate = gain, tuple(drift), load_rate
        self.nan_beyond = math.inf if nan_beyond is None else nan_beyond

    def config(self) -> dict:
        finite = math.isfinite(self.nan_beyond)
        return {"gain": self.gain, "drift": list(self.drift), "load_rate": self.load_rate,
                "nan_beyond": self.nan_beyond if finite else None}

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        loads = torch.tensor([self.load_rate, -self.load_rate]).expand_as(action)
        nxt = z + torch.cat([self.gain * action + torch.tensor(self.drift), loads], -1)
        return nxt.masked_fill((nxt[:, :1] > self.nan_beyond).expand_as(nxt), math.nan)


class SlowToy(Toy):
    """:class:`Toy` taking ``step_s`` seconds a step: a plan long enough to stop in the middle of."""

    kind = "test_slow_toy"

    def __init__(self, step_s: float = 0.05, **toy: object) -> None:
        super().__init__(**toy)  # type: ignore[arg-type]
        self.step_s = step_s

    def config(self) -> dict:
        return {**super().config(), "step_s": self.step_s}

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        time.sleep(self.step_s)
        return super().latent_step(z, action)


@dataclass
class ToyHand:
    """The true system for closed-loop tests: ``(x, y) += gain * a`` (a model with gain 1 is biased)."""

    gain: float
    state: np.ndarray

    def step_info(self, action: np.ndarray) -> StepInfo:
        self.state = self.state + np.concatenate([self.gain * np.asarray(action), [0.0, 0.0]])
        return StepInfo(done=False, end_reason="", refused=False)
