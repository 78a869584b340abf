"""data.bag.episodes: bags as ``ros2 bag record`` writes them, and every way their messages can make bad episodes."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
import pytest
import yaml
from bag_builders import ACTION, JOINTS, POSE, assert_same, read_quietly, step_messages, write_messages
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2 import StoragePlugin, Writer

import msg_adapters as ma
from msg_adapters import names
from t42_transfer.conventions import CONTROL_PERIOD_NS, MIN_EPISODE_STEPS
from t42_transfer.data.bag import (
    EPISODES_KEY,
    bag_info,
    read_bag,
    write_bag,
)
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import Trajectory, TrajectorySet


def test_reads_a_bag_made_like_ros2_bag_record(tmp_path, make_set):
    """MCAP written with the mcap library as rosbag2_storage_mcap does (Jazzy), header stamps
    jittered, log times (receive times) later and interleaved, an extra topic, no custom_data."""
    data = make_set((30, 18), seed=3, angles=False)
    rng = np.random.default_rng(1)
    records = []  # (log time, topic, message)
    first_states = []
    for traj in data:
        for topic, stamp, msg in step_messages(traj):
            jitter = int(rng.integers(-3_000_000, 3_000_000)) if topic == JOINTS else 0
            skew = {POSE: 7_000_000, JOINTS: 0, ACTION: 1_000_000}[topic]
            msg.header.stamp = ma.ns_to_stamp(stamp + skew + jitter)
            records.append((stamp + int(rng.integers(1_000_000, 40_000_000)), topic, msg))
            if topic == JOINTS and stamp == traj.start_ns:
                first_states.append(stamp + jitter)
    chatter = ma.TYPESTORE.types["std_msgs/msg/String"](data="hello")
    records.append((data[0].start_ns + 5, "/chatter", chatter))
    records.sort(key=lambda r: r[0])
    types = {**ma.HAND_TOPICS, "/chatter": "std_msgs/msg/String"}
    qos = yaml.safe_dump(
        [
            {
                "history": "keep_last",
                "depth": 10,
                "reliability": "reliable",
                "durability": "volatile",
                "deadline": {"sec": 9223372036, "nsec": 854775807},
                "lifespan": {"sec": 9223372036, "nsec": 854775807},
                "liveliness": "automatic",
                "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
                "avoid_ros_namespace_conventions": False,
            }
        ]
    )
    bag = tmp_path / "rosbag2_2025_01_01-00_00_00"
    bag.mkdir()
    file = bag / "rosbag2_2025_01_01-00_00_00_0.mcap"
    with file.open("wb") as stream:
        mcap = McapWriter(stream, compression=CompressionType.ZSTD)
        mcap.start(profile="ros2", library="libmcap 1.4.0")
        schemas = {
            msgtype: mcap.register_schema(
                name=msgtype,
                encoding="ros2msg",
                data=ma.TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0].encode(),
            )
            for msgtype in set(types.values())
        }
        channels = {
            topic: mcap.register_channel(
                topic=topic,
                message_encoding="cdr",
                schema_id=schemas[msgtype],
                metadata={"offered_qos_profiles": qos, "topic_type_hash": ma.TYPESTORE.hash_rihs01(msgtype)},
            )
            for topic, msgtype in types.items()
        }
        for seq, (log_ns, topic, msg) in enumerate(records):
            raw = ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__)
            mcap.add_message(channels[topic], log_time=log_ns, data=raw, publish_time=log_ns, sequence=seq)
        mcap.add_metadata("rosbag2", {"serialized_metadata": "custom_data: ~\nros_distro: jazzy\n"})
        mcap.finish()
    counts = {t: sum(1 for r in records if r[1] == t) for t in types}
    first, last = records[0][0], records[-1][0]
    metadata = {
        "rosbag2_bagfile_information": {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": last - first},
            "starting_time": {"nanoseconds_since_epoch": first},
            "message_count": len(records),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": yaml.safe_load(qos),
                        "type_description_hash": ma.TYPESTORE.hash_rihs01(msgtype),
                    },
                    "message_count": counts[topic],
                }
                for topic, msgtype in types.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [file.name],
            "files": [
                {
                    "path": file.name,
                    "starting_time": {"nanoseconds_since_epoch": first},
                    "duration": {"nanoseconds": last - first},
                    "message_count": len(records),
                }
            ],
            "custom_data": None,
            "ros_distro": "jazzy",
        }
    }
    (bag / "metadata.yaml").write_text(yaml.safe_dump(metadata, sort_keys=False))

    got = read_quietly(bag)
    assert got.hand == "" and len(got) == 2
    for recorded, original, start in zip(got, data, first_states, strict=True):
        assert np.array_equal(recorded.states, original.states)
        assert np.array_equal(recorded.actions, original.actions)
        assert recorded.actuator_angles is None and recorded.end_reason == "" and recorded.hand == ""
        assert recorded.start_ns == start
    info = bag_info(bag)
    assert info["ros_distro"] == "jazzy" and info["topics"]["/chatter"]["count"] == 1


def test_reads_bags_without_custom_data_and_bare_storage_files(tmp_path, episode):
    path = write_messages(tmp_path / "bag", step_messages(episode))
    (got,) = read_quietly(path)
    assert np.array_equal(got.states, episode.states) and got.end_reason == "" and got.hand == ""
    (got,) = read_quietly(path / "bag.mcap")
    assert np.array_equal(got.actions, episode.actions)
    sqlite = write_bag(tmp_path / "sq", TrajectorySet([episode], hand="h"), storage="sqlite3")
    (got,) = read_quietly(sqlite / "sq.db3")
    assert got.start_ns == episode.start_ns


def test_missing_topic_is_named_with_what_the_bag_has(tmp_path, episode):
    types = {POSE: ma.POSE_STAMPED, JOINTS: ma.JOINT_STATE}
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[0] != ACTION], types)
    with pytest.raises(BagError, match="required topic /hand/applied_action .* is missing") as err:
        read_bag(path)
    assert "/hand/joint_states (sensor_msgs/msg/JointState)" in str(err.value)
    assert str(path) in str(err.value)


def test_unexpected_topic_type(tmp_path, episode):
    types = {**ma.HAND_TOPICS, ACTION: "std_msgs/msg/String"}
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[0] != ACTION], types)
    with pytest.raises(BagError, match="/hand/applied_action has type std_msgs/msg/String"):
        read_bag(path)


def test_foreign_type_definition_is_refused(tmp_path, episode):
    path = tmp_path / "bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            topic: writer.add_connection(
                topic,
                msgtype,
                msgdef=ma.TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0],
                rihs01="RIHS01_" + "0" * 64,
            )
            for topic, msgtype in ma.HAND_TOPICS.items()
        }
        for topic, stamp, msg in step_messages(episode):
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    with pytest.raises(BagError, match="type hash RIHS01_0000"):
        read_bag(path)


def test_nan_is_named_by_topic_and_stamp(tmp_path, episode):
    messages = step_messages(episode)
    topic, stamp, msg = messages[3 * 5 + 1]
    assert topic == JOINTS
    msg.effort = np.array([np.nan, 1.0])
    path = write_messages(tmp_path / "bag", messages)
    with pytest.raises(BagError, match=f"/hand/joint_states at stamp {stamp} ns: .*non-finite"):
        read_bag(path)


def test_header_stamps_must_increase(tmp_path, episode):
    messages = step_messages(episode)
    a, b = messages[3 * 5 + 1][2], messages[3 * 6 + 1][2]
    a.header, b.header = b.header, a.header
    path = write_messages(tmp_path / "bag", messages)
    with pytest.raises(BagError, match="/hand/joint_states: header stamps must increase"):
        read_bag(path)


def test_missing_steps_split_the_episode_with_a_warning(tmp_path, episode):
    gone = {episode.start_ns + k * CONTROL_PERIOD_NS for k in range(20, 24)}  # a 0.5 s hole, no driver status
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[1] not in gone])
    with pytest.warns(UserWarning, match="500 ms apart, with no hand message between and no 'late' status"):
        first, second = read_bag(path)
    assert np.array_equal(first.states, episode.states[:20]) and np.array_equal(first.actions, episode.actions[:19])
    assert second.start_ns == episode.start_ns + 24 * CONTROL_PERIOD_NS
    assert np.array_equal(second.states, episode.states[24:]) and np.array_equal(second.actions, episode.actions[24:])
    assert first.step_ns is None and second.step_ns is None


def late_episode(episode: Trajectory, late: dict[int, int]) -> Trajectory:
    """``episode`` with transitions ``k`` taking ``late[k]`` ns (a driver that stalled there)."""
    steps = np.full(len(episode), CONTROL_PERIOD_NS, np.int64)
    for k, ns in late.items():
        steps[k] = ns
    return dataclasses.replace(episode, step_ns=steps)


def test_a_late_step_the_driver_named_is_kept_with_its_duration(tmp_path, episode):
    stalled = late_episode(episode, {19: 450_000_000, 30: 170_000_000})
    path = write_bag(tmp_path / "bag", TrajectorySet([stalled], hand=episode.hand))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing dropped, nothing split
        (got,) = read_bag(path)
    assert got == stalled
    assert got.late_steps.tolist() == [19, 30] and got.step_ns[19] == 450_000_000
    assert bag_info(path)["late_steps"] == 2

    # The same messages without the driver's word for it: steps are missing there, and the episode splits.
    messages = []
    for topic, stamp, msg in step_messages(episode):
        shift = 350_000_000 * (stamp >= episode.start_ns + 20 * CONTROL_PERIOD_NS) \
            + 70_000_000 * (stamp >= episode.start_ns + 31 * CONTROL_PERIOD_NS)
        msg.header.stamp = ma.ns_to_stamp(stamp + shift)
        messages.append((topic, stamp + shift, msg))
    with pytest.warns(UserWarning, match="450 ms apart.*steps are missing"):
        pieces = read_bag(write_messages(tmp_path / "unmarked", messages))
    assert [len(t) for t in pieces] == [19, 29]  # the 10 transitions between the two stalls are too few to keep


def test_stamps_closer_than_half_a_period_split_the_episode(tmp_path, episode):
    messages = step_messages(episode)
    stamp = episode.start_ns + 20 * CONTROL_PERIOD_NS + 20_000_000
    at = next(i for i, m in enumerate(messages) if m[1] > stamp)
    messages[at:at] = [(POSE, stamp, ma.object_pose_msg([1.0, 1.0], stamp)),
                       (JOINTS, stamp, ma.joint_state_msg([1.0, 1.0], [0.0, 0.0], stamp))]
    with pytest.warns(UserWarning, match="20 ms apart, less than half"):
        first, second = read_bag(write_messages(tmp_path / "bag", messages))
    assert np.array_equal(first.states, episode.states[:21])  # the stray state has no action: no transition
    assert second.start_ns == episode.start_ns + 21 * CONTROL_PERIOD_NS


def assert_slice(got: Trajectory, whole: Trajectory, first: int, last: int) -> None:
    """``got`` is states ``first..last`` of ``whole`` with their actions, starting at state ``first``'s stamp."""
    assert got.start_ns == whole.start_ns + first * CONTROL_PERIOD_NS
    assert np.array_equal(got.states, whole.states[first : last + 1])
    assert np.array_equal(got.actions, whole.actions[first:last])
    assert np.array_equal(got.actuator_angles, whole.actuator_angles[first : last + 1])


