"""Data quality: frozen tracking and one-step jumps found where they are, and nowhere in clean paths."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from t42_transfer.conventions import CONTROL_PERIOD_NS, MIN_EPISODE_STEPS
from t42_transfer.data.quality import (
    FROZEN,
    JUMP,
    LATE,
    THRESHOLDS,
    Finding,
    find_problems,
    handle_flagged,
    scan,
    summarise,
    summary_lines,
)
from t42_transfer.data.trajectory import Trajectory, TrajectorySet


def path(steps: int = 600, seed: int = 0, noise_mm: float = 0.3, angles: bool = False) -> np.ndarray:
    """A clean hand-made path: states ``[steps + 1, 4]``, a smooth arc plus tracker noise, loads that wander."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2 * np.pi, steps + 1)
    xy = np.column_stack([30 + 20 * np.sin(t), 100 + 10 * np.cos(t)]) + rng.normal(0.0, noise_mm, (steps + 1, 2))
    loads = np.column_stack([100 + 30 * np.sin(3 * t), -100 - 30 * np.cos(3 * t)])
    return np.column_stack([xy, loads])


def freeze(states: np.ndarray, first: int, last: int, loads: bool = False) -> np.ndarray:
    """``states`` with the pose held from state ``first`` to ``last`` and the path going on from there afterwards
    (no jump when it resumes); the loads too when ``loads``."""
    held = last - first
    cols = slice(None) if loads else slice(0, 2)
    out = states.copy()
    out[first : last + 1, cols] = states[first, cols]
    out[last + 1 :, cols] = states[first + 1 : len(states) - held, cols]
    return out


def episode(
    states: np.ndarray, angles: np.ndarray | None = None, start_ns: int = 0, reason: str = "length"
) -> Trajectory:
    actions = np.tile([1.0, -1.0], (len(states) - 1, 1))
    return Trajectory(states=states, actions=actions, actuator_angles=angles, start_ns=start_ns, end_reason=reason)


def test_clean_paths_are_not_flagged() -> None:
    assert find_problems(episode(path(noise_mm=0.0))) == ()
    assert find_problems(episode(path(noise_mm=0.3, seed=1))) == ()  # a clean noisy path
    # The camera ran below 10 Hz: the pose stands still a few steps at a time, a third of all steps.
    stuttering = path(noise_mm=0.2, seed=2)
    for k in range(0, 600, 30):
        stuttering[k + 1 : k + 19, :2] = stuttering[k, :2]  # 18 steps in a row, the real files' longest
    assert find_problems(episode(stuttering)) == ()
    # A hand holding still (loads fixed too) is not lost tracking, however long.
    still = freeze(path(seed=3), 100, 400, loads=True)
    assert find_problems(episode(still)) == ()
    # Steps up to the real paths' largest (4.1 mm) are moves, not jumps.
    fast = path(seed=4)
    fast[300:, 0] += 4.1
    assert find_problems(episode(fast)) == ()


def test_a_frozen_stretch_is_found_where_it_is() -> None:
    states = freeze(path(seed=5), 120, 320)  # states 120..320 share one pose while the loads go on changing
    (found,) = find_problems(episode(states))
    assert (found.kind, found.start, found.end) == (FROZEN, 120, 321)  # transitions 120..320 are untrustworthy
    assert found.steps == 201
    assert found.size == pytest.approx(np.ptp(states[120:321, 2:], axis=0).max())
    assert "frozen tracking at steps 120-320 (201 steps" in found.describe()


def test_frozen_within_a_tiny_epsilon_and_with_turning_actuators() -> None:
    states = freeze(path(seed=6), 200, 299, loads=True)  # loads stay put ...
    states[200:300, :2] += np.random.default_rng(0).uniform(-2e-4, 2e-4, (100, 2))
    angles = np.column_stack([np.linspace(0, 1, 601)] * 2)  # ... but the actuators turn
    assert [(f.kind, f.start) for f in find_problems(episode(states, angles))] == [(FROZEN, 200)]
    assert find_problems(episode(states)) == ()  # without the angles: the hand held still


def test_too_short_a_freeze_is_not_flagged() -> None:
    states = path(seed=7)
    short = freeze(states, 50, 49 + THRESHOLDS.frozen_min_steps)  # one step short of the threshold
    assert find_problems(episode(short)) == ()
    assert [f.start for f in find_problems(episode(freeze(states, 50, 50 + THRESHOLDS.frozen_min_steps)))] == [50]


