"""data.bag.storage: damaged MCAP and sqlite3 files give their readable prefix; non-regular files are never opened."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from bag_builders import (
    BROKEN,
    BROKEN_TOPIC,
    BROKEN_WHY,
    FOO,
    IDL_TOPIC,
    LOG,
    UNPARSED,
    assert_same,
    broken_definition_bag,
    clashing_definitions_bag,
    damaged_copy,
    fixture_copy,
    idl_topic_bag,
    read_quietly,
    refusal,
    sqlite3_without_a_definition,
)
from fuzz_harness import DecoderWorker
from rosbags.rosbag2 import StoragePlugin

from t42_transfer.cli import main
from t42_transfer.data.bag import (
    bag_info,
    read_bag,
    verify_bag,
    write_bag,
)
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import TrajectorySet


def assert_prefix_of(got: TrajectorySet, original: TrajectorySet, with_custom_data: bool) -> None:
    """Recovered episodes are the originals in order, only the last possibly cut short; without
    custom_data (a killed writer never wrote it) end reasons and hands are unknown."""
    assert [t.start_ns for t in got] == [t.start_ns for t in original[: len(got)]]
    for traj, whole in zip(got, original, strict=False):
        n = len(traj)
        assert n == len(whole) or traj is got[-1]
        assert np.array_equal(traj.states, whole.states[: n + 1]) and np.array_equal(traj.actions, whole.actions[:n])
        cut = n < len(whole)
        assert traj.end_reason == ("" if cut or not with_custom_data else whole.end_reason)
        assert traj.hand == (whole.hand if with_custom_data else "")


@pytest.mark.parametrize("drop_yaml", [False, True], ids=["cut", "killed"])
@pytest.mark.parametrize("fraction", [0.0001, 0.25, 0.6, 0.9])
def test_truncated_mcap_gives_its_readable_prefix(tmp_path, big_bag, fraction, drop_yaml):
    bag, data = big_bag
    size = int((bag / "bag.mcap").stat().st_size * fraction)
    copy = damaged_copy(tmp_path, bag, size, drop_yaml)
    if fraction < 0.3:  # inside the first chunk: nothing is readable
        with pytest.raises(BagError, match="recovered no hand messages"):
            read_bag(copy)
        return
    with pytest.warns(UserWarning, match=rf"{re.escape(str(copy))}: .*recovered the readable prefix"):
        got = read_bag(copy)
    assert len(got) >= 4 and got.hand == ("" if drop_yaml else data.hand)
    assert_prefix_of(got, data, with_custom_data=not drop_yaml)


def test_cut_in_the_summary_loses_nothing(tmp_path, big_bag):
    bag, data = big_bag
    copy = damaged_copy(tmp_path, bag, (bag / "bag.mcap").stat().st_size - 10)
    with pytest.warns(UserWarning, match="recovered the readable prefix"):
        assert_same(read_bag(copy), data)


def test_corrupt_sqlite3_bag(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set, storage="sqlite3")
    (bag / "bag.db3").write_bytes(b"SQLite format 3\x00" + bytes(200))
    with pytest.raises(BagError, match="rosbags cannot read it") as err:
        read_bag(bag)
    assert str(bag) in str(err.value)


def test_a_sqlite3_bag_with_a_topic_stored_without_a_definition_is_read(tmp_path, small_set):
    """``ros2 bag record`` stores a type whose .msg it cannot find with an empty definition (encoding ""); rosbags'
    sqlite3 reader refused the whole bag (KeyError: '').  The hand's topics are read, the other one counted."""
    bag = sqlite3_without_a_definition(tmp_path / "bag", small_set)
    for path in (bag, bag / "bag.db3"):
        got = read_quietly(path)
        assert len(got) == len(small_set)
        for traj, want in zip(got, small_set, strict=True):
            assert np.array_equal(traj.states, want.states) and np.array_equal(traj.actions, want.actions)
        info = bag_info(path)
        assert info["topics"]["/rosout"] == {"type": LOG, "count": 1} and info["episodes"] == len(small_set)
    assert verify_bag(bag) == []


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_bag_with_a_topic_of_an_idl_type_is_read(tmp_path, small_set, capsys, storage):
    """``ros2 bag record -a`` where a vendor's package defines a message in IDL: rosbag2 stores its definition with
    ``#include`` lines and include guards, which rosbags' IDL parser refuses, and rosbags refused the whole sqlite3
    bag ("Could not parse").  The hand's topics are read, the vendor's counted; ``t42 bag info`` lists it."""
    bag, written = idl_topic_bag(tmp_path / "bag", small_set, storage)
    for path in (bag, next(bag.glob("bag.[dm]*"))):
        got = read_quietly(path)
        assert len(got) == len(small_set)
        for traj, want in zip(got, small_set, strict=True):
            assert np.array_equal(traj.states, want.states) and np.array_equal(traj.actions, want.actions)
        info = bag_info(path)
        assert info["topics"][IDL_TOPIC] == {"type": FOO, "count": len(written)} and info["episodes"] == len(small_set)
    assert verify_bag(bag) == []
    assert main(["bag", "info", str(bag)]) == 0
    assert f"{IDL_TOPIC}: {{'type': '{FOO}', 'count': {len(written)}}}" in capsys.readouterr().out


