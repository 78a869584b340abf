"""Training loops: single-step regression, and the shared loop (:func:`fit`) that trajectory fine-tuning
(:mod:`t42_transfer.transfer.methods`) also runs.

Both index tensors directly (no DataLoader: it costs 1.5-2.4x here), are seeded,
report each epoch to an optional progress hook, and keep the weights of the best
validation epoch when a validation set is given (early stopping).

Progress has one mechanism: a :data:`ProgressHook` called with a
:class:`Progress` after every epoch.  Long work (a transfer behind a ROS
service, an experiment's source model) passes a hook that forwards it to where
it is watched; :class:`ProgressBar` is the hook for a terminal.
"""

from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from t42_transfer.config import MAX_EVAL_STEPS, NON_NEGATIVE, POSITIVE, SEED, STEPS, Rule, between, check
from t42_transfer.data.trajectory import TrajectorySet, split_by_fraction
from t42_transfer.models.network import Normalisation, TransitionModel

if TYPE_CHECKING:
    from tqdm import tqdm

LOAD_LOSS_WEIGHT = 0.1
"""The authors' trajectory loss weighs loads 0.1 against positions 1.0."""


def import_optimizer_machinery() -> None:
    """Import what torch's first optimizer imports (``torch._dynamo``, from ``Optimizer.__init__``): measured 1.1 s
    on a quiet machine, inside the first transfer of a process; a server calls this while it waits for work."""
    import torch._dynamo  # noqa: F401


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser settings.  The defaults train a model from scratch: weight decay, batch size and the gradient clip
    are the authors'; the learning rate, epochs and early stopping are ours (docs/transfer_methods.md)."""

    lr: float = 1e-3
    epochs: int = 100
    batch_size: int = 64
    weight_decay: float = 1e-3
    grad_clip: float = 10.0
    patience: int | None = 10
    """Stop after this many epochs without validation improvement (None: run all epochs)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check(self, TRAIN_RULES)  # here, so file, server and code configs keep the same ranges


TRAIN_RULES: dict[str, Rule] = {
    "lr": POSITIVE, "epochs": STEPS, "batch_size": between(1, 2**31 - 1), "weight_decay": NON_NEGATIVE,
    "grad_clip": POSITIVE, "patience": between(0, MAX_EVAL_STEPS), "seed": SEED,
}
"""What each :class:`TrainConfig` setting must be beyond its type."""


@dataclass
class TrainReport:
    epochs_run: int = 0
    best_epoch: int = -1
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    seconds: float = 0.0
    samples_per_s: float = 0.0
    validation: str = ""
    """What early stopping validated on, or why it had nothing (see :func:`validation_split`)."""


@dataclass(frozen=True)
class Progress:
    """One finished epoch of one training phase, as reported to a :data:`ProgressHook`."""

    phase: str
    """What is being trained (e.g. "source model", "residual"): a transfer reports its phases by this name."""
    epoch: int
    """Epochs done in this phase, from 1; early stopping can end a phase before ``epochs``."""
    epochs: int
    """The phase's epoch budget."""
    train_loss: float
    """Mean minibatch loss of this epoch (penalty included)."""
    val_loss: float | None
    """Validation loss after this epoch; None when the phase has no validation set."""


ProgressHook = Callable[[Progress], None]
"""Called after every training epoch; the only way training reports where it is."""


class ProgressBar:
    """A :data:`ProgressHook` drawing a tqdm bar per phase (the terminal view of the same reports).

    A bar closes at its phase's last budgeted epoch, when the next phase starts,
    or when the hook is dropped (tqdm closes a bar it deletes), which covers a
    phase ended early by early stopping.
    """

    def __init__(self) -> None:
        self._bar: tqdm | None = None

    def __call__(self, progress: Progress) -> None:
        from t42_transfer.progress import progress_bar

        if self._bar is None or progress.epoch == 1:
            self._close()
            self._bar = progress_bar(total=progress.epochs, desc=progress.phase, unit="ep", leave=False)
        val = "-" if progress.val_loss is None else f"{progress.val_loss:.4f}"
        self._bar.set_postfix(train=f"{progress.train_loss:.4f}", val=val)
        self._bar.update()
        if progress.epoch >= progress.epochs:
            self._close()

    def _close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


@dataclass(frozen=True)
class StepBatch:
    """Single-step training tensors: the network's (normalised) inputs and its targets."""

    features: Tensor
    target: Tensor

    def __len__(self) -> int:
        return len(self.features)