def test_jumps_are_found_with_their_size() -> None:
    states = path(seed=8)
    states[400:, 0] += 12.0  # transition 399 jumps 12 mm (plus the path's own step)
    states[500:, 1] -= 26.0
    found = find_problems(episode(states))
    assert [(f.kind, f.start, f.end) for f in found] == [(JUMP, 399, 400), (JUMP, 499, 500)]
    assert 11 < found[0].size < 13 and 25 < found[1].size < 27
    assert found[1].describe().startswith("jump of 2") and "at step 499" in found[1].describe()


def test_late_steps_are_found_with_their_duration_and_split_at() -> None:
    steps = np.full(100, CONTROL_PERIOD_NS, np.int64)
    steps[[40, 41]] = [450_000_000, 160_000_000]
    late = dataclasses.replace(episode(path(100, seed=2)), step_ns=steps)
    found = find_problems(late)
    assert [(f.kind, f.start, f.end, round(f.size)) for f in found] == [(LATE, 40, 41, 450), (LATE, 41, 42, 160)]
    assert found[0].describe() == "late step 40 (450 ms)"
    first, second = handle_flagged(TrajectorySet([late]), "split").data
    assert np.array_equal(first.states, late.states[:41]) and np.array_equal(second.states, late.states[42:])
    assert second.step_ns.tolist() == [CONTROL_PERIOD_NS] * 58
    assert second.start_ns == 40 * CONTROL_PERIOD_NS + 450_000_000 + 160_000_000


def test_a_late_step_may_move_the_jump_a_period_it_lasted() -> None:
    """A 0.3 s step moving 15 mm is late, not a jump (three periods' 24 mm); moving 30 mm it is both."""
    steps = np.full(100, CONTROL_PERIOD_NS, np.int64)
    steps[[30, 60]] = 300_000_000
    states = path(100, seed=3)
    states[31:, 0] += 15.0
    states[61:, 0] += 30.0
    found = find_problems(dataclasses.replace(episode(states), step_ns=steps))
    assert [(f.kind, f.start) for f in found] == [(LATE, 30), (JUMP, 60), (LATE, 60)]
    assert [(f.kind, f.start) for f in find_problems(episode(states))] == [(JUMP, 30), (JUMP, 60)]  # 0.1 s steps


def test_frozen_then_jump_as_on_the_real_hand() -> None:
    states = freeze(path(seed=9), 0, 198)  # tracking lost from the start, found again 26 mm away
    states[199:, 0] += 26.0
    found = find_problems(episode(states))
    assert [(f.kind, f.start, f.end) for f in found] == [(FROZEN, 0, 199), (JUMP, 198, 199)]


def _flagged_set() -> TrajectorySet:
    clean = episode(path(seed=10), start_ns=0)
    broken = freeze(path(seed=11), 100, 200)  # frozen: transitions 100..200
    broken[400:, :2] += broken[399, :2] - broken[400, :2] + (0.0, 15.0)  # jump: transition 399, exactly 15 mm
    angles = np.column_stack([np.linspace(0, 1, 601)] * 2)
    return TrajectorySet([clean, episode(broken, angles, start_ns=10**12, reason="dropped")], hand="h")


def test_scan_summary_and_lines() -> None:
    data = _flagged_set()
    findings = scan(data)
    assert list(findings) == [1]
    summary = summarise(data, findings)
    assert summary["episodes"] == 2 and summary["flagged_episodes"] == 1
    assert summary["flagged_transitions"] == 101 + 1
    assert [f["kind"] for f in summary["findings"]["1"]] == [FROZEN, JUMP]
    (line,) = summary_lines(findings, unit="path")
    assert line.startswith("path 1: frozen tracking at steps 100-200") and "jump of 15.0 mm at step 399" in line
    assert summary_lines({}) == ["none"]