def undecodable_said(said: list[warnings.WarningMessage], path: Path, msgtype: str, why: str = UNPARSED) -> str:
    """The one warning in ``said``: that BROKEN_TOPIC of ``path`` is not decodable from the bag, and ``why`` (e.g.
    rosbags' parse error, its type and where it stopped, in one short line)."""
    assert len(said) == 1, [str(w.message) for w in said]
    text = str(said[0].message)
    assert text.startswith(f"{path}: {BROKEN_TOPIC} ({msgtype}) is not decodable from the bag: {why}"), text
    assert text.isprintable() and len(text) < len(str(path)) + 240, text  # (rosbags' error quotes the whole text)
    return text


@pytest.mark.parametrize("kind", list(BROKEN))
@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_topic_whose_stored_definition_does_not_parse_is_named_once_and_the_hand_read(tmp_path, small_set, capsys,
                                                                                        storage, kind):
    """``ros2 bag record -a`` where one topic's stored definition does not parse (cut off, malformed), lacks a type
    it uses or hashes to another type hash: rosbags refused the whole sqlite3 bag ("Could not parse", a KeyError,
    "hash mismatch").  That topic is taken as one stored without a definition: the hand's
    topics are read, it is counted, and a warning names it once, with why; ``t42 bag info`` lists it."""
    bag, count = broken_definition_bag(tmp_path / "bag", small_set, storage, kind)
    msgtype = BROKEN[kind][0]
    for path in (bag, next(bag.glob("bag.[dm]*"))):
        got = {}
        for read in (read_bag, bag_info):
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")
                got[read] = read(path)
            if kind in BROKEN_WHY and path.suffix == ".mcap":  # an MCAP file alone has no hashes (metadata.yaml does)
                assert said == [], [str(w.message) for w in said]
                continue
            text = undecodable_said(said, path, msgtype, BROKEN_WHY.get(kind, UNPARSED))
            if kind == "ros2msg":
                assert text.endswith("(TypesysError: Could not parse at 'my_msgs/Fi')"), text
        for traj, want in zip(got[read_bag], small_set, strict=True):
            assert np.array_equal(traj.states, want.states) and np.array_equal(traj.actions, want.actions)
        info = got[bag_info]
        assert info["topics"][BROKEN_TOPIC] == {"type": msgtype, "count": count}
        assert info["episodes"] == len(small_set) and info["no_hand_episodes"] is None
    assert verify_bag(bag) == []
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert main(["bag", "info", str(bag)]) == 0
    undecodable_said(said, bag, msgtype, BROKEN_WHY.get(kind, UNPARSED))
    assert f"{BROKEN_TOPIC}: {{'type': '{msgtype}', 'count': {count}}}" in capsys.readouterr().out


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_two_definitions_that_do_not_hash_together_leave_one_topic_undecodable(tmp_path, small_set, storage):
    """Two vendor topics whose definitions give a type they share otherwise (each sound alone): rosbags, registering
    every definition in one store, refused the whole sqlite3 bag ("hash mismatch").  The topic whose definition lost
    is named once; the hand's topics are read."""
    bag = clashing_definitions_bag(tmp_path / "bag", small_set, storage)
    for read in (read_bag, bag_info):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            got = read(bag)
        assert [str(w.message) for w in said] == [
            f"{bag}: /vendor/a (my_msgs/msg/A) is not decodable from the bag: its stored definition gives a type it "
            "uses otherwise than another topic's definition does, and the two do not hash together"]
    assert got["episodes"] == len(small_set) and got["topics"]["/vendor/b"]["count"] == 1


