"""Opening a bag to play it (one check for the player, the view's server and its snapshots) and the playback clock."""

from __future__ import annotations

import os
import shutil
import sqlite3
import warnings
from pathlib import Path

import pytest
from bag_builders import (
    BROKEN,
    BROKEN_TOPIC,
    BROKEN_WHY,
    FOO,
    IDL_TOPIC,
    UNPARSED,
    broken_definition_bag,
    clashing_definitions_bag,
    fixture_copy,
    idl_topic_bag,
    plain,
    sqlite3_without_a_definition,
)
from fuzz_harness import DecoderWorker
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import StoragePlugin

import msg_adapters as ma
from t42_transfer.data.bag import write_bag
from t42_transfer.data.bag.playback import Timeline, open_bag
from t42_transfer.data.errors import BagError

BAG = Path(__file__).resolve().parents[1] / "bags" / "target_small"


def test_a_sound_bag_opens_with_its_topics() -> None:
    reader = open_bag(BAG)
    try:
        assert {c.topic for c in reader.connections} >= {"/hand/object_pose", "/hand/applied_action"}
        assert reader.end_time > reader.start_time
    finally:
        reader.close()


def test_a_sqlite3_bag_with_a_topic_stored_without_a_definition_plays(tmp_path: Path, small_set: object) -> None:
    """``t42 bag play`` of a bag whose /rosout definition ``ros2 bag record`` did not find (rosbags refused it whole):
    every message plays, the hand's decode; the definition-less topic is just not decodable from the bag."""
    reader = open_bag(sqlite3_without_a_definition(tmp_path / "bag", small_set))
    try:
        formats = {c.topic: c.msgdef.format for c in reader.connections}
        assert formats["/rosout"] == MessageDefinitionFormat.NONE
        assert {f for topic, f in formats.items() if topic != "/rosout"} == {MessageDefinitionFormat.MSG}
        played = [(conn.topic, log_ns, raw) for conn, log_ns, raw in reader.messages()]
        assert len(played) == reader.message_count == sum(c.msgcount for c in reader.connections)
        assert [log_ns for _, log_ns, _ in played] == sorted(log_ns for _, log_ns, _ in played)
        assert sum(topic == "/rosout" for topic, _, _ in played) == 1
        pose = next(raw for topic, _, raw in played if topic == "/hand/object_pose")
        assert reader.deserialize(pose, "geometry_msgs/msg/PoseStamped").header.stamp.sec >= 0
        assert reader.start_time == small_set[0].start_ns
    finally:
        reader.close()


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_bag_with_a_topic_of_an_idl_type_plays_it_decoded(tmp_path: Path, small_set: object,
                                                            storage: StoragePlugin) -> None:
    """``t42 bag play`` and ``t42 view --bag`` of a ``ros2 bag record -a`` bag holding a vendor's IDL-defined type:
    rosbag2 stores its definition with ``#include`` lines and include guards, which rosbags' IDL parser refuses, and
    the whole bag was refused ("Could not parse").  Every message plays; the vendor's decode from the bag's own
    definition (its type hash checked) to the values written, the hand's as always."""
    bag, written = idl_topic_bag(tmp_path / "bag", small_set, storage)
    for path in (bag, next(bag.glob("bag.[dm]*"))):
        reader = open_bag(path)
        try:
            (conn,) = [c for c in reader.connections if c.topic == IDL_TOPIC]
            assert conn.msgtype == FOO and conn.msgdef.format == MessageDefinitionFormat.IDL
            got = [plain(reader.deserialize(raw, FOO)) for _, _, raw in reader.messages(connections=[conn])]
            assert got == [plain(message) for message in written]
            assert (reader.typestore.types[FOO].OPEN, reader.typestore.types[FOO].CLOSED) == (0, 1)
            played = [(c.topic, raw) for c, _, raw in reader.messages()]
            assert len(played) == reader.message_count == sum(c.msgcount for c in reader.connections)
            pose = next(raw for topic, raw in played if topic == "/hand/object_pose")
            assert reader.deserialize(pose, "geometry_msgs/msg/PoseStamped").header.stamp.sec >= 0
        finally:
            reader.close()


