"""The paper's transition model and its training loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.models.training import (
    Progress,
    TrainConfig,
    fit,
    train_transition_model,
    trajectory_weights,
)


def test_architecture_is_the_papers() -> None:
    model = TransitionModel(Normalisation.identity())
    kinds = [type(m) for m in model.net]
    assert kinds == [nn.Linear, nn.SELU, nn.AlphaDropout, nn.Linear, nn.Tanh, nn.Dropout, nn.Linear]
    assert (model.net[0].in_features, model.net[0].out_features) == (6, 128)
    assert (model.net[3].in_features, model.net[3].out_features) == (128, 128)
    assert model.net[6].out_features == 4
    assert model.net[2].p == model.net[5].p == 0.1
    assert TransitionModel(Normalisation.identity(), grasp_input=True).net[0].in_features == 10


def test_rollout_shapes_start_and_evaluation_mode() -> None:
    torch.manual_seed(0)
    model = TransitionModel(Normalisation.identity()).train()
    x0, actions = torch.randn(5, 4), torch.rand(5, 7, 2) * 2 - 1
    states = model.rollout(x0, actions)
    assert states.shape == (5, 8, 4)
    assert torch.equal(states[:, 0], x0)
    assert torch.equal(states, model.rollout(x0, actions))  # dropout is off in rollouts
    assert model.training  # and the caller's mode is restored
    with pytest.raises(ValueError, match="actions must be"):
        model.rollout(x0, torch.zeros(4, 7, 2))
    with pytest.raises(ValueError, match="x0 must be"):
        model.rollout(torch.zeros(5, 3), actions)


def test_zero_output_layer_moves_by_the_mean_change() -> None:
    norm = Normalisation(
        np.zeros(4, np.float32), np.ones(4, np.float32), np.array([1, -2, 0, 3], np.float32), np.ones(4, np.float32)
    )
    model = TransitionModel(norm)
    nn.init.zeros_(model.net[6].weight)
    nn.init.zeros_(model.net[6].bias)
    states = model.rollout(torch.zeros(2, 4), torch.zeros(2, 5, 2))
    np.testing.assert_allclose(states[0, -1].numpy(), [5, -10, 0, 15])


def test_training_is_seeded_learns_and_keeps_the_best_epoch(make_set) -> None:
    data = make_set([40] * 30, seed=3)  # a validation share of 0.1: 3 episodes, enough for early stopping
    cfg = TrainConfig(epochs=6, patience=2, seed=4)
    first, report = train_transition_model(data, cfg)
    again, _ = train_transition_model(data, cfg)
    for p, q in zip(first.parameters(), again.parameters(), strict=True):
        assert torch.equal(p, q)
    assert report.train_loss[-1] < report.train_loss[0]
    assert report.best_epoch == int(np.argmin(report.val_loss))
    assert len(report.val_loss) == report.epochs_run <= 6


def test_progress_hook_is_called_once_per_epoch_until_early_stopping() -> None:
    torch.manual_seed(0)
    net = nn.Linear(3, 1)
    x, y = torch.randn(32, 3), torch.randn(32, 1)
    rising = iter(range(100))  # validation never improves after the first epoch: patience 2 stops after 3

    def loss_on(idx: torch.Tensor) -> torch.Tensor:
        return torch.mean((net(x[idx]) - y[idx]) ** 2)

    calls: list[Progress] = []
    cfg = TrainConfig(epochs=20, batch_size=8, patience=2)
    report = fit(list(net.parameters()), net, loss_on, 32, lambda: float(next(rising)), cfg, "probe", calls.append)
    assert report.epochs_run == 3
    assert [p.epoch for p in calls] == [1, 2, 3]
    assert all(p.phase == "probe" and p.epochs == 20 for p in calls)
    assert all(np.isfinite(p.train_loss) for p in calls)
    assert [p.val_loss for p in calls] == [0.0, 1.0, 2.0]
    assert [p.train_loss for p in calls] == report.train_loss


def test_training_reports_every_epoch_of_its_phase(make_set) -> None:
    calls: list[Progress] = []
    _, report = train_transition_model(make_set([30] * 3, seed=2), TrainConfig(epochs=3), on_epoch=calls.append,
                                       phase="source model")
    assert [(p.phase, p.epoch, p.epochs) for p in calls] == [("source model", e, 3) for e in (1, 2, 3)]
    assert all(p.val_loss is None and np.isfinite(p.train_loss) for p in calls)  # 3 episodes: no validation set


def test_trajectory_weights_are_one_over_i() -> None:
    np.testing.assert_allclose(trajectory_weights(4).numpy(), [1, 1 / 2, 1 / 3, 1 / 4])


def test_early_stopping_validates_on_three_episodes_or_says_it_cannot(make_set) -> None:
    from t42_transfer.models.training import MIN_VAL_EPISODES, ValidationWarning, validation_split

    six = make_set([1000] * 6, seed=5)  # the real hands' case: a share of 0.1 is one path
    with pytest.warns(ValidationWarning, match="^no validation set: a validation share of 0.1 would hold 1 of 6 "
                      "episodes .* source model runs its full epoch"):
        train, val = validation_split(six, 0.1, seed=0, phase="source model")
    assert val is None and train is six
    _, report = train_transition_model(make_set([30] * 4, seed=5), TrainConfig(epochs=2))
    assert report.val_loss == [] and report.validation.startswith("none: a validation share of 0.1")
    thirty = make_set([40] * 30, seed=5)
    train, val = validation_split(thirty, 0.1, seed=0)
    assert len(val) == MIN_VAL_EPISODES and len(train) == 27
