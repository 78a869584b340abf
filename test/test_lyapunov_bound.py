"""The paper's Lyapunov bound term by term: exact cases (a model of itself, affine and quadratic maps) and refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor
from toys import StateIsLatent

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.evaluation.lyapunov_bound import bound_terms, gap_bound, jacobian_lipschitz, training_error
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.residual import CumulativeResidualModel

ONES = np.ones(4)


class Affine(StateIsLatent):
    """``x' = A x + a-gain``: a constant Jacobian, so ``c`` is 0."""

    def __init__(self, matrix: np.ndarray) -> None:
        super().__init__()
        self.matrix = torch.as_tensor(matrix, dtype=torch.float64)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return z @ self.matrix.to(z.dtype).T + 0.1 * torch.cat([action, action], dim=-1)


class Quadratic(StateIsLatent):
    """``x' = x + k x^2`` elementwise: ``J = I + 2k diag(x)``, so ``||J(p) - J(q)|| = 2k max|p_i - q_i|``."""

    def __init__(self, k: float) -> None:
        super().__init__()
        self.k = k

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return z + self.k * z**2 + 0.0 * action.sum(-1, keepdim=True)


def own_paths(model, episodes: int = 4, steps: int = 60, seed: int = 0) -> TrajectorySet:  # noqa: ANN001
    """Episodes of ``model``'s own open-loop rollouts (float64): data a model of itself fits exactly."""
    rng = np.random.default_rng(seed)
    x0 = torch.as_tensor(rng.normal(0.0, 1.0, (episodes, 4)))
    actions = torch.as_tensor(rng.uniform(-1, 1, (episodes, steps, 2)))
    with torch.no_grad():
        states = model.double().rollout(x0, actions)
    return TrajectorySet(Trajectory(states[i].numpy(), actions[i].numpy()) for i in range(episodes))


def grasp_net(seed: int = 0) -> TransitionModel:
    torch.manual_seed(seed)
    norm = Normalisation(np.zeros(4, np.float32), np.ones(4, np.float32), np.zeros(4, np.float32),
                         np.full(4, 0.05, np.float32))
    return TransitionModel(norm, grasp_input=True).eval()


def test_gap_bound_is_the_theorems_b():
    assert gap_bound(0.0, 0.0, 3.0) == 0.0
    assert gap_bound(0.5, 0.2, 2.0) == pytest.approx(4 * math.sqrt(6 * 0.25 * 4 + 0.4) + 10.0)
    assert gap_bound(1.0, 1.0, 0.0) == 0.0  # affine maps: no Jacobian gap whatever the data
    with pytest.raises(ValueError, match="non-negative"):
        gap_bound(-1.0, 0.1, 1.0)
    with pytest.raises(ValueError, match="finite"):
        gap_bound(math.inf, 0.1, 1.0)


def test_a_model_of_itself_on_its_own_paths_meets_the_bound_with_equality():
    """f_hat = f and the data from f: r = 0, epsilon = 0, so b = 0 and the bound is the exponent itself."""
    model = grasp_net()
    data = own_paths(model)
    terms = bound_terms(model, model, data, data, ONES, steps=60, burn_in=10, pairs=400)
    assert terms.r < 1e-6 and terms.epsilon < 1e-6  # float32 weights run in float64
    assert terms.c_model == terms.c_reference > 0  # a tanh network's Jacobian changes
    assert terms.b < 1e-2 and terms.log_term < 0.05
    assert terms.reference_exponent == pytest.approx(terms.measured, abs=1e-9)
    assert terms.bound >= terms.measured and terms.orbits == 4


def test_the_grasp_is_held_at_the_episode_start_in_the_training_error():
    """A start-state network's one-step error is taken with its episode's start state, as its rollouts run."""
    from t42_transfer.evaluation.metrics import max_training_error

    model = grasp_net(1)
    data = own_paths(model, seed=3)
    assert training_error(model, data, ONES) < 1e-6
    assert max_training_error(model, data.transitions(), ONES, starts=data.start_states()).normalised < 1e-5
    assert max_training_error(model, data.transitions(), state_scale=ONES).normalised > 1e-3  # grasp = x_t there


def test_the_bounds_epsilon_is_the_metrics_training_error_and_a_nan_one_shows():
    """One computation: epsilon is max_training_error's normalised metric (on the float64 copy), so a model that
    predicts NaN gives a NaN epsilon, which the bound then refuses, not a silent zero."""
    from t42_transfer.evaluation.metrics import max_training_error

    data = own_paths(Affine(np.diag([0.9, 0.8, 0.95, 0.7])), episodes=3, steps=40)
    model = Affine(np.diag([0.92, 0.8, 0.95, 0.7]))
    expected = max_training_error(model, data.transitions(), ONES, starts=data.start_states()).normalised
    assert training_error(model, data, ONES) == pytest.approx(expected, rel=1e-5) and expected > 0  # float32 there
    model.matrix[0, 0] = math.nan
    assert math.isnan(training_error(model, data, ONES))
    with pytest.raises(ValueError, match="finite"):
        gap_bound(0.1, training_error(model, data, ONES), 1.0)


