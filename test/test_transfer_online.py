"""The online transfer's reading of recorded bags (transfer/online.py): what a transfer trains on."""

from __future__ import annotations

import dataclasses

from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.transfer.online import read_target


def test_recorded_episodes_end_at_their_first_drop(tmp_path, make_set) -> None:
    """A real hand's driver cannot tell a drop: its bag holds the fall (a jump over 8 mm) and what followed, which
    a transfer must not train on, as a simulated collection never holds them."""
    clean, held = make_set([30, 40], seed=3)
    states = held.states.copy()
    states[21:, 1] -= 12.0  # the object falls in step 20 and lies there
    episodes = assign_start_times([clean, dataclasses.replace(held, states=states)])
    bag = write_bag(tmp_path / "b0", TrajectorySet(episodes, hand="target"))
    data, read, skipped, notes = read_target([bag])
    assert read == [bag] and skipped == []
    assert [len(e) for e in data] == [30, 20] and data[1].end_reason == "dropped"
    assert len(notes) == 1 and "step 20" in notes[0] and "drop rule" in notes[0]
