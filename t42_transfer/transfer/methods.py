"""The transfer methods behind one registry: ``METHODS[name](source, target, config, seed, on_epoch)``.

Every method takes the source model (trained on the full source set), a little
target data and the one :class:`TransferConfig`, and returns a model obeying the
one contract (:class:`LatentDynamics`).  The source model is never modified.
Each training epoch is reported to ``on_epoch`` (see
:class:`~t42_transfer.models.training.Progress`) under a phase name saying what
is trained, so an epoch count reads right whatever the method.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable

import torch
from torch import Tensor

from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.training import (
    ProgressHook,
    TrainConfig,
    fit,
    fit_single_step,
    train_transition_model,
    trajectory_loss,
    trajectory_weights,
    validation_split,
    windows,
)
from t42_transfer.transfer.config import ResidualConfig, TransferConfig
from t42_transfer.models.residual import CumulativeResidualModel, RecurrentResidualModel

Method = Callable[[TransitionModel, TrajectorySet, TransferConfig, int, ProgressHook | None], LatentDynamics]


def _seeded(cfg: TrainConfig, seed: int) -> TrainConfig:
    return dataclasses.replace(cfg, seed=seed)


def _copy_trainable(source: TransitionModel) -> TransitionModel:
    model = copy.deepcopy(source)
    for p in model.parameters():
        p.requires_grad_(True)
    return model


def new_model(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """A fresh model trained on the target data alone (the source is ignored)."""
    c = cfg.new_model
    model, _ = train_transition_model(
        target, _seeded(c.train, seed), grasp_input=source.grasp_input, val_fraction=c.val_fraction,
        on_epoch=on_epoch, phase="new model",
    )
    return model


def direct(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """The source model unchanged."""
    return copy.deepcopy(source)


def naive_finetune(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """Single-step training of a copy of the source on target data, source normalisation kept."""
    model = _copy_trainable(source)
    fit_single_step(model, target, None, _seeded(cfg.naive_finetune.train, seed), on_epoch=on_epoch, phase="naive fine-tune")
    return model


def l2_finetune(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """Single-step fine-tuning with an L2 pull toward the source weights."""
    model = _copy_trainable(source)
    anchors = [p.detach().clone() for p in source.net.parameters()]
    params = list(model.net.parameters())
    strength = cfg.l2_finetune.l2

    def penalty() -> Tensor:
        return strength * sum(((p - q) ** 2).sum() for p, q in zip(params, anchors))

    fit_single_step(
        model, target, None, _seeded(cfg.l2_finetune.train, seed), on_epoch=on_epoch, phase="L2 fine-tune", penalty=penalty
    )
    return model


def trajectory_finetune(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """Algorithm 1: fine-tune on open-loop rollouts of target windows, loss weighted 1/i."""
    c = cfg.trajectory_finetune
    model = _copy_trainable(source)
    shortest = min(len(t) for t in target)
    horizon = min(c.horizon, shortest)
    batch = windows(target, horizon, stride=min(c.stride, horizon))
    weights = trajectory_weights(horizon)
    cutoff = c.cutoff_mm2

    def loss_on(idx: Tensor) -> Tensor:
        true = batch.x[idx]
        predicted = model.rollout_with_grad(true[:, 0], batch.a[idx])
        xy_err = ((predicted[:, 1:, :2] - true[:, 1:, :2]) ** 2).sum(-1).detach()
        # Once a rollout is this far off, later steps only teach noise: leave them out.
        keep = (torch.cumsum((xy_err > cutoff).float(), dim=1) == 0).float()
        return trajectory_loss(predicted, true, model.state_std, weights * keep)

    fit(list(model.net.parameters()), model, loss_on, len(batch), None, _seeded(c.train, seed), "trajectory fine-tune", on_epoch)
    return model


def _residual_net(
    source: TransitionModel, target: TrajectorySet, c: ResidualConfig, seed: int, on_epoch: ProgressHook | None
) -> TransitionModel:
    """g fitted single-step to the source model's one-step error on the target data."""

    @torch.no_grad()
    def source_prediction(x: Tensor, a: Tensor) -> Tensor:
        source.eval()
        return source.observe(source.latent_step(source.initial_latent(x), a))

    x, a, x_next = (torch.from_numpy(v) for v in target.transitions())
    residual = (x_next - source_prediction(x, a)).numpy()
    norm = Normalisation.from_transitions(x.numpy(), x.numpy() + residual)
    torch.manual_seed(seed)
    g = TransitionModel(norm)
    train, val = validation_split(target, c.val_fraction, seed)
    fit_single_step(g, train, val, _seeded(c.train, seed), on_epoch=on_epoch, phase="residual", reference=source_prediction)
    return g


def cumulative_residual(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """Algorithm 2: frozen source plus a discounted running sum of residuals."""
    c = cfg.cumulative_residual
    g = _residual_net(source, target, c, seed, on_epoch)
    return CumulativeResidualModel(copy.deepcopy(source), g, c.alpha, c.gamma).eval()


def recurrent_residual(source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None) -> LatentDynamics:
    """The same residual network, fed back inside the loop."""
    c = cfg.recurrent_residual
    g = _residual_net(source, target, c, seed, on_epoch)
    return RecurrentResidualModel(copy.deepcopy(source), g, c.alpha).eval()


METHODS: dict[str, Method] = {
    "new_model": new_model,
    "direct": direct,
    "naive_finetune": naive_finetune,
    "trajectory_finetune": trajectory_finetune,
    "cumulative_residual": cumulative_residual,
    "recurrent_residual": recurrent_residual,
    "l2_finetune": l2_finetune,
}
"""The paper's six methods, in its order, then the authors' L2-constrained fine-tuning."""

PAPER_METHODS = tuple(list(METHODS)[:6])


def transfer(
    method: str, source: TransitionModel, target: TrajectorySet, cfg: TransferConfig = TransferConfig(), seed: int = 0,
    on_epoch: ProgressHook | None = None,
) -> LatentDynamics:
    """Run ``method``, reporting its training epochs to ``on_epoch``; unknown names and empty target data are refused."""
    if method not in METHODS:
        raise ValueError(f"unknown transfer method {method!r}; expected one of {sorted(METHODS)}")
    if len(target) == 0 or target.num_transitions < 2:
        raise ValueError(f"{method} needs target data; got {target.num_transitions} transitions")
    model = METHODS[method](source, target, cfg, seed, on_epoch)
    return model.eval()
