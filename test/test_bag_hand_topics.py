"""Where a bag keeps the hand topics: found by name, or as a recorder with remapped topics wrote them down."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_builders import ACTION, JOINTS, POSE, step_messages, write_messages
from rosbags.rosbag2 import StoragePlugin

import msg_adapters as ma
from t42_transfer.data.bag import HAND_KEY, bag_info, read_bag
from t42_transfer.data.bag.hand_topics import (
    HAND_ROLES,
    HAND_TOPICS_KEY,
    hand_topic_names,
    recorded_topics_custom,
    written_names,
)
from t42_transfer.data.errors import BagError
from t42_transfer.view.bag_scene import bag_scene_inputs

REMAPPED = {POSE: "/pose", JOINTS: "/arm/joint_states", ACTION: "/hand/applied_action", ma.HAND_STATUS_TOPIC: "/st"}


def test_without_a_record_the_names_are_found_under_one_namespace() -> None:
    names = hand_topic_names("bag", {}, ["/left" + t for t in ma.HAND_TOPICS] + ["/rosout"])
    assert names == {role: "/left" + role for role in HAND_ROLES}
    assert hand_topic_names("bag", {}, []) == {role: role for role in HAND_ROLES}


def test_a_record_is_taken_over_the_names() -> None:
    custom = recorded_topics_custom(REMAPPED)
    assert json.loads(custom[HAND_TOPICS_KEY]) == REMAPPED
    # The standard names present as well (another recorder's) do not matter: the record says where this one's went.
    assert hand_topic_names("bag", custom, list(ma.HAND_TOPICS)) == REMAPPED
    assert written_names(custom) == set(REMAPPED.values())


@pytest.mark.parametrize(("text", "says"), [
    ("{not json", "is not JSON"),
    ("[1, 2]", "must map hand topics to recorded topics, got list"),
    (json.dumps({**REMAPPED, "/hand/camera": "/c"}), "names /hand/camera, not hand topics"),
    (json.dumps({**REMAPPED, POSE: "pose"}), "gives /hand/object_pose the name 'pose'"),
    (json.dumps({**REMAPPED, POSE: 7}), "gives /hand/object_pose the name '7'"),
    (json.dumps({**REMAPPED, POSE: "/" + "p" * 300}), "at most 256 characters"),
    (json.dumps({JOINTS: "/j"}), "gives no name for /hand/object_pose, /hand/applied_action"),
])
def test_a_damaged_record_is_refused_saying_what_is_wrong(text: str, says: str) -> None:
    with pytest.raises(BagError, match=says):
        hand_topic_names("bag", {HAND_TOPICS_KEY: text}, [])


def test_a_loader_keeps_no_names_from_an_unreadable_record() -> None:
    assert written_names({HAND_TOPICS_KEY: "{not json"}) == set() == written_names({HAND_TOPICS_KEY: "[1, 2]"})
    assert written_names({HAND_TOPICS_KEY: json.dumps({POSE: 7, JOINTS: "/j"})}) == {"/j"}


def test_a_writer_cannot_record_other_topics_as_hand_topics() -> None:
    with pytest.raises(ValueError, match="not hand topics: /hand/camera"):
        recorded_topics_custom({"/hand/camera": "/c"})


def _same_steps(got, want) -> None:
    assert len(got) == len(want) and got.hand == want.hand
    for traj, expected in zip(got, want, strict=True):
        assert np.array_equal(traj.states, expected.states) and np.array_equal(traj.actions, expected.actions)


def _remapped_bag(path: Path, data, storage=StoragePlugin.MCAP, custom: bool = True) -> Path:
    messages = [(REMAPPED[topic], stamp, msg) for traj in data for topic, stamp, msg in step_messages(traj)]
    types = {REMAPPED[topic]: msgtype for topic, msgtype in ma.HAND_TOPICS.items()}
    record = {HAND_KEY: data.hand, **(recorded_topics_custom(REMAPPED) if custom else {})}
    return write_messages(path, messages, types, record, storage)


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_a_bag_of_remapped_topics_reads_as_its_record_says(tmp_path: Path, small_set, storage) -> None:
    bag = _remapped_bag(tmp_path / "remapped", small_set, storage)
    _same_steps(read_bag(bag), small_set)
    info = bag_info(bag)
    assert info["hand_topics"] == REMAPPED and info["episodes"] == len(small_set) and info["no_hand_episodes"] is None


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_a_bag_without_its_metadata_file_reads_by_the_copy_inside(tmp_path: Path, small_set, storage) -> None:
    """An MCAP keeps a copy of metadata.yaml in its metadata record, a db3 in its metadata table."""
    bag = _remapped_bag(tmp_path / "remapped", small_set, storage)
    (bag / "metadata.yaml").unlink()
    with pytest.warns(UserWarning, match="metadata.yaml is missing"):
        _same_steps(read_bag(bag), small_set)


def test_without_the_record_remapped_topics_hold_no_episodes(tmp_path: Path, small_set) -> None:
    bag = _remapped_bag(tmp_path / "unrecorded", small_set, custom=False)
    assert bag_info(bag)["no_hand_episodes"].startswith("it has no /hand/object_pose")
    with pytest.raises(BagError, match="required topic /hand/object_pose"):
        read_bag(bag)


def test_one_recorded_topic_for_two_hand_topics_is_refused() -> None:
    """Joint states carrying velocities would otherwise read as the actions too (found by review)."""
    text = json.dumps({**REMAPPED, ACTION: REMAPPED[JOINTS]})
    with pytest.raises(BagError, match="gives /hand/applied_action and /hand/joint_states the same topic /arm/joint"):
        hand_topic_names("bag", {HAND_TOPICS_KEY: text}, [])


def test_a_status_topic_of_another_type_is_refused(tmp_path: Path, small_set) -> None:
    """Before, its resets and end reasons were silently ignored."""
    wrong = {**REMAPPED, ma.HAND_STATUS_TOPIC: "/marker"}
    messages = [(REMAPPED[topic], stamp, msg) for traj in small_set for topic, stamp, msg in step_messages(traj)]
    messages.append(("/marker", messages[0][1], messages[0][2]))  # a pose
    types = {**{REMAPPED[topic]: msgtype for topic, msgtype in ma.HAND_TOPICS.items()}, "/marker": ma.POSE_STAMPED}
    bad = write_messages(tmp_path / "status_is_a_pose", messages, types, recorded_topics_custom(wrong))
    with pytest.raises(BagError, match="topic /marker .the hand's status. has type geometry_msgs/msg/PoseStamped"):
        read_bag(bad)


def test_the_scene_of_a_remapped_bag_draws_the_object_and_fingers(tmp_path: Path, small_set) -> None:
    bag = _remapped_bag(tmp_path / "remapped", small_set)
    inputs = bag_scene_inputs(bag)
    last = small_set[-1]
    np.testing.assert_allclose(inputs.object_xy_mm, last.states[-1, :2], atol=1e-3)
    np.testing.assert_allclose(inputs.actuator_angles, last.actuator_angles[-1], atol=1e-6)


def test_the_scene_of_a_bag_with_nothing_to_draw_is_empty(tmp_path: Path, small_set) -> None:
    """rosbags reads every connection when given none: a status-only bag crashed the snapshot (found by review)."""
    stamp = small_set[0].start_ns
    status = ma.TYPESTORE.types[ma.STRING](data="reset")
    bag = write_messages(tmp_path / "only_status", [("/hand/status", stamp, status)], {"/hand/status": ma.STRING})
    inputs = bag_scene_inputs(bag)
    assert inputs.object_xy_mm is None and inputs.actuator_angles is None and inputs.log_ns == 0


def test_the_scene_reads_a_recorded_bag_by_its_record_only(tmp_path: Path, small_set) -> None:
    """Another source's /hand/object_pose in the same bag is not the hand's pose when the record says /pose is
    (read_bag reads it so; the scene drew the other one, found by review)."""
    messages = [(REMAPPED[topic], stamp, msg) for traj in small_set for topic, stamp, msg in step_messages(traj)]
    decoy = small_set[-1].start_ns + len(small_set[-1]) * 100_000_000
    messages.append((POSE, decoy, ma.object_pose_msg((999.0, 999.0), decoy)))
    types = {**{REMAPPED[topic]: msgtype for topic, msgtype in ma.HAND_TOPICS.items()}, POSE: ma.POSE_STAMPED}
    bag = write_messages(tmp_path / "with_decoy", messages, types, recorded_topics_custom(REMAPPED))
    np.testing.assert_allclose(bag_scene_inputs(bag).object_xy_mm, small_set[-1].states[-1, :2], atol=1e-3)


def test_a_locked_db3_without_its_metadata_file_still_reads_its_record(tmp_path: Path, small_set) -> None:
    """A writer's lock on the db3 neither stalls the read of its metadata table nor hides it (review)."""
    import sqlite3

    bag = _remapped_bag(tmp_path / "locked", small_set, StoragePlugin.SQLITE3)
    (bag / "metadata.yaml").unlink()
    holder = sqlite3.connect(next(bag.glob("*.db3")))
    try:
        holder.execute("BEGIN EXCLUSIVE")
        with pytest.warns(UserWarning, match="metadata.yaml is missing"):
            _same_steps(read_bag(bag), small_set)
    finally:
        holder.close()
