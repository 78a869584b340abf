"""Bag repair: a bag left by a killed recorder becomes a clean rosbag2 MCAP bag, originals kept."""

from __future__ import annotations

import os
import re
import shutil
import struct
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from bag_builders import (
    FINGER,
    FOO,
    IDL,
    assert_same,
    fixture_message_count,
    foo_message,
    idl_store,
    mcap_ros_distro,
    plain,
    rosbag2_idl,
)
from fuzz_harness import DecoderWorker
from mcap.reader import make_reader
from mcap.records import Chunk, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.highlevel import AnyReader
from rosbags.interfaces import MessageDefinitionFormat
from test_recorder import Hand, add_recorder, now_ns  # the recorder tests' hand: CDR bytes as a driver sends

from msg_adapters import HAND_TOPICS, JOINT_STATES_TOPIC, TYPESTORE, stamp_to_ns
from t42_transfer.cli import main
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import EPISODES_KEY, REPAIRED_KEY, bag_info, read_bag, verify_bag, write_bag
from t42_transfer.data.bag.repair import repair_bag
from t42_transfer.data.bag.storage import scan_mcap
from t42_transfer.data.bag.writer import JazzyWriter
from t42_transfer.data.errors import BagError

REPO = Path(__file__).resolve().parents[1]


def killed_bag(ros: Any, tmp_path: Path, steps: int = 60, unflushed: int = 5) -> tuple[Path, dict[str, list[bytes]]]:
    """What a recorder killed mid-bag leaves on disk, and the messages written before its last flush.

    A recorder (its flush timer an hour away: only this helper's ``flush()`` calls
    flush) records ``steps + unflushed`` whole control steps, flushed after every
    10th; the bag directory is copied while it is open: the copy is the state a
    SIGKILL leaves (flushed writes are in the page cache, the open chunk nowhere).
    """
    recorder = add_recorder(ros, tmp_path / "live", mode="recording", flush_period_s=3600.0)
    hand = Hand(ros, recorder)
    flushed: dict[str, list[bytes]] = {topic: [] for topic in HAND_TOPICS}
    rng = np.random.default_rng(0)
    t0 = now_ns()
    for k in range(steps + unflushed):
        # returns once the recorder took the step's three messages: a whole step, written at once
        hand.step(t0 + k * CONTROL_PERIOD_NS, rng.uniform(-20, 20, 2), rng.uniform(-200, 200, 2),
                  action=rng.uniform(-1, 1, 2))
        if (k + 1) % 10 == 0 and k < steps:
            recorder.flush()
            flushed = {topic: list(sent) for topic, sent in hand.sent.items()}
    assert recorder.current_count == 3 * (steps + unflushed) and recorder.dropped == 0
    live = recorder.current_bag
    assert live is not None
    bag = tmp_path / live.name
    shutil.copytree(live, bag)
    recorder.close()
    return bag, flushed


def first_stamp(flushed: dict[str, list[bytes]]) -> int:
    return stamp_to_ns(TYPESTORE.deserialize_cdr(flushed[JOINT_STATES_TOPIC][0], HAND_TOPICS[JOINT_STATES_TOPIC])
                       .header.stamp)


def test_a_killed_recorders_bag_is_repaired(ros: Any, tmp_path: Path) -> None:
    bag, flushed = killed_bag(ros, tmp_path)
    mcap = bag / f"{bag.name}.mcap"
    assert not (bag / "metadata.yaml").exists()
    with open(mcap, "ab") as stream:  # killed in the middle of writing a chunk
        stream.write(b"\x06" + (5000).to_bytes(8, "little") + b"\x00" * 100)
    damaged = mcap.read_bytes()
    with pytest.warns(UserWarning, match="recovered the readable prefix"):
        assert len(read_bag(bag)) == 1

    report = repair_bag(bag)
    assert report.repaired
    assert any("metadata.yaml is missing" in p for p in report.problems)
    assert "unreadable" in report.stopped
    assert report.counts == {topic: len(m) for topic, m in flushed.items()}
    assert report.originals == (bag / f"{bag.name}.mcap.orig",)
    assert report.originals[0].read_bytes() == damaged  # nothing lost

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data = read_bag(bag)
        info = bag_info(bag)
    assert data.num_transitions == len(flushed["/hand/applied_action"]) - 1  # the last action has no next state
    assert {t: v["count"] for t, v in info["topics"].items()} == report.counts
    assert info["recovered_prefix"]  # a salvaged prefix says so: its last step may be cut
    assert "metadata.yaml is missing" in info["metadata"]["t42_transfer.repaired"]
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == report.message_count
    assert meta["ros_distro"] == info["ros_distro"] == mcap_ros_distro(mcap) == "jazzy"  # as the recorder's
    # logged on receipt, after the first step was stamped (its stamp: the clock floored to a period)
    assert 0 <= meta["starting_time"]["nanoseconds_since_epoch"] - first_stamp(flushed) < 5_000_000_000
    assert meta["relative_file_paths"] == [mcap.name]
    for entry in meta["topics_with_message_count"]:
        topic = entry["topic_metadata"]
        assert topic["type"] == HAND_TOPICS[topic["name"]]
        assert topic["offered_qos_profiles"][0]["reliability"] == "reliable"  # as recorded

    with AnyReader([bag]) as reader:
        got = {topic: [] for topic in HAND_TOPICS}
        for conn, _, raw in reader.messages():
            got[conn.topic].append(bytes(raw))
    assert got == flushed  # the payloads, in order, byte for byte

    again = repair_bag(bag)
    assert not again.repaired and again.counts == report.counts


