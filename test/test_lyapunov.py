"""Benettin/QR Lyapunov exponents: Henon map, linear maps, masking, models, and the cumulative residual theorem."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor, nn
from toys import StateIsLatent

from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.lyapunov import (
    lyapunov_spectrum,
    maximal_lyapunov,
    model_lyapunov,
    model_lyapunov_spectrum,
    state_scales,
)
from t42_transfer.models.dynamics import LatentDynamics
from t42_transfer.models.network import Normalisation, TransitionModel

HENON_A, HENON_B = 1.4, 0.3
HENON_EXPONENTS = (0.4192, -1.6232)  # a = 1.4, b = 0.3 (Sprott, Chaos and Time-Series Analysis, 2003)


def henon(z: Tensor, a: Tensor) -> Tensor:
    """The Henon map as an autonomous system: the action input is ignored."""
    x, y = z[:, 0], z[:, 1]
    return torch.stack([1 - HENON_A * x**2 + y, HENON_B * x], dim=-1)


def henon_starts(batch: int, seed: int = 0) -> Tensor:
    """Starts near the origin, inside the attractor's basin."""
    return 0.1 + 0.05 * torch.rand(batch, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


# ------------------------------------------------------------------ generic maps


def test_henon_exponents():
    batch, steps = 64, 900
    spectrum = lyapunov_spectrum(henon, henon_starts(batch), torch.zeros(batch, steps, 1), burn_in=100)
    assert spectrum.shape == (batch, 2) and spectrum.dtype == torch.float64
    mean = spectrum.mean(dim=0)
    assert mean[0].item() == pytest.approx(HENON_EXPONENTS[0], abs=0.01)
    assert mean[1].item() == pytest.approx(HENON_EXPONENTS[1], abs=0.01)
    # Each finite-time orbit is close too (their spread is about 0.015 at this length).
    assert (spectrum[:, 0] - HENON_EXPONENTS[0]).abs().max() < 0.08
    # |det J| = b at every step, so the exponents of every orbit sum to ln b up to rounding.
    torch.testing.assert_close(spectrum.sum(dim=1), torch.full((batch,), math.log(HENON_B), dtype=torch.float64))


def test_henon_largest_exponent_after_burn_in_is_tight():
    """128 orbits of 2000 averaged steps after 200 of burn-in: their mean is within 0.003 of 0.4192."""
    batch, burn_in, steps = 128, 200, 2200
    exponent = maximal_lyapunov(henon, henon_starts(batch, seed=5), torch.zeros(batch, steps, 1), burn_in=burn_in)
    # One finite-time orbit spreads by about 0.008 at this length, so the mean's error is below 0.001.
    assert exponent.mean().item() == pytest.approx(HENON_EXPONENTS[0], abs=0.003)
    assert exponent.std().item() < 0.015


def test_contracting_linear_map_gives_its_log_eigenvalue_after_burn_in():
    """``[[0.5, 0], [5, 0.9]]``: exponents ln 0.9 and ln 0.5, but the first column of the starting frame is
    stretched about 5-fold at first (the matrix is far from normal); burn-in leaves that transient out."""
    matrix = torch.tensor([[0.5, 0.0], [5.0, 0.9]], dtype=torch.float64)

    def linear(z: Tensor, a: Tensor) -> Tensor:
        return z @ matrix.T

    z0, actions = torch.ones(1, 2, dtype=torch.float64), torch.zeros(1, 250, 1)
    expected = torch.tensor([[math.log(0.9), math.log(0.5)]], dtype=torch.float64)
    torch.testing.assert_close(lyapunov_spectrum(linear, z0, actions, burn_in=200), expected, rtol=0, atol=1e-9)
    # Without burn-in the 50-step estimate sits far above ln 0.9, although still below 0 after 250 steps.
    short = lyapunov_spectrum(linear, z0, actions[:, :50])
    assert short[0, 0] > math.log(0.9) + 0.02
    # The whole spectrum sums to ln |det| = ln 0.45 with or without burn-in.
    torch.testing.assert_close(short.sum(dim=1), expected.sum(dim=1), rtol=0, atol=1e-12)


def test_scales_analyse_the_map_in_normalised_coordinates():
    """Exponents with ``scales`` are those of the conjugate map ``u -> f(u * s) / s`` from ``z0 / s``."""
    scales = torch.tensor([20.0, 0.05], dtype=torch.float64)

    def stretched(z: Tensor, a: Tensor) -> Tensor:  # the Henon map in coordinates z = u * scales
        return henon(z / scales, a) * scales

    # Short orbits: the chaotic map amplifies the rounding of z / s * s by e^(0.42 t).
    z0, actions = henon_starts(6, seed=6) * scales, torch.zeros(6, 25, 1)
    raw = lyapunov_spectrum(stretched, z0, actions)
    normalised = lyapunov_spectrum(stretched, z0, actions, scales=scales)
    torch.testing.assert_close(normalised, lyapunov_spectrum(henon, z0 / scales, actions), rtol=0, atol=1e-9)
    assert (raw[:, 0] - normalised[:, 0]).abs().max() > 1e-3  # over a short orbit the units matter
    for bad in ([1.0], [1.0, 0.0], [1.0, float("nan")]):
        with pytest.raises(ValueError, match="scales"):
            lyapunov_spectrum(stretched, z0, actions, scales=torch.tensor(bad))


def test_linear_map_gives_log_abs_eigenvalues():
    eigenvalues = torch.tensor([2.0, -0.5, 0.25], dtype=torch.float64)
    basis = torch.tensor([[1.0, 0.3, -0.2], [0.1, 1.0, 0.4], [-0.3, 0.2, 1.0]], dtype=torch.float64)
    matrix = basis @ torch.diag(eigenvalues) @ torch.linalg.inv(basis)

    def linear(z: Tensor, a: Tensor) -> Tensor:
        return z @ matrix.T

    z0 = torch.randn(4, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    actions = torch.zeros(4, 250, 1)
    spectrum = lyapunov_spectrum(linear, z0, actions)
    expected = eigenvalues.abs().log().expand(4, 3)
    torch.testing.assert_close(spectrum, expected, atol=0.01, rtol=0)
    # Fewer frame columns give the leading exponents of the full spectrum.
    torch.testing.assert_close(lyapunov_spectrum(linear, z0, actions, k=2), spectrum[:, :2])
    torch.testing.assert_close(maximal_lyapunov(linear, z0, actions), spectrum[:, 0])


def test_actions_drive_the_map_in_float64():
    seen: list[torch.dtype] = []

    def scale_by_action(z: Tensor, a: Tensor) -> Tensor:
        seen.append(z.dtype)
        return z * a

    actions = torch.rand(3, 50, 1, generator=torch.Generator().manual_seed(2)) + 0.2  # float32 in
    exponent = maximal_lyapunov(scale_by_action, torch.ones(3, 1, dtype=torch.float32), actions)
    torch.testing.assert_close(exponent, actions.double().log().mean(dim=(1, 2)))
    assert set(seen) == {torch.float64}
    # Zero actions padding a short orbit collapse it (log 0 = -inf), but only past its length.
    padded = torch.cat([torch.full((1, 5, 1), 2.0), torch.zeros(1, 45, 1)], dim=1)
    both = maximal_lyapunov(
        scale_by_action, torch.ones(2, 1), torch.cat([padded, actions[:1]]), lengths=torch.tensor([5, 50])
    )
    torch.testing.assert_close(both, torch.stack([torch.tensor(math.log(2.0), dtype=torch.float64), exponent[0]]))


def test_lengths_end_orbits_as_if_run_alone():
    batch, steps = 5, 120
    z0, actions = henon_starts(batch, seed=3), torch.zeros(batch, steps, 1)
    lengths = torch.tensor([120, 40, 77, 31, 100])
    padded = lyapunov_spectrum(henon, z0, actions, burn_in=30, lengths=lengths)
    alone = torch.cat(
        [lyapunov_spectrum(henon, z0[i : i + 1], actions[i : i + 1, :n], burn_in=30) for i, n in enumerate(lengths)]
    )
    torch.testing.assert_close(padded, alone, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"k": 3}, "k must be"),
        ({"k": 0}, "k must be"),
        ({"burn_in": 10}, "burn_in"),
        ({"lengths": torch.tensor([10, 11])}, "at most"),
    ],
)
def test_bad_arguments_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        lyapunov_spectrum(henon, henon_starts(2), torch.zeros(2, 10, 1), **kwargs)


