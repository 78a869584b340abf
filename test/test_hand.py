"""The simulated hands: step interface, determinism, physics sanity, variants, collection."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from t42_transfer.conventions import GRASP_LOAD, MIN_EPISODE_STEPS, OVERLOAD_LOAD, REAL_HAND_ACTIONS
from t42_transfer.hand import SimulatedHand, sim, variant
from t42_transfer.hand.collect import POLICIES, RandomPolicy, SustainedPolicy, collect, run_episode
from t42_transfer.hand.params import ABRUPT_REGION, RegionChange
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


def test_transmission_friction_holds_the_fingers_before_the_object_moves() -> None:
    """Dry friction in the tendons is a dead band: after a change of move the fingers wait until the tension has
    changed by the friction (the real hands wait 35-73 steps); without it the object moves at once."""
    from t42_transfer.data.trajectory import TrajectorySet
    from t42_transfer.hand.mjcf import hand_mjcf
    from t42_transfer.hand.realism import held_move_onsets

    actions = np.array([(1.0, -1.0)] * 60 + [(-1.0, 1.0)] * 60)
    waits = {}
    for friction in ({}, {"tendon_friction_n": 10.0}, {"joint_friction_nm": 0.05}):
        hand = SimulatedHand(variant("source").with_(**friction))
        path = run_episode(hand, actions, 0)
        assert len(path) == len(actions)
        onsets = held_move_onsets("sim", TrajectorySet([path]), threshold_mm=2.0, window=10, min_steps=50)
        waits[tuple(friction)] = [o.onset_steps for o in onsets]
    assert waits[()] == [1.0, 1.0]
    assert min(waits[("tendon_friction_n",)]) >= 3 and min(waits[("joint_friction_nm",)]) >= 3
    for name in ("source", "target", "target_abrupt"):  # the named hands have none: their model is as before
        assert "frictionloss" not in hand_mjcf(variant(name), (0.0, 90.0))
    assert variant("source").with_(joint_friction_nm=np.float32(0.01)).joint_friction_nm == np.float32(0.01)
    for field in ("tendon_friction_n", "joint_friction_nm"):
        for bad in (-1.0, float("nan"), "1", True):
            with pytest.raises(ValueError, match=field):
                variant("source").with_(**{field: bad})


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
    assert all(a == b for a, b in zip(serial, parallel, strict=True))
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


# ------------------------------------------------------------------ the abrupt target


def test_region_change_contains_and_refuses_bad_axes() -> None:
    right = RegionChange(axis="x", threshold_mm=10.0)
    assert right.contains(np.array([10.5, 0.0])) and not right.contains(np.array([9.5, 99.0]))
    low = RegionChange(axis="y", threshold_mm=60.0, above=False)
    assert low.contains(np.array([50.0, 59.0])) and not low.contains(np.array([0.0, 61.0]))
    with pytest.raises(ValueError, match="axis"):
        RegionChange(axis="z")
    abrupt = variant("target_abrupt")
    assert abrupt.region == ABRUPT_REGION and variant("source").region is None
    assert abrupt.with_(name="source", region=None) == variant("source")  # the source everywhere else


def test_a_region_covering_the_workspace_is_the_same_as_changing_the_hand() -> None:
    """Every field a region changes reaches the physics: region values everywhere == a hand built with them."""
    change = RegionChange(axis="y", threshold_mm=0.0, pad_friction=0.5, link_friction=0.6, k_proximal_scale=2.0,
                          k_distal_scale=0.5)
    base = variant("source")
    changed = base.with_(
        pad_friction=0.5, link_friction=0.6,
        left=dataclasses.replace(base.left, k_proximal=2.0 * base.left.k_proximal, k_distal=0.5 * base.left.k_distal),
        right=dataclasses.replace(base.right, k_proximal=2.0 * base.right.k_proximal,
                                  k_distal=0.5 * base.right.k_distal),
    )
    actions = RandomPolicy().sample(np.random.default_rng(6), 80)
    everywhere = run_episode(SimulatedHand(base.with_(region=change)), actions, seed=5)
    assert everywhere == run_episode(SimulatedHand(changed), actions, seed=5)
    unchanged = run_episode(SimulatedHand(base), actions, seed=5)
    for field in ("pad_friction", "link_friction", "k_proximal_scale", "k_distal_scale"):  # each one reaches it
        one = RegionChange(axis="y", threshold_mm=0.0, **{field: getattr(change, field)})
        assert not np.array_equal(run_episode(SimulatedHand(base.with_(region=one)), actions, seed=5).states,
                                  unchanged.states), field


def test_abrupt_target_steps_like_the_source_outside_its_region_only(source_hand: SimulatedHand) -> None:
    """From the same instant and action, one step of each hand: identical outside the region, not inside."""
    abrupt = SimulatedHand("target_abrupt")
    gaps: dict[bool, list[float]] = {True: [], False: []}
    for episode in range(4):
        source_hand.reset(seed=40 + episode)
        actions = RandomPolicy().sample(np.random.default_rng([13, episode]), 150)
        for action in actions:
            snap = source_hand.snapshot()
            abrupt.restore(snap)
            inside = abrupt.in_region
            assert inside == (source_hand.object_xy[0] > ABRUPT_REGION.threshold_mm)
            expected, got = source_hand.step(action), abrupt.step(action)
            gaps[inside].append(float(np.abs(got - expected).max()))
            if source_hand.done:
                break
    assert len(gaps[False]) > 100 and len(gaps[True]) > 30, {k: len(v) for k, v in gaps.items()}
    assert max(gaps[False]) == 0.0  # bit for bit: same physics, same sensor noise
    assert np.median(gaps[True]) > 1.0  # millimetres or load units per step, where steps are ~0.5 mm


def test_abrupt_target_replays_source_episodes_until_the_object_enters_the_region() -> None:
    entered = 0
    for episode in range(6):
        actions = SustainedPolicy().sample(np.random.default_rng([14, episode]), 300)
        source = run_episode(SimulatedHand("source"), actions, seed=episode)
        abrupt = run_episode(SimulatedHand("target_abrupt"), actions, seed=episode)
        x = source.states[:, 0]
        clear = np.flatnonzero(x > ABRUPT_REGION.threshold_mm - 0.5)  # tracker noise is 0.05 mm
        first = int(clear[0]) if len(clear) else len(x)
        np.testing.assert_array_equal(abrupt.states[: first + 1], source.states[: first + 1])
        deep = np.flatnonzero(x > ABRUPT_REGION.threshold_mm + 0.5)
        if len(deep) and deep[0] + 1 < len(abrupt.states):
            entered += 1
            later = slice(deep[0] + 1, min(len(source.states), len(abrupt.states)))
            assert not np.array_equal(abrupt.states[later], source.states[later])
    assert entered >= 2


# ------------------------------------------------------------------ sustained test paths


def _holds(actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first index, length) of every run of equal consecutive actions."""
    changes = np.flatnonzero(np.any(np.diff(actions, axis=0) != 0, axis=1))
    starts = np.r_[0, changes + 1]
    return starts, np.diff(np.r_[starts, len(actions)])