def test_flipped_bytes_never_escape_as_library_errors(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set)
    original = (bag / "bag.mcap").read_bytes()
    offsets = sorted({*range(0, 40, 3), *np.linspace(40, len(original) - 1, 24).astype(int).tolist()})
    outcomes = set()
    for offset in offsets:
        damaged = bytearray(original)
        damaged[offset] ^= 0xFF
        (bag / "bag.mcap").write_bytes(bytes(damaged))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                outcomes.add(type(read_bag(bag)).__name__)
            except BagError as err:
                assert str(bag) in str(err)
                outcomes.add("BagError")
    assert "BagError" in outcomes


@pytest.mark.parametrize("where", ["bag", "storage file", "metadata.yaml", "bare file"])
@pytest.mark.parametrize("function", ["read_bag", "bag_info", "verify_bag"])
def test_fifos_are_refused_before_opening(where, function):
    """A FIFO blocks whoever opens it for reading; each run goes through the fuzz worker, whose alarm ends a hang."""
    with DecoderWorker(f"t42_transfer.data.bag:{function}", timeout_s=10.0) as worker:
        case = worker.new_case_dir()
        if where in ("bag", "bare file"):
            path = case / ("bag" if where == "bag" else "bag.mcap")
            os.mkfifo(path)
        else:
            path = fixture_copy(case)
            name = "metadata.yaml" if where == "metadata.yaml" else "target_small.mcap"
            (path / name).unlink()
            os.mkfifo(path / name)
        verdict = worker.check_path(path)
    assert verdict.outcome == "refused" and "FIFO" in verdict.detail, verdict


@pytest.mark.parametrize("name", ["metadata.yaml", "target_small.mcap"])
def test_a_directory_where_a_file_belongs_is_refused(tmp_path, name):
    bag = fixture_copy(tmp_path)
    (bag / name).unlink()
    (bag / name).mkdir()
    assert f"{name} is a directory, not a regular file" in refusal(bag)


@pytest.mark.parametrize("error", [PermissionError(13, "Permission denied"), IsADirectoryError(21, "Is a directory"),
                                   NotADirectoryError(20, "Not a directory")], ids=lambda e: type(e).__name__)
@pytest.mark.parametrize("at", ["stat", "read_bytes"])
def test_os_errors_become_one_line_bag_errors(tmp_path, monkeypatch, error, at):
    """As an unreadable bag directory, or metadata.yaml, fails for a user without root."""
    bag = fixture_copy(tmp_path)
    failing = bag if at == "stat" else bag / "metadata.yaml"
    original = getattr(Path, at)

    def fail_at(self, *args, **kwargs):
        if self == failing:
            raise type(error)(error.errno, error.strerror, str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, at, fail_at)
    for function in (read_bag, bag_info, verify_bag):
        assert refusal(bag, function).endswith(f"{error.strerror}: {failing}")