# ------------------------------------------------------------------ models


def zero_net_model(grasp_input: bool = False) -> TransitionModel:
    """``x' = x + delta_mean``: its Jacobian is the identity, so every exponent is exactly 0."""
    norm = Normalisation.identity()
    norm = Normalisation(norm.state_mean, norm.state_std, np.array([0.5, -0.2, 3.0, 1.0], np.float32), norm.delta_std)
    model = TransitionModel(norm, grasp_input=grasp_input)
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
    return model


@pytest.mark.parametrize("grasp_input", [False, True])
def test_translation_model_has_zero_exponents_over_its_state(grasp_input, small_set):
    spectrum = model_lyapunov_spectrum(zero_net_model(grasp_input), small_set)
    assert spectrum.shape == (len(small_set), 4)  # the grasp input is a parameter of the episode, not state
    torch.testing.assert_close(spectrum, torch.zeros_like(spectrum), rtol=0, atol=1e-12)


class ContractingWithGrasp(LatentDynamics):
    """Latent ``[x, g]``: ``x' = 0.9 x + 0.5 g`` and ``g' = g``, the grasp held as a network's start-state input is.

    Over the whole latent the spectrum is ``ln 0.9`` (x4) and 0 (x4, the held block); the dynamics is ``ln 0.9``.
    """

    kind = "test_contracting_with_grasp"
    latent_dim = 8

    def config(self) -> dict:
        return {}

    @classmethod
    def from_config(cls, config: dict) -> ContractingWithGrasp:
        return cls()

    def initial_latent(self, x0: Tensor) -> Tensor:
        return torch.cat([x0, x0], dim=-1)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        x, g = z[:, :4], z[:, 4:]
        return torch.cat([0.9 * x + 0.5 * g + 0.0 * action.sum(-1, keepdim=True), g], dim=-1)

    def observe(self, z: Tensor) -> Tensor:
        return z[:, :4]

    def held_latents(self) -> tuple[int, ...]:
        return (4, 5, 6, 7)


