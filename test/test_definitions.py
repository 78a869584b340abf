"""The paper's and the authors' definitions: each switch changes exactly what it names, on hand-made cases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.experiment_config import DataSpec, ExperimentConfig, load_config
from t42_transfer.evaluation.metrics import METRIC_DEFINITIONS, divergence_time, evaluate_model, position_mse
from t42_transfer.models import AdjustedStateResidualModel, Normalisation, RecurrentResidualModel, TransitionModel
from t42_transfer.models.training import Progress, TrainConfig, train_transition_model
from t42_transfer.transfer import methods
from t42_transfer.transfer.config import DEFINITIONS, SOURCE_TRAINING, TransferConfig

PAPER, AUTHORS = TransferConfig.for_definition("paper"), TransferConfig.for_definition("authors")


def _flat(obj: object, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in (dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj).items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _hand_made(model: TransitionModel, scale: float) -> TransitionModel:
    """Every weight and bias set by a fixed pattern (no randomness), dropout off."""
    with torch.no_grad():
        for i, p in enumerate(model.net.parameters()):
            p.copy_(scale * torch.sin(torch.arange(p.numel(), dtype=torch.float32) * 0.7 + i).reshape(p.shape))
    return model.eval()


def _norm(state_mean, state_std, delta_mean, delta_std) -> Normalisation:
    return Normalisation(*(np.asarray(v, np.float32) for v in (state_mean, state_std, delta_mean, delta_std)))


SOURCE_NORM = _norm([10, -5, 60, 70], [30, 12, 60, 50], [0.02, -0.01, 0.5, -0.3], [0.1, 0.06, 3.0, 2.5])
IDENTITY_NORM = Normalisation.identity()


def _source() -> TransitionModel:
    return _hand_made(TransitionModel(SOURCE_NORM, hidden=4, dropout=0.0), 0.5)


def _zero_change(norm: Normalisation = IDENTITY_NORM) -> TransitionModel:
    model = TransitionModel(norm, hidden=4, dropout=0.0)
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
    return model.eval()


# ------------------------------------------------------------------ the config switch
def test_switching_definition_changes_only_the_named_settings() -> None:
    paper, authors = _flat(PAPER), _flat(AUTHORS)
    changed = {k for k in paper if paper[k] != authors[k]}
    residual = {"alpha", "train.lr", "train.epochs", "train.patience", "val_fraction", "normalisation"}
    assert changed == {
        "new_model.train.lr", "new_model.train.epochs", "new_model.train.patience", "new_model.val_fraction",
        "trajectory_finetune.loss", "trajectory_finetune.cutoff_mm2", "trajectory_finetune.train.batch_size",
        *(f"cumulative_residual.{k}" for k in residual | {"gamma"}),
        *(f"recurrent_residual.{k}" for k in residual | {"form"}),
    }
    assert TransferConfig() == PAPER
    with pytest.raises(ValueError, match="definition must be one of"):
        TransferConfig.for_definition("code")


def test_cumulative_residual_settings_per_definition() -> None:
    p, a = PAPER.cumulative_residual, AUTHORS.cumulative_residual
    assert (p.alpha, p.gamma, p.train.lr, p.train.epochs, p.normalisation) == (0.3, 0.9997, 1e-3, 100, "residual")
    assert (a.alpha, a.gamma, a.train.lr, a.train.epochs, a.train.patience, a.val_fraction, a.normalisation) == (
        1.0, 0.993, 2e-5, 5, None, 0.0, "source")


def test_authors_cumulative_residual_trains_g_five_epochs_and_uses_its_gamma(make_set) -> None:
    source = _source()
    calls: list[Progress] = []
    model = methods.cumulative_residual(source, make_set([20, 20], seed=2), AUTHORS, 0, calls.append)
    assert (model.alpha, model.gamma) == (1.0, 0.993)
    assert [c.epoch for c in calls] == [1, 2, 3, 4, 5] and {c.phase for c in calls} == {"residual"}
    assert all(c.val_loss is None for c in calls)  # no validation share: all five epochs, the last kept
    np.testing.assert_array_equal(model.residual.state_std.numpy(), SOURCE_NORM.state_std)
    np.testing.assert_array_equal(model.residual.delta_std.numpy(), SOURCE_NORM.delta_std)
    np.testing.assert_array_equal(model.residual.delta_mean.numpy(), np.zeros(4, np.float32))


def test_metric_and_experiment_definitions_agree_and_differ_only_where_named() -> None:
    assert set(METRIC_DEFINITIONS) == set(DEFINITIONS) == set(SOURCE_TRAINING)
    paper, authors = METRIC_DEFINITIONS["paper"], METRIC_DEFINITIONS["authors"]
    assert (paper.epsilon_mm, paper.count_crossing_step, paper.mse_per_coordinate) == (4.0, False, False)
    assert (authors.epsilon_mm, authors.count_crossing_step, authors.mse_per_coordinate) == (10.0, True, True)
    assert SOURCE_TRAINING["authors"] == TrainConfig(lr=2.5e-6, epochs=300, patience=None)
    built = {d: ExperimentConfig("x", DataSpec(hand="source"), DataSpec(hand="target"), definition=d)
             for d in DEFINITIONS}
    a, p = _flat(built["authors"]), _flat(built["paper"])
    assert {k.split(".")[0] for k in a if a[k] != p[k]} == {"definition", "epsilon_mm", "source_training", "transfer"}
    assert built["authors"].transfer == AUTHORS and built["authors"].epsilon_mm == 10.0


def test_a_config_file_applies_its_settings_on_top_of_its_definition(tmp_path) -> None:
    path = tmp_path / "run.yaml"
    path.write_text(
        "name: run\nsource: {hand: source}\ntarget: {hand: target}\ndefinition: authors\n"
        "source_training: {epochs: 3}\ntransfer: {cumulative_residual: {gamma: 0.9}}\n"
    )
    cfg = load_config(path)
    assert cfg.definition == "authors" and cfg.epsilon_mm == 10.0
    assert cfg.source_training == TrainConfig(lr=2.5e-6, epochs=3, patience=None)
    assert cfg.transfer.cumulative_residual == dataclasses.replace(AUTHORS.cumulative_residual, gamma=0.9)
    assert cfg.transfer.recurrent_residual == AUTHORS.recurrent_residual
    path.write_text("name: run\nsource: {hand: source}\ntarget: {hand: target}\ndefinition: code\n")
    with pytest.raises(ValueError, match="definition must be one of"):
        load_config(path)


# ------------------------------------------------------------------ recurrent residual, both forms
def test_authors_recurrent_residual_is_net_s_plus_coeff_res_in_normalised_space() -> None:
    source = _source()
    res_norm = dataclasses.replace(source.norm, delta_mean=np.zeros(4, np.float32))  # the "source" normalisation
    res = _hand_made(TransitionModel(res_norm, hidden=4, dropout=0.0), 0.3)
    coeff = 0.7
    x0 = torch.tensor([[12.0, -3.0, 55.0, 80.0]])
    actions = torch.tensor([[[1.0, -1.0], [0.5, 1.5]]])
    states = RecurrentResidualModel(source, res, coeff).rollout(x0, actions)[0]
    mean, std = torch.from_numpy(SOURCE_NORM.delta_mean), torch.from_numpy(SOURCE_NORM.delta_std)
    x = x0
    for k in range(2):
        u = torch.cat([(x - source.state_mean) / source.state_std, actions[:, k]], dim=-1)
        with torch.no_grad():
            out = source.net(u) + coeff * res.net(u)  # the authors' TrajNet.forward
        x = x + out * std + mean
        torch.testing.assert_close(states[k + 1], x[0])


def test_authors_recurrent_residual_method_builds_g_in_the_sources_space_with_coeff_one(make_set) -> None:
    model = methods.recurrent_residual(_source(), make_set([20, 20], seed=3), AUTHORS, 0)
    assert isinstance(model, RecurrentResidualModel) and model.alpha == 1.0
    np.testing.assert_array_equal(model.residual.state_mean.numpy(), SOURCE_NORM.state_mean)
    np.testing.assert_array_equal(model.residual.delta_mean.numpy(), np.zeros(4, np.float32))


def test_paper_recurrent_residual_feeds_the_adjusted_state_to_g() -> None:
    source = _zero_change()  # x stays x0: only g moves the prediction
    g = _hand_made(TransitionModel(Normalisation.identity(), grasp_input=True, hidden=4, dropout=0.0), 0.8)
    alpha, gamma = 0.3, 0.9
    x0 = torch.tensor([[1.0, 2.0, 0.5, -0.5]])
    actions = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [-1.0, 1.0]]])
    states = AdjustedStateResidualModel(source, g, alpha, gamma).rollout(x0, actions)[0]
    y = torch.zeros(1, 4)
    for k in range(3):  # y' = gamma y + alpha g(x, a, x + y), shown x + y
        with torch.no_grad():
            y = gamma * y + alpha * g.delta(x0, actions[:, k], x0 + y)
        torch.testing.assert_close(states[k + 1], (x0 + y)[0])
    # The adjusted input matters: feeding g the source state alone gives another rollout.
    y_plain = torch.zeros(1, 4)
    for k in range(3):
        with torch.no_grad():
            y_plain = gamma * y_plain + alpha * g.delta(x0, actions[:, k], x0)
    assert not torch.allclose(states[3], (x0 + y_plain)[0])


def test_paper_recurrent_residual_method_trains_g_on_both_inputs(make_set) -> None:
    model = methods.recurrent_residual(_source(), make_set([20, 20], seed=4), dataclasses.replace(
        PAPER, recurrent_residual=dataclasses.replace(PAPER.recurrent_residual, train=TrainConfig(epochs=2))), 0)
    assert isinstance(model, AdjustedStateResidualModel) and model.residual.grasp_input
    assert (model.alpha, model.gamma) == (0.3, 0.9997)


# ------------------------------------------------------------------ trajectory fine-tuning
def test_trajectory_loss_paper_and_authors_on_hand_made_numbers() -> None:
    true = torch.zeros(1, 3, 4)
    predicted = torch.zeros(1, 3, 4)
    predicted[0, 1] = torch.tensor([2.0, 0.0, 0.0, 0.0])
    predicted[0, 2] = torch.tensor([0.0, 0.0, 4.0, 0.0])
    std = torch.tensor([2.0, 1.0, 4.0, 1.0])
    # paper: sum_i (1/i) MSE over 4 normalised coordinates: step 1 (2/2)^2/4, step 2 (4/4)^2/4
    assert float(methods.trajectory_loss(predicted, true, std, "paper")) == pytest.approx(0.25 + 0.5 * 0.25)
    # authors: raw units; step 1 mean of pairs (4 + 0, 0 + 0) = 2; step 2 (0 + 0.1 * 16, 0) / 2 = 0.8; / n = 2
    assert float(methods.trajectory_loss(predicted, true, std, "authors")) == pytest.approx((2.0 + 0.5 * 0.8) / 2)


def test_the_authors_cutoff_stops_the_whole_batch() -> None:
    model = _zero_change()
    true = torch.zeros(2, 8, 4)
    true[0, :, 0] = 10.0 * torch.arange(8)  # batch-mean per-coordinate x,y error at step k: 100 k^2 / 4
    actions = torch.zeros(2, 7, 2)
    assert methods.rollout_until(model, true, actions, 150.0).shape == (2, 3, 4)  # 25 * 3^2 > 150: stop at 3
    assert methods.rollout_until(model, true, actions, None).shape == (2, 8, 4)
    assert methods.rollout_until(model, true, actions, 1e-9).shape == (2, 2, 4)  # step 1 always kept


@pytest.mark.parametrize("definition", DEFINITIONS)
def test_trajectory_finetune_rolls_out_whole_episodes_or_cropped_batches(definition, make_set, monkeypatch) -> None:
    cfg = TransferConfig.for_definition(definition)
    cfg = dataclasses.replace(cfg, trajectory_finetune=dataclasses.replace(
        cfg.trajectory_finetune, train=dataclasses.replace(cfg.trajectory_finetune.train, epochs=2, batch_size=(
            1 if definition == "paper" else 3))))
    shapes, cutoffs = [], set()
    original = methods.rollout_until

    def spy(model, true, actions, cutoff_mm2, starts=None):
        shapes.append(tuple(true.shape))
        cutoffs.add(cutoff_mm2)
        return original(model, true, actions, cutoff_mm2, starts)

    monkeypatch.setattr(methods, "rollout_until", spy)
    target = make_set([12, 20, 15, 9], seed=6)
    source, _ = train_transition_model(make_set([20] * 4, seed=7), TrainConfig(epochs=1))
    methods.trajectory_finetune(source, target, cfg, 0)
    if definition == "paper":  # Algorithm 1: every episode whole, from its first state, once per epoch
        assert sorted(shapes) == sorted([(1, n + 1, 4) for n in (12, 20, 15, 9)] * 2) and cutoffs == {None}
    else:  # batches of 3 and 1 episodes, each cropped to its shortest
        assert sorted(s[0] for s in shapes) == [1, 1, 3, 3] and cutoffs == {150.0}
        assert all(s[1] <= 21 for s in shapes)


# ------------------------------------------------------------------ metrics
def _line(n: int, speed_mm: float) -> Trajectory:
    """A path whose object moves ``speed_mm`` along x each step."""
    states = np.zeros((n + 1, 4), np.float32)
    states[:, 0] = speed_mm * np.arange(n + 1)
    return Trajectory(states, np.zeros((n, 2), np.float32))


def test_divergence_threshold_and_count_per_definition_on_a_hand_made_path() -> None:
    still = _zero_change()  # predicts no motion: its error is the path's distance from the start
    episodes = TrajectorySet([_line(20, 1.0), _line(3, 1.0)])
    paper = evaluate_model(still, episodes, definition="paper")
    authors = evaluate_model(still, episodes, definition="authors")
    # errors 1, 2, 3...: past 4 mm first at step 5 -> 4 steps; past 10 mm at step 11 -> 11 (crossing counted)
    assert list(paper["divergence_steps"]) == [4, 3] and paper["epsilon_mm"] == 4.0
    assert list(authors["divergence_steps"]) == [11, 4] and authors["epsilon_mm"] == 10.0
    assert paper["never_diverged"] == authors["never_diverged"] == 1  # the 3-step path, censored at 3 / 3 + 1
    same_threshold = evaluate_model(still, episodes, epsilon_mm=4.0, definition="authors")
    assert list(same_threshold["divergence_steps"] - paper["divergence_steps"]) == [1, 1]
    true = np.stack([e.states for e in [_line(20, 1.0)]])
    assert divergence_time(np.zeros_like(true), true, 4.0) + 1 == divergence_time(
        np.zeros_like(true), true, 4.0, count_crossing_step=True)
    with pytest.raises(ValueError, match="definition must be one of"):
        evaluate_model(still, episodes, definition="code")


def test_mse_per_definition_on_hand_made_numbers() -> None:
    true = np.zeros((1, 3, 4))
    predicted = np.zeros((1, 3, 4))
    predicted[0, 1, :2] = [3.0, 4.0]  # 25 mm^2
    predicted[0, 2, :2] = [1.0, 0.0]  # 1 mm^2
    assert position_mse(predicted, true) == pytest.approx(13.0)  # paper: dx^2 + dy^2, mean over steps
    assert position_mse(predicted, true, per_coordinate=True) == pytest.approx(6.5)  # authors: over x and y
    still = _zero_change()
    episodes = TrajectorySet([_line(2, 2.0)])  # errors 2, 4 mm -> 4, 16 mm^2
    assert evaluate_model(still, episodes, definition="paper")["position_mse_mean"] == pytest.approx(10.0)
    assert evaluate_model(still, episodes, definition="authors")["position_mse_mean"] == pytest.approx(5.0)
