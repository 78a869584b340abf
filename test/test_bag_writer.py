"""data.bag.writer: exact round trips, the wire layout, episodes laid out in time, writes that fail leave nothing."""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_builders import ACTION, JOINTS, POSE, assert_same, read_quietly
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from rosbags.highlevel import AnyReader

import msg_adapters as ma
from t42_transfer.conventions import (
    ACTION_LIMIT,
    ACTION_UNIT_RAD,
    AUTHORS_ACTION_UNIT_RAD,
    CONTROL_PERIOD_NS,
    MIN_EPISODE_STEPS,
)
from t42_transfer.data.bag import (
    EPISODE_GAP_NS,
    EPISODES_KEY,
    HAND_KEY,
    assign_start_times,
    declared_bag_unit,
    read_bag,
    write_bag,
)
from t42_transfer.data.bag import writer as bag_writer
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import END_REASONS, Trajectory, TrajectorySet

F32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
ACTIONS = st.floats(-ACTION_LIMIT, ACTION_LIMIT, width=32)
"""Any action a hand takes (the reader refuses a step past ``ACTION_LIMIT``: a bag of another unit)."""


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_is_exact(tmp_path, small_set, storage):
    path = write_bag(tmp_path / "bag", small_set, storage=storage)
    assert path == tmp_path / "bag"
    assert_same(read_quietly(path), small_set)


@st.composite
def trajectory_sets(draw) -> TrajectorySet:
    hand = draw(st.text(max_size=12).filter(lambda s: "\x85" not in s))
    episodes = []
    for _ in range(draw(st.integers(1, 3))):
        steps = draw(st.integers(MIN_EPISODE_STEPS, MIN_EPISODE_STEPS + 4))
        episodes.append(
            Trajectory(
                states=draw(arrays(np.float32, (steps + 1, 4), elements=F32)),
                actions=draw(arrays(np.float32, (steps, 2), elements=ACTIONS)),
                actuator_angles=draw(st.none() | arrays(np.float32, (steps + 1, 2), elements=F32)),
                end_reason=draw(st.sampled_from(END_REASONS)),
                hand=draw(st.sampled_from([hand, "other"])),
            )
        )
    t0 = draw(st.integers(0, 10**15))
    gap = draw(st.integers(EPISODE_GAP_NS, 3 * EPISODE_GAP_NS))
    return TrajectorySet(assign_start_times(episodes, t0, gap), hand=hand)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=trajectory_sets())
def test_round_trip_property(data):
    with tempfile.TemporaryDirectory() as tmp:
        assert_same(read_quietly(write_bag(Path(tmp) / "bag", data)), data)


def test_bag_layout_matches_the_wire_format(tmp_path, small_set):
    path = write_bag(tmp_path / "bag", small_set, metadata={"operator": "ada"})
    with AnyReader([path]) as reader:
        topics = {t: (i.msgtype, i.msgcount) for t, i in reader.topics.items()}
        states = sum(len(t) + 1 for t in small_set)
        assert topics == {
            POSE: (ma.POSE_STAMPED, states),
            JOINTS: (ma.JOINT_STATE, states),
            ACTION: (ma.JOINT_STATE, small_set.num_transitions),
        }
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert ma.stamp_to_ns(msg.header.stamp) == log_ns
    meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    for entry in meta["topics_with_message_count"]:
        (qos,) = entry["topic_metadata"]["offered_qos_profiles"]
        assert (qos["reliability"], qos["history"], qos["depth"], qos["durability"]) == (
            "reliable",
            "keep_last",
            10,
            "volatile",
        )
    custom = meta["custom_data"]
    assert custom["operator"] == "ada" and custom[HAND_KEY] == "sim_a"
    assert [e["start_ns"] for e in json.loads(custom[EPISODES_KEY])] == [t.start_ns for t in small_set]


def test_assign_start_times_lays_episodes_end_to_end(small_set):
    placed = assign_start_times(small_set, t0_ns=5, gap_ns=EPISODE_GAP_NS)
    assert placed[0].start_ns == 5
    for before, after in zip(placed, placed[1:], strict=False):
        assert after.start_ns == before.start_ns + len(before) * CONTROL_PERIOD_NS + EPISODE_GAP_NS
    assert [np.array_equal(a.states, b.states) for a, b in zip(placed, small_set, strict=True)] == [True] * 3
    with pytest.raises(ValueError, match="gap_ns"):
        assign_start_times(small_set, gap_ns=EPISODE_GAP_NS - 1)


@pytest.mark.parametrize("offset_ns", [-CONTROL_PERIOD_NS, 0, EPISODE_GAP_NS - 1])
def test_write_refuses_overlapping_or_close_episodes(tmp_path, small_set, offset_ns):
    first, second = small_set[0], small_set[1]
    too_close = second.__class__(
        second.states, second.actions, start_ns=first.start_ns + len(first) * CONTROL_PERIOD_NS + offset_ns
    )
    with pytest.raises(ValueError, match="at least 1.0 s apart"):
        write_bag(tmp_path / "bag", TrajectorySet([first, too_close]))
    assert not (tmp_path / "bag").exists()