def test_stale_metadata_is_rewritten(tmp_path: Path) -> None:
    bag = tmp_path / "source_small"
    shutil.copytree(REPO / "bags" / "source_small", bag)
    assert not repair_bag(bag).repaired
    meta_file = bag / "metadata.yaml"
    meta = yaml.safe_load(meta_file.read_text())
    meta["rosbag2_bagfile_information"]["message_count"] = 7
    meta_file.write_text(yaml.safe_dump(meta))
    report = repair_bag(bag)
    assert report.repaired and "metadata.yaml counts 7 messages" in report.problems[0]
    assert report.message_count == fixture_message_count(REPO / "bags" / "source_small") and not report.stopped
    info = bag_info(bag)
    assert info["metadata"]["t42_transfer.hand"] == "source"  # custom_data survives
    assert info["episodes"] == 6
    assert info["ros_distro"] == mcap_ros_distro(bag / "source_small.mcap") == "jazzy"  # as the recorder writes


def test_bad_inputs_raise_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        repair_bag(tmp_path / "missing")
    file = tmp_path / "file.mcap"
    file.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(BagError, match="not a bag directory"):
        repair_bag(file)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagError, match="no .mcap file"):
        repair_bag(empty)
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    (wrong / "wrong.mcap").write_text("hello, not an mcap")
    with pytest.raises(BagError, match="bad magic"):
        repair_bag(wrong)


@pytest.mark.parametrize("size", [9, 43])
def test_a_bag_killed_right_after_it_was_opened_becomes_an_empty_bag(tmp_path: Path, size: int) -> None:
    """The recorder's file at its first kill point (the magic and part or all of the header record, 43 bytes):
    repaired to an empty bag that every reader takes, the original kept."""
    from t42_transfer.data.bag import bag_info, verify_bag

    recorded = Path(__file__).parents[1] / "bags" / "target_small" / "target_small.mcap"
    opened = tmp_path / "opened"
    opened.mkdir()
    (opened / "opened.mcap").write_bytes(recorded.read_bytes()[:size])
    report = repair_bag(opened)
    assert report.repaired and report.counts == {} and report.originals == (opened / "opened.mcap.orig",)
    info = bag_info(opened)
    assert info["topics"] == {} and info["episodes"] == 0 and verify_bag(opened) == []
    assert repair_bag(opened).repaired is False  # sound now


def test_an_earlier_repairs_originals_are_never_overwritten(ros: Any, tmp_path: Path) -> None:
    bag, _ = killed_bag(ros, tmp_path, steps=20, unflushed=0)
    (bag / f"{bag.name}.mcap.orig").write_text("kept")
    with pytest.raises(FileExistsError):
        repair_bag(bag)
    assert (bag / f"{bag.name}.mcap.orig").read_text() == "kept"