def test_held_grasp_coordinates_do_not_make_a_contracting_model_look_neutral(small_set):
    model = ContractingWithGrasp()
    spectrum = model_lyapunov_spectrum(model, small_set, burn_in=2)
    torch.testing.assert_close(spectrum, torch.full_like(spectrum, math.log(0.9)), rtol=0, atol=1e-9)
    scaled = model_lyapunov(model, small_set, scales=np.array([2.0, 3.0, 50.0, 60.0]))  # per state, repeated
    torch.testing.assert_close(scaled, torch.full_like(scaled, math.log(0.9)), rtol=0, atol=1e-9)
    # The same map with the grasp counted as state: its spectrum adds the held block's four exponents of 0.
    whole = lyapunov_spectrum(model.latent_step, model.initial_latent(torch.as_tensor(
        np.stack([t.states[0] for t in small_set]), dtype=torch.float64)), torch.zeros(len(small_set), 15, 2))
    torch.testing.assert_close(whole.sort(dim=1).values, torch.tensor([[math.log(0.9)] * 4 + [0.0] * 4],
                               dtype=torch.float64).expand(len(small_set), -1), rtol=0, atol=1e-9)


def test_held_latents_of_the_project_models():
    from t42_transfer.models.residual import CumulativeResidualModel, RecurrentResidualModel
    from t42_transfer.models.start_state import StartStateCumulativeResidualModel

    plain, grasp = TransitionModel(Normalisation.identity()), TransitionModel(Normalisation.identity(), True)
    assert plain.held_latents() == () and grasp.held_latents() == (4, 5, 6, 7)
    assert RecurrentResidualModel(grasp, TransitionModel(Normalisation.identity()), 1.0).held_latents() == (4, 5, 6, 7)
    cumulative = StartStateCumulativeResidualModel(grasp, TransitionModel(Normalisation.identity(), True), 1.0, 0.9)
    x0 = torch.zeros(3, 4)
    assert cumulative.held_latents() == (4, 5, 6, 7)
    assert cumulative.latent_dim == cumulative.initial_latent(x0).shape[1] == 12  # state, grasp, residual sum
    plain_sum = CumulativeResidualModel(plain, TransitionModel(Normalisation.identity()), 1.0, 0.9)
    assert plain_sum.held_latents() == () and plain_sum.latent_dim == plain_sum.initial_latent(x0).shape[1] == 8


