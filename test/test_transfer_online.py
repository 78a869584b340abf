"""The online transfer's reading of recorded bags (transfer/online.py): what a transfer trains on."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from safetensors import safe_open
from safetensors.torch import save_file

from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, CONTROL_PERIOD_NS
from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.models.checkpoint import UNIT_KEY, read_metadata, save_model
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.transfer.online import OnlineTransferSpec, TransferRefused, hold_out, read_target, run_transfer


def test_recorded_episodes_end_at_their_first_drop(tmp_path, make_set) -> None:
    """A bag may hold a fall (a jump over 8 mm) and what followed (a drop the driver did not see, another driver's
    recording), which a transfer must not train on, as a simulated collection never holds them."""
    clean, held = make_set([30, 40], seed=3)
    states = held.states.copy()
    states[21:, 1] -= 12.0  # the object falls in step 20 and lies there
    episodes = assign_start_times([clean, dataclasses.replace(held, states=states)])
    bag = write_bag(tmp_path / "b0", TrajectorySet(episodes, hand="target"))
    target = read_target([bag])
    assert target.read == [bag] and target.skipped == [] and target.late_steps == 0
    assert [len(e) for e in target.data] == [30, 20] and target.data[1].end_reason == "dropped"
    assert len(target.notes) == 1 and "step 20" in target.notes[0] and "drop rule" in target.notes[0]


def test_late_steps_are_left_out_and_their_episode_split_there(tmp_path, make_set) -> None:
    """A late step is kept by the reader with its duration, but it is no 0.1 s transition: the object moved on
    while the hand waited, by more than the drop rule in a long stall.  A transfer trains on the stretches
    around it, each kept when it has 15 transitions; a stall is not taken for a drop."""
    (episode,) = make_set([60], seed=4)
    steps = np.full(60, CONTROL_PERIOD_NS, np.int64)
    steps[[20, 50]] = [900_000_000, 200_000_000]  # 40 steps on from a stall, 9 after the second
    states = episode.states.copy()
    states[21:, 0] += 9.0  # the object moved on 9 mm during the stall: over the drop rule if taken as one step
    stalled = dataclasses.replace(episode, states=states, step_ns=steps)
    bag = write_bag(tmp_path / "b0", TrajectorySet(assign_start_times([stalled]), hand="target"))
    target = read_target([bag])
    assert target.late_steps == 2
    assert [len(e) for e in target.data] == [20, 29]  # steps 0-19, 21-49; the last 9 are too few
    np.testing.assert_array_equal(target.data[1].states, states[21:51])
    assert all(e.late_steps.size == 0 and e.end_reason != "dropped" for e in target.data)
    assert len(target.notes) == 1 and "2 late step(s) (the longest 900 ms) left out: 49 of its 60" in target.notes[0]


@pytest.mark.parametrize("fall_mm, late_step", [(12.0, 40), (25.0, 20)], ids=["then a late step", "in a late step"])
def test_after_a_drop_nothing_is_kept(tmp_path, make_set, fall_mm: float, late_step: int) -> None:
    """The drop rule runs on the episode as recorded: what follows the fall stays out, however a later late step
    splits it, and the notes name the episode as the reader gave it.  A late step may move the rule's 8 mm a period
    it lasted: 25 mm in a 0.3 s step is still a fall."""
    clean, held = make_set([30, 60], seed=5)
    states = held.states.copy()
    states[21:, 1] -= fall_mm  # the object falls in step 20 and lies there
    steps = np.full(60, CONTROL_PERIOD_NS, np.int64)
    steps[late_step] = 300_000_000
    fallen = dataclasses.replace(held, states=states, step_ns=steps)
    bag = write_bag(tmp_path / "b0", TrajectorySet(assign_start_times([clean, fallen]), hand="target"))
    target = read_target([bag])
    assert [len(e) for e in target.data] == [30, 20] and target.data[1].end_reason == "dropped"
    assert target.late_steps == 0  # cut off with the rest of the fall
    assert len(target.notes) == 1 and target.notes[0].startswith("episode 1 ") and "step 20" in target.notes[0]


def test_a_split_episodes_stretches_are_held_out_or_trained_on_together(tmp_path, make_set) -> None:
    """Neighbouring stretches of one recording on both sides would score a model on the episode it trained on."""
    episodes = list(make_set([40, 60, 40, 40, 40], seed=6))
    steps = np.full(60, CONTROL_PERIOD_NS, np.int64)
    steps[30] = 300_000_000
    episodes[1] = dataclasses.replace(episodes[1], step_ns=steps)
    bag = write_bag(tmp_path / "b0", TrajectorySet(assign_start_times(episodes), hand="target"))
    target = read_target([bag])
    assert target.episodes == (0, 1, 1, 2, 3, 4) and target.recorded_episodes == 5
    stretches = (target.data[1].start_ns, target.data[2].start_ns)
    separated = 0
    for seed in range(12):
        train, held = hold_out(target.data, 0.4, seed, target.episodes)
        assert len(held) in (2, 3) and len(train) + len(held) == 6
        sides = [any(t.start_ns == start for t in held) for start in stretches]
        assert sides[0] == sides[1], seed  # together
        loose = hold_out(target.data, 0.4, seed)[1]  # as pieces: apart for some draw
        separated += any(t.start_ns == stretches[0] for t in loose) != any(t.start_ns == stretches[1] for t in loose)
    assert separated > 0


def test_a_source_in_the_authors_unit_reads_the_bags_in_it_and_its_transfer_keeps_it(tmp_path, make_set) -> None:
    """Bags hold the actuators' steps (rad/s on the wire); a model of the authors' real hands learnt their unit."""
    source = save_model(TransitionModel(Normalisation.identity()), tmp_path / "authors.safetensors", method="source",
                        action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    episodes = make_set([30] * 4, seed=3, hand="target")
    scale = np.float32(AUTHORS_ACTION_UNIT_RAD / ACTION_UNIT_RAD)
    driven = TrajectorySet([dataclasses.replace(t, actions=t.actions * scale) for t in episodes], hand="target")
    write_bag(tmp_path / "bags" / "b0", TrajectorySet(assign_start_times(driven)))
    read = read_target([tmp_path / "bags" / "b0"], AUTHORS_ACTION_UNIT_RAD).data
    np.testing.assert_allclose(np.vstack([t.actions for t in read]), np.vstack([t.actions for t in episodes]),
                               rtol=1e-5, atol=1e-6)
    spec = OnlineTransferSpec(source_model=source, model_dir=tmp_path / "models", bag_dir=tmp_path / "bags",
                              method="direct")
    assert read_metadata(run_transfer(spec).model_path)[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD

    # A source saved before files stored units: taken as the suite's, and the transfer says so.
    with safe_open(str(source), framework="pt") as f:
        meta, tensors = json.loads(f.metadata()["t42_transfer"]), {k: f.get_tensor(k) for k in f.keys()}
    del meta[UNIT_KEY]
    save_file(tensors, str(tmp_path / "old.safetensors"), metadata={"t42_transfer": json.dumps(meta)})
    old = run_transfer(dataclasses.replace(spec, source_model=tmp_path / "old.safetensors",
                                           model_dir=tmp_path / "old_models", exact_bags=True,
                                           bags=(tmp_path / "bags" / "b0",)))
    assert "old.safetensors was saved before model files stored their action unit: its actions, and the bags', are " \
        "taken as 0.025 rad a step" in old.summary()
    write_bag(tmp_path / "suite" / "b0", TrajectorySet(assign_start_times(episodes)))  # driven in the suite's unit
    spec = dataclasses.replace(spec, bag_dir=tmp_path / "suite", model_dir=tmp_path / "refused")
    with pytest.raises(TransferRefused, match=r"too little data: 0 episode\(s\) .* skipped 1 unreadable bag\(s\): "
                                              r".*b0: .*applied_action at stamp \d+ ns: an action of \d\.\d+ in units "
                                              r"of 0\.00388 rad a step, past 1\.5"):
        run_transfer(spec)
    assert not (tmp_path / "refused").exists() or not any((tmp_path / "refused").iterdir())
