"""The oracle: the planner with a perfect model, the true simulated hand itself.

Peg-in-hole needs an upper reference beside the do-nothing floor: what the same
planner, with the same samples, achieves when its predictions are exact.
:class:`HandRollout` predicts a batch of sequences by replaying each one on a
copy of the executing hand from a snapshot taken where the plan starts, sensor
noise included, so the oracle's prediction of the sequence it picks is exactly
what execution then shows.  A sequence that ends the episode (drop, lost
contact, overload) is predicted as NaN from that step on, which the planner
rejects like any unsafe prediction.  It costs one simulated step per sample and
step (about 0.3 ms here), hundreds of times a learned model's batch rollout.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from t42_transfer.conventions import STATE_DIM
from t42_transfer.hand.sim import HandSnapshot, SimulatedHand


class HandRollout:
    """A time-major rollout function ``(x0[B, 4], actions[B, T, 2]) -> states[T+1, B, 4]`` of the true hand.

    ``x0`` must be the snapshot's state: the hand's hidden state (contacts, servo
    angles, noise generator) is what makes the prediction exact, so it comes from
    the snapshot, and ``x0`` only checks that the planner starts where it should.
    """

    def __init__(self, hand: SimulatedHand, start: HandSnapshot) -> None:
        self.hand, self.start = hand, start

    def __call__(self, x0: Tensor, actions: Tensor) -> Tensor:
        expected = torch.as_tensor(self.start.state, dtype=x0.dtype)
        if not torch.allclose(x0, expected.expand_as(x0), atol=1e-3):
            raise ValueError("the oracle predicts from its snapshot's state only")
        moves = actions.detach().cpu().double().numpy()
        count, horizon = moves.shape[:2]
        out = np.full((horizon + 1, count, STATE_DIM), np.nan)
        out[0] = self.start.state
        for i in range(count):
            self.hand.restore(self.start)
            for t in range(horizon):
                info = self.hand.step_info(moves[i, t])
                if info.done:
                    break
                out[t + 1, i] = self.hand.state
        return torch.as_tensor(out, dtype=x0.dtype)