def test_a_recording_begun_between_a_state_and_its_action_keeps_the_rest(tmp_path, episode):
    """The issue's case: under load the recorder started after step 0's state, so the bag begins with an
    /hand/applied_action whose state is absent; the whole bag was refused."""
    start = episode.start_ns
    messages = [m for m in step_messages(episode) if not (m[1] == start and m[0] != ACTION)]
    assert messages[0][:2] == (ACTION, start)
    path = write_messages(tmp_path / "bag", messages)
    warned = rf"{re.escape(str(path))}: kept the whole steps only; dropped {ACTION} messages with no {JOINTS} " \
             rf"within 50 ms: 1 \(stamp {start} ns\)$"
    with pytest.warns(UserWarning, match=warned):
        (got,) = read_bag(path)
    assert_slice(got, episode, 1, len(episode))


def test_a_recording_ended_mid_step_keeps_the_rest(tmp_path, episode):
    last = episode.start_ns + len(episode) * CONTROL_PERIOD_NS
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[:2] != (POSE, last)])
    with pytest.warns(UserWarning, match=f"dropped {JOINTS} messages with no {POSE} within 50 ms, with their "
                                         f"actions: 1 \\(stamp {last} ns\\)"):
        (got,) = read_bag(path)
    assert_slice(got, episode, 0, len(episode) - 1)


