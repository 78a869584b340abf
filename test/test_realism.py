"""Sim-vs-real statistics on hand-made paths with known answers."""

from __future__ import annotations

import numpy as np

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.hand.realism import markdown_table, replay, summarise


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
