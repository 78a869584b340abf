"""Dropout members: thinned copies of the paper's MLP, for choosing among a search's best sequences; and fresh
dropout masks at every step (:class:`DropoutRollout`, ``PlannerConfig(uncertainty="dropout")``).

A member is the model with one draw of its dropout masks held fixed (the AlphaDropout after the SELU, the Dropout
after the tanh): the model in training mode with those masks, whose arithmetic folds into the second and third
layers, so every member rolls out as the fused deterministic path does.  Unlike fresh masks at every step
(``PlannerConfig(uncertainty="dropout")``), a member errs the same way all along a rollout, as one network of an
ensemble does.

:class:`MembersRollout` predicts the same sequences with every member in one batched product per layer: per
member a rollout would be dispatch-bound at the planner's 30-sequence batches.

:func:`robust_choice` is the planner's last step (``PlannerConfig.rerank``): of the search's best sequences, the
one whose members agree on ending nearest the goal.  Measured on the tuning and held-out goals of
``docs/experiments/planner_tuning``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from t42_transfer.conventions import ACTION_DIM, STATE_DIM
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import TransitionModel
from t42_transfer.planning.fused import LN2, NEGATIVE_BRANCH, SELU_SCALE, fuse, is_paper_mlp
from t42_transfer.planning.sampling import stream_generator
from t42_transfer.planning.workspace import Workspace

ALPHA_DROPOUT_ALPHA = 1.7580993408473766
"""torch's AlphaDropout drives a dropped unit to ``-alpha``, SELU's negative saturation (``scale * alpha``)."""


def can_rerank(model: LatentDynamics) -> bool:
    """Whether ``model`` has members to draw: the paper's MLP with dropout."""
    return is_paper_mlp(model) and 0.0 < model.dropout < 1.0


class DropoutRollout:
    """The model's rollout with dropout on: each call draws new masks (one stochastic member).

    The masks come from a generator seeded by the plan's seed, so a plan is reproducible."""

    def __init__(self, model: LatentDynamics, seed: int) -> None:
        self.model, self.seed, self.calls = model, seed, 0

    def __call__(self, x0: Tensor, actions: Tensor) -> Tensor:
        self.calls += 1
        was_training = self.model.training
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            torch.manual_seed(hash((self.seed, self.calls)) & 0x7FFF_FFFF)
            self.model.train()
            try:
                return self.model.rollout_with_grad(x0, actions).transpose(0, 1)
            finally:
                self.model.train(was_training)


def dropout_masks(model: TransitionModel, count: int, seed: int) -> tuple[Tensor, Tensor]:
    """``count`` draws of the kept units ``[M, H]`` (1 kept, 0 dropped) of the AlphaDropout and of the Dropout,
    from a generator of their own seeded by ``seed``."""
    generator = stream_generator(seed, 7)
    hidden = model.net[3].weight.shape[1]
    kept = torch.rand(2, count, hidden, generator=generator) >= model.dropout
    return kept[0].float(), kept[1].float()


class MembersRollout:
    """Every member's rollout of the same sequences, ``(x0[B, 4], actions[B, T, 2]) -> states[T + 1, M, B, 4]``:
    the fused rollout's arithmetic (:mod:`~t42_transfer.planning.fused`) with a member dimension, each member's
    masks folded into the fused second and third layers."""

    def __init__(self, model: TransitionModel, count: int, seed: int) -> None:
        base, p = fuse(model), model.dropout
        kept_1, kept_2 = (k.to(base.w1.dtype) for k in dropout_masks(model, count, seed))
        self.grasp_input = base.grasp_input
        self.w1, self.b1 = base.w1.expand(count, -1, -1), base.b1.expand(count, 1, -1)
        # AlphaDropout, a * (x * kept + alpha * (kept - 1 + p)) on selu's x = SELU_SCALE * (ln 2 * h1 - SELU_ALPHA)
        # in the fused h1: a * kept scales the layer's rows; what is left goes into its bias.
        a = 1.0 / math.sqrt((ALPHA_DROPOUT_ALPHA**2 * p + 1.0) * (1.0 - p))
        scale = a * kept_1  # [M, H]
        shift = a * ALPHA_DROPOUT_ALPHA * (kept_1 - 1.0 + p) + ALPHA_DROPOUT_ALPHA * (1.0 - scale)
        self.w2 = base.w2 * scale[:, :, None]
        self.b2 = (base.b2 + shift @ base.w2 / (SELU_SCALE * LN2))[:, None, :]
        # Dropout, x * kept / (1 - p), on tanh's x = 2 * sigmoid - 1: the third layer's columns, and its bias
        kept = kept_2 / (1.0 - p)
        self.w3 = base.w3 * kept[:, None, :]
        self.b3 = base.b3 + ((1.0 - kept) @ base.w3.T / 2.0)[:, :, None]

    @torch.inference_mode()
    def __call__(self, x0: Tensor, actions: Tensor) -> Tensor:
        dtype = self.w1.dtype
        members, inputs_dim, hidden = self.w1.shape
        batch, horizon = actions.shape[:2]
        inputs = torch.empty(horizon + 1, members, batch, inputs_dim, dtype=dtype)
        inputs[0, :, :, :STATE_DIM] = x0.to(dtype)
        inputs[:horizon, :, :, STATE_DIM : STATE_DIM + ACTION_DIM] = actions.to(dtype).transpose(0, 1)[:, None]
        if self.grasp_input:
            inputs[:, :, :, STATE_DIM + ACTION_DIM :] = x0.to(dtype)
        h1, exponential, h2 = (torch.empty(members, batch, hidden, dtype=dtype) for _ in range(3))
        delta = torch.empty(members, STATE_DIM, batch, dtype=dtype)
        step_inputs = inputs.unbind(0)
        step_states = [step[..., :STATE_DIM] for step in step_inputs]
        for t in range(horizon):
            torch.baddbmm(self.b1, step_inputs[t], self.w1, out=h1)
            torch.exp2(h1, out=exponential).clamp_max_(1.0)
            h1.clamp_min_(0.0).add_(exponential, alpha=NEGATIVE_BRANCH)
            torch.baddbmm(self.b2, h1, self.w2, out=h2).sigmoid_()
            torch.baddbmm(self.b3, self.w3, h2.transpose(1, 2), out=delta)
            torch.add(step_states[t], delta.transpose(1, 2), out=step_states[t + 1])
        return inputs[..., :STATE_DIM].contiguous()


def robust_choice(rollout: MembersRollout, workspace: Workspace, x0: Tensor, goal: Tensor, candidates: Tensor,
                  risk: float) -> int | None:
    """Index of the sequence of ``candidates[K, T, 2]`` with the lowest ``mean + risk * std`` of the members'
    final distances to ``goal``, a sequence any member takes out of the workspace never chosen; None when every
    one is."""
    states = rollout(x0.expand(len(candidates), STATE_DIM), candidates)  # [T + 1, M, K, 4]
    safe = workspace.allows(states[1:].float()).all(0).all(0)
    final = states[-1, :, :, :2].float() - goal
    distance = torch.hypot(final[..., 0], final[..., 1])
    score = (distance.mean(0) + risk * distance.std(0, correction=1 if len(distance) > 1 else 0))
    score = score.masked_fill(~safe, math.inf)
    best = int(torch.argmin(score))
    return best if math.isfinite(float(score[best])) else None