@pytest.mark.parametrize("lost,fragments,dropped", ids=["pose", "state", "action"], argvalues=[
    (POSE, [(0, 29), (31, 60)], f"{JOINTS} messages with no {POSE} within 50 ms, with their actions"),
    (JOINTS, [(0, 29), (31, 60)], f"{POSE} messages with no {JOINTS} within 50 ms"),
    (ACTION, [(0, 30), (31, 60)], f"the transitions from {JOINTS} messages with no {ACTION} within 50 ms"),
])
def test_one_lost_message_splits_its_episode_there(tmp_path, episode, lost, fragments, dropped):
    stamp = episode.start_ns + 30 * CONTROL_PERIOD_NS
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[:2] != (lost, stamp)])
    with pytest.warns(UserWarning, match=f"{re.escape(dropped)}: 1 \\(stamp {stamp} ns\\)"):
        got = read_bag(path)
    assert len(got) == len(fragments)
    for traj, (first, last) in zip(got, fragments, strict=True):
        assert_slice(traj, episode, first, last)


def test_stray_messages_are_dropped_and_named(tmp_path, episode):
    after = episode.start_ns + len(episode) * CONTROL_PERIOD_NS + 300_000_000
    extra = [*step_messages(episode), (ACTION, after, ma.applied_action_msg([1.0, 1.0], after)),
             (POSE, after + 1, ma.object_pose_msg([0.0, 0.0], after + 1))]
    with pytest.warns(UserWarning, match=f"{ACTION} messages with no {JOINTS} within 50 ms: 1 \\(stamp {after} ns\\); "
                                         f"{POSE} messages with no {JOINTS} within 50 ms: 1 "
                                         f"\\(stamp {after + 1} ns\\)"):
        (got,) = read_bag(write_messages(tmp_path / "bag", extra))
    assert_slice(got, episode, 0, len(episode))