def test_model_lyapunov_leaves_the_model_alone_and_ignores_dropout(small_set):
    torch.manual_seed(0)
    model = TransitionModel(Normalisation.identity()).train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    first = model_lyapunov(model, small_set)
    second = model_lyapunov(model, small_set)
    assert model.training and all(p.dtype == torch.float32 for p in model.parameters())
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert first.shape == (len(small_set),) and first.dtype == torch.float64
    torch.testing.assert_close(first, second, rtol=0, atol=0)  # dropout off: deterministic
    assert torch.isfinite(first).all() and first.abs().max() > 1e-3  # a random net is not a translation


@pytest.mark.parametrize("grasp_input", [False, True])
def test_model_exponents_in_the_models_normalised_coordinates(grasp_input):
    torch.manual_seed(3)
    norm = Normalisation(
        np.array([0, 90, 100, -100], np.float32), np.array([20, 10, 50, 50], np.float32),
        np.zeros(4, np.float32), np.array([0.3, 0.3, 3.0, 3.0], np.float32),
    )
    model = TransitionModel(norm, grasp_input=grasp_input).eval().double()
    std = state_scales(model)
    np.testing.assert_array_equal(std, [20, 10, 50, 50])
    x0 = torch.tensor([[0.0, 90.0, 100.0, -100.0]], dtype=torch.float64).repeat(3, 1) + torch.randn(3, 4).double()
    actions = torch.rand(3, 40, 2, dtype=torch.float64) * 2 - 1
    scales = torch.tensor(std)

    def in_units_of_std(u: Tensor, a: Tensor) -> Tensor:  # the grasp, when there is one, rides in a's columns 2-5
        z = torch.cat([u * scales, a[:, 2:]], dim=1)
        return model.latent_step(z, a[:, :2])[:, :4] / scales

    got = model_lyapunov_spectrum(model, (x0, actions), burn_in=10, scales=std)
    grasp = x0[:, None, :].expand(-1, actions.shape[1], -1)[..., : 4 if grasp_input else 0]
    expected = lyapunov_spectrum(in_units_of_std, x0 / scales, torch.cat([actions, grasp], dim=2), burn_in=10)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-10)
    assert not torch.allclose(got, model_lyapunov_spectrum(model, (x0, actions), burn_in=10), atol=1e-3)
    with pytest.raises(ValueError, match="scales must have"):
        model_lyapunov_spectrum(model, (x0, actions), scales=np.ones(3))


