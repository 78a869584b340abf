"""Trajectory, TrajectorySet and split_by_fraction: validation, equality, fingerprints, splits."""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from t42_transfer.data.trajectory import Trajectory, TrajectorySet, split_by_fraction


def episode(steps: int = 5, seed: int = 0, **kwargs) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(states=rng.normal(size=(steps + 1, 4)), actions=rng.uniform(-1, 1, (steps, 2)), **kwargs)


# ------------------------------------------------------------------ Trajectory


def test_arrays_become_read_only_float32():
    traj = episode(actuator_angles=np.zeros((6, 2)))
    for arr in (traj.states, traj.actions, traj.actuator_angles):
        assert arr.dtype == np.float32 and arr.flags.c_contiguous and not arr.flags.writeable
    assert len(traj) == 5
    x, a, x_next = traj.transitions()
    assert np.array_equal(x, traj.states[:-1]) and np.array_equal(x_next, traj.states[1:]) and a is traj.actions


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"states": np.zeros((4, 3)), "actions": np.zeros((3, 2))}, r"states must have shape \[n, 4\]"),
        ({"states": np.zeros(4), "actions": np.zeros((3, 2))}, "states must have shape"),
        ({"states": np.zeros((4, 4)), "actions": np.zeros((3, 1))}, r"actions must have shape \[n, 2\]"),
        ({"states": np.zeros((4, 4)), "actions": np.zeros((4, 2))}, "one more state than actions"),
        (
            {"states": np.zeros((4, 4)), "actions": np.zeros((3, 2)), "actuator_angles": np.zeros((3, 2))},
            "actuator_angles has 3 rows",
        ),
        ({"states": np.zeros((4, 4)), "actions": np.zeros((3, 2)), "end_reason": "crashed"}, "unknown end_reason"),
    ],
)
def test_bad_shapes_and_values_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Trajectory(**kwargs)