def test_several_actions_for_one_state_are_still_refused(tmp_path, episode):
    stamp = episode.start_ns + 5 * CONTROL_PERIOD_NS
    second = stamp + 10_000_000
    extra = [*step_messages(episode), (ACTION, second, ma.applied_action_msg([0.0, 0.0], second))]
    extra.sort(key=lambda m: m[1])
    with pytest.raises(BagError, match=f"several /hand/applied_action messages match the state at stamp {stamp} ns"):
        read_bag(write_messages(tmp_path / "bag", extra))


def test_episode_mixing_known_and_unknown_angles(tmp_path, episode):
    messages = step_messages(episode)
    topic, stamp, msg = messages[3 * 4 + 1]
    msg.position = np.zeros(0)
    with pytest.raises(BagError, match=f"at stamp {stamp} ns has no positions"):
        read_bag(write_messages(tmp_path / "bag", messages))


def test_malformed_custom_data(tmp_path, episode):
    path = write_messages(tmp_path / "bag", step_messages(episode), custom={EPISODES_KEY: "[{"})
    with pytest.raises(BagError, match="t42_transfer.episodes is malformed"):
        read_bag(path)


def test_short_episodes_are_dropped_with_a_warning(tmp_path, make_set):
    data = make_set((MIN_EPISODE_STEPS - 1, MIN_EPISODE_STEPS))
    path = write_bag(tmp_path / "bag", data)
    expected = rf"{re.escape(str(path))}: dropped the episode starting at {data[0].start_ns} ns"
    with pytest.warns(UserWarning, match=expected):
        got = read_bag(path)
    assert_same(got, TrajectorySet([data[1]], hand=data.hand))


