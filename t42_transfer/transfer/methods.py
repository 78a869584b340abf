"""The transfer methods behind one registry: ``METHODS[name](source, target, config, seed, on_epoch)``.

Every method takes the source model (trained on the full source set), a little
target data and the one :class:`TransferConfig`, and returns a model obeying the
one contract (:class:`LatentDynamics`).  The source model's weights are never modified (the residual
models hold it, in evaluation mode).
Each training epoch is reported to ``on_epoch`` (see
:class:`~t42_transfer.models.training.Progress`) under a phase name saying what
is trained, so an epoch count reads right whatever the method.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from t42_transfer.conventions import ACTION_DIM, STATE_DIM
from t42_transfer.data.trajectory import TrajectorySet, split_by_fraction
from t42_transfer.evaluation.metrics import evaluate_model
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.residual import AdjustedStateResidualModel, CumulativeResidualModel, RecurrentResidualModel
from t42_transfer.models.training import (
    LOAD_LOSS_WEIGHT,
    ProgressHook,
    Reference,
    StepBatch,
    TrainConfig,
    fit,
    fit_single_step,
    step_batch,
    step_loss,
    train_transition_model,
    trajectory_weights,
    validation_split,
)
from t42_transfer.transfer.config import ResidualConfig, TransferConfig

Method = Callable[[TransitionModel, TrajectorySet, TransferConfig, int, ProgressHook | None], LatentDynamics]


def _seeded(cfg: TrainConfig, seed: int) -> TrainConfig:
    return dataclasses.replace(cfg, seed=seed)


def _copy_trainable(source: TransitionModel) -> TransitionModel:
    model = copy.deepcopy(source)
    for p in model.parameters():
        p.requires_grad_(True)
    return model


def new_model(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """A fresh model trained on the target data alone (the source is ignored)."""
    c = cfg.new_model
    model, _ = train_transition_model(
        target, _seeded(c.train, seed), grasp_input=source.grasp_input, val_fraction=c.val_fraction,
        on_epoch=on_epoch, phase="new model",
    )
    return model


def direct(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """The source model unchanged."""
    return copy.deepcopy(source)


def naive_finetune(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """Single-step training of a copy of the source on target data, source normalisation kept."""
    model = _copy_trainable(source)
    fit_single_step(model, target, None, _seeded(cfg.naive_finetune.train, seed), on_epoch=on_epoch,
                    phase="naive fine-tune")
    return model


def _pull_toward(source: TransitionModel, model: TransitionModel, strength: float) -> Callable[[], Tensor]:
    """``strength * |theta - theta_source|^2`` over the network's weights."""
    anchors = [p.detach().clone() for p in source.net.parameters()]
    params = list(model.net.parameters())

    def penalty() -> Tensor:
        return strength * sum(((p - q) ** 2).sum() for p, q in zip(params, anchors, strict=True))

    return penalty


