"""data.bag.metadata: metadata.yaml of the wrong types, nested, compressed or pointing out of the bag
is refused in one line."""

from __future__ import annotations

import re
import tempfile

import pytest
import zstandard
from bag_builders import assert_same, damaged_copy, fixture_copy, read_quietly, refusal

from t42_transfer.data.bag import (
    bag_info,
    read_bag,
    verify_bag,
    write_bag,
)


def nested(depth: int) -> list:
    value: list = []
    for _ in range(depth):
        value = [value]
    return value


def test_missing_metadata_yaml_on_an_intact_bag(tmp_path, small_set):
    copy = damaged_copy(tmp_path, write_bag(tmp_path / "bag", small_set), drop_yaml=True)
    with pytest.warns(UserWarning, match="metadata.yaml is missing"):
        assert_same(read_bag(copy), small_set)  # custom_data comes from the MCAP metadata record


def test_garbled_metadata_yaml(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.warns(UserWarning, match="metadata.yaml is unreadable"):
        assert_same(read_bag(bag), small_set)


WRONG_TYPES = {
    "relative_file_paths a bool": (lambda i: i.update(relative_file_paths=True), "relative_file_paths must be a list"),
    "a topic entry a string": (lambda i: i.update(topics_with_message_count=["oops"]),
                               r"topics_with_message_count\[0\] must be a mapping, not str"),
    "deeply nested custom_data": (lambda i: i["custom_data"].update(deep=nested(100)), "custom_data deep must be text"),
    "storage_identifier a list": (lambda i: i.update(storage_identifier=["mcap"]), "storage_identifier must be text"),
    "a file name a number": (lambda i: i.update(relative_file_paths=[7]), "relative_file_paths must list file names"),
    "custom_data a list": (lambda i: i.update(custom_data=["a"]), "custom_data must be a mapping, not list"),
    "a count as text": (lambda i: i["topics_with_message_count"][1].update(message_count="many"),
                        r"topics_with_message_count\[1\].message_count must be an integer"),
    "a topic name missing": (lambda i: i["topics_with_message_count"][0]["topic_metadata"].pop("name"),
                             r"topics_with_message_count\[0\] names no topic"),
    "start time a bool": (lambda i: i["starting_time"].update(nanoseconds_since_epoch=True),
                          "starting_time.nanoseconds_since_epoch must be an integer, not bool"),
    "not bag information": (lambda i: i.clear() or i.update(rosbag2_bagfile_information=None),
                            "no rosbag2_bagfile_information"),
}


@pytest.mark.parametrize("case", sorted(WRONG_TYPES))
def test_metadata_of_the_wrong_types_is_refused_in_one_line(tmp_path, case):
    edit, problem = WRONG_TYPES[case]
    bag = fixture_copy(tmp_path, edit if case != "not bag information" else None)
    if case == "not bag information":
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: 3\n")
    for function in (read_bag, bag_info, verify_bag):
        assert re.search(problem, refusal(bag, function))


def test_metadata_nested_beyond_the_parser_is_unreadable_yaml(tmp_path):
    bag = fixture_copy(tmp_path)
    deep = f"  custom_data:\n    deep: {'[' * 5000}{']' * 5000}\n"
    (bag / "metadata.yaml").write_text((bag / "metadata.yaml").read_text().replace("  custom_data:\n", deep))
    with pytest.warns(UserWarning, match=r"metadata.yaml is unreadable \(RecursionError"):
        assert len(read_bag(bag)) == 4
    assert verify_bag(bag)[0].startswith("metadata.yaml is unreadable (RecursionError")


def test_a_compressed_bag_is_refused_without_unpacking_it_anywhere(tmp_path, monkeypatch):
    """rosbags unpacks a compression_mode FILE bag into a temporary folder outside the bag."""
    bag = fixture_copy(tmp_path, lambda i: i.update(compression_mode="FILE", compression_format="zstd",
                                                    relative_file_paths=["target_small.mcap.zstd"]))
    mcap = bag / "target_small.mcap"
    (bag / "target_small.mcap.zstd").write_bytes(zstandard.ZstdCompressor().compress(mcap.read_bytes()))
    mcap.unlink()
    made = []
    monkeypatch.setattr(tempfile, "mkdtemp", lambda *a, **k: made.append(a) or pytest.fail("a temporary folder"))
    for function in (read_bag, bag_info, verify_bag):
        assert "is compressed (compression_mode FILE, compression_format zstd)" in refusal(bag, function)
    assert made == []


def test_metadata_paths_never_lead_out_of_the_bag(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "target_small.mcap").write_bytes(b"not the bag's")
    bag = fixture_copy(tmp_path, lambda i: i.update(relative_file_paths=["../outside/target_small.mcap"]))
    assert len(read_quietly(bag)) == 4  # the bag's own file, by name
    bag = fixture_copy(tmp_path / "2", lambda i: i.update(relative_file_paths=["/etc/passwd"]))
    assert "metadata.yaml lists passwd, which is missing" in refusal(bag)
    bag = fixture_copy(tmp_path / "3", lambda i: i.update(relative_file_paths=[".."]))
    assert "names no file" in refusal(bag)