def test_state_scales_of_a_residual_model_are_the_sources():
    from t42_transfer.models import CumulativeResidualModel

    source_norm = Normalisation(np.zeros(4, np.float32), np.array([20, 10, 50, 50], np.float32),
                                np.zeros(4, np.float32), np.ones(4, np.float32))
    model = CumulativeResidualModel(TransitionModel(source_norm), TransitionModel(Normalisation.identity()), 0.3, 0.9)
    np.testing.assert_array_equal(state_scales(model), [20, 10, 50, 50])
    with pytest.raises(ValueError, match="no transition model"):
        state_scales(ToySource())


def test_episodes_and_explicit_arrays_agree(small_set: TrajectorySet):
    torch.manual_seed(1)
    model = TransitionModel(Normalisation.identity())
    from_set = model_lyapunov(model, small_set, steps=18)
    for i, ep in enumerate(small_set):  # lengths 20, 25, 16: cropped to 18, 18, 16
        n = min(len(ep), 18)
        alone = model_lyapunov(model, (ep.states[:1], ep.actions[None, :n]))
        torch.testing.assert_close(from_set[i : i + 1], alone, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ cumulative residual theorem


def small_mlp(inputs: int, outputs: int, seed: int, gain: float) -> nn.Sequential:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(inputs, 16), nn.Tanh(), nn.Linear(16, outputs))
    with torch.no_grad():
        for layer in (net[0], net[2]):
            layer.weight.mul_(gain)
    return net


class ToySource(StateIsLatent):
    """A contracting source model ``x' = 0.6 x + h(x, a)`` whose maximal exponent is negative."""

    def __init__(self) -> None:
        super().__init__()
        self.h = small_mlp(6, 4, seed=0, gain=1.5)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return 0.6 * z + self.h(torch.cat([z, action], dim=-1))


class ToyCumulativeResidual(LatentDynamics):
    """The paper's algorithm as a latent map: ``z = (x, y)``, ``x' = f_S(x, a)``, ``y' = gamma y + alpha g(x, a)``."""

    def __init__(self, source: LatentDynamics, gamma: float, alpha: float = 0.3) -> None:
        super().__init__()
        self.source, self.gamma, self.alpha = source, gamma, alpha
        self.latent_dim = 2 * source.latent_dim
        self.g = small_mlp(6, 4, seed=1, gain=3.0)

    def config(self) -> dict:
        return {"gamma": self.gamma, "alpha": self.alpha}

    @classmethod
    def from_config(cls, config: dict) -> ToyCumulativeResidual:
        return cls(ToySource(), **config)

    def initial_latent(self, x0: Tensor) -> Tensor:
        return torch.cat([self.source.initial_latent(x0), torch.zeros_like(x0)], dim=-1)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        x, y = z[:, :4], z[:, 4:]
        residual = self.g(torch.cat([x, action], dim=-1))
        return torch.cat([self.source.latent_step(x, action), self.gamma * y + self.alpha * residual], dim=-1)

    def observe(self, z: Tensor) -> Tensor:
        return self.source.observe(z[:, :4]) + z[:, 4:]


def check_cumulative_residual_theorem(
    source: LatentDynamics, model: LatentDynamics, gamma: float, x0: Tensor, actions: Tensor, tol: float
) -> Tensor:
    """Assert the paper's theorem on every orbit, and return the source's maximal exponents.

    The model's exponents are the source's together with ``ln gamma`` (once per
    residual dimension), so its maximal exponent is ``max(lambda_source, ln gamma)``.
    """
    source_spectrum = model_lyapunov_spectrum(source, (x0, actions))
    spectrum = model_lyapunov_spectrum(model, (x0, actions))
    residual_dims = spectrum.shape[1] - source_spectrum.shape[1]
    residual = torch.full((len(x0), residual_dims), math.log(gamma), dtype=torch.float64)
    expected = torch.cat([source_spectrum, residual], dim=1)
    torch.testing.assert_close(spectrum[:, 0], expected.max(dim=1).values, atol=tol, rtol=0)
    torch.testing.assert_close(spectrum.sort(dim=1).values, expected.sort(dim=1).values, atol=tol, rtol=0)
    return source_spectrum[:, 0]