@pytest.mark.parametrize("kind", list(BROKEN))
@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_topic_whose_stored_definition_does_not_parse_plays_without_one(tmp_path: Path, small_set: object,
                                                                          storage: StoragePlugin, kind: str) -> None:
    """``t42 bag play`` and ``t42 view --bag`` of a ``ros2 bag record -a`` bag where one topic's stored definition
    does not parse: rosbags refused the whole bag ("Could not parse"; an MCAP one with a hint to repair it).  The bag
    opens with that topic as one stored without a definition, named once in a warning saying why; every message
    plays, the hand's decode."""
    bag, count = broken_definition_bag(tmp_path / "bag", small_set, storage, kind)
    msgtype = BROKEN[kind][0]
    for path in (bag, next(bag.glob("bag.[dm]*"))):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            reader = open_bag(path)
        try:
            if kind in BROKEN_WHY and path.suffix == ".mcap":  # an MCAP file alone has no hashes to check
                assert said == [] and reader.undecodable == {}
                continue
            assert len(said) == 1 and str(said[0].message).startswith(
                f"{path}: {BROKEN_TOPIC} ({msgtype}) is not decodable from the bag: {BROKEN_WHY.get(kind, UNPARSED)}")
            assert list(reader.undecodable) == [BROKEN_TOPIC]
            formats = {c.topic: c.msgdef.format for c in reader.connections}
            assert formats.pop(BROKEN_TOPIC) == MessageDefinitionFormat.NONE
            assert set(formats.values()) == {MessageDefinitionFormat.MSG}
            played = [(c.topic, raw) for c, _, raw in reader.messages()]
            assert len(played) == reader.message_count == sum(c.msgcount for c in reader.connections)
            assert sum(topic == BROKEN_TOPIC for topic, _ in played) == count
            pose = next(raw for topic, raw in played if topic == "/hand/object_pose")
            assert reader.deserialize(pose, "geometry_msgs/msg/PoseStamped").header.stamp.sec >= 0
        finally:
            reader.close()


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_of_two_definitions_that_do_not_hash_together_the_later_decodes(tmp_path: Path, small_set: object,
                                                                        storage: StoragePlugin) -> None:
    """rosbags refused such a bag whole ("hash mismatch"); it plays, the topic whose definition lost without one."""
    bag = clashing_definitions_bag(tmp_path / "bag", small_set, storage)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        reader = open_bag(bag)
    try:
        assert len(said) == 1 and list(reader.undecodable) == ["/vendor/a"]
        formats = {c.topic: c.msgdef.format for c in reader.connections}
        none, msg = MessageDefinitionFormat.NONE, MessageDefinitionFormat.MSG
        assert (formats["/vendor/a"], formats["/vendor/b"]) == (none, msg)
        (raw,) = [raw for c, _, raw in reader.messages() if c.topic == "/vendor/b"]
        assert reader.deserialize(raw, "my_msgs/msg/B").s.y == 0.0
    finally:
        reader.close()


def test_a_definition_that_leaves_a_type_to_another_topics_definition_reads_as_rosbags_reads_it(
        tmp_path: Path, small_set: object) -> None:
    """rosbags checks a bag's hashes with all its definitions together: a joint state definition cut to its own
    lines still hashes right with the pose's Header, and decodes (checked alone, it had been dropped)."""
    bag = write_bag(tmp_path / "bag", small_set, storage="sqlite3")
    with sqlite3.connect(next(bag.glob("*.db3"))) as db:
        (text,) = db.execute("SELECT encoded_message_definition FROM message_definitions WHERE topic_type = ?",
                             (ma.JOINT_STATE,)).fetchone()
        db.execute("UPDATE message_definitions SET encoded_message_definition = ? WHERE topic_type = ?",
                   (text.split("=" * 80)[0], ma.JOINT_STATE))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        reader = open_bag(bag)
    try:
        assert said == [] and reader.undecodable == {}
        raw = next(raw for c, _, raw in reader.messages() if c.topic == "/hand/joint_states")
        assert len(reader.deserialize(raw, ma.JOINT_STATE).name) == 2
    finally:
        reader.close()


def test_refusals_name_the_bag_and_what_it_was_opened_for(tmp_path: Path, small_set: object) -> None:
    killed = tmp_path / "killed"
    shutil.copytree(BAG, killed)
    (killed / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"killed.*cannot be served .*t42 bag repair"):
        open_bag(killed, "served")
    sqlite = write_bag(tmp_path / "sqlite", small_set, storage="sqlite3")
    (sqlite / "sqlite.db3").write_bytes(b"SQLite format 3\x00" + bytes(200))
    with pytest.raises(BagError, match="cannot be played") as refused:
        open_bag(sqlite)
    assert "repair" not in str(refused.value)  # repair takes MCAP bags only
    with pytest.raises(BagError, match="does not exist"):
        open_bag(tmp_path / "missing")


@pytest.mark.parametrize("where", ["metadata.yaml", "target_small.mcap", "bare file"])
def test_a_fifo_where_a_bag_file_belongs_is_refused_before_opening(where: str) -> None:
    """Opening a FIFO blocks forever (``t42 bag play`` hung): the worker's alarm fails a hang, not the suite."""
    with DecoderWorker("t42_transfer.data.bag.playback:open_bag", timeout_s=10.0) as worker:
        if where == "bare file":
            bag = worker.new_case_dir() / "bag.mcap"
        else:
            bag = fixture_copy(worker.new_case_dir())
            (bag / where).unlink()
        os.mkfifo(bag if where == "bare file" else bag / where)
        verdict = worker.check_path(bag)
    assert verdict.outcome == "refused" and "is a FIFO" in verdict.detail, verdict


def test_timeline_maps_bag_time_to_steady_time() -> None:
    now = [1_000]
    line = Timeline(5_000, rate=2.0, paused=True, now_ns=lambda: now[0])
    assert line.due_ns(6_000) == float("inf") and line.bag_now() == 5_000
    now[0] = 2_000
    line.resume()
    assert line.due_ns(6_000) == 2_500 and line.bag_now() == 5_000
    now[0] = 2_500
    assert line.bag_now() == 6_000
    line.set_rate(4.0)
    assert line.due_ns(8_000) == 3_000
    line.pause()
    now[0] = 9_999
    assert line.bag_now() == 6_000
    line.resume()
    line.restart(5_000, 10_000.4)  # a loop's next pass: the first message again, at a steady time to come
    assert line.due_ns(5_400) == 10_100
    now[0] = 10_050
    assert line.bag_now() == 5_200