def l2_finetune(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """Single-step fine-tuning with an L2 pull toward the source weights."""
    model = _copy_trainable(source)
    fit_single_step(
        model, target, None, _seeded(cfg.l2_finetune.train, seed), on_epoch=on_epoch, phase="L2 fine-tune",
        penalty=_pull_toward(source, model, cfg.l2_finetune.l2),
    )
    return model


def multistep_l2_finetune(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """L2 fine-tuning on ``horizon``-step open-loop rollouts from every window of the target episodes.

    Each window starts from its recorded state (with the episode's grasp state, for a model that reads it) and
    follows the recorded actions; the loss is the mean squared state error over its steps in units of the
    source's change std (:class:`~t42_transfer.transfer.config.MultiStepL2Config`).
    """
    c = cfg.multistep_l2_finetune
    model = _copy_trainable(source)
    episodes = [(torch.from_numpy(t.states.copy()), torch.from_numpy(t.actions.copy())) for t in target
                if len(t) >= c.horizon]
    if not episodes:
        raise ValueError(f"multistep_l2_finetune needs an episode of at least {c.horizon} steps; the longest has "
                         f"{max((len(t) for t in target), default=0)}")
    windows = torch.tensor([(e, start) for e, (_, actions) in enumerate(episodes)
                            for start in range(len(actions) - c.horizon + 1)])
    scale = model.delta_std

    def loss_on(idx: Tensor) -> Tensor:
        picked = windows[idx].tolist()
        true = torch.stack([episodes[e][0][s : s + c.horizon + 1] for e, s in picked])
        actions = torch.stack([episodes[e][1][s : s + c.horizon] for e, s in picked])
        z = model.episode_latent(true[:, 0], torch.stack([episodes[e][0][0] for e, _ in picked]))
        errors = []
        for k in range(c.horizon):
            z = model.latent_step(z, actions[:, k])
            errors.append((model.observe(z) - true[:, k + 1]) / scale)
        return torch.stack(errors, dim=1).pow(2).mean()

    fit(list(model.net.parameters()), model, loss_on, len(windows), None, _seeded(c.train, seed),
        "multi-step L2 fine-tune", on_epoch, penalty=_pull_toward(source, model, c.l2))
    return model


def anchored_finetune(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """Single-step fine-tuning plus a pull toward the frozen source's outputs at points off the target data
    (:class:`~t42_transfer.transfer.config.AnchoredFineTuneConfig`)."""
    c = cfg.anchored_finetune
    model = _copy_trainable(source)
    batch = step_batch(model, target)
    frozen = copy.deepcopy(source.net).eval().requires_grad_(False)
    actions = batch.features[:, STATE_DIM : STATE_DIM + ACTION_DIM]
    low, span = actions.min(0).values, actions.max(0).values - actions.min(0).values
    draws = torch.Generator().manual_seed(seed)

    def loss_on(idx: Tensor) -> Tensor:
        if not c.anchor:  # no off-data points drawn: the network's dropout draws stay naive fine-tuning's
            return step_loss(model.net, batch, idx)
        off = batch.features[idx].clone()
        off[:, :STATE_DIM] += c.state_noise * torch.randn(len(idx), STATE_DIM, generator=draws)
        off[:, STATE_DIM : STATE_DIM + ACTION_DIM] = low + span * torch.rand(len(idx), ACTION_DIM, generator=draws)
        with torch.no_grad():
            reference = frozen(off)
        pull = torch.mean((model.net(off) - reference) ** 2)
        return step_loss(model.net, batch, idx) + c.anchor * pull

    fit(list(model.net.parameters()), model, loss_on, len(batch), None, _seeded(c.train, seed),
        "anchored fine-tune", on_epoch)
    return model


def trajectory_finetune(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """Algorithm 1: fine-tune on open-loop rollouts of whole target episodes from their first true state.

    One episode per update is the algorithm as the paper writes it; a batch of
    several is cropped to its shortest episode at random start offsets (the
    authors' batching; offsets drawn from a generator seeded with ``seed``).
    """
    c = cfg.trajectory_finetune
    model = _copy_trainable(source)
    episodes = [(torch.from_numpy(t.states.copy()), torch.from_numpy(t.actions.copy())) for t in target if len(t)]
    offsets = torch.Generator().manual_seed(seed)

    def loss_on(idx: Tensor) -> Tensor:
        picked = [episodes[i] for i in idx.tolist()]
        length = min(len(actions) for _, actions in picked)
        starts = [int(torch.randint(0, len(a) - length + 1, (1,), generator=offsets)) for _, a in picked]
        true = torch.stack([x[s : s + length + 1] for (x, _), s in zip(picked, starts, strict=True)])
        actions = torch.stack([a[s : s + length] for (_, a), s in zip(picked, starts, strict=True)])
        firsts = torch.stack([x[0] for x, _ in picked])  # a crop is still within its episode (the grasp input)
        predicted = rollout_until(model, true, actions, c.cutoff_mm2, firsts)
        return trajectory_loss(predicted, true[:, : predicted.shape[1]], model.state_std, c.loss)

    fit(list(model.net.parameters()), model, loss_on, len(episodes), None, _seeded(c.train, seed),
        "trajectory fine-tune", on_epoch)
    return model


def rollout_until(model: LatentDynamics, true: Tensor, actions: Tensor, cutoff_mm2: float | None,
                  starts: Tensor | None = None) -> Tensor:
    """Open-loop rollout ``[B, n + 1, 4]`` from ``true[:, 0]``, with gradients, stopped for the whole batch
    before the first step ``k >= 2`` whose batch-mean per-coordinate x,y squared error passes ``cutoff_mm2``.
    ``starts``: the episodes' first states, when ``true`` is cropped from within them (default ``true[:, 0]``).

    The authors' rule (TrajNet.run_traj with threshold 150); the first step is always kept.
    """
    z = model.episode_latent(true[:, 0], true[:, 0] if starts is None else starts)
    states = [model.observe(z)]
    for k in range(actions.shape[1]):
        z = model.latent_step(z, actions[:, k])
        x = model.observe(z)
        if cutoff_mm2 is not None and k >= 1:
            with torch.no_grad():
                if float(((x[:, :2] - true[:, k + 1, :2]) ** 2).mean()) > cutoff_mm2:
                    break
        states.append(x)
    return torch.stack(states, dim=1)


def trajectory_loss(predicted: Tensor, true: Tensor, state_std: Tensor, definition: str = "paper") -> Tensor:
    """Algorithm 1's loss over steps ``i = 1..n`` of rollouts ``[B, n + 1, 4]``, weighted ``1/i``.

    ``paper``: ``sum_i (1/i) MSE(x_i, x*_i)``, the MSE over the batch and the four
    state coordinates, each divided by ``state_std``.  ``authors`` (utils_clean_traj.py,
    ``pointwise``): raw units; step ``i``'s error is the mean over the batch and the
    (x, load 1), (y, load 2) pairs of ``d_pos^2 + 0.1 d_load^2``; the weighted sum is
    divided by ``n``.
    """
    n = predicted.shape[1] - 1
    weights = trajectory_weights(n).to(predicted.device)
    err = predicted[:, 1:] - true[:, 1:]
    if definition == "paper":
        return ((err / state_std) ** 2).mean(dim=(0, 2)).mul(weights).sum()
    if definition == "authors":
        pairs = err[..., :2] ** 2 + LOAD_LOSS_WEIGHT * err[..., 2:] ** 2
        return pairs.mean(dim=(0, 2)).mul(weights).sum() / n
    raise ValueError(f"trajectory loss must be 'paper' or 'authors', got {definition!r}")


def _source_prediction(source: TransitionModel) -> Reference:
    """The frozen source's one-step prediction within the episode (its start state held), dropout off: as the
    residual model's rollout runs the source, so that g learns the error of the function it is added to."""

    @torch.no_grad()
    def predict(x: Tensor, a: Tensor, start: Tensor) -> Tensor:
        source.eval()
        return source.observe(source.latent_step(source.episode_latent(x, start), a))

    return predict


def _residual_net(
    source: TransitionModel, target: TrajectorySet, c: ResidualConfig, seed: int, on_epoch: ProgressHook | None,
    adjusted_input: bool = False,
) -> TransitionModel:
    """g fitted single-step to the source model's one-step error ``x' - f_S(x, a)`` on the target data.

    ``c.normalisation`` ``source`` scales g like the source (its state normalisation,
    outputs in units of its change std, no mean), so ``f_S + g`` is ``net_S + res`` in
    the source's normalised space.  With ``adjusted_input`` (the paper's recurrent
    residual) g also reads the adjusted state; a single-step sample has only the true
    state, so it fills both inputs (the paper does not say; ours).
    """
    predict = _source_prediction(source)
    if c.normalisation == "source":
        norm = dataclasses.replace(source.norm, delta_mean=np.zeros_like(source.norm.delta_mean))
    else:
        x, a, x_next, start = (torch.from_numpy(v) for v in (*target.transitions(), target.start_states()))
        norm = Normalisation.from_transitions(x.numpy(), x.numpy() + (x_next - predict(x, a, start)).numpy())
    torch.manual_seed(seed)
    g = TransitionModel(norm, grasp_input=adjusted_input)
    train, val = validation_split(target, c.val_fraction, seed)
    train_cfg = _seeded(c.train, seed)
    if not adjusted_input:
        fit_single_step(g, train, val, train_cfg, on_epoch=on_epoch, phase="residual", reference=predict)
        return g

    def batch_of(data: TrajectorySet) -> StepBatch:
        x, a, x_next, start = (torch.from_numpy(v) for v in (*data.transitions(), data.start_states()))
        with torch.no_grad():
            return StepBatch(g.features(x, a, x), g.normalise_delta(x_next - predict(x, a, start)))

    batch = batch_of(train)
    val_batch = batch_of(val) if val is not None and len(val) else None
    val_fn = None if val_batch is None else (lambda: float(step_loss(g.net, val_batch, slice(None))))
    fit(list(g.net.parameters()), g, lambda idx: step_loss(g.net, batch, idx), len(batch), val_fn, train_cfg,
        "residual", on_epoch)
    return g


def _gamma(c: ResidualConfig, source: TransitionModel, target: TrajectorySet) -> float:
    """The residual sum's decay: as set, or by the proof's rule from the source's spectrum on the target data."""
    if c.gamma_rule == "fixed":
        return c.gamma
    from t42_transfer.evaluation.lyapunov import lyapunov_gamma

    return lyapunov_gamma(source, target)


def cumulative_residual(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """Algorithm 2: frozen source plus a discounted running sum of residuals."""
    c = cfg.cumulative_residual
    g = _residual_net(source, target, c, seed, on_epoch)
    return CumulativeResidualModel(copy.deepcopy(source), g, c.alpha, _gamma(c, source, target)).eval()


def _rollout_residual_samples(
    source: TransitionModel, data: TrajectorySet, alpha: float, gamma: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """g's single-step samples off the diagonal (``residual_inputs: source_rollout``), raw: per step of every
    episode the source's own open-loop state ``x_S`` along the recorded actions, the action, the recorded state
    ``x`` (the adjusted state g should keep), and the target ``(y' - gamma y) / alpha`` for ``y = x - x_S``.
    Steps from the first one whose rollout or target is not finite on are left out."""
    parts = []
    source.eval()
    for episode in data:
        states, actions = torch.tensor(episode.states), torch.tensor(episode.actions)  # copies: episodes are read-only
        with torch.no_grad():
            rolled = source.rollout(states[:1], actions[None])[0].to(states.dtype)
        y = states - rolled
        step = (y[1:] - gamma * y[:-1]) / alpha
        usable = torch.cumprod((torch.isfinite(rolled[1:]).all(1) & torch.isfinite(step).all(1)).long(), 0).bool()
        parts.append((rolled[:-1][usable], actions[usable], states[:-1][usable], step[usable]))
    x_s, a, x, steps = (torch.cat(column) for column in zip(*parts, strict=True))
    if len(x_s) < 2:
        raise ValueError("the source's rollouts along the target episodes give fewer than 2 usable steps")
    return x_s, a, x, steps


def _paper_recurrent_net(
    source: TransitionModel, target: TrajectorySet, c: ResidualConfig, seed: int, gamma: float,
    on_epoch: ProgressHook | None,
) -> TransitionModel:
    """g of the paper's recurrent residual, fitted on the source's own rollouts (:func:`_rollout_residual_samples`)."""
    if c.normalisation == "source":
        norm = dataclasses.replace(source.norm, delta_mean=np.zeros_like(source.norm.delta_mean))
    else:  # g's own statistics: the source states it reads and the steps it learns
        x_s, _, _, steps = _rollout_residual_samples(source, target, c.alpha, gamma)
        norm = Normalisation.from_transitions(x_s.numpy(), (x_s + steps).numpy())
    torch.manual_seed(seed)
    g = TransitionModel(norm, grasp_input=True)

    def batch_of(data: TrajectorySet) -> StepBatch:
        x_s, a, x, steps = _rollout_residual_samples(source, data, c.alpha, gamma)
        with torch.no_grad():
            return StepBatch(g.features(x_s, a, x), g.normalise_delta(steps))

    train, val = validation_split(target, c.val_fraction, seed)
    batch = batch_of(train)
    val_batch = batch_of(val) if val is not None and len(val) else None
    val_fn = None if val_batch is None else (lambda: float(step_loss(g.net, val_batch, slice(None))))
    fit(list(g.net.parameters()), g, lambda idx: step_loss(g.net, batch, idx), len(batch), val_fn,
        _seeded(c.train, seed), "residual", on_epoch)
    return g


def recurrent_residual(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """The residual fed back inside the loop: the paper's adjusted-state form or the authors' normalised sum."""
    c = cfg.recurrent_residual
    if c.form == "adjusted_state":
        gamma = _gamma(c, source, target)
        if c.residual_inputs == "source_rollout":
            g = _paper_recurrent_net(source, target, c, seed, gamma, on_epoch)
        else:
            g = _residual_net(source, target, c, seed, on_epoch, adjusted_input=True)
        return AdjustedStateResidualModel(copy.deepcopy(source), g, c.alpha, gamma).eval()
    g = _residual_net(source, target, c, seed, on_epoch)
    return RecurrentResidualModel(copy.deepcopy(source), g, c.alpha).eval()


# ------------------------------------------------------------------ auto: pick by held-out evidence
@dataclass(frozen=True)
class CandidateScore:
    """One candidate of :func:`select_method`: its held-out scores, or why it could not be trained."""

    method: str
    divergence_steps: float | None = None
    position_mse_mm2: float | None = None
    error: str = ""

    def describe(self) -> str:
        if self.error:
            return f"{self.method} failed ({self.error})"
        return f"{self.method} {self.divergence_steps:.1f} steps / {self.position_mse_mm2:.2f} mm^2"


@dataclass(frozen=True)
class Selection:
    """What ``auto`` did: the model it keeps, the method that made it, every candidate's score, and how."""

    model: LatentDynamics
    best: str
    candidates: tuple[CandidateScore, ...]
    train_episodes: int
    held_out_episodes: int
    note: str = ""
    """How the pick was made when it was not by held-out scores (the fallback), else empty."""

    def describe(self) -> str:
        how = self.note or (f"best held-out divergence of {len(self.candidates)} candidates on "
                            f"{self.held_out_episodes} held-out episode(s), trained on {self.train_episodes}")
        return f"auto picked {self.best} ({how}): " + "; ".join(c.describe() for c in self.candidates)

    def to_dict(self) -> dict[str, object]:
        return {
            "best": self.best, "train_episodes": self.train_episodes, "held_out_episodes": self.held_out_episodes,
            "note": self.note, "candidates": [dataclasses.asdict(c) for c in self.candidates],
        }


def select_method(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int = 0,
    on_epoch: ProgressHook | None = None,
) -> Selection:
    """Train every candidate of ``cfg.auto`` on part of ``target``, score each on the other whole episodes,
    keep the best.

    Best: the longest mean time before divergence (the paper's metric, 4 mm), then the
    lower position MSE, then the earlier candidate.  The kept model is the one scored,
    trained without the held-out episodes.  With fewer than ``cfg.auto.min_episodes``
    episodes nothing can be held out: ValueError saying so, unless ``cfg.auto.fallback``
    names a method, which is then trained on all of ``target`` and reported as the fallback.
    A candidate that cannot use the data is reported with why; if none can, ValueError.
    """
    a = cfg.auto
    unknown = [m for m in (*a.candidates, *([a.fallback] if a.fallback else [])) if m not in METHODS or m == "auto"]
    if unknown or not a.candidates:
        raise ValueError(f"auto candidates and fallback must be methods other than auto, one of "
                         f"{sorted(set(METHODS) - {'auto'})}; got {unknown or 'no candidates'}")
    if len(target) < a.min_episodes:
        why = (f"auto needs at least {a.min_episodes} target episodes to train candidates on some and score them on "
               f"others held out whole; got {len(target)}")
        if a.fallback is None:
            raise ValueError(f"{why} (set auto.fallback to use one method instead)")
        model = METHODS[a.fallback](source, target, cfg, seed, on_epoch).eval()
        return Selection(model, a.fallback, (), len(target), 0, f"fallback: {why}; nothing scored")
    held_out, train = split_by_fraction(target, a.holdout_fraction, seed)
    scores: list[CandidateScore] = []
    models: dict[str, LatentDynamics] = {}
    for name in a.candidates:
        hook = None if on_epoch is None else (
            lambda p, name=name: on_epoch(dataclasses.replace(p, phase=f"{name}: {p.phase}")))
        try:
            models[name] = METHODS[name](source, train, cfg, seed, hook).eval()
        except ValueError as err:  # a method that cannot use this data is reported, not fatal
            scores.append(CandidateScore(name, error=str(err)))
            continue
        result = evaluate_model(models[name], held_out)
        scores.append(CandidateScore(name, result["divergence_mean"], result["position_mse_mean"]))
    scored = [s for s in scores if not s.error]
    if not scored:
        raise ValueError("auto: no candidate could be trained: " + "; ".join(s.describe() for s in scores))
    best = max(scored, key=lambda s: (s.divergence_steps, -s.position_mse_mm2, -a.candidates.index(s.method)))
    return Selection(models[best.method], best.method, tuple(scores), len(train), len(held_out))


def auto(
    source: TransitionModel, target: TrajectorySet, cfg: TransferConfig, seed: int, on_epoch: ProgressHook | None = None
) -> LatentDynamics:
    """The candidate method with the best held-out score (:func:`select_method`, which also reports them all)."""
    return select_method(source, target, cfg, seed, on_epoch).model


METHODS: dict[str, Method] = {
    "new_model": new_model,
    "direct": direct,
    "naive_finetune": naive_finetune,
    "trajectory_finetune": trajectory_finetune,
    "cumulative_residual": cumulative_residual,
    "recurrent_residual": recurrent_residual,
    "l2_finetune": l2_finetune,
    "auto": auto,
    "multistep_l2_finetune": multistep_l2_finetune,
    "anchored_finetune": anchored_finetune,
}
"""The paper's six methods, in its order, the authors' L2-constrained fine-tuning, the pick by evidence, and issue
24's candidates of our own: L2 fine-tuning on short rollouts, and fine-tuning held to the source off the data."""

PAPER_METHODS = tuple(list(METHODS)[:6])

_DEFAULT_CFG = TransferConfig()
"""The paper's settings: :func:`transfer`'s default (frozen, so one instance serves every call)."""


def data_problem(method: str, episodes: int, transitions: int, cfg: TransferConfig = _DEFAULT_CFG) -> str | None:
    """Why ``method`` cannot run on target data of ``episodes`` episodes and ``transitions`` transitions, or None.

    Counts only, so a run can refuse an impossible configuration before training anything: unknown methods,
    no target data, and ``auto`` with fewer episodes than it holds out from and no fallback."""
    if method not in METHODS:
        return f"unknown transfer method {method!r}; expected one of {sorted(METHODS)}"
    if episodes == 0 or transitions < 2:
        return f"{method} needs target data; got {transitions} transitions"
    if method == "auto" and episodes < cfg.auto.min_episodes:
        if cfg.auto.fallback is None:
            return (f"auto needs at least {cfg.auto.min_episodes} target episodes to train candidates on some and "
                    f"score them on others held out whole; got {episodes} (set auto.fallback to use one method "
                    f"instead)")
        return data_problem(cfg.auto.fallback, episodes, transitions, cfg)
    return None


def transfer(
    method: str, source: TransitionModel, target: TrajectorySet, cfg: TransferConfig = _DEFAULT_CFG, seed: int = 0,
    on_epoch: ProgressHook | None = None,
) -> LatentDynamics:
    """Run ``method``, reporting its training epochs to ``on_epoch``; what :func:`data_problem` names is
    refused."""
    if (why := data_problem(method, len(target), target.num_transitions, cfg)) is not None:
        raise ValueError(why)
    model = METHODS[method](source, target, cfg, seed, on_epoch)
    return model.eval()
