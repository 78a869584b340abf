"""The simulated hands: step interface, determinism, physics sanity, variants, collection."""

from __future__ import annotations

import numpy as np
import pytest

from t42_transfer.conventions import GRASP_LOAD, MIN_EPISODE_STEPS, OVERLOAD_LOAD
from t42_transfer.hand import SimulatedHand, sim, variant
from t42_transfer.hand.collect import RandomPolicy, collect, run_episode
from t42_transfer.hand.sim import LOAD_GUARD


@pytest.fixture(scope="module")
def source_hand() -> SimulatedHand:
    return SimulatedHand("source")


def test_reset_grasps_the_object(source_hand: SimulatedHand) -> None:
    state = source_hand.reset(seed=0)
    assert state.shape == (4,)
    assert abs(state[0]) < 15.0 and 60.0 < state[1] < 100.0
    # Loads are signed like the real servos and have passed the grasp threshold (minus sensor noise).
    assert state[2] > GRASP_LOAD - 5 and state[3] < -(GRASP_LOAD - 5)
    assert not source_hand.done


def test_same_seed_same_numbers(source_hand: SimulatedHand) -> None:
    actions = RandomPolicy().sample(np.random.default_rng(5), 60)
    first = run_episode(source_hand, actions, seed=11)
    again = run_episode(SimulatedHand("source"), actions, seed=11)
    other = run_episode(source_hand, actions, seed=12)
    assert first == again
    assert not np.array_equal(first.states, other.states)


@pytest.mark.parametrize(
    "action, message",
    [((np.nan, 0.0), "finite"), ((0.0, np.inf), "finite"), ((1.6, 0.0), "outside"), ((0.1, 0.2, 0.3), "2 finite")],
)
def test_bad_actions_are_refused(source_hand: SimulatedHand, action: tuple, message: str) -> None:
    source_hand.reset(seed=1)
    before = source_hand.state
    with pytest.raises(ValueError, match=message):
        source_hand.step(np.array(action))
    np.testing.assert_array_equal(source_hand.state, before)


def test_step_after_episode_end_raises(source_hand: SimulatedHand) -> None:
    source_hand.reset(seed=2)
    for _ in range(400):
        source_hand.step((-1.0, -1.0))
        if source_hand.done:
            break
    assert source_hand.done
    with pytest.raises(RuntimeError, match="reset"):
        source_hand.step((0.0, 0.0))


def test_opening_both_fingers_drops_the_object(source_hand: SimulatedHand) -> None:
    source_hand.reset(seed=3)
    for _ in range(400):
        source_hand.step((-1.0, -1.0))
        if source_hand.done:
            break
    assert source_hand.end_reason in ("dropped", "lost_contact")


def test_tightening_past_the_load_guard_is_refused(source_hand: SimulatedHand) -> None:
    source_hand.reset(seed=4)
    refused, peak = False, 0.0
    for _ in range(300):
        info = source_hand.step_info((1.0, 1.0))
        refused |= info.refused
        peak = max(peak, float(np.max(np.abs(source_hand.state[2:]))))
    assert refused and not source_hand.done
    assert LOAD_GUARD - 20 < peak < OVERLOAD_LOAD


def test_overload_ends_the_episode(source_hand: SimulatedHand, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sim, "LOAD_GUARD", np.inf)  # a driver without the guard
    source_hand.reset(seed=4)
    for _ in range(400):
        state = source_hand.step((1.0, 1.0))
        if source_hand.done:
            break
    assert source_hand.end_reason == "overload"
    assert np.max(np.abs(state[2:])) > OVERLOAD_LOAD


def _x_shift(params, action) -> float:
    hand = SimulatedHand(params)
    start = hand.reset(seed=0)
    for _ in range(15):
        state = hand.step(action)
    return float(state[0] - start[0])


def test_differential_actions_move_the_object_sideways_and_mirroring_reverses_it() -> None:
    right = _x_shift("source", (1.0, -1.0))
    left = _x_shift("source", (-1.0, 1.0))
    assert right * left < 0 and min(abs(right), abs(left)) > 2.0
    mirrored = variant("source").with_(name="mirrored", actuator_order=(1, 0))
    assert _x_shift(mirrored, (1.0, -1.0)) * right < 0


def test_variants_are_reproducible_and_distinct() -> None:
    assert variant("family-3") == variant("family-3")
    assert variant("family-3") != variant("family-4")
    assert variant("source") != variant("target")
    with pytest.raises(ValueError, match="unknown hand variant"):
        variant("blue")
    with pytest.raises(ValueError, match="family-<integer seed>"):
        variant("family-x")


def test_random_policy_bounds_and_holding() -> None:
    actions = RandomPolicy(hold_max=4).sample(np.random.default_rng(0), 500)
    assert actions.shape == (500, 2)
    assert np.all(np.abs(actions) <= 1.0)
    changes = np.flatnonzero(np.any(np.diff(actions, axis=0) != 0, axis=1))
    runs = np.diff(np.r_[-1, changes, len(actions) - 1])
    assert runs.max() <= 4 and runs.min() >= 1
    assert np.all(RandomPolicy(hold_max=1).sample(np.random.default_rng(0), 50)[1:] != 0)


def test_collection_is_deterministic_whatever_the_worker_count() -> None:
    serial, stats = collect("target", episodes=6, steps=80, seed=9, workers=1, progress=False)
    parallel, _ = collect("target", episodes=6, steps=80, seed=9, workers=2, progress=False)
    assert len(serial) == len(parallel) > 0
    assert all(a == b for a, b in zip(serial, parallel))
    assert stats.kept + stats.too_short + stats.grasp_failed == stats.requested
    assert all(len(t) >= MIN_EPISODE_STEPS and t.hand == "target" for t in serial)
    assert all(t.actuator_angles is not None for t in serial)


def _nearest_neighbour_divergence(train, test, epsilon_mm: float = 4.0) -> float:
    """Mean steps before an open-loop nearest-neighbour rollout leaves epsilon of the truth."""
    x, a, y = train.transitions()
    features = np.c_[x, a]
    mean, std = features.mean(0), features.std(0)
    table, deltas = (features - mean) / std, y - x
    steps = []
    for traj in test:
        state = traj.states[0].astype(np.float64)
        k = 0
        for k, action in enumerate(traj.actions):
            query = (np.r_[state, action] - mean) / std
            state = state + deltas[np.argmin(((table - query) ** 2).sum(1))]
            if np.linalg.norm(state[:2] - traj.states[k + 1, :2]) > epsilon_mm:
                break
        steps.append(k)
    return float(np.mean(steps))


def test_source_data_predicts_the_target_hand_measurably_worse() -> None:
    train, _ = collect("source", episodes=40, steps=150, seed=1, progress=False)
    source_test, _ = collect("source", episodes=10, steps=150, seed=2, progress=False)
    target_test, _ = collect("target", episodes=10, steps=150, seed=2, progress=False)
    on_source = _nearest_neighbour_divergence(train, source_test)
    on_target = _nearest_neighbour_divergence(train, target_test)
    assert on_target < 0.8 * on_source, (on_source, on_target)