def test_affine_maps_have_c_zero_and_a_bound_of_the_references_exponent():
    reference = Affine(np.diag([0.9, 0.8, 0.95, 0.7]))
    model = Affine(np.diag([0.92, 0.8, 0.95, 0.7]))
    data = own_paths(reference, episodes=3, steps=80)
    train = TrajectorySet([data[0]])
    terms = bound_terms(model, reference, train, data, ONES, steps=80, burn_in=10)
    assert terms.c_model == pytest.approx(0, abs=1e-12) and terms.c_reference == pytest.approx(0, abs=1e-12)
    assert terms.b == pytest.approx(0, abs=1e-5) and terms.r > 0 and terms.epsilon > 0
    assert terms.reference_exponent == pytest.approx(math.log(0.95), abs=1e-9)
    assert terms.measured == pytest.approx(math.log(0.95), abs=1e-9)
    assert terms.inverse_norm == pytest.approx(1 / 0.7)


def test_c_of_a_quadratic_map_is_between_k_and_2k():
    """||J(p) - J(q)|| / ||p - q|| = 2k max|d_i| / ||d||, in [2k / sqrt(4), 2k]; near pairs along the paths reach it."""
    k = 0.05
    data = own_paths(Affine(np.eye(4) * 0.99), episodes=3, steps=50)
    c = jacobian_lipschitz(Quadratic(k), data, ONES, pairs=600)
    assert k <= c <= 2 * k * (1 + 1e-9)
    scaled = jacobian_lipschitz(Quadratic(k), data, np.full(4, 2.0), pairs=600)  # x / 2: J's change per unit doubles
    assert scaled == pytest.approx(2 * c)


def test_models_with_hidden_state_are_refused():
    plain = TransitionModel(Normalisation.identity())
    summed = CumulativeResidualModel(plain, TransitionModel(Normalisation.identity()), 1.0, 0.9)
    data = own_paths(Affine(np.eye(4) * 0.99), episodes=2, steps=20)
    with pytest.raises(ValueError, match="hidden state beyond the hand state"):
        bound_terms(summed, plain, data, data, ONES)


def test_orbits_shorter_than_the_burn_in_are_refused():
    model = Affine(np.eye(4) * 0.9)
    data = own_paths(model, episodes=2, steps=20)
    with pytest.raises(ValueError, match="longer than the burn-in"):
        bound_terms(model, model, data, data, ONES, steps=300, burn_in=50)


def test_the_script_analyses_every_kept_cell_of_a_run(source_model, tmp_path, one_torch_thread):  # noqa: ANN001
    """scripts/lyapunov_bound.py on a small stored run: the source as the reference makes direct's bound exact."""
    import importlib.util
    import json
    from pathlib import Path

    from t42_transfer.evaluation.experiment import run_experiment
    from t42_transfer.evaluation.experiment_config import DataSpec, ExperimentConfig

    repo = Path(__file__).resolve().parents[1]
    cfg = ExperimentConfig(name="b", source=DataSpec(model=str(source_model)),
                           target=DataSpec(bag=str(repo / "bags" / "target_small")),
                           methods=("direct", "naive_finetune", "cumulative_residual"), split="paths", amounts=(2,),
                           seeds=1, lyapunov_steps=5, workers=1)
    run_experiment(cfg, tmp_path / "runs", progress=False)
    spec = importlib.util.spec_from_file_location("lyapunov_bound_script", repo / "scripts" / "lyapunov_bound.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "bound.json"
    assert script.main([str(tmp_path / "runs" / "b"), "--reference", str(source_model), "--steps", "40",
                        "--burn-in", "5", "--pairs", "200", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    cells = {c["method"]: c for c in result["cells"]}
    assert set(cells) == {"direct", "naive_finetune"}
    direct = cells["direct"]  # the model is its own reference: same Jacobians along the same orbits
    assert direct["reference_exponent"] == pytest.approx(direct["measured"], abs=1e-9)
    assert direct["bound"] >= direct["measured"] and direct["r"] > 0 and direct["epsilon"] > 0
    assert cells["naive_finetune"]["r"] == direct["r"]  # a property of the cell's data, not of the model
    (skipped,) = result["skipped"]
    assert skipped["cell"][0] == "cumulative_residual" and "hidden state" in skipped["why"]
    assert math.isfinite(skipped["measured"])
