"""data.bag.reader: bag_info and verify_bag summarise and check a bag, and name what is not a bag."""

from __future__ import annotations

import json
import shutil

import pytest
from bag_builders import (
    ACTION,
    JOINTS,
    LOG,
    TARGET,
    damaged_copy,
    fixture_copy,
    log_message,
    mcap_ros_distro,
    refusal,
    write_messages,
)

import msg_adapters as ma
from t42_transfer.cli import main
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import (
    HAND_KEY,
    bag_info,
    read_bag,
    verify_bag,
    write_bag,
)
from t42_transfer.data.bag.metadata import UNIT_KEY
from t42_transfer.data.errors import BagError


def test_bag_info_summarises(tmp_path, small_set):
    path = write_bag(tmp_path / "bag", small_set, metadata={"operator": "ada"})
    info = bag_info(path)
    states = sum(len(t) + 1 for t in small_set)
    assert info["storage"] == "mcap"
    assert info["topics"][JOINTS] == {"type": ma.JOINT_STATE, "count": states}
    assert info["topics"][ACTION]["count"] == small_set.num_transitions
    assert (info["episodes"], info["transitions"], info["hand"]) == (3, small_set.num_transitions, "sim_a")
    last = small_set[-1]
    assert info["start_ns"] == small_set[0].start_ns
    assert info["duration_s"] == pytest.approx((last.start_ns + len(last) * CONTROL_PERIOD_NS - info["start_ns"]) / 1e9)
    assert info["metadata"] == {"operator": "ada", HAND_KEY: "sim_a", UNIT_KEY: "0.025"}  # (the unit it declares)
    assert info["recovered_prefix"] is False


@pytest.mark.parametrize("name", ["source_small", "target_small"])
def test_the_shipped_fixture_bags_are_as_the_recorder_writes_them(name):
    """bags/make_fixtures.sh output: rosbag2's metadata says Jazzy, in metadata.yaml and in the MCAP's own record."""
    bag = TARGET.parent / name
    info = bag_info(bag)
    assert info["storage"] == "mcap" and info["ros_distro"] == "jazzy"
    assert "ros_distro: jazzy" in (bag / "metadata.yaml").read_text()
    assert mcap_ros_distro(bag / f"{name}.mcap") == "jazzy"


def test_missing_or_non_bag_paths(tmp_path):
    with pytest.raises(BagError, match="does not exist") as err:
        read_bag(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="no metadata.yaml and no .mcap or .db3"):
        read_bag(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(BagError, match="not a rosbag2 bag"):
        read_bag(tmp_path / "notes.txt")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(BagError, match="recovered no hand messages"):
        read_bag(tmp_path / "junk.mcap")


def test_verify_a_sound_bag(tmp_path, small_set, capsys):
    assert verify_bag(TARGET) == []
    assert verify_bag(write_bag(tmp_path / "bag", small_set)) == []
    assert verify_bag(write_bag(tmp_path / "sq", small_set, storage="sqlite3")) == []
    assert main(["bag", "info", "--verify", str(TARGET)]) == 0
    assert "verify: metadata.yaml agrees with the data" in capsys.readouterr().out


def test_verify_names_each_mismatch(tmp_path, capsys):
    def edit(info):
        info["message_count"] = 1000
        info["topics_with_message_count"][2]["message_count"] = 359
        info["topics_with_message_count"].pop(0)
        info["starting_time"]["nanoseconds_since_epoch"] = 5
        info["duration"]["nanoseconds"] = 7

    bag = fixture_copy(tmp_path, edit)
    shutil.copy(bag / "target_small.mcap", bag / "extra.mcap")
    found = verify_bag(bag)
    assert found == [
        "metadata.yaml lists files ['target_small.mcap'], the bag holds ['extra.mcap', 'target_small.mcap']",
        "metadata.yaml counts 359 messages on /hand/applied_action, the data holds 360",
        "/hand/object_pose: 364 messages in the data, not listed in metadata.yaml",
        "metadata.yaml counts 1000 messages, the data holds 1088",
        "metadata.yaml says the bag starts at 5 ns, its first message is logged at 1000000000 ns",
        "metadata.yaml says the bag lasts 7 ns, its messages span 42000000000 ns",
    ]
    assert main(["bag", "info", "--verify", str(bag)]) == 1
    out = capsys.readouterr().out
    assert "verify: 6 mismatches between metadata.yaml and the data" in out and all(f in out for f in found)
    assert main(["bag", "info", "--verify", "--json", str(bag)]) == 1
    assert json.loads(capsys.readouterr().out)["verify"] == found


def test_verify_a_killed_or_cut_bag(tmp_path, big_bag, capsys):
    bag, _ = big_bag
    copy = damaged_copy(tmp_path, bag, int((bag / "bag.mcap").stat().st_size * 0.6))
    (stopped, *rest) = verify_bag(copy)
    assert stopped.startswith("bag.mcap is unreadable from offset") and rest
    (copy / "metadata.yaml").unlink()
    assert verify_bag(copy)[-1] == "metadata.yaml is missing: nothing to verify the data against"
    assert "is a storage file, not a bag directory" in refusal(copy / "bag.mcap", verify_bag)
    assert main(["bag", "info", "--verify", str(copy / "bag.mcap")]) == 2
    assert capsys.readouterr().err.startswith(f"t42: error: {copy / 'bag.mcap'}: is a storage file")


def test_a_bag_without_the_hands_topics_is_listed_not_read(tmp_path, capsys):
    """``ros2 bag record /hand/status /rosout``: ``bag info`` lists it as ``ros2 bag info`` does, saying it holds no
    hand episodes (it failed: "required topic ... missing"); read_bag, and so the transfer server, refuses it."""
    status = ma.TYPESTORE.types[ma.STRING](data="reset: episode 1 grasped")
    types = {ma.HAND_STATUS_TOPIC: ma.STRING, "/rosout": LOG}
    bag = write_messages(tmp_path / "bag", [(ma.HAND_STATUS_TOPIC, 10**9, status),
                                            ("/rosout", 2 * 10**9, log_message(2 * 10**9))], types)
    info = bag_info(bag)
    assert info["topics"] == {topic: {"type": msgtype, "count": 1} for topic, msgtype in types.items()}
    assert (info["episodes"], info["transitions"], info["hand"]) == (0, 0, None)
    assert info["no_hand_episodes"].startswith(f"it has no {ma.OBJECT_POSE_TOPIC} ({ma.POSE_STAMPED}), {JOINTS}")
    assert bag_info(TARGET)["no_hand_episodes"] is None
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/rosout: {'type': 'rcl_interfaces/msg/Log', 'count': 1}" in out and "episodes: 0" in out
    assert f"no hand episodes: {info['no_hand_episodes']}" in out
    assert main(["bag", "info", "--json", str(bag)]) == 0
    assert json.loads(capsys.readouterr().out)["no_hand_episodes"] == info["no_hand_episodes"]
    assert f"required topic {ma.OBJECT_POSE_TOPIC} ({ma.POSE_STAMPED}) is missing" in refusal(bag)