def test_sustained_policy_holds_real_moves_for_long() -> None:
    policy = SustainedPolicy(hold_min=50, hold_max=200)
    actions = policy.sample(np.random.default_rng(3), 20_000)
    assert actions.shape == (20_000, 2)
    moves = {tuple(a) for a in REAL_HAND_ACTIONS}
    assert {tuple(a) for a in actions} <= moves and np.abs(actions).max() == 1.5
    starts, lengths = _holds(actions)
    assert lengths[:-1].min() >= 50 and lengths.max() <= 200  # the last hold may be cut short
    # Log-uniform lengths: the median hold is near the geometric mean, sqrt(50 * 200) = 100.
    assert 85 < np.median(lengths[:-1]) < 115
    # Moves follow the real paths' mix: differential moves about 11 holds in 20, never one twice in a row.
    chosen = actions[starts]
    differential = np.mean(chosen[:, 0] * chosen[:, 1] == -1.0)
    assert 0.45 < differential < 0.65
    np.testing.assert_array_equal(SustainedPolicy().sample(np.random.default_rng(3), 500),
                                  SustainedPolicy().sample(np.random.default_rng(3), 500))
    only_two = SustainedPolicy(hold_min=5, hold_max=5, weights=(0, 0, 1, 1, 0, 0, 0, 0)).sample(
        np.random.default_rng(0), 40)
    np.testing.assert_array_equal(only_two[::5], np.array([only_two[0], -only_two[0]] * 4))


@pytest.mark.parametrize(
    "kwargs", [{"hold_min": 0}, {"hold_min": 10, "hold_max": 9}, {"hold_max": 10**6}, {"weights": (1.0,) * 7},
               {"weights": (1, 0, 0, 0, 0, 0, 0, 0)}, {"weights": (1, -1, 1, 1, 1, 1, 1, 1)}],
)
def test_sustained_policy_refuses_bad_settings(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        SustainedPolicy(**kwargs)


def test_collect_runs_named_policies() -> None:
    assert set(POLICIES) == {"random", "sustained"}
    data, stats = collect("target_abrupt", episodes=2, steps=200, seed=0, workers=1, policy=POLICIES["sustained"](),
                          progress=False)
    assert stats.requested == 2 and all(t.hand == "target_abrupt" for t in data)
    for t in data:
        assert {tuple(a) for a in t.actions} <= {tuple(a) for a in REAL_HAND_ACTIONS}
        assert _holds(t.actions)[1][0] >= min(len(t.actions), 120)


def test_a_settled_grasp_continued_is_the_whole_episode_run_again() -> None:
    """run_settled replays exactly what run_episode gives for the settling then the actions: the goal search of the
    demo's same-grasp goals relies on it (one settling, many attempts)."""
    from t42_transfer.hand.collect import run_episode, run_settled, settle

    hand = SimulatedHand("target")
    rng = np.random.default_rng(3)
    settled = settle(hand, seed=11, steps=20)
    assert len(settled.prefix) == 20 and settled.snapshot is not None
    for _ in range(3):
        actions = rng.uniform(-1, 1, size=(25, 2)).astype(np.float32)
        again = run_settled(hand, settled, actions)
        whole = run_episode(hand, np.concatenate([np.zeros((20, 2), np.float32), actions]), 11)
        assert again == whole and np.array_equal(again.actuator_angles, whole.actuator_angles)
        assert again.end_reason == whole.end_reason
