"""Training loops: single-step regression and open-loop trajectory fitting.

Both index tensors directly (no DataLoader: it costs 1.5-2.4x here), are seeded,
show a progress bar, and keep the weights of the best validation epoch when a
validation set is given (early stopping).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from t42_transfer.data.trajectory import TrajectorySet, split_by_fraction
from t42_transfer.models.network import Normalisation, TransitionModel

# The authors' trajectory loss weighs loads 0.1 against positions 1.0.
LOAD_LOSS_WEIGHT = 0.1


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser settings; defaults are the authors' single-step settings."""

    lr: float = 1e-3
    epochs: int = 100
    batch_size: int = 64
    weight_decay: float = 1e-3
    grad_clip: float = 10.0
    patience: int | None = 10
    """Stop after this many epochs without validation improvement (None: run all epochs)."""
    seed: int = 0


@dataclass
class TrainReport:
    epochs_run: int = 0
    best_epoch: int = -1
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    seconds: float = 0.0
    samples_per_s: float = 0.0


@dataclass(frozen=True)
class StepBatch:
    """Single-step training tensors: the network's (normalised) inputs and its targets."""

    features: Tensor
    target: Tensor

    def __len__(self) -> int:
        return len(self.features)


def step_batch(model: TransitionModel, data: TrajectorySet, reference: Callable[[Tensor, Tensor], Tensor] | None = None) -> StepBatch:
    """Every transition of ``data`` as ``model``'s inputs and normalised targets ``x' - reference(x, a)``.

    Built once per training run: the normalisation is fixed while training, so
    the per-batch work is one gather and the network.
    """
    xs, acts, nexts, grasps = [], [], [], []
    for traj in data:
        x, a, x_next = traj.transitions()
        xs.append(x)
        acts.append(a)
        nexts.append(x_next)
        grasps.append(np.repeat(traj.states[:1], len(x), axis=0))
    if not xs:
        raise ValueError("no transitions to train on")
    x, a, x_next, grasp = (torch.from_numpy(np.concatenate(p)) for p in (xs, acts, nexts, grasps))
    with torch.no_grad():
        base = x if reference is None else reference(x, a)
        return StepBatch(model.features(x, a, grasp), model.normalise_delta(x_next - base))


def _progress(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="ep", disable=not enabled, leave=False)


def fit(
    params: list[nn.Parameter],
    module: nn.Module,
    loss_on: Callable[[Tensor], Tensor],
    n_train: int,
    val_loss: Callable[[], float] | None,
    cfg: TrainConfig,
    desc: str,
    progress: bool,
    penalty: Callable[[], Tensor] | None = None,
) -> TrainReport:
    """The shared loop: shuffled minibatches of indices ``loss_on(idx)``, Adam, clipping, early stop."""
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    # fused Adam: at batch 64 the per-parameter optimiser ops were ~45 % of a step (bench/bench_training.py).
    opt = torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    report, best, best_state, waited = TrainReport(), math.inf, None, 0
    start = time.perf_counter()
    bar = _progress(cfg.epochs, desc, progress)
    for epoch in range(cfg.epochs):
        module.train()
        order = torch.randperm(n_train, generator=gen)
        total, batches = 0.0, 0
        for i in range(0, n_train, cfg.batch_size):
            loss = loss_on(order[i : i + cfg.batch_size])
            if penalty is not None:
                loss = loss + penalty()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(params, cfg.grad_clip, foreach=True)
            opt.step()
            total += loss.item()
            batches += 1
        report.train_loss.append(total / max(1, batches))
        report.epochs_run = epoch + 1
        if val_loss is not None:
            module.eval()
            with torch.no_grad():
                current = val_loss()
            report.val_loss.append(current)
            if current < best:
                best, best_state, waited, report.best_epoch = current, copy.deepcopy(module.state_dict()), 0, epoch
            else:
                waited += 1
        bar.set_postfix(train=f"{report.train_loss[-1]:.4f}", val=f"{report.val_loss[-1]:.4f}" if report.val_loss else "-")
        bar.update()
        if cfg.patience is not None and val_loss is not None and waited >= cfg.patience:
            break
    bar.close()
    if best_state is not None:
        module.load_state_dict(best_state)
    else:
        report.best_epoch = report.epochs_run - 1
    module.eval()
    report.seconds = time.perf_counter() - start
    report.samples_per_s = report.epochs_run * n_train / max(report.seconds, 1e-9)
    return report