@pytest.mark.parametrize(("gamma", "dominant"), [(0.9997, "ln gamma"), (0.5, "source")])
def test_cumulative_residual_theorem_on_toy_model(gamma, dominant):
    generator = torch.Generator().manual_seed(4)
    x0 = torch.randn(6, 4, generator=generator)
    actions = torch.rand(6, 200, 2, generator=generator) * 2 - 1
    source = ToySource()
    source_exponent = check_cumulative_residual_theorem(
        source, ToyCumulativeResidual(source, gamma), gamma, x0, actions, tol=0.02
    )
    # The construction must put each case on the intended side, with a clear margin.
    if dominant == "ln gamma":
        assert (source_exponent < math.log(gamma) - 0.1).all()
    else:
        assert (source_exponent > math.log(gamma) + 0.1).all()


@pytest.mark.parametrize("gamma", [0.5, 0.9997])
def test_cumulative_residual_theorem_on_the_real_model_classes(gamma):
    from t42_transfer.models import CumulativeResidualModel, Normalisation, TransitionModel

    torch.manual_seed(7)
    norm = Normalisation(
        np.array([0, 90, 100, -100], np.float32), np.array([20, 10, 50, 50], np.float32),
        np.zeros(4, np.float32), np.array([0.3, 0.3, 3.0, 3.0], np.float32),
    )
    source, residual = TransitionModel(norm), TransitionModel(norm)
    model = CumulativeResidualModel(source, residual, alpha=0.3, gamma=gamma)
    x0 = torch.tensor([[0.0, 90.0, 100.0, -100.0]]).repeat(4, 1) + torch.randn(4, 4)
    actions = torch.rand(4, 150, 2) * 2 - 1
    check_cumulative_residual_theorem(source, model, gamma, x0, actions, tol=0.02)


class Diagonal(StateIsLatent):
    """``z' = c * z`` per coordinate: exponents ``ln |c|``."""

    def __init__(self, c: tuple[float, ...]) -> None:
        super().__init__()
        self.c = torch.tensor(c, dtype=torch.float64)

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return z * self.c.to(z.dtype)


@pytest.mark.parametrize("c, gamma", [((0.5, 0.9, 0.95, 0.99), 0.5), ((1.2, 1.1, 1.05, 1.3), 1.0)])
def test_the_gamma_rule_is_e_to_the_smallest_exponent_capped_at_one(c, gamma, small_set):
    from t42_transfer.evaluation.lyapunov import lyapunov_gamma

    assert lyapunov_gamma(Diagonal(c), small_set) == pytest.approx(gamma, rel=1e-9)
    with pytest.raises(ValueError, match="at least one episode"):
        lyapunov_gamma(Diagonal(c), TrajectorySet([]))


def test_cumulative_residual_takes_the_rules_gamma(small_set):
    import dataclasses

    from t42_transfer.evaluation.lyapunov import lyapunov_gamma
    from t42_transfer.models.training import TrainConfig
    from t42_transfer.transfer.config import TransferConfig
    from t42_transfer.transfer.methods import transfer

    torch.manual_seed(0)
    source = TransitionModel(Normalisation.identity())
    base = TransferConfig()
    rule = dataclasses.replace(base.cumulative_residual, gamma_rule="lyapunov", train=TrainConfig(epochs=1))
    model = transfer("cumulative_residual", source, small_set, dataclasses.replace(base, cumulative_residual=rule), 0)
    assert model.gamma == pytest.approx(lyapunov_gamma(source, small_set)) and model.gamma != rule.gamma
    with pytest.raises(ValueError, match="gamma_rule must be one of"):
        dataclasses.replace(rule, gamma_rule="largest")
