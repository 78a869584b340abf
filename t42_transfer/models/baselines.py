"""The trivial model every score is compared with: the hand holds still.

A model earns its place only by beating the prediction "nothing moves": a
divergence time or an MSE means little without it, and on the real hands this
baseline outlasts several transfer methods.  It follows the one contract, so
metrics, planner and reports take it like any model (nothing to train).
"""

from __future__ import annotations

from torch import Tensor

from t42_transfer.models.dynamics import LatentDynamics


class HoldStill(LatentDynamics):
    """``x' = x``: the object stays where it is and the loads stay as they are."""

    kind = "hold_still"

    def config(self) -> dict:
        return {}

    @classmethod
    def from_config(cls, config: dict) -> HoldStill:
        if config:
            raise ValueError(f"{cls.kind} takes no arguments, got {sorted(config)}")
        return cls()

    def initial_latent(self, x0: Tensor) -> Tensor:
        return x0

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return z + 0.0 * action.sum(-1, keepdim=True)  # differentiable in the action, and exactly z

    def observe(self, z: Tensor) -> Tensor:
        return z