Reference = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``reference(x, a, start)``: a prediction of ``x'`` from state, action and the episode's first state."""


def step_batch(model: TransitionModel, data: TrajectorySet, reference: Reference | None = None) -> StepBatch:
    """Every transition of ``data`` as ``model``'s inputs and normalised targets ``x' - reference(x, a, start)``.

    Built once per training run: the normalisation is fixed while training, so
    the per-batch work is one gather and the network.
    """
    if not data.num_transitions:
        raise ValueError("no transitions to train on")
    x, a, x_next, grasp = (torch.from_numpy(v) for v in (*data.transitions(), data.start_states()))
    with torch.no_grad():
        base = x if reference is None else reference(x, a, grasp)
        return StepBatch(model.features(x, a, grasp), model.normalise_delta(x_next - base))


def fit(
    params: list[nn.Parameter],
    module: nn.Module,
    loss_on: Callable[[Tensor], Tensor],
    n_train: int,
    val_loss: Callable[[], float] | None,
    cfg: TrainConfig,
    phase: str,
    on_epoch: ProgressHook | None = None,
    penalty: Callable[[], Tensor] | None = None,
) -> TrainReport:
    """The shared loop: shuffled minibatches of indices ``loss_on(idx)``, Adam, clipping, early stop.

    ``on_epoch`` gets a :class:`Progress` named ``phase`` after every epoch run.
    """
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    # fused Adam: at batch 64 the per-parameter optimiser ops were ~45 % of a step (bench/bench_training.py).
    opt = torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    report, best, best_state, waited = TrainReport(), math.inf, None, 0
    start = time.perf_counter()
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
        if on_epoch is not None:
            val = report.val_loss[-1] if val_loss is not None else None
            on_epoch(Progress(phase, epoch + 1, cfg.epochs, report.train_loss[-1], val))
        if cfg.patience is not None and val_loss is not None and waited >= cfg.patience:
            break
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


def trajectory_weights(horizon: int) -> Tensor:
    """Per-step loss weights ``1/i`` for predicted states ``i = 1..horizon`` (Algorithm 1)."""
    return 1.0 / torch.arange(1, horizon + 1, dtype=torch.float32)


MIN_VAL_EPISODES = 3
"""Early stopping needs a validation share of at least this many whole episodes.  With one, that one path's
quirks decide when training stops: on the real hands a validation path with a tracking jump held a source
model at its first epoch.  Three is the fewest where one odd path is outvoted."""

MIN_VAL_TRANSITIONS = 100
"""...and at least this many transitions (10 s of data): a loss over fewer is mostly noise."""


class ValidationWarning(UserWarning):
    """Training runs without early stopping because its validation share would be too small to trust."""


def validation_split(
    data: TrajectorySet, fraction: float, seed: int, phase: str = "training"
) -> tuple[TrajectorySet, TrajectorySet | None]:
    """``(train, validation)``: whole episodes held out for early stopping, if enough.

    The share ``fraction`` of ``data`` (by transitions, at least one episode) must hold MIN_VAL_EPISODES
    episodes and MIN_VAL_TRANSITIONS transitions and leave an episode to train on; otherwise there is
    no validation set, training runs its full epoch budget, and a :class:`ValidationWarning` says why.
    ``fraction`` 0 asks for no validation.
    """
    train, val, _ = _validation(data, fraction, seed, phase)
    return train, val


def _validation(
    data: TrajectorySet, fraction: float, seed: int, phase: str
) -> tuple[TrajectorySet, TrajectorySet | None, str]:
    """:func:`validation_split` and a note saying which it was, for the training report."""
    if fraction <= 0.0:
        return data, None, "none asked for"
    if len(data) > 1:
        val, train = split_by_fraction(data, fraction, seed)
        if len(val) >= MIN_VAL_EPISODES and val.num_transitions >= MIN_VAL_TRANSITIONS and len(train):
            return train, val, f"{len(val)} episodes, {val.num_transitions} transitions"
        held = f"would hold {len(val)} of {len(data)} episodes ({val.num_transitions} transitions)"
    else:
        held = f"cannot be taken from {len(data)} episode{'' if len(data) == 1 else 's'}"
    why = (f"a validation share of {fraction:g} {held}; early stopping needs at least {MIN_VAL_EPISODES} "
           f"episodes and {MIN_VAL_TRANSITIONS} transitions, so {phase} runs its full epoch budget")
    warnings.warn(f"no validation set: {why}", ValidationWarning, stacklevel=3)
    return data, None, f"none: {why}"


def train_transition_model(
    data: TrajectorySet,
    cfg: TrainConfig = TrainConfig(),
    grasp_input: bool = False,
    val_fraction: float = 0.1,
    on_epoch: ProgressHook | None = None,
    phase: str = "train",
) -> tuple[TransitionModel, TrainReport]:
    """A fresh paper MLP fitted single-step to ``data`` (normalisation from the training part)."""
    train, val, note = _validation(data, val_fraction, cfg.seed, phase)
    x, _, x_next = train.transitions()
    torch.manual_seed(cfg.seed)
    model = TransitionModel(Normalisation.from_transitions(x, x_next), grasp_input=grasp_input)
    report = fit_single_step(model, train, val, cfg, on_epoch=on_epoch, phase=phase)
    report.validation = note
    return model, report


def fit_single_step(
    model: TransitionModel,
    train: TrajectorySet,
    val: TrajectorySet | None,
    cfg: TrainConfig,
    on_epoch: ProgressHook | None = None,
    phase: str = "train",
    penalty: Callable[[], Tensor] | None = None,
    reference: Reference | None = None,
) -> TrainReport:
    """Fit ``model``'s normalised output to ``x_next - reference(x, a, start)`` on ``train``, keeping its normalisation.

    The default reference is ``x`` itself (a transition model learns the state
    change); a residual network's reference is the source model's prediction.
    """

    batch = step_batch(model, train, reference)
    val_batch = step_batch(model, val, reference) if val is not None and len(val) else None
    net = model.net
    val_fn = None if val_batch is None else (lambda: float(step_loss(net, val_batch, slice(None))))
    return fit(
        list(net.parameters()), model, lambda idx: step_loss(net, batch, idx), len(batch), val_fn, cfg, phase,
        on_epoch, penalty,
    )
