"""The planner's fast rollout of the paper's MLP: every constant folded into the matrices.

``model.rollout`` is right for every model kind but spends most of a planning
call outside the matrix products: normalising, concatenating, SELU and tanh
kernels, broadcasting biases, and allocating each step's tensors.  For a plain
:class:`~t42_transfer.models.network.TransitionModel` all of that folds away:

- input normalisation ``(x - m) / s`` goes into the first layer (``W1 / s``,
  ``b1 - W1 m / s``); its bias becomes the row of a constant-1 input column, and
  the grasp input (constant per sample) four more input columns;
- ``selu(u) = scale * (relu(u) + alpha * exp(min(u, 0)) - alpha)``: ``scale`` and
  ``- alpha`` go into the second layer, leaving four cheap in-place passes
  (eager ``torch.selu`` costs about twice that here).  The first layer is divided by
  ln 2 so that the exponential is ``exp2`` (``u = v ln 2``: ``relu(u) = ln 2 relu(v)``,
  ``exp(min(u, 0)) = exp2(min(v, 0))``, ln 2 going into the second layer): torch's
  ``exp2_`` took 52 us on a [1000, 129] block where ``exp_`` took 138 (one thread,
  AVX-512).  One extra hidden unit with zero weights comes out of them as exactly
  ``alpha / ln 2`` and carries the second layer's bias, so neither big product
  broadcasts a bias (7 % per step);
- ``tanh(v) = 2 sigmoid(2 v) - 1``: the 2s go into the second layer and the
  third, leaving one in-place sigmoid.  The reference AMD Zen 4 machines run
  eager tanh ~3x slower than sigmoid; on this project's Intel hosts tanh_ wins on
  unit-normal inputs but lost in the full loop (its cost depends on the inputs);
- output de-normalisation ``d * s_d + m_d`` goes into the third layer.

Each step is then two ``mm`` and one small ``addmm`` into preallocated buffers
plus the activations, in inference mode, writing states time-major so every
step's output is one contiguous block.  Equal to ``model.rollout`` up to float
rounding (the tests check 1e-4); dropout is off, as in ``rollout``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from t42_transfer.conventions import ACTION_DIM, STATE_DIM
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import TransitionModel

TimeMajorRollout = Callable[[Tensor, Tensor], Tensor]
"""``(x0[B, 4], actions[B, T, 2]) -> states[T + 1, B, 4]``: the contract's rollout, time-major.

The planner scores time-major: every reduction over time then runs along
contiguous rows, and the fused path produces that layout without a copy."""

SELU_ALPHA = 1.6732632423543772848170429916717
SELU_SCALE = 1.0507009873554804934193349852946
LN2 = 0.69314718055994530941723212145818
CARRIER = SELU_ALPHA / LN2
"""What the first layer's activation makes of a zero input: the bias-carrying hidden unit's value."""
_LAYOUT = (nn.Linear, nn.SELU, nn.AlphaDropout, nn.Linear, nn.Tanh, nn.Dropout, nn.Linear)


def is_paper_mlp(model: LatentDynamics) -> bool:
    """Whether ``model`` is a TransitionModel with exactly the paper's layer layout (what :func:`fuse` folds)."""
    if type(model) is not TransitionModel:
        return False
    layers = list(model.net)
    return len(layers) == len(_LAYOUT) and all(type(layer) is kind for layer, kind in zip(layers, _LAYOUT, strict=True))


@dataclass(frozen=True)
class FusedWeights:
    """Folded weights, stored ``[in, out]`` for ``mm(inputs, w)``."""

    w1: Tensor
    """``[I + 1, H + 1]``, divided by ln 2: rows for the raw state (4), the action (2), the raw grasp state (4,
    with grasp input), then the bias (the constant-1 input); column H is zero (the bias carrier)."""
    w2: Tensor
    """``[H + 1, H]``: the last row is the second layer's bias divided by :data:`CARRIER`."""
    w3: Tensor
    b3: Tensor
    grasp_input: bool