def test_a_reset_mid_episode_ends_the_episode_at_the_state_it_names(tmp_path, episode):
    """A simulated hand is grasped anew between two steps 0.1 s apart: the driver's ``reset`` status names the
    last state before it, whose action leads to no recorded state; no transition may join the two grasps."""
    reset_after = 29
    stamp = episode.start_ns + reset_after * CONTROL_PERIOD_NS
    status = ma.ROSBAGS.make(ma.STRING, data=ma.status_message("reset", "episode 2 grasped", stamp))
    messages = sorted([*step_messages(episode), (ma.HAND_STATUS_TOPIC, stamp + 1, status)], key=lambda m: m[1])
    path = write_messages(tmp_path / "bag", messages, types={**ma.HAND_TOPICS, ma.HAND_STATUS_TOPIC: ma.STRING})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a border, not a loss: nothing is named as dropped
        before, after = read_bag(path)
    assert np.array_equal(before.states, episode.states[: reset_after + 1])
    assert np.array_equal(before.actions, episode.actions[:reset_after])
    assert after.start_ns == stamp + CONTROL_PERIOD_NS
    assert np.array_equal(after.states, episode.states[reset_after + 1 :])
    assert (before.end_reason, after.end_reason) == (names.RESET, "")  # the second ran to the end of the bag
    assert bag_info(path)["end_reasons"] == {names.RESET: 1, "unknown": 1}


def with_statuses(episode: Trajectory, statuses: list[tuple[str, int]], drop: set[int] = frozenset()) -> list:
    """``episode``'s messages, less those stamped in ``drop``, with ``(word, state index)`` statuses naming states."""
    messages = [m for m in step_messages(episode) if m[1] not in drop]
    for word, k in statuses:
        stamp = episode.start_ns + k * CONTROL_PERIOD_NS
        text = ma.status_message(word, f"episode 1 ended after {k} steps", stamp)
        messages.append((ma.HAND_STATUS_TOPIC, stamp + 1, ma.ROSBAGS.make(ma.STRING, data=text)))
    return sorted(messages, key=lambda m: m[1])


STATUS_TYPES = {**ma.HAND_TOPICS, ma.HAND_STATUS_TOPIC: ma.STRING}


@pytest.mark.parametrize("word", [names.DROPPED, names.LOST_CONTACT])
def test_the_state_a_driver_said_the_object_fell_into_is_left_out_and_ends_the_episode(tmp_path, episode, word):
    """As a simulated collection ends an episode at a drop: the states before it, the end reason the driver gave.
    The driver published no action from that state; the bag's other episode, with no status, is untouched."""
    fell = len(episode)  # the episode's last state
    head = dataclasses.replace(episode, actions=episode.actions[:-1], states=episode.states[:-1],
                               actuator_angles=episode.actuator_angles[:-1])
    other = dataclasses.replace(episode, start_ns=episode.start_ns + 10**10)
    messages = [*with_statuses(episode, [(word, fell)]), *step_messages(other)]
    path = write_messages(tmp_path / "bag", messages, types=STATUS_TYPES)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an end the driver named: nothing lost, nothing to warn about
        got, untouched = read_bag(path)
    assert got.end_reason == word and len(got) == len(episode) - 1
    assert np.array_equal(got.states, head.states) and np.array_equal(got.actions, head.actions)
    assert untouched.end_reason == "" and np.array_equal(untouched.states, episode.states)
    assert bag_info(path)["end_reasons"] == {word: 1, "unknown": 1}


def test_an_overload_ends_the_episode_at_the_state_it_names_and_keeps_it(tmp_path, episode):
    """An overload is no fall: the hand still holds the object in the state the driver stopped at."""
    path = write_messages(tmp_path / "bag", with_statuses(episode, [(names.OVERLOAD, len(episode))]),
                          types=STATUS_TYPES)
    (got,) = read_bag(path)
    assert got.end_reason == names.OVERLOAD and np.array_equal(got.states, episode.states)
    assert bag_info(path)["end_reasons"] == {names.OVERLOAD: 1}