def test_write_refuses_existing_paths_and_bad_arguments(tmp_path, small_set):
    (tmp_path / "taken").mkdir()
    with pytest.raises(FileExistsError):
        write_bag(tmp_path / "taken", small_set)
    with pytest.raises(ValueError, match="reserved"):
        write_bag(tmp_path / "a", small_set, metadata={HAND_KEY: "x"})
    with pytest.raises(ValueError, match="strings"):
        write_bag(tmp_path / "b", small_set, metadata={"n": 3})
    with pytest.raises(ValueError, match="storage"):
        write_bag(tmp_path / "c", small_set, storage="rosbag1")
    with pytest.raises(ValueError, match="U\\+0085"):
        write_bag(tmp_path / "d", TrajectorySet(small_set, hand="a\x85b"))
    too_far = dataclasses.replace(small_set[0], actions=np.full_like(small_set[0].actions, ACTION_LIMIT + 0.01))
    with pytest.raises(ValueError, match=r"/e: episode 0 has an action of 1\.51, past the largest a hand takes "
                                         r"\(1\.5\): no bag holds it"):
        write_bag(tmp_path / "e", TrajectorySet([too_far]))
    with pytest.raises(ValueError, match="an action unit must be"):
        write_bag(tmp_path / "f", small_set, action_unit_rad=0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_a_bag_holds_the_actuators_steps_and_is_read_in_any_unit_they_fit(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set, action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    assert declared_bag_unit(bag) == AUTHORS_ACTION_UNIT_RAD == declared_bag_unit(bag / "bag.mcap")
    assert all(a == b for a, b in zip(read_bag(bag), small_set, strict=True))  # in the unit it declares
    assert all(a == b for a, b in zip(read_bag(bag / "bag.mcap"), small_set, strict=True))  # (the MCAP's copy)
    ratio = AUTHORS_ACTION_UNIT_RAD / ACTION_UNIT_RAD
    for ours, theirs in zip(read_bag(bag, ACTION_UNIT_RAD), small_set, strict=True):
        np.testing.assert_allclose(ours.actions, theirs.actions * ratio, rtol=1e-6)
    suite = write_bag(tmp_path / "suite", small_set)  # actions near 1 in the suite's unit are 6.4 in theirs
    assert declared_bag_unit(suite) == ACTION_UNIT_RAD
    with pytest.raises(BagError, match=r"applied_action at stamp \d+ ns: an action of \d\.\d+ in units of 0\.00388 "
                                       r"rad a step, past 1\.5: the hand stepped 0\.0\d+ rad"):
        read_bag(suite, AUTHORS_ACTION_UNIT_RAD)
    # A unit written to three figures reads the largest actions of the unit it stands for.
    largest = dataclasses.replace(small_set[0], actions=np.full_like(small_set[0].actions, ACTION_LIMIT))
    edge = write_bag(tmp_path / "edge", TrajectorySet([largest]), action_unit_rad=AUTHORS_ACTION_UNIT_RAD)
    assert float(np.abs(read_bag(edge, 0.00388)[0].actions).max()) == pytest.approx(1.5, rel=1e-3)



def test_a_bag_another_writer_finishes_first_at_the_same_path_is_a_file_exists_error(tmp_path, small_set,
                                                                                     monkeypatch):
    """Two experiments collecting the same data set into one cache: the later rename finds the earlier's bag."""
    target, close, others = tmp_path / "bag", bag_writer.BagWriter.close, []

    def the_other_writer_finishes_now(writer):
        close(writer)
        if not others:
            others.append(writer)
            write_bag(target, small_set)

    monkeypatch.setattr(bag_writer.BagWriter, "close", the_other_writer_finishes_now)
    with pytest.raises(FileExistsError, match=f"{target} exists already \\(written while this bag was built\\)"):
        write_bag(target, small_set)
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # the other's, whole; no staging left


def test_failed_write_leaves_nothing(tmp_path, small_set, monkeypatch):
    calls = []
    write = bag_writer.JazzyWriter.write

    def fail_in_the_second_episode(writer, connection, log_ns, data):  # the storage layer: rosbags' writer
        calls.append(log_ns)
        if len(calls) > 3 * len(small_set[0]) + 5:
            raise RuntimeError("disk full")
        write(writer, connection, log_ns, data)

    monkeypatch.setattr(bag_writer.JazzyWriter, "write", fail_in_the_second_episode)
    with pytest.raises(RuntimeError, match="disk full"):
        write_bag(tmp_path / "bag", small_set)
    assert list(tmp_path.iterdir()) == []


def test_a_writer_says_when_its_storage_file_is_removed_or_replaced(tmp_path: Path) -> None:
    """The recorder's check for a removed out_dir: the open file is gone, or another file stands at its path."""
    import shutil

    writer = bag_writer.BagWriter(tmp_path / "a", ma.HAND_TOPICS)
    try:
        assert writer.lost() is None
        shutil.rmtree(tmp_path / "a")
        assert "was removed while it was recorded" in writer.lost()
        (tmp_path / "a").mkdir()
        (tmp_path / "a" / "a.mcap").write_bytes(b"another file")
        assert "was replaced by another file" in writer.lost()
    finally:
        writer.abort()