def test_keep_drop_and_split() -> None:
    data = _flagged_set()
    kept = handle_flagged(data, "keep")
    assert all(a is b for a, b in zip(kept.data, data, strict=True)) and kept.origins == (0, 1)

    dropped = handle_flagged(data, "drop")
    assert len(dropped.data) == 1 and dropped.data[0] is data[0] and dropped.origins == (0,)

    split = handle_flagged(data, "split")
    assert split.origins == (0, 1, 1, 1)
    first, middle, last = split.data.trajectories[1:]
    broken = data[1]
    # States 0..100, 201..399, 400..600: the frozen and the jumping transitions are gone.
    assert np.array_equal(first.states, broken.states[:101]) and len(first) == 100
    assert np.array_equal(middle.states, broken.states[201:400]) and len(middle) == 198
    assert np.array_equal(last.states, broken.states[400:]) and len(last) == 200
    assert np.array_equal(middle.actions, broken.actions[201:399])
    assert np.array_equal(middle.actuator_angles, broken.actuator_angles[201:400])
    assert middle.start_ns == broken.start_ns + 201 * CONTROL_PERIOD_NS
    assert (first.end_reason, middle.end_reason, last.end_reason) == ("", "", "dropped")
    assert all(find_problems(t) == () for t in split.data)


def test_split_leaves_out_pieces_too_short_to_keep() -> None:
    states = freeze(path(seed=12), 0, MIN_EPISODE_STEPS + 59)  # frozen from the start: nothing before it
    states[590:, 0] += 10.0  # jump 10 steps before the end: too short after it
    whole = episode(states)
    (piece,) = handle_flagged(TrajectorySet([whole]), "split").data
    assert np.array_equal(piece.states, whole.states[MIN_EPISODE_STEPS + 60 : 590])


def test_unknown_handling_is_refused() -> None:
    with pytest.raises(ValueError, match="flagged must be one of"):
        handle_flagged(_flagged_set(), "repair")


def test_finding_is_typed_and_plain() -> None:
    finding = Finding(JUMP, 3, 4, 9.5)
    assert finding.as_dict() == {"kind": "jump", "start": 3, "end": 4, "size": 9.5} and finding.steps == 1


def test_the_drop_rule_ends_an_episode_before_its_first_jump_and_leaves_out_a_short_rest() -> None:
    """The paper's 8 mm rule on recorded episodes: a fall a real hand's driver may not have seen (hidden from its
    tracker), and a simulated hand's bag holds as its falling step."""
    from t42_transfer.data.quality import usable_stretches

    states = path(60)
    fallen = states.copy()
    fallen[31:, 1] -= 20.0  # the object falls in step 30 and lies there
    early = states.copy()
    early[6:, 0] += 9.0  # a jump in step 5: too little is left before it
    data = TrajectorySet([episode(states), episode(fallen, start_ns=10**10), episode(early, start_ns=2 * 10**10)])
    usable, notes = usable_stretches(data)
    kept = usable.data
    assert usable.origins == (0, 1) and usable.findings == {}
    assert len(kept) == 2 and kept[0] is data[0]  # a clean episode is left as it is
    assert np.array_equal(kept[1].states, data[1].states[:31]) and np.array_equal(kept[1].actions, data[1].actions[:30])
    assert kept[1].end_reason == "dropped" and kept[1].start_ns == 10**10
    assert len(notes) == 2 and "step 30" in notes[0] and "kept its first 30" in notes[0] and "left out" in notes[1]


def test_a_jump_out_of_frozen_tracking_is_the_marker_found_again_not_a_drop() -> None:
    """Hand B's path 0: the tracker froze for 198 steps, then the pose jumped 26 mm to where the object was. The
    frozen stretch is no data and the jump no fall: both are left out and the tracked rest is kept (the drop rule
    alone kept the frozen stretch and threw the rest away)."""
    from t42_transfer.data.quality import usable_stretches

    states = path(400)
    lost = states.copy()
    lost[1:120, :2] = states[0, :2]  # the pose stays put while the hand moves on; at state 120 it is found again
    assert np.linalg.norm(lost[120, :2] - lost[119, :2]) > 8.0  # the re-acquisition jumps like a fall
    fallen = states.copy()
    fallen[301:, 1] -= 20.0  # a true fall later in another episode still ends it
    data = TrajectorySet([episode(lost), episode(fallen, start_ns=10**11)])
    usable, notes = usable_stretches(data)
    assert usable.origins == (0, 1)
    rest, ended = usable.data
    assert np.array_equal(rest.states, lost[120:].astype(np.float32)) and len(rest) == 280  # the tracked rest, whole
    assert np.array_equal(ended.states, fallen[:301].astype(np.float32)) and ended.end_reason == "dropped"
    assert any("frozen tracking at steps 0-119" in n and "280 of its 400" in n for n in notes), notes