def test_a_drop_named_mid_episode_ends_it_there_and_a_fall_into_a_stale_step_keeps_what_came_before(
        tmp_path, episode):
    """A driver that went on after its own drop (not ours: it holds) still ends the episode at the state it named:
    no transition leaves it.  A drop named on a step that went out without a pose (the tracker lost the object as
    it fell) ends the episode at the state before, which is kept."""
    fell = 30
    path = write_messages(tmp_path / "bag", with_statuses(episode, [(names.DROPPED, fell)]), types=STATUS_TYPES)
    before, after = read_bag(path)
    assert before.end_reason == names.DROPPED and np.array_equal(before.states, episode.states[:fell])
    assert after.start_ns == episode.start_ns + (fell + 1) * CONTROL_PERIOD_NS and after.end_reason == ""
    assert np.array_equal(after.states, episode.states[fell + 1 :])

    last = len(episode)
    stale = episode.start_ns + last * CONTROL_PERIOD_NS
    messages = [m for m in with_statuses(episode, [(names.DROPPED, last)]) if not (m[0] == POSE and m[1] == stale)]
    with pytest.warns(UserWarning, match="messages with no /hand/object_pose"):
        (got,) = read_bag(write_messages(tmp_path / "stale", messages, types=STATUS_TYPES))
    assert got.end_reason == names.DROPPED and np.array_equal(got.states, episode.states[:last])


@pytest.mark.parametrize("lost", [JOINTS, POSE])
def test_a_fall_whose_step_lost_a_message_still_gives_the_episode_its_end(tmp_path, episode, lost):
    """The state the driver named never reached the bag whole: the episode is the states before it all the same."""
    fall = episode.start_ns + len(episode) * CONTROL_PERIOD_NS
    messages = [m for m in with_statuses(episode, [(names.DROPPED, len(episode))])
                if not (m[0] == lost and m[1] == fall)]
    with pytest.warns(UserWarning, match="kept the whole steps only"):
        (got,) = read_bag(write_messages(tmp_path / "bag", messages, types=STATUS_TYPES))
    assert got.end_reason == names.DROPPED and np.array_equal(got.states, episode.states[:-1])


def test_an_end_named_twice_is_a_fall_and_a_reset_border_takes_no_end_of_the_next_grasp(tmp_path, episode):
    """``dropped`` and ``overload`` on one state: the fall wins (however the bag orders them).  The first state
    of the grasp after a reset, named dropped and out of sight, ends nothing before the reset."""
    last = len(episode)
    for order in ([(names.OVERLOAD, last), (names.DROPPED, last)], [(names.DROPPED, last), (names.OVERLOAD, last)]):
        (got,) = read_bag(write_messages(tmp_path / f"twice_{order[0][0]}", with_statuses(episode, order),
                                         types=STATUS_TYPES))
        assert got.end_reason == names.DROPPED and len(got) == len(episode) - 1

    border = 30
    unseen = episode.start_ns + (border + 1) * CONTROL_PERIOD_NS
    messages = [m for m in with_statuses(episode, [(names.RESET, border), (names.DROPPED, border + 1)])
                if not (m[0] == POSE and m[1] == unseen)]
    with pytest.warns(UserWarning, match="kept the whole steps only"):
        before, after = read_bag(write_messages(tmp_path / "border", messages, types=STATUS_TYPES))
    assert before.end_reason == names.RESET and np.array_equal(before.states, episode.states[: border + 1])
    assert after.end_reason == "" and np.array_equal(after.states, episode.states[border + 2 :])
    assert bag_info(tmp_path / "border")["end_reasons"] == {names.RESET: 1, "unknown": 1}


@pytest.mark.parametrize("lost", [JOINTS, POSE])
def test_a_reset_whose_named_state_lost_a_message_still_ends_the_episode_as_reset(tmp_path, episode, lost):
    named = 29
    stamp = episode.start_ns + named * CONTROL_PERIOD_NS
    messages = [m for m in with_statuses(episode, [(names.RESET, named)]) if not (m[0] == lost and m[1] == stamp)]
    with pytest.warns(UserWarning, match="kept the whole steps only"):
        before, after = read_bag(write_messages(tmp_path / "bag", messages, types=STATUS_TYPES))
    assert before.end_reason == names.RESET and np.array_equal(before.states, episode.states[:named])
    assert after.end_reason == "" and np.array_equal(after.states, episode.states[named + 1:])