def fuse(model: TransitionModel) -> FusedWeights:
    """Fold ``model``'s normalisation, biases and activation constants into its layers (computed in float64)."""
    if not is_paper_mlp(model):
        raise TypeError(f"cannot fuse a {type(model).__name__} that is not the paper's MLP")
    l1, l2, l3 = (model.net[i] for i in (0, 3, 6))
    dtype, hidden = l1.weight.dtype, l1.out_features
    f64 = {"dtype": torch.float64}
    with torch.no_grad():
        mean, std = model.state_mean.to(**f64), model.state_std.to(**f64)
        d_mean, d_std = model.delta_mean.to(**f64), model.delta_std.to(**f64)
        w1, b1 = l1.weight.to(**f64), l1.bias.to(**f64)
        w1_state = w1[:, :STATE_DIM] / std
        parts = [w1_state, w1[:, STATE_DIM : STATE_DIM + ACTION_DIM]]
        b1 = b1 - w1_state @ mean
        if model.grasp_input:
            w1_grasp = w1[:, STATE_DIM + ACTION_DIM :] / std
            parts.append(w1_grasp)
            b1 = b1 - w1_grasp @ mean
        w1_f = torch.zeros(hidden + 1, sum(p.shape[1] for p in parts) + 1, **f64)
        w1_f[:hidden] = torch.cat([*parts, b1[:, None]], dim=1) / LN2
        w2, b2 = l2.weight.to(**f64), l2.bias.to(**f64)
        b2_f = 2.0 * (b2 - SELU_SCALE * SELU_ALPHA * w2.sum(1))
        w2_f = torch.cat([2.0 * SELU_SCALE * LN2 * w2, b2_f[:, None] / CARRIER], dim=1)
        w3, b3 = l3.weight.to(**f64), l3.bias.to(**f64)
        w3_f = 2.0 * w3 * d_std[:, None]
        b3_f = (b3 - w3.sum(1)) * d_std + d_mean

    def out(t: Tensor) -> Tensor:
        return t.to(dtype).contiguous()

    return FusedWeights(out(w1_f.T), out(w2_f.T), out(w3_f.T), out(b3_f), model.grasp_input)


class FusedRollout:
    """``model.rollout`` for the paper's MLP, fast; built per planning call, so it sees current weights."""

    def __init__(self, model: TransitionModel) -> None:
        self.weights = fuse(model)

    def __call__(self, x0: Tensor, actions: Tensor) -> Tensor:
        """``states[B, T + 1, 4]``, as ``model.rollout``."""
        return self.time_major(x0, actions).transpose(0, 1)

    @torch.inference_mode()
    def time_major(self, x0: Tensor, actions: Tensor) -> Tensor:
        """``states[T + 1, B, 4]``, contiguous."""
        w = self.weights
        dtype, hidden = w.w1.dtype, w.w2.shape[1]
        batch, horizon = actions.shape[:2]
        x0, actions = x0.to(dtype), actions.to(dtype)
        states = torch.empty(horizon + 1, batch, STATE_DIM, dtype=dtype)
        states[0] = x0
        inputs = torch.ones(batch, w.w1.shape[0], dtype=dtype)  # state, action, [grasp,] 1
        if w.grasp_input:
            inputs[:, STATE_DIM + ACTION_DIM : -1] = x0
        h1, negative = (torch.empty(batch, hidden + 1, dtype=dtype) for _ in range(2))
        h2 = torch.empty(batch, hidden, dtype=dtype)
        delta = torch.empty(batch, STATE_DIM, dtype=dtype)
        # Views made once: per-step indexing would cost as much as the small kernels.
        step_states, step_actions = states.unbind(0), actions.unbind(1)
        input_state, input_action = inputs[:, :STATE_DIM], inputs[:, STATE_DIM : STATE_DIM + ACTION_DIM]
        for t in range(horizon):
            input_state.copy_(step_states[t])
            input_action.copy_(step_actions[t])
            torch.mm(inputs, w.w1, out=h1)
            torch.clamp_max(h1, 0.0, out=negative)
            negative.exp2_()
            h1.clamp_min_(0.0).add_(negative, alpha=CARRIER)  # column H: 0 -> CARRIER
            torch.mm(h1, w.w2, out=h2)
            h2.sigmoid_()
            # The change first, then the add: accumulating the products onto the
            # state (~100 mm) inside addmm would round each at the state's scale.
            torch.addmm(w.b3, h2, w.w3, out=delta)
            torch.add(step_states[t], delta, out=step_states[t + 1])
        return states


def make_rollout(model: LatentDynamics, fast: bool = True) -> TimeMajorRollout:
    """The fused path when ``fast`` and ``model`` is the paper's MLP, else the contract's ``model.rollout``."""
    if fast and is_paper_mlp(model):
        return FusedRollout(model).time_major
    return lambda x0, actions: model.rollout(x0, actions).transpose(0, 1)