def test_the_old_metadata_yaml_is_kept_and_its_custom_data_carried_over(tmp_path: Path) -> None:
    """A closed bag's copy cut short loses the MCAP's own metadata record (written last), not its metadata.yaml:
    the yaml's custom_data is the only copy of the collector, seed, hand and episodes."""
    bag = Path(shutil.copytree(REPO / "bags" / "target_small", tmp_path / "target_small"))
    mcap, meta_file = bag / "target_small.mcap", bag / "metadata.yaml"
    old_yaml = meta_file.read_bytes()
    old_custom = yaml.safe_load(old_yaml)["rosbag2_bagfile_information"]["custom_data"]
    assert {"collector", "seed", EPISODES_KEY} <= set(old_custom)
    with mcap.open("rb") as stream:  # cut where rosbag2's metadata record starts: every message stays
        cut = 0
        for record in StreamReader(stream).records:
            if isinstance(record, Metadata):
                break
            cut = stream.tell()
    mcap.write_bytes(mcap.read_bytes()[:cut])
    assert scan_mcap([mcap], None).custom == {}  # the yaml is the only copy left
    report = repair_bag(bag)
    assert report.repaired and report.message_count == fixture_message_count()
    assert bag / "metadata.yaml.orig" in report.originals
    assert (bag / "metadata.yaml.orig").read_bytes() == old_yaml  # nothing lost
    custom = yaml.safe_load(meta_file.read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert {k: v for k, v in custom.items() if k != REPAIRED_KEY} == old_custom and REPAIRED_KEY in custom
    info = bag_info(bag)
    assert info["metadata"]["collector"] == old_custom["collector"] and info["episodes"] == 4
    meta = yaml.safe_load(meta_file.read_text())
    meta["rosbag2_bagfile_information"]["message_count"] = 7  # stale again
    meta_file.write_text(yaml.safe_dump(meta))
    with pytest.raises(FileExistsError, match="metadata.yaml.orig"):
        repair_bag(bag)  # an earlier repair's original is never overwritten
    assert (bag / "metadata.yaml.orig").read_bytes() == old_yaml


def test_cli_bag_repair(ros: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag, flushed = killed_bag(ros, tmp_path, steps=30)
    assert main(["bag", "repair", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "repaired" in out and f"/hand/joint_states: {len(flushed['/hand/joint_states'])} messages" in out
    assert main(["bag", "repair", str(bag)]) == 0
    assert "sound" in capsys.readouterr().out
    assert main(["bag", "repair", str(tmp_path / "nope")]) == 2
    assert str(tmp_path / "nope") in capsys.readouterr().err


@pytest.fixture(scope="module")
def chunked_bag(tmp_path_factory: pytest.TempPathFactory, make_set: Any) -> Path:
    """A bag of about three 1 MiB MCAP chunks (rosbags' chunk size), as the recorder writes them."""
    return write_bag(tmp_path_factory.mktemp("chunked") / "bag", make_set((450,) * 14, seed=7))


@pytest.mark.parametrize("fraction", [0.5, 0.62, 0.7, 0.8, 0.95, 0.999])
def test_a_cut_bag_loses_no_message_of_a_finished_chunk(tmp_path: Path, chunked_bag: Path, fraction: float) -> None:
    """A writer killed anywhere: the repaired bag holds, byte for byte, every message of each chunk written whole."""
    bag = Path(shutil.copytree(chunked_bag, tmp_path / "bag"))
    mcap = bag / "bag.mcap"
    cut = int(mcap.stat().st_size * fraction)
    with mcap.open("rb") as stream:  # the mcap library's own reading of the intact file
        summary = make_reader(stream).get_summary()
        stream.seek(0)
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records if isinstance(r, Chunk)]
    finished = [chunk for index, chunk in zip(summary.chunk_indexes, chunks, strict=True)
                if index.chunk_start_offset + index.chunk_length <= cut]
    kept = [(summary.channels[r.channel_id].topic, r.data)
            for chunk in finished for r in breakup_chunk(chunk) if isinstance(r, Message)]
    assert kept
    mcap.write_bytes(mcap.read_bytes()[:cut])
    (bag / "metadata.yaml").unlink()
    assert repair_bag(bag).repaired
    with AnyReader([bag]) as reader:
        repaired = [(conn.topic, bytes(raw)) for conn, _, raw in reader.messages()]
    assert repaired == kept  # in order, byte for byte


@pytest.mark.parametrize("where", ["bag", "storage file", "metadata.yaml"])
def test_fifos_are_refused_before_opening(where: str) -> None:
    """A FIFO blocks whoever opens it; the fuzz worker's alarm would end a hang."""
    with DecoderWorker("t42_transfer.data.bag.repair:repair_bag", timeout_s=10.0) as worker:
        case = worker.new_case_dir()
        if where == "bag":
            path = case / "bag"
            os.mkfifo(path)
        else:
            path = Path(shutil.copytree(REPO / "bags" / "target_small", case / "target_small"))
            name = "metadata.yaml" if where == "metadata.yaml" else "target_small.mcap"
            (path / name).unlink()
            os.mkfifo(path / name)
        verdict = worker.check_path(path)
    assert verdict.outcome == "refused", verdict
    assert ("FIFO" if where != "bag" else "not a bag directory") in verdict.detail


def test_non_regular_files_and_os_errors_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bag = Path(shutil.copytree(REPO / "bags" / "target_small", tmp_path / "target_small"))
    (bag / "other.mcap").mkdir()
    with pytest.raises(BagError, match="other.mcap is a directory, not a regular file"):
        repair_bag(bag)
    (bag / "other.mcap").rmdir()
    (bag / "metadata.yaml").unlink()
    (bag / "metadata.yaml").mkdir()
    with pytest.raises(BagError, match="metadata.yaml is a directory, not a regular file"):
        repair_bag(bag)
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "target_small.mcap"]  # untouched
    stat = Path.stat

    def denied(self: Path, *args: Any, **kwargs: Any) -> Any:
        if self == bag:
            raise PermissionError(13, "Permission denied", str(self))
        return stat(self, *args, **kwargs)

    monkeypatch.setattr(Path, "stat", denied)
    with pytest.raises(BagError, match=f"Permission denied: {bag}$"):
        repair_bag(bag)


@pytest.mark.parametrize("edit", [
    lambda info: info.update(relative_file_paths=True),
    lambda info: info.update(topics_with_message_count=["oops"]),
    lambda info: info.update(compression_mode="FILE", compression_format="zstd"),
], ids=["paths a bool", "a topic a string", "compressed"])
def test_unusable_metadata_on_a_sound_mcap_is_rewritten(tmp_path: Path, edit: Any) -> None:
    bag = Path(shutil.copytree(REPO / "bags" / "target_small", tmp_path / "target_small"))
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    edit(meta["rosbag2_bagfile_information"])
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    report = repair_bag(bag)
    assert report.repaired and report.problems[0].startswith("metadata.yaml is unusable (")
    assert report.message_count == fixture_message_count() and not report.stopped
    assert verify_bag(bag) == [] and not repair_bag(bag).repaired


def test_a_recorders_closed_bag_verifies(ros: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``t42 bag info --verify`` on what the recorder writes: metadata.yaml's counts and times are the data's."""
    recorder = add_recorder(ros, tmp_path / "live", mode="recording")
    hand = Hand(ros, recorder)
    hand.episode(now_ns(), 20)
    hand.settle()
    recorder.close()
    (bag,) = recorder.bags
    assert verify_bag(bag) == []
    assert main(["bag", "info", "--verify", str(bag)]) == 0
    assert "verify: metadata.yaml agrees with the data" in capsys.readouterr().out


def foo_int32(index: int) -> bytes:
    """A FOO of definition ``int32 a`` (a = ``index``), CDR-serialized."""
    return b"\x00\x01\x00\x00" + struct.pack("<i", index)


def humble_killed_copy(tmp_path: Path, foo_schema: tuple[str, bytes], hand: bool = True,
                       foo_data: Callable[[int], bytes] = foo_int32) -> Path:
    """The target fixture bag as Humble's MCAP plugin records it (no topic_type_hash on any channel), plus /foo of
    type FOO with schema ``foo_schema`` (encoding, definition) every 10th message (its CDR bytes
    ``foo_data(index)``, ``index`` counting the fixture's messages), killed: cut at 90 %, no metadata.yaml.  Without
    ``hand`` the hand's channels hold no message."""
    bag = tmp_path / "killed"
    bag.mkdir(parents=True)
    mcap = bag / "killed.mcap"
    with (REPO / "bags" / "target_small" / "target_small.mcap").open("rb") as source, mcap.open("wb") as stream:
        reader = make_reader(source)
        summary = reader.get_summary()
        assert summary is not None
        writer = McapWriter(stream, compression=CompressionType.ZSTD, chunk_size=4096)
        writer.start(profile="ros2", library="libmcap 0.8.0")
        foo = writer.register_channel("/foo", "cdr", writer.register_schema(FOO, *foo_schema), {})
        schemas = {k: writer.register_schema(s.name, s.encoding, s.data) for k, s in summary.schemas.items()}
        channels = {k: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id],
                                               {"offered_qos_profiles": c.metadata["offered_qos_profiles"]})
                    for k, c in summary.channels.items()}
        for index, (_, channel, message) in enumerate(reader.iter_messages(log_time_order=False)):
            if index % 10 == 0:
                writer.add_message(foo, message.log_time, foo_data(index), message.log_time, index)
            if hand:
                writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
        writer.finish()
    mcap.write_bytes(mcap.read_bytes()[: int(mcap.stat().st_size * 0.9)])
    return bag


def read_anyway(bag: Path) -> Any:
    with warnings.catch_warnings():  # a killed or repaired bag: its recovered prefix is warned of
        warnings.simplefilter("ignore")
        return read_bag(bag)


def test_a_custom_type_without_a_type_hash_is_carried_over(tmp_path: Path) -> None:
    """rosbags' writer needs a type hash, and a Humble recording's channels carry none: the repair hashes the
    file's definition (the writer's assertion was taken for damage, and the repaired bag was empty)."""
    bag = humble_killed_copy(tmp_path, ("ros2msg", b"int32 a\n"))
    read = {topic: t.count for topic, t in scan_mcap([bag / "killed.mcap"], None).topics.items()}
    before = read_anyway(bag)
    assert len(before) >= 3 and read["/foo"] > 0
    report = repair_bag(bag)
    assert report.repaired and report.counts == read and report.left_out == () and report.left_out_messages == 0
    assert_same(read_anyway(bag), before)
    with AnyReader([bag]) as reader:  # which checks each definition against its hash
        (conn,) = [c for c in reader.connections if c.topic == "/foo"]
        values = [reader.deserialize(raw, FOO).a for c, _, raw in reader.messages(connections=[conn])]
    assert conn.digest.startswith("RIHS01_") and conn.msgdef.data == "int32 a\n"
    assert values == list(range(0, 10 * read["/foo"], 10))


def test_a_topic_whose_type_cannot_be_written_is_left_out_and_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A type rosbag2 found no definition of (an empty schema): rosbags cannot write it, so it is left out, named,
    and the command fails; every other topic is carried over."""
    bag = humble_killed_copy(tmp_path, ("", b""))
    read = {topic: t.count for topic, t in scan_mcap([bag / "killed.mcap"], None).topics.items()}
    before = read_anyway(bag)
    assert main(["bag", "repair", str(bag)]) == 1
    out, err = capsys.readouterr()
    assert (f"left out /foo ({FOO}, {read['/foo']} messages): the file holds no definition of {FOO} (schema "
            "encoding '') and ROS 2 Jazzy's types do not include it") in out
    assert "now an empty bag" not in out and f"{read['/foo']} messages read could not be carried over" in err
    assert_same(read_anyway(bag), before)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        info = bag_info(bag)
    assert {topic: t["count"] for topic, t in info["topics"].items()} == {k: v for k, v in read.items() if k != "/foo"}
    assert "left out /foo" in info["metadata"][REPAIRED_KEY]


def test_a_repair_that_would_carry_nothing_over_leaves_the_bag_alone(tmp_path: Path) -> None:
    bag = humble_killed_copy(tmp_path, ("", b""), hand=False)
    original = (bag / "killed.mcap").read_bytes()
    with pytest.raises(BagError, match=r"none of the messages read can be carried over \(/foo .*left as it is"):
        repair_bag(bag)
    assert [p.name for p in bag.iterdir()] == ["killed.mcap"] and (bag / "killed.mcap").read_bytes() == original


def test_a_failure_writing_the_new_bag_is_no_damage_of_the_old(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Only reading the input finds damage: what the writing raises propagates, the bag untouched (it was taken for
    a cut file, and the bag rewritten without the messages after it)."""
    bag = humble_killed_copy(tmp_path, ("ros2msg", b"int32 a\n"))
    original = (bag / "killed.mcap").read_bytes()

    def failing(*_: Any) -> None:
        raise RuntimeError("the disk caught fire")

    monkeypatch.setattr(JazzyWriter, "write", failing)
    with pytest.raises(RuntimeError, match="the disk caught fire"):
        repair_bag(bag)
    assert [p.name for p in bag.iterdir()] == ["killed.mcap"] and (bag / "killed.mcap").read_bytes() == original


def idl_killed_copy(tmp_path: Path, schema_text: str) -> tuple[Path, dict[str, int]]:
    """:func:`humble_killed_copy` whose /foo is the IDL type FOO, schema ``schema_text`` (encoding ``ros2idl``), and
    the messages the scan of its cut file reads per topic."""
    store = idl_store()
    bag = humble_killed_copy(tmp_path, ("ros2idl", schema_text.encode()),
                             foo_data=lambda index: store.serialize_cdr(foo_message(store, index), FOO))
    return bag, {topic: t.count for topic, t in scan_mcap([bag / "killed.mcap"], None).topics.items()}


@pytest.mark.parametrize("variant", ["rosbag2", "no header"])
def test_a_custom_type_defined_in_idl_is_carried_over(tmp_path: Path, variant: str) -> None:
    """A killed bag with a topic of a vendor's IDL type (a nested type and Jazzy's Time in its definition): every
    salvaged message of it is carried over, and rosbags' AnyReader, from the repaired bag's own schemas alone, decodes
    each to the values written.  rosbag2 puts the separator and ``IDL: <type>`` line before each type's IDL; some
    writers store the IDL without that header."""
    schema_text = rosbag2_idl(IDL) if variant == "rosbag2" else "\n".join(IDL.values())
    assert FOO not in TYPESTORE.types and FINGER not in TYPESTORE.types  # not Jazzy's: the file's definition is used
    bag, read = idl_killed_copy(tmp_path, schema_text)
    before = read_anyway(bag)
    assert read["/foo"] > 3 and len(before) >= 3
    report = repair_bag(bag)
    assert report.repaired and "unreadable" in report.stopped
    assert report.counts == read and report.left_out == () and report.left_out_messages == 0
    assert_same(read_anyway(bag), before)  # the hand's topics as they were
    with AnyReader([bag]) as reader:  # no type registered: its typestore is the bag's definitions, hashes checked
        (conn,) = [c for c in reader.connections if c.topic == "/foo"]
        got = [plain(reader.deserialize(raw, FOO)) for _, _, raw in reader.messages(connections=[conn])]
        constants = reader.typestore.types[FOO].OPEN, reader.typestore.types[FOO].CLOSED
    assert conn.msgtype == FOO and conn.msgdef.format == MessageDefinitionFormat.IDL
    assert conn.digest.startswith("RIHS01_") and constants == (0, 1)
    # the file's definition, its preprocessor lines (which rosbags cannot parse) made comments
    header = "" if variant == "rosbag2" else "=" * 80 + f"\nIDL: {FOO}\n"
    assert conn.msgdef.data == re.sub(r"^#", "// #", header + schema_text, flags=re.MULTILINE)
    store = idl_store()
    assert got == [plain(foo_message(store, index)) for index in range(0, 10 * read["/foo"], 10)]
    assert not repair_bag(bag).repaired  # sound now


@pytest.mark.parametrize(("definition", "why", "where"), [
    # rosbags' parse error ends with what it expected: the "}" the cut took away (not the first #include's "#")
    (rosbag2_idl(IDL).replace("      string<16> label;\n    };\n", ""),
     f"its definition of {FOO} cannot be used (TypesysError: Could not parse", "\n{\"'}'\"})\n"),
    (rosbag2_idl({**IDL, FOO: IDL[FOO].replace('#include "my_msgs/msg/Finger.idl"\n', "")}),
     f"its definition of {FOO} cannot be used (KeyError: '{FINGER}')", ""),
], ids=["a struct cut short", "a type it uses left out"])
def test_a_topic_whose_idl_cannot_be_used_is_left_out_and_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], definition: str, why: str, where: str) -> None:
    """A broken IDL definition: its topic is left out with the reason, the command fails, the rest is repaired."""
    bag, read = idl_killed_copy(tmp_path, definition)
    before = read_anyway(bag)
    assert main(["bag", "repair", str(bag)]) == 1
    out, err = capsys.readouterr()
    assert f"left out /foo ({FOO}, {read['/foo']} messages): {why}" in out and where in out
    assert f"{read['/foo']} messages read could not be carried over; they are in the originals" in err
    assert_same(read_anyway(bag), before)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        info = bag_info(bag)
    assert {topic: t["count"] for topic, t in info["topics"].items()} == {k: v for k, v in read.items() if k != "/foo"}
    assert f"left out /foo ({FOO}, {read['/foo']} messages): {why}" in info["metadata"][REPAIRED_KEY]
    assert (bag / "killed.mcap.orig").exists()
