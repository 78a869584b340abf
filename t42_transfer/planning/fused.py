"""The planner's fast rollout of the paper's MLP: every constant folded into the matrices.

``model.rollout`` is right for every model kind but spends most of a planning
call outside the matrix products: normalising, concatenating, SELU and tanh
kernels, broadcasting biases, and allocating each step's tensors.  For a plain
:class:`~t42_transfer.models.network.TransitionModel` all of that folds away:

- input normalisation ``(x - m) / s`` goes into the first layer (``W1 / s``,
  ``b1 - W1 m / s``), and the grasp input (constant per sample) four more input columns;
- ``selu(u) = scale * (relu(u) + alpha * (min(exp(u), 1) - 1))``: ``scale`` and
  ``- alpha`` go into the second layer, leaving four passes, one of them the
  exponential (eager ``torch.selu`` costs about twice that here).  The first layer is divided by
  ln 2 so that the exponential is ``exp2`` (``u = v ln 2``: ``relu(u) = ln 2 relu(v)``,
  ``exp(u) = exp2(v)``, ln 2 going into the second layer): torch's ``exp2_`` took
  52 us on a [1000, 129] block (the earlier layout's) where ``exp_`` took 138 (one
  thread, AVX-512);
- ``tanh(v) = 2 sigmoid(2 v) - 1``: the 2s go into the second layer and the
  third, leaving one in-place sigmoid.  The reference AMD Zen 4 machines run
  eager tanh ~3x slower than sigmoid; on this project's Intel hosts tanh_ wins on
  unit-normal inputs but lost in the full loop (its cost depends on the inputs);
- output de-normalisation ``d * s_d + m_d`` goes into the third layer, computed
  transposed, ``W3 @ h2.T`` [4, B]: MKL took 141 us for ``h2 @ W3.T`` at B = 1000
  (4 outputs) and 29 us for the transposed product (2026-12-05, AMD EPYC, one thread).

The network's inputs for every step live in one buffer ``[T + 1, B, I]``: the
actions are written into it once, and each step's new state straight into the
next step's row, so no step copies its inputs.  Each step is then three
``addmm`` and the activations' passes, in inference mode.  oneDNN's linear with
the sigmoid inside the product (``torch.ops.mkldnn._linear_pointwise``) was
tried: at B = 1000 it takes 365 us against 383 for ``addmm`` and a sigmoid, but
at B = 30, the planner's refinement batches, 32 us against 15, and a step there
took 1.6 times as long (``bench/bench_planner.py`` measures each product's
forms as ``matmul_forms``).  Equal to ``model.rollout`` up to float rounding
(the tests check 1e-4); dropout is off, as in ``rollout``.
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
NEGATIVE_BRANCH = SELU_ALPHA / LN2
"""The weight of ``min(exp2(v), 1)`` beside ``relu(v)`` in the first hidden layer, in ln 2 units."""
_LAYOUT = (nn.Linear, nn.SELU, nn.AlphaDropout, nn.Linear, nn.Tanh, nn.Dropout, nn.Linear)


def is_paper_mlp(model: LatentDynamics) -> bool:
    """Whether ``model`` is a TransitionModel with exactly the paper's layer layout (what :func:`fuse` folds)."""
    if type(model) is not TransitionModel:
        return False
    layers = list(model.net)
    return len(layers) == len(_LAYOUT) and all(type(layer) is kind for layer, kind in zip(layers, _LAYOUT, strict=True))


@dataclass(frozen=True)
class FusedWeights:
    """Folded weights and biases of the three layers, each stored as its product takes it."""

    w1: Tensor
    """``[I, H]``, ``[in, out]``, divided by ln 2: rows for the raw state (4), the action (2), then the raw
    grasp state (4, with grasp input)."""
    b1: Tensor
    w2: Tensor
    """``[H, H]``, ``[in, out]``."""
    b2: Tensor
    w3: Tensor
    """``[4, H]``, ``[out, in]``, for MKL's ``W3 @ h2.T``."""
    b3: Tensor
    """``[4, 1]``: a column, as that product's output is ``[4, B]``."""
    grasp_input: bool


def fuse(model: TransitionModel) -> FusedWeights:
    """Fold ``model``'s normalisation and activation constants into its layers (computed in float64)."""
    if not is_paper_mlp(model):
        raise TypeError(f"cannot fuse a {type(model).__name__} that is not the paper's MLP")
    l1, l2, l3 = (model.net[i] for i in (0, 3, 6))
    dtype = l1.weight.dtype
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
        w1_f, b1_f = torch.cat(parts, dim=1).T / LN2, b1 / LN2
        w2, b2 = l2.weight.to(**f64), l2.bias.to(**f64)
        w2_f = (2.0 * SELU_SCALE * LN2 * w2).T
        b2_f = 2.0 * (b2 - SELU_SCALE * SELU_ALPHA * w2.sum(1))
        w3, b3 = l3.weight.to(**f64), l3.bias.to(**f64)
        w3_f = 2.0 * w3 * d_std[:, None]
        b3_f = (b3 - w3.sum(1)) * d_std + d_mean

    def out(t: Tensor) -> Tensor:
        return t.to(dtype).contiguous()

    return FusedWeights(out(w1_f), out(b1_f), out(w2_f), out(b2_f), out(w3_f), out(b3_f[:, None]), model.grasp_input)


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
        dtype, hidden = w.w1.dtype, w.w1.shape[1]
        batch, horizon = actions.shape[:2]
        x0, actions = x0.to(dtype), actions.to(dtype)
        inputs = torch.empty(horizon + 1, batch, w.w1.shape[0], dtype=dtype)  # state, action[, grasp] per step
        inputs[0, :, :STATE_DIM] = x0
        inputs[:horizon, :, STATE_DIM : STATE_DIM + ACTION_DIM] = actions.transpose(0, 1)
        if w.grasp_input:
            inputs[:, :, STATE_DIM + ACTION_DIM :] = x0
        h1, exponential, h2 = (torch.empty(batch, hidden, dtype=dtype) for _ in range(3))
        delta = torch.empty(STATE_DIM, batch, dtype=dtype)
        # Views made once: per-step indexing would cost as much as the small kernels.
        step_inputs = inputs.unbind(0)
        step_states = [step[:, :STATE_DIM] for step in step_inputs]
        for t in range(horizon):
            torch.addmm(w.b1, step_inputs[t], w.w1, out=h1)
            torch.exp2(h1, out=exponential).clamp_max_(1.0)
            h1.clamp_min_(0.0).add_(exponential, alpha=NEGATIVE_BRANCH)
            torch.addmm(w.b2, h1, w.w2, out=h2).sigmoid_()
            # The change first, then the add: accumulating the products onto the
            # state (~100 mm) inside the product would round each at the state's scale.
            torch.addmm(w.b3, w.w3, h2.T, out=delta)
            torch.add(step_states[t], delta.T, out=step_states[t + 1])
        return inputs[:, :, :STATE_DIM].contiguous()

def make_rollout(model: LatentDynamics, fast: bool = True) -> TimeMajorRollout:
    """The fused path when ``fast`` and ``model`` is the paper's MLP, else the contract's ``model.rollout``."""
    if fast and is_paper_mlp(model):
        return FusedRollout(model).time_major
    return lambda x0, actions: model.rollout(x0, actions).transpose(0, 1)