def step_loss(net: nn.Module, batch: StepBatch, idx: Tensor | slice) -> Tensor:
    """MSE between the network's output and the normalised target on rows ``idx``."""
    return torch.mean((net(batch.features[idx]) - batch.target[idx]) ** 2)


@dataclass(frozen=True)
class WindowBatch:
    """Equal-length windows of target episodes for trajectory training: ``x[N, H+1, 4]``, ``a[N, H, 2]``."""

    x: Tensor
    a: Tensor

    def __len__(self) -> int:
        return len(self.x)


def windows(data: TrajectorySet, horizon: int, stride: int | None = None) -> WindowBatch:
    """Cut every episode into windows of ``horizon`` steps (the last window ends at the episode's end)."""
    stride = stride or horizon
    xs, acts = [], []
    for traj in data:
        n = len(traj)
        if n < horizon:
            continue
        starts = list(range(0, n - horizon + 1, stride))
        if starts[-1] != n - horizon:
            starts.append(n - horizon)
        for s in starts:
            xs.append(traj.states[s : s + horizon + 1])
            acts.append(traj.actions[s : s + horizon])
    if not xs:
        raise ValueError(f"no episode is at least {horizon} steps long")
    return WindowBatch(torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(acts)))


def trajectory_weights(horizon: int) -> Tensor:
    """Per-step loss weights ``1/i`` for predicted states ``i = 1..horizon`` (Algorithm 1)."""
    return 1.0 / torch.arange(1, horizon + 1, dtype=torch.float32)


def trajectory_loss(predicted: Tensor, true: Tensor, state_std: Tensor, weights: Tensor) -> Tensor:
    """Sum over steps of ``w_i * (MSE(x, y) + 0.1 MSE(loads))`` in normalised units, averaged over the batch."""
    err = ((predicted[:, 1:] - true[:, 1:]) / state_std) ** 2
    per_step = err[..., :2].mean(-1) + LOAD_LOSS_WEIGHT * err[..., 2:].mean(-1)
    return (per_step * weights).sum(-1).mean()


def validation_split(data: TrajectorySet, fraction: float, seed: int, min_episodes: int = 5) -> tuple[TrajectorySet, TrajectorySet | None]:
    """Hold out whole episodes for early stopping; too few episodes means no validation set."""
    if len(data) < min_episodes or fraction <= 0.0:
        return data, None
    val, train = split_by_fraction(data, fraction, seed)
    return train, val


def train_transition_model(
    data: TrajectorySet,
    cfg: TrainConfig = TrainConfig(),
    grasp_input: bool = False,
    val_fraction: float = 0.1,
    progress: bool = True,
    desc: str = "train",
) -> tuple[TransitionModel, TrainReport]:
    """A fresh paper MLP fitted single-step to ``data`` (normalisation from the training part)."""
    train, val = validation_split(data, val_fraction, cfg.seed)
    x, _, x_next = train.transitions()
    torch.manual_seed(cfg.seed)
    model = TransitionModel(Normalisation.from_transitions(x, x_next), grasp_input=grasp_input)
    report = fit_single_step(model, train, val, cfg, progress=progress, desc=desc)
    return model, report


def fit_single_step(
    model: TransitionModel,
    train: TrajectorySet,
    val: TrajectorySet | None,
    cfg: TrainConfig,
    progress: bool = True,
    desc: str = "train",
    penalty: Callable[[], Tensor] | None = None,
    reference: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> TrainReport:
    """Fit ``model``'s normalised output to ``x_next - reference(x, a)`` on ``train``, keeping its normalisation.

    The default reference is ``x`` itself (a transition model learns the state
    change); a residual network's reference is the source model's prediction.
    """

    batch = step_batch(model, train, reference)
    val_batch = step_batch(model, val, reference) if val is not None and len(val) else None
    net = model.net
    val_fn = None if val_batch is None else (lambda: float(step_loss(net, val_batch, slice(None))))
    return fit(
        list(net.parameters()), model, lambda idx: step_loss(net, batch, idx), len(batch), val_fn, cfg, desc,
        progress, penalty,
    )
