"""Divergence time, position MSE, evaluate_model, covering radius and max training error on known answers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.metrics import (
    covering_radius,
    divergence_time,
    evaluate_model,
    max_training_error,
    position_mse,
    position_mse_per_rollout,
    xy_error,
)
from t42_transfer.models.network import Normalisation, TransitionModel


def drifting(
    steps: int, per_step: tuple[float, float], start=(10.0, 110.0, 100.0, -100.0)
) -> tuple[np.ndarray, np.ndarray]:
    """``(predicted, true)`` where the prediction drifts from the truth by ``per_step`` (x, y mm) every step."""
    rng = np.random.default_rng(steps)
    true = np.asarray(start) + np.cumsum(rng.normal(0, 0.5, (steps + 1, 4)), axis=0)
    true[0] = start
    true = np.round(true * 64) / 64  # on a binary grid, so whole-mm drifts are exact
    drift = np.zeros((steps + 1, 4))
    drift[:, :2] = np.arange(steps + 1)[:, None] * np.asarray(per_step)
    return true + drift, true


def reference_divergence(err: np.ndarray, eps: float) -> int:
    """The definition, step by step: steps before the first k >= 1 whose error is not within eps."""
    for k in range(1, len(err)):
        if not err[k] <= eps:
            return k - 1
    return len(err) - 1


# ------------------------------------------------------------------ divergence time


def test_one_mm_per_step_diverges_after_four_steps_at_4mm():
    pred, true = drifting(10, (1.0, 0.0))
    # error k mm at step k: 4 mm at k = 4 is not more than 4 mm, 5 mm at k = 5 is.
    assert divergence_time(pred, true).tolist() == [4]
    assert divergence_time(pred, true, epsilon_mm=3.5).tolist() == [3]
    assert divergence_time(pred, true, epsilon_mm=0.5).tolist() == [0]


@pytest.mark.parametrize(("eps", "expected"), [(0.2, 0), (1.7, 3), (4.2, 8), (4.6, 9), (100.0, 12)])
def test_epsilon_is_configurable_and_error_is_euclidean_in_xy(eps, expected):
    pred, true = drifting(12, (0.3, -0.4))  # 0.5 mm per step along a 3-4-5 triangle
    pred[..., 2:] += 1e3  # load errors never count
    assert divergence_time(pred, true, epsilon_mm=eps).tolist() == [expected]


def test_never_and_first_step_divergence_in_one_batch():
    steps = 7
    pairs = [drifting(steps, (0.0, 0.1)), drifting(steps, (5.0, 0.0)), drifting(steps, (0.0, 0.0))]
    pred = np.stack([p for p, _ in pairs])
    true = np.stack([t for _, t in pairs])
    result = divergence_time(torch.as_tensor(pred), torch.as_tensor(true))
    assert result.shape == (3,) and result.dtype == np.int64
    assert result.tolist() == [steps, 0, steps]


def test_non_finite_prediction_counts_as_diverged():
    pred, true = drifting(6, (0.0, 0.0))
    pred[3, 0] = np.nan
    assert divergence_time(pred, true).tolist() == [2]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.0, 10.0, allow_nan=False), min_size=1, max_size=30),
    st.floats(0.1, 9.0, allow_nan=False),
)
def test_divergence_matches_the_definition(errors, eps):
    true = np.zeros((len(errors) + 1, 4))
    pred = true.copy()
    pred[1:, 1] = errors  # error purely in y, so the Euclidean error is exactly |dy|
    assert divergence_time(pred, true, epsilon_mm=eps)[0] == reference_divergence(xy_error(pred, true)[0], eps)


def test_lengths_mask_padding():
    pred, true = drifting(10, (1.0, 0.0))
    batch_pred, batch_true = np.stack([pred, pred]), np.stack([true, true])
    # Orbit 0 ends after 3 steps, before its error passes 4 mm; orbit 1 uses all 10.
    assert divergence_time(batch_pred, batch_true, lengths=[3, 10]).tolist() == [3, 4]
    with pytest.raises(ValueError, match="lengths"):
        divergence_time(batch_pred, batch_true, lengths=[0, 10])
    with pytest.raises(ValueError, match="lengths"):
        divergence_time(batch_pred, batch_true, lengths=[3, 11])


@pytest.mark.parametrize(
    ("pred_shape", "true_shape"), [((5, 4), (6, 4)), ((5, 3), (5, 3)), ((1, 4), (1, 4)), ((2, 3, 5, 4), (2, 3, 5, 4))]
)
def test_bad_shapes_are_rejected(pred_shape, true_shape):
    with pytest.raises(ValueError):
        divergence_time(np.zeros(pred_shape), np.zeros(true_shape))


# ------------------------------------------------------------------ position MSE


def test_position_mse_of_linear_drift():
    steps = 6
    pred, true = drifting(steps, (1.0, 0.0))
    expected = np.mean(np.arange(1, steps + 1) ** 2)  # step 0 is excluded
    assert position_mse(pred, true) == pytest.approx(expected)
    pred2, true2 = drifting(steps, (3.0, 4.0))  # 5 mm per step: squared distance 25 k^2
    per = position_mse_per_rollout(np.stack([pred, pred2]), np.stack([true, true2]), lengths=[2, 6])
    assert per == pytest.approx([(1 + 4) / 2, 25 * expected])
    assert position_mse(np.stack([pred, pred2]), np.stack([true, true2])) == pytest.approx(13 * expected)


# ------------------------------------------------------------------ evaluate_model

DELTA_MEAN = np.array([0.5, -0.25, 1.0, 0.0], np.float32)


def constant_step_model() -> TransitionModel:
    """A model whose net outputs zero, so it predicts ``x_{k+1} = x_k + delta_mean`` exactly."""
    norm = Normalisation(
        state_mean=np.array([5.0, 100.0, 50.0, -50.0], np.float32),
        state_std=np.array([2.0, 4.0, 30.0, 30.0], np.float32),
        delta_mean=DELTA_MEAN,
        delta_std=np.ones(4, np.float32),
    )
    model = TransitionModel(norm)
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
    return model


def episode_drifting_from_model(steps: int, speed_mm: float, seed: int) -> Trajectory:
    """True states that move ``speed_mm`` per step faster in x than the constant-step model predicts."""
    rng = np.random.default_rng(seed)
    start = np.array([5.0, 100.0, 50.0, -50.0]) + rng.normal(0, 1, 4)
    k = np.arange(steps + 1)[:, None]
    states = start + k * (DELTA_MEAN + np.array([speed_mm, 0.0, 0.0, 0.0]))
    return Trajectory(states=states, actions=rng.uniform(-1, 1, (steps, 2)))


def test_evaluate_model_on_an_analytic_rollout():
    # Divergence at 4 mm: 0.9 mm/step -> 4 steps; 0.3 mm/step -> 13 steps; 0 -> never.
    episodes = TrajectorySet(
        [
            episode_drifting_from_model(20, 0.9, 0),
            episode_drifting_from_model(8, 0.3, 1),
            episode_drifting_from_model(30, 0.3, 2),
            episode_drifting_from_model(16, 0.0, 3),
        ]
    )
    model = constant_step_model().train()
    result = evaluate_model(model, episodes, start_offsets=(0, 5, 25))
    assert model.training  # rollout switched dropout off only for itself

    # Rollouts ordered by episode, then offset; offset 25 exists only in the 30-step episode.
    assert result["episode"].tolist() == [0, 0, 1, 1, 2, 2, 2, 3, 3]
    assert result["offset"].tolist() == [0, 5, 0, 5, 0, 5, 25, 0, 5]
    assert result["steps"].tolist() == [20, 15, 8, 3, 30, 25, 5, 16, 11]
    expected_div = [4, 4, 8, 3, 13, 13, 5, 16, 11]
    assert result["divergence_steps"].tolist() == expected_div
    assert result["num_rollouts"] == 9 and result["num_episodes"] == 4
    assert result["never_diverged"] == 5  # both windows of episode 1, episode 2 from offset 25, both of episode 3
    assert result["divergence_mean"] == pytest.approx(np.mean(expected_div))
    assert result["divergence_median"] == pytest.approx(np.median(expected_div))

    speed = np.array([0.9, 0.9, 0.3, 0.3, 0.3, 0.3, 0.3, 0.0, 0.0])
    n = result["steps"]
    expected_mse = speed**2 * (n + 1) * (2 * n + 1) / 6  # mean of (speed k)^2 over k = 1..n
    np.testing.assert_allclose(result["position_mse"], expected_mse, rtol=1e-4, atol=1e-6)
    assert result["position_mse_mean"] == pytest.approx(expected_mse.mean(), rel=1e-4)


def test_evaluate_model_horizon_and_epsilon():
    episodes = TrajectorySet([episode_drifting_from_model(20, 0.9, 0)])
    result = evaluate_model(constant_step_model(), episodes, epsilon_mm=2.0, horizon=6)
    assert result["steps"].tolist() == [6]
    assert result["divergence_steps"].tolist() == [2]  # 1.8 mm at k = 2, 2.7 mm at k = 3
    assert result["epsilon_mm"] == 2.0


def test_evaluate_model_rejects_nothing_to_evaluate():
    episodes = TrajectorySet([episode_drifting_from_model(5, 0.0, 0)])
    with pytest.raises(ValueError, match="nothing to evaluate"):
        evaluate_model(constant_step_model(), episodes, start_offsets=(5, 9))
    with pytest.raises(ValueError, match="non-negative"):
        evaluate_model(constant_step_model(), episodes, start_offsets=(-1,))


# ------------------------------------------------------------------ covering radius


def test_covering_radius_of_a_grid():
    grid = np.stack(np.meshgrid(np.arange(11.0), np.arange(11.0)), axis=-1).reshape(-1, 2)
    centres = grid[grid.max(axis=1) < 10] + 0.5
    assert covering_radius(grid, centres) == pytest.approx(np.sqrt(0.5))
    assert covering_radius(grid, grid) == 0.0
    far = np.vstack([centres, [[20.0, 3.0]]])  # 10 mm right of (10, 3)
    assert covering_radius(grid, far) == pytest.approx(10.0)
    # Tiny blocks exercise the chunking and must agree with the one-block answer.
    assert covering_radius(torch.as_tensor(grid), far, max_pairs=7) == pytest.approx(10.0)


def test_covering_radius_matches_brute_force_in_4d():
    rng = np.random.default_rng(0)
    data, query = rng.normal(size=(300, 4)), rng.normal(size=(2100, 4)) * 2
    brute = np.sqrt(((query[:, None] - data[None]) ** 2).sum(-1)).min(axis=1).max()
    assert covering_radius(data, query, max_pairs=5000) == pytest.approx(brute, rel=1e-9)
    with pytest.raises(ValueError):
        covering_radius(data, query[:, :3])
    with pytest.raises(ValueError):
        covering_radius(np.zeros((0, 4)), query)


# ------------------------------------------------------------------ max training error


def test_max_training_error_in_normalised_units_and_mm():
    model = constant_step_model()
    rng = np.random.default_rng(0)
    x = rng.normal(0, 5, (50, 4)).astype(np.float32) + model.norm.state_mean
    a = rng.uniform(-1, 1, (50, 2)).astype(np.float32)
    offsets = np.zeros((50, 4), np.float32)
    offsets[7] = [0.0, 0.0, 60.0, 0.0]  # 2 state stds in load1, no x,y error
    offsets[31] = [0.6, 0.8, 0.0, 0.0]  # 1 mm in x,y: 0.3 and 0.2 state stds
    x_next = x + DELTA_MEAN + offsets
    err = max_training_error(model, (x, a, x_next), chunk=16)
    assert err.normalised == pytest.approx(2.0, rel=1e-4)
    assert err.xy_mm == pytest.approx(1.0, rel=1e-4)
    unit = max_training_error(model, (x, a, x_next), state_scale=np.ones(4))
    assert unit.normalised == pytest.approx(60.0, rel=1e-4)
