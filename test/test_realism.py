"""Sim-vs-real statistics on hand-made paths with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.hand.realism import (
    held_move_onsets,
    held_move_rates,
    held_moves_table,
    held_onsets_table,
    held_runs,
    markdown_table,
    plot_held_moves,
    plot_held_onsets,
    replay,
    rows_as_dicts,
    summarise,
)


def _path(xy: list[tuple[float, float]], end_reason: str = "length") -> Trajectory:
    states = np.array([[x, y, 100.0 + i, -90.0 - i] for i, (x, y) in enumerate(xy)])
    return Trajectory(states=states, actions=np.zeros((len(xy) - 1, 2)), end_reason=end_reason)


def test_summarise_known_numbers() -> None:
    data = TrajectorySet(
        [_path([(0, 0), (3, 4), (3, 4), (6, 8)]), _path([(10, 10), (10, 12), (10, 14)], end_reason="dropped")]
    )
    stats = summarise("hand-made", data)
    assert stats.paths == 2 and stats.steps == 5
    # steps: 5, 0, 5, 2, 2 mm
    assert stats.step_median_mm == 2.0
    assert stats.zero_step_fraction == 0.2
    assert stats.x_span_mm == 3.0  # median of spans 6 and 0
    assert stats.y_span_mm == 6.0  # median of spans 8 and 4
    assert stats.load1_range == (100.0, 103.0) and stats.load2_range == (-93.0, -90.0)
    assert stats.drop_rate == 0.5
    table = markdown_table([stats])
    assert table.count("\n") == 3 and "| hand-made | 2 | 5 |" in table


def test_replay_runs_the_same_actions_on_the_simulated_hand() -> None:
    actions = np.tile([[1.0, -1.0]], (30, 1))
    real = TrajectorySet([Trajectory(states=np.zeros((31, 4)), actions=actions)])
    sim = replay(real, "source", seed=0)
    assert len(sim) == 1
    np.testing.assert_array_equal(sim[0].actions, actions[: len(sim[0])])
    assert np.ptp(sim[0].states[:, 0]) > 2.0  # a sustained sideways action moves the object


def test_held_runs_finds_stretches_of_one_action() -> None:
    actions = np.array([[1, 1]] * 3 + [[-1, 1]] * 5 + [[0, 1.5]] * 2 + [[-1, 1]] * 4, dtype=float)
    assert held_runs(actions, 4) == [(3, 8), (10, 14)]
    assert held_runs(actions, 6) == []
    assert held_runs(actions, 1) == [(0, 3), (3, 8), (8, 10), (10, 14)]


def _held_path(moves: list[tuple[tuple[float, float], int, float, float]]) -> Trajectory:
    """A path of held moves, each (action, steps, object speed mm/step along x, load1 change per step)."""
    actions, states = [], [np.array([0.0, 50.0, 100.0, -100.0])]
    for action, steps, speed, load_rate in moves:
        for _ in range(steps):
            actions.append(action)
            states.append(states[-1] + np.array([speed, 0.0, load_rate, -load_rate]))
    return Trajectory(states=np.array(states), actions=np.array(actions, dtype=float))


def test_held_move_rates_measure_the_first_window_of_each_run() -> None:
    # Path 2's run of [-1, 1] moves 0.1 mm/step for 10 steps, then stands still (the end of travel):
    # over a 10-step window it is 0.1 mm/step, not the whole run's 0.05.
    data = TrajectorySet([
        _held_path([((-1.0, 1.0), 12, 0.3, 2.0), ((1.0, 1.0), 5, 9.0, 9.0), ((-1.0, 1.0), 10, 0.1, 1.0)]),
        _held_path([((-1.0, 1.0), 10, 0.1, 1.0), ((-1.0, 1.0), 10, 0.0, 0.0)]),  # one run of 20 that stops at 10
    ])
    rows = held_move_rates("made", data, window=10)
    assert [r.action for r in rows] == [(-1.0, 1.0)]  # [1, 1] is held 5 < 10 steps
    (row,) = rows
    assert row.runs == 3 and row.window == 10
    assert row.speed_mm_per_step == pytest.approx(0.1)  # median of 0.3, 0.1, 0.1
    assert row.load1_per_step == pytest.approx(1.0) and row.load2_per_step == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="window"):
        held_move_rates("made", data, window=0)
    (later,) = held_move_rates("made", data, window=10, later_only=True)  # each path's first hold left out
    assert later.runs == 1 and later.speed_mm_per_step == pytest.approx(0.1)


def test_held_moves_table_gives_the_speed_against_the_real_hands() -> None:
    real = TrajectorySet([_held_path([((-1.0, 1.0), 20, 0.1, 1.0)])])
    fast = TrajectorySet([_held_path([((-1.0, 1.0), 20, 2.5, 1.0)])])
    rates = held_move_rates("real A", real, 10) + held_move_rates("sim source", fast, 10)
    table = held_moves_table(rates)
    assert "| [-1, 1] | sim source | 1 | 2.500 | +1.00 | -1.00 | 25.0x |" in table
    assert "| [-1, 1] | real A | 1 | 0.100 | +1.00 | -1.00 |  |" in table


def test_held_moves_figure_is_written(tmp_path) -> None:
    rates = held_move_rates("real A", TrajectorySet([_held_path([((-1.0, 1.0), 20, 0.1, 1.0)])]), 10)
    rates += held_move_rates("sim source", TrajectorySet([_held_path([((-1.0, 1.0), 20, 2.5, 1.0)])]), 10)
    path = plot_held_moves(rates, tmp_path / "speeds.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5_000


def test_a_real_speed_of_zero_gives_no_ratio_and_no_warning() -> None:
    """The real tracker stands still on a third of steps: over a short window a real median speed can be 0."""
    import warnings

    rates = held_move_rates("real A", TrajectorySet([_held_path([((-1.0, 1.0), 20, 0.0, 1.0)])]), 10)
    rates += held_move_rates("sim source", TrajectorySet([_held_path([((-1.0, 1.0), 20, 2.5, 1.0)])]), 10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        table = held_moves_table(rates)
    assert "| [-1, 1] | sim source | 1 | 2.500 | +1.00 | -1.00 |  |" in table and "inf" not in table


def _waiting_path(moves: list[tuple[tuple[float, float], int, int, float]]) -> Trajectory:
    """A path of held moves, each standing still for its first ``wait`` steps, then moving ``speed`` mm/step in x."""
    actions, states = [], [np.array([0.0, 50.0, 100.0, -100.0])]
    for action, steps, wait, speed in moves:
        for k in range(steps):
            actions.append(action)
            states.append(states[-1] + np.array([0.0 if k < wait else speed, 0.0, 0.0, 0.0]))
    return Trajectory(states=np.array(states), actions=np.array(actions, dtype=float))


def test_held_move_onsets_separate_the_wait_from_the_speed() -> None:
    # Three runs of [-1, 1]: waits of 30, 40 and 50 steps, then 0.1, 0.2 and 0.3 mm/step. The object has moved
    # 2 mm (the threshold) after 20 steps of 0.1, 10 of 0.2 and 7 of 0.3 (6.67 rounded up).
    data = TrajectorySet([
        _waiting_path([((-1.0, 1.0), 120, 30, 0.1), ((1.0, 1.0), 120, 200, 0.0)]),  # [1, 1] never moves
        _waiting_path([((-1.0, 1.0), 120, 40, 0.2)]),
        _waiting_path([((-1.0, 1.0), 120, 50, 0.3), ((1.0, -1.0), 50, 0, 1.0)]),  # [1, -1] held < 100 steps
    ])
    rows = held_move_onsets("made", data, threshold_mm=2.0, window=20, min_steps=100)
    assert [r.action for r in rows] == [(-1.0, 1.0), (1.0, 1.0)]
    moving, still = rows
    assert (moving.runs, moving.stuck, moving.moving_runs) == (3, 0, 3)
    assert moving.onset_steps == 50  # median of 30 + 20, 40 + 10 and 50 + 7
    assert moving.moving_speed_mm_per_step == pytest.approx(0.2)
    assert (still.runs, still.stuck, still.moving_runs) == (1, 1, 0)
    assert np.isnan(still.onset_steps) and np.isnan(still.moving_speed_mm_per_step)
    import json

    (row,) = [r for r in rows_as_dicts([still])]
    assert row["onset_steps"] is None and row["moving_speed_mm_per_step"] is None
    json.dumps(rows_as_dicts(rows), allow_nan=False)  # strict JSON: no NaN


def test_held_move_onsets_leave_out_a_speed_the_run_cannot_measure() -> None:
    # The object passes 2 mm at step 110 of a 120-step run: a 20-step window would run past the hold.
    rows = held_move_onsets("made", TrajectorySet([_waiting_path([((-1.0, 1.0), 120, 100, 0.2)])]), window=20)
    (row,) = rows
    assert row.onset_steps == 110 and row.moving_runs == 0 and np.isnan(row.moving_speed_mm_per_step)
    for bad in ({"threshold_mm": 0.0}, {"window": 0}, {"min_steps": 0}):
        with pytest.raises(ValueError):
            held_move_onsets("made", TrajectorySet([_waiting_path([((-1.0, 1.0), 120, 100, 0.2)])]), **bad)


def test_held_move_onsets_reach_the_holds_last_state_and_no_further() -> None:
    # Speeds are exact binary fractions, so a threshold or a window's end falls on the step it is meant to.
    # A 100-step hold whose object passes 2 mm only at the hold's last state (step 100): found, with no speed. The
    # next hold passes 2 mm at step 100 too (84 still, then 16 steps of 0.125 mm); the hold after it moves fast from
    # its first step, and none of that may leak into the holds before it.
    path = _waiting_path([((-1.0, 1.0), 100, 99, 2.5), ((1.0, -1.0), 100, 84, 0.125), ((1.0, 1.0), 100, 0, 9.0)])
    rows = {r.action: r for r in held_move_onsets("made", TrajectorySet([path]), window=20, min_steps=100)}
    for late in (rows[(-1.0, 1.0)], rows[(1.0, -1.0)]):
        assert late.onset_steps == 100 and late.moving_runs == 0
    # Onset at step 80 (64 still, 16 steps of 0.125): the 20-step window ends exactly on the hold's last state.
    path = _waiting_path([((1.0, -1.0), 100, 64, 0.125), ((1.0, 1.0), 100, 0, 9.0)])
    (edge, _) = held_move_onsets("made", TrajectorySet([path]), window=20, min_steps=100)
    assert edge.onset_steps == 80 and edge.moving_runs == 1 and edge.moving_speed_mm_per_step == 0.125


def test_held_move_onsets_speed_starts_at_the_onset() -> None:
    # 40 steps still, 20 steps at 0.0625 mm/step (1.25 mm: under the threshold), then 0.5 mm/step: 2 mm out at step
    # 62, and the 10 steps from there move 5 mm (from the hold's start, the mean would be lower).
    path = _waiting_path([((-1.0, 1.0), 60, 40, 0.0625), ((-1.0, 1.0), 60, 0, 0.5)])
    (row,) = held_move_onsets("made", TrajectorySet([path]), window=10, min_steps=100)
    assert row.onset_steps == 62 and row.moving_speed_mm_per_step == 0.5


def test_held_onsets_table_and_figure(tmp_path) -> None:
    real = held_move_onsets("real A", TrajectorySet([_waiting_path([((-1.0, 1.0), 120, 40, 0.1)])]))
    sim = held_move_onsets("sim source", TrajectorySet([_waiting_path([((-1.0, 1.0), 120, 0, 2.5)])]))
    stuck = held_move_onsets("sim target", TrajectorySet([_waiting_path([((-1.0, 1.0), 120, 500, 0.0)])]))
    table = held_onsets_table(real + sim + stuck)
    assert "| [-1, 1] | real A | 1 | 0 | 60 | 0.100 (1 runs) |  |" in table
    assert "| [-1, 1] | sim source | 1 | 0 | 1 | 2.500 (1 runs) | 25.0x |" in table
    assert "| [-1, 1] | sim target | 1 | 1 | never | none |  |" in table
    path = plot_held_onsets(real + sim + stuck, tmp_path / "onsets.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5_000