@pytest.mark.parametrize("field", ["states", "actions", "actuator_angles"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_refused_with_their_row(field, bad):
    arrays = {"states": np.zeros((4, 4)), "actions": np.zeros((3, 2)), "actuator_angles": np.zeros((4, 2))}
    arrays[field][2, 1] = bad
    with pytest.raises(ValueError, match=f"{field} has a non-finite value at row 2"):
        Trajectory(**arrays)


def test_equality_covers_every_field():
    base = episode(actuator_angles=np.ones((6, 2)), start_ns=5, end_reason="length", hand="a")
    assert base == dataclasses.replace(base)
    assert base != "not a trajectory"
    for change in (
        {"states": base.states + 1},
        {"actions": base.actions * 0},
        {"actuator_angles": None},
        {"actuator_angles": np.zeros((6, 2))},
        {"start_ns": 6},
        {"end_reason": "dropped"},
        {"hand": "b"},
        {"step_ns": [100_000_000] * 4 + [400_000_000]},
    ):
        assert base != dataclasses.replace(base, **change), change
    with pytest.raises(TypeError):
        hash(base)


def test_step_durations_mark_late_steps_and_default_to_one_period():
    assert episode().durations_ns.tolist() == [100_000_000] * 5 and episode().late_steps.tolist() == []
    late = episode(step_ns=[100_000_000, 150_000_000, 150_000_001, 98_000_000, 900_000_000])
    assert late.late_steps.tolist() == [2, 4] and not late.step_ns.flags.writeable
    assert late == episode(step_ns=late.durations_ns) and episode() == episode(step_ns=[100_000_000] * 5)
    for bad in ([100_000_000] * 4, [100_000_000] * 4 + [0]):
        with pytest.raises(ValueError, match="step_ns must hold one positive duration per action"):
            episode(step_ns=bad)


def test_fingerprint_is_a_stable_content_hash():
    a, b = episode(seed=1), episode(seed=1, start_ns=9, hand="other")
    assert a.fingerprint() == b.fingerprint()  # numbers only
    assert len(a.fingerprint()) == 64 and a.fingerprint() != episode(seed=2).fingerprint()
    zeros = Trajectory(states=np.zeros((2, 4)), actions=np.zeros((1, 2)))
    assert zeros.fingerprint() == hashlib.sha256(bytes(4 * 8 + 4 * 2)).hexdigest()  # float32 states then actions


# ------------------------------------------------------------------ TrajectorySet


def test_set_basics():
    data = TrajectorySet([episode(3, 0), episode(4, 1)], hand="h")
    assert len(data) == 2 and data.num_transitions == 7 and data[1] == episode(4, 1)
    assert [len(t) for t in data] == [3, 4]
    assert repr(data) == "TrajectorySet(hand='h', episodes=2, transitions=7)"
    x, a, x_next = data.transitions()
    assert x.shape == x_next.shape == (7, 4) and a.shape == (7, 2)
    assert np.array_equal(x_next[3:], data[1].states[1:])
    starts = data.start_states()  # row for row with the transitions: each one's episode's first state
    assert starts.shape == (7, 4) and starts.dtype == np.float32
    assert np.array_equal(starts, np.repeat([data[0].states[0], data[1].states[0]], [3, 4], axis=0))
    sub = data.subset([1])
    assert sub.hand == "h" and len(sub) == 1 and sub[0] == data[1]
    empty = TrajectorySet(hand="h")
    assert [arr.shape for arr in empty.transitions()] == [(0, 4), (0, 2), (0, 4)]
    assert empty.start_states().shape == (0, 4)
    assert data.fingerprint() == TrajectorySet([episode(3, 0), episode(4, 1)]).fingerprint()
    assert data.fingerprint() != data.subset([1, 0]).fingerprint()


# ------------------------------------------------------------------ split_by_fraction


def varied_set(n: int = 20, seed: int = 0) -> TrajectorySet:
    lengths = np.random.default_rng(seed).integers(15, 60, size=n)
    return TrajectorySet([episode(int(k), i) for i, k in enumerate(lengths)], hand="h")


def test_split_keeps_whole_episodes_and_is_deterministic():
    data = varied_set()
    train, held = split_by_fraction(data, 0.3, seed=4)
    again = split_by_fraction(data, 0.3, seed=4)
    assert [t.fingerprint() for t in train] == [t.fingerprint() for t in again[0]]
    assert [t.fingerprint() for t in held] == [t.fingerprint() for t in again[1]]
    other = split_by_fraction(data, 0.3, seed=5)[0]
    assert [t.fingerprint() for t in train] != [t.fingerprint() for t in other]
    originals = {t.fingerprint() for t in data}
    assert all(t.fingerprint() in originals for t in [*train, *held])
    assert train.hand == held.hand == "h"


@settings(max_examples=60, deadline=None)
@given(fraction=st.floats(0.001, 1.0), seed=st.integers(0, 2**32 - 1), n=st.integers(2, 12))
def test_split_honours_the_fraction_and_partitions(fraction, seed, n):
    data = varied_set(n, seed=n)
    train, held = split_by_fraction(data, fraction, seed)
    got = sorted(t.fingerprint() for t in [*train, *held])
    assert got == sorted(t.fingerprint() for t in data)  # disjoint and complete
    assert len(train) >= 1
    assert len(held) == 0 if fraction == 1.0 else len(held) >= 1
    if len(train) > 1 and len(held) > 0:
        # taking stopped as soon as the target was met: without the last episode it was not
        assert train.num_transitions - len(train[-1]) < fraction * data.num_transitions
    if len(held) > 0 and len(train) < n - 1:
        assert train.num_transitions >= fraction * data.num_transitions


def test_single_episode_set_still_trains_on_one_episode():
    train, _ = split_by_fraction(varied_set(1), 0.5, seed=0)
    assert len(train) == 1


def test_tiny_fraction_of_equal_episodes_is_one_episode():
    data = TrajectorySet([episode(40, i) for i in range(300)])
    train, held = split_by_fraction(data, 0.003, seed=0)
    assert len(train) == 1 and len(held) == 299


@pytest.mark.parametrize("fraction", [0.0, -0.1, 1.5])
def test_split_rejects_bad_fractions(fraction):
    with pytest.raises(ValueError, match="fraction"):
        split_by_fraction(varied_set(3), fraction, seed=0)


def test_split_rejects_empty_sets():
    with pytest.raises(ValueError, match="empty"):
        split_by_fraction(TrajectorySet(), 0.5, seed=0)
