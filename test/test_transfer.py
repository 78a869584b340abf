"""Transfer methods: the registry, shapes, determinism, the source left untouched, each method's mechanics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.residual import CumulativeResidualModel, RecurrentResidualModel
from t42_transfer.models.training import Progress, TrainConfig, train_transition_model
from t42_transfer.transfer import METHODS, PAPER_METHODS, TransferConfig, transfer

FAST = TransferConfig(
    new_model=dataclasses.replace(TransferConfig().new_model, train=TrainConfig(epochs=2)),
    naive_finetune=dataclasses.replace(
        TransferConfig().naive_finetune, train=TrainConfig(lr=1e-3, epochs=2, patience=None)
    ),
    l2_finetune=dataclasses.replace(TransferConfig().l2_finetune, train=TrainConfig(lr=1e-3, epochs=2, patience=None)),
    multistep_l2_finetune=dataclasses.replace(
        TransferConfig().multistep_l2_finetune, train=TrainConfig(lr=1e-3, epochs=2, patience=None)
    ),
    anchored_finetune=dataclasses.replace(
        TransferConfig().anchored_finetune, train=TrainConfig(lr=1e-3, epochs=2, patience=None)
    ),
    trajectory_finetune=dataclasses.replace(
        TransferConfig().trajectory_finetune, train=TrainConfig(lr=1e-3, epochs=2, batch_size=1, patience=None)
    ),
    cumulative_residual=dataclasses.replace(TransferConfig().cumulative_residual, train=TrainConfig(epochs=2)),
    recurrent_residual=dataclasses.replace(TransferConfig().recurrent_residual, train=TrainConfig(epochs=2)),
)


@pytest.fixture(scope="module")
def source(make_set) -> TransitionModel:
    model, _ = train_transition_model(make_set([40] * 8, seed=10, hand="src"), TrainConfig(epochs=3))
    return model


@pytest.fixture(scope="module")
def target(make_set):
    return make_set([30, 35, 25], seed=11, hand="tgt")


SINGLE_METHODS = [m for m in METHODS if m != "auto"]  # auto picks among these: test/test_transfer_auto.py


def test_registry_has_the_papers_six_methods_l2_auto_and_ours() -> None:
    assert PAPER_METHODS == (
        "new_model", "direct", "naive_finetune", "trajectory_finetune", "cumulative_residual", "recurrent_residual"
    )
    assert set(METHODS) == set(PAPER_METHODS) | {"l2_finetune", "auto", "multistep_l2_finetune", "anchored_finetune"}


@pytest.mark.parametrize("grasp_input", [False, True])
def test_multistep_l2_finetuning_over_one_step_is_l2_finetuning(make_set, grasp_input: bool) -> None:
    """Its first step is the single-step loss: with a horizon of 1 it trains the same model (up to rounding)."""
    source, _ = train_transition_model(make_set([30] * 4, seed=12, hand="src"), TrainConfig(epochs=2),
                                       grasp_input=grasp_input)
    target = make_set([20, 25], seed=13, hand="tgt")
    train = TrainConfig(lr=1e-3, epochs=3, patience=None)
    cfg = dataclasses.replace(
        FAST, l2_finetune=dataclasses.replace(FAST.l2_finetune, train=train),
        multistep_l2_finetune=dataclasses.replace(FAST.multistep_l2_finetune, train=train, horizon=1),
    )
    single, multi = (transfer(m, source, target, cfg, seed=5) for m in ("l2_finetune", "multistep_l2_finetune"))
    x0, actions = torch.tensor(target[0].states[:1]).repeat(4, 1), torch.rand(4, 30, 2) * 2 - 1
    assert torch.allclose(single.rollout(x0, actions), multi.rollout(x0, actions), atol=1e-3)
    assert not torch.allclose(single.rollout(x0, actions), source.rollout(x0, actions), atol=1e-3)
    longer = transfer("multistep_l2_finetune", source, target, dataclasses.replace(
        cfg, multistep_l2_finetune=dataclasses.replace(cfg.multistep_l2_finetune, horizon=8)), seed=5)
    assert not torch.allclose(longer.rollout(x0, actions), single.rollout(x0, actions), atol=1e-3)


def test_anchored_finetuning_without_its_pull_is_naive_finetuning_and_its_pull_holds_the_source_off_the_data(
        source, target) -> None:
    """anchor 0 leaves the data term alone (naive fine-tuning's loss at this lr); a strong anchor keeps the model's
    predictions at off-data points nearer the source's than no anchor does."""
    train = TrainConfig(lr=1e-3, epochs=3, patience=None)
    cfg = dataclasses.replace(FAST, naive_finetune=dataclasses.replace(FAST.naive_finetune, train=train),
                              anchored_finetune=dataclasses.replace(FAST.anchored_finetune, train=train, anchor=0.0))
    naive, free = (transfer(m, source, target, cfg, seed=2) for m in ("naive_finetune", "anchored_finetune"))
    x0, actions = torch.tensor(target[0].states[:1]).repeat(4, 1), torch.rand(4, 20, 2) * 2 - 1
    assert torch.allclose(naive.rollout(x0, actions), free.rollout(x0, actions), atol=1e-3)
    held = transfer("anchored_finetune", source, target, dataclasses.replace(
        cfg, anchored_finetune=dataclasses.replace(cfg.anchored_finetune, anchor=100.0)), seed=2)
    off = torch.cat([torch.randn(256, 4) * source.state_std + source.state_mean, torch.rand(256, 2) * 2 - 1], dim=1)
    with torch.no_grad():
        reference = source.net.eval()(off)
        gaps = [float(((m.net.eval()(off) - reference) ** 2).mean()) for m in (free, held)]
    assert gaps[1] < 0.5 * gaps[0], gaps


def test_multistep_l2_finetuning_refuses_episodes_shorter_than_its_horizon(source, make_set) -> None:
    cfg = dataclasses.replace(FAST, multistep_l2_finetune=dataclasses.replace(FAST.multistep_l2_finetune, horizon=50))
    with pytest.raises(ValueError, match="at least 50 steps; the longest has 35"):
        transfer("multistep_l2_finetune", source, make_set([30, 35], seed=14, hand="tgt"), cfg)


@pytest.mark.parametrize("method", SINGLE_METHODS)
def test_each_method_shapes_determinism_and_untouched_source(method: str, source, target) -> None:
    before = {k: v.clone() for k, v in source.state_dict().items()}
    model = transfer(method, source, target, FAST, seed=3)
    again = transfer(method, source, target, FAST, seed=3)
    x0, actions = torch.tensor(target[0].states[:1]).repeat(3, 1), torch.rand(3, 12, 2) * 2 - 1
    states = model.rollout(x0, actions)
    assert states.shape == (3, 13, 4) and torch.isfinite(states).all()
    assert torch.equal(states, again.rollout(x0, actions))
    for k, v in source.state_dict().items():
        assert torch.equal(v, before[k]), f"{method} modified the source's {k}"
    if method != "direct":
        assert not torch.equal(states, source.rollout(x0, actions))


@pytest.mark.parametrize("method", SINGLE_METHODS)
def test_each_method_reports_its_training_epochs_by_phase(method: str, source, target) -> None:
    calls: list[Progress] = []
    transfer(method, source, target, FAST, seed=3, on_epoch=calls.append)
    if method == "direct":
        assert calls == []  # nothing to train
        return
    assert calls and all(p.phase and 1 <= p.epoch <= p.epochs == 2 for p in calls)
    for phase in {p.phase for p in calls}:
        assert [p.epoch for p in calls if p.phase == phase] == list(range(1, 1 + sum(p.phase == phase for p in calls)))
    assert all(np.isfinite(p.train_loss) for p in calls)


def test_bad_requests_are_refused(source, target) -> None:
    with pytest.raises(ValueError, match="unknown transfer method"):
        transfer("magic", source, target)
    with pytest.raises(ValueError, match="needs target data"):
        transfer("naive_finetune", source, target.subset([]))


def _zero_change_model() -> TransitionModel:
    """A transition model that predicts no change anywhere."""
    model = TransitionModel(Normalisation.identity(), hidden=4, dropout=0.0)
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
    return model


def test_cumulative_residual_follows_algorithm_2() -> None:
    source = _zero_change_model()
    residual = TransitionModel(Normalisation.identity(), hidden=4, dropout=0.0)
    with torch.no_grad():
        for p in residual.net.parameters():
            p.zero_()
        residual.net[6].bias.copy_(torch.tensor([1.0, 2.0, 0.0, 0.0]))  # g = (1, 2, 0, 0) everywhere
    alpha, gamma = 0.3, 0.5
    model = CumulativeResidualModel(source, residual, alpha, gamma)
    states = model.rollout(torch.zeros(1, 4), torch.zeros(1, 4, 2))[0]
    y, expected = 0.0, []
    for _ in range(4):
        y = gamma * y + alpha
        expected.append(y)
    np.testing.assert_allclose(states[1:, 0].numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(states[1:, 1].numpy(), 2 * np.array(expected), rtol=1e-6)
    recurrent = RecurrentResidualModel(source, residual, alpha).rollout(torch.zeros(1, 4), torch.zeros(1, 4, 2))[0]
    np.testing.assert_allclose(recurrent[1:, 0].numpy(), alpha * np.arange(1, 5), rtol=1e-6)


def _start_state_source_and_its_own_paths() -> tuple[TransitionModel, TrajectorySet]:
    """An untrained network that reads the episode's start state (as the authors' models do), and four episodes of
    its own open-loop rollouts: data it predicts exactly when its start state is held, and not otherwise."""
    torch.manual_seed(1)
    norm = Normalisation(np.zeros(4, np.float32), np.ones(4, np.float32), np.zeros(4, np.float32),
                         np.full(4, 0.05, np.float32))
    source = TransitionModel(norm, grasp_input=True, dropout=0.0).eval()  # no dropout: training sees what eval does
    rng = np.random.default_rng(0)
    x0 = torch.as_tensor(rng.normal(0.0, 1.0, (4, 4)), dtype=torch.float32)
    actions = torch.as_tensor(rng.uniform(-1, 1, (4, 30, 2)), dtype=torch.float32)
    states = source.rollout(x0, actions)
    lengths = (30, 24, 27, 21)
    return source, TrajectorySet(Trajectory(states[i, : n + 1].numpy(), actions[i, :n].numpy())
                                 for i, n in enumerate(lengths))


def test_the_residuals_target_is_the_sources_error_within_the_episode() -> None:
    """g learns ``x' - f_S(x, a)`` with f_S run as the residual model's rollout runs it: its start state is the
    episode's, not each transition's own state. On the source's own paths that error is zero."""
    from t42_transfer.models.training import step_batch
    from t42_transfer.transfer.methods import _source_prediction

    source, own = _start_state_source_and_its_own_paths()
    batch = step_batch(TransitionModel(Normalisation.identity()), own, _source_prediction(source))
    assert batch.target.abs().max() < 1e-5
    x, a, x_next = (torch.from_numpy(v) for v in own.transitions())
    assert (x_next - source.rollout(x, a[:, None])[:, 1]).abs().max() > 1e-3  # each state its own start: not zero


def test_trajectory_finetuning_keeps_a_cropped_episodes_start_state() -> None:
    """The authors' batches crop episodes at random offsets; a start-state model still reads each episode's first
    state, so on its own paths (lr ~0: the model stays put) the loss is zero from the first epoch."""
    source, own = _start_state_source_and_its_own_paths()
    epochs = []
    cfg = dataclasses.replace(FAST, trajectory_finetune=dataclasses.replace(
        FAST.trajectory_finetune, train=TrainConfig(lr=1e-12, epochs=2, batch_size=4, patience=None)))
    transfer("trajectory_finetune", source, own, cfg, seed=3, on_epoch=epochs.append)
    assert len(epochs) == 2 and max(p.train_loss for p in epochs) < 1e-8, epochs


def _constant_drift_source(step: tuple[float, float, float, float]) -> TransitionModel:
    """A source that predicts the same change ``step`` from any state and action (zero last layer)."""
    norm = Normalisation(np.zeros(4, np.float32), np.ones(4, np.float32), np.asarray(step, np.float32),
                         np.ones(4, np.float32))
    model = TransitionModel(norm)
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
    return model.eval()


def test_the_papers_recurrent_residual_learns_off_the_diagonal_from_the_sources_own_rollout(make_set) -> None:
    from t42_transfer.transfer.methods import _rollout_residual_samples

    data = make_set([6, 4], seed=12, hand="tgt")
    source = _constant_drift_source((1.0, 0.0, -2.0, 0.0))
    alpha, gamma = 0.5, 0.9
    x_s, a, x, steps = _rollout_residual_samples(source, data, alpha, gamma)
    assert x_s.shape == x.shape == steps.shape == (10, 4) and a.shape == (10, 2)
    row = 0
    for episode in data:
        states = torch.tensor(episode.states)
        t = torch.arange(len(states), dtype=torch.float32)[:, None]
        rolled = states[0] + t * torch.tensor([1.0, 0.0, -2.0, 0.0])  # the source on its own, from the first state
        y = states - rolled
        n = len(episode.actions)
        assert torch.allclose(x_s[row:row + n], rolled[:-1], atol=1e-4)  # not the recorded state: off the diagonal
        assert torch.equal(x[row:row + n], states[:-1])
        assert torch.equal(a[row:row + n], torch.tensor(episode.actions))
        assert torch.allclose(steps[row:row + n], (y[1:] - gamma * y[:-1]) / alpha, atol=1e-4)
        row += n


def test_the_papers_recurrent_residual_form_is_a_config_choice_and_trains(source, target) -> None:
    from t42_transfer.models.residual import AdjustedStateResidualModel

    cfg = dataclasses.replace(FAST, recurrent_residual=dataclasses.replace(FAST.recurrent_residual,
                                                                          residual_inputs="source_rollout"))
    paper = transfer("recurrent_residual", source, target, cfg, seed=3)
    ours = transfer("recurrent_residual", source, target, FAST, seed=3)
    assert isinstance(paper, AdjustedStateResidualModel) and isinstance(ours, AdjustedStateResidualModel)
    x0, actions = torch.tensor(target[0].states[:1]), torch.from_numpy(target[0].actions)[None]
    rolled = paper.rollout(x0, actions)
    assert torch.isfinite(rolled).all() and not torch.equal(rolled, ours.rollout(x0, actions))
    with pytest.raises(ValueError, match="residual_inputs must be one of"):
        dataclasses.replace(FAST.recurrent_residual, residual_inputs="diagonal")


# --------------------------------------------------------------------------- does transfer help?
@pytest.fixture(scope="module")
def simulated_pair() -> tuple[TransitionModel, object, object]:
    """A source model trained on the simulated source hand, and target-hand episodes to transfer on and to test
    on (other grasps), all collected by the simulator (one worker: the same episodes every run)."""
    from t42_transfer.hand.collect import collect

    source_data, _ = collect("source", episodes=30, steps=120, seed=1, workers=1, progress=False)
    target_train, _ = collect("target", episodes=8, steps=120, seed=3, workers=1, progress=False)
    target_test, _ = collect("target", episodes=8, steps=120, seed=4, workers=1, progress=False)
    source, _ = train_transition_model(source_data, TrainConfig(epochs=20))
    return source, target_train, target_test


def _one_step_error_mm2(model, data) -> float:
    """Mean squared x,y error (mm²) of one-step predictions on every transition of ``data``."""
    x, a, x_next = (torch.from_numpy(v) for v in data.transitions())
    with torch.no_grad():
        predicted = model.rollout(x, a[:, None, :])[:, 1]
    return float(((predicted[:, :2] - x_next[:, :2]) ** 2).sum(dim=1).mean())


@pytest.mark.parametrize("method", ["naive_finetune", "l2_finetune", "cumulative_residual", "recurrent_residual"])
def test_transfer_predicts_the_target_hand_better_than_the_source_used_directly(method: str, simulated_pair) -> None:
    """What transfer is for: on held-out target episodes, a transferred model's one-step error is clearly below the
    source's (``direct``), which is itself below doing nothing's (holding still), with the methods' own settings."""
    from t42_transfer.models.baselines import HoldStill

    source, target_train, target_test = simulated_pair
    direct = _one_step_error_mm2(source, target_test)
    assert direct < 0.5 * _one_step_error_mm2(HoldStill(), target_test)  # the source model is no straw man
    transferred = _one_step_error_mm2(transfer(method, source, target_train, TransferConfig(), seed=0), target_test)
    assert transferred < 0.85 * direct, (transferred, direct)
