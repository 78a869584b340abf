"""bag_io: exact round trips, bags as ``ros2 bag record`` writes them, and every way a bag can be bad."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
import zstandard
from fuzz_harness import DecoderWorker
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

import msg_adapters as ma
from t42_transfer.cli import main
from t42_transfer.conventions import CONTROL_PERIOD_NS, MIN_EPISODE_STEPS
from t42_transfer.data import bag_io
from t42_transfer.data.bag_io import (
    EPISODE_GAP_NS,
    EPISODES_KEY,
    HAND_KEY,
    assign_start_times,
    bag_info,
    read_bag,
    verify_bag,
    write_bag,
)
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import END_REASONS, Trajectory, TrajectorySet

POSE, JOINTS, ACTION = ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC


def assert_same(got: TrajectorySet, want: TrajectorySet) -> None:
    assert got.hand == want.hand
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert a == b  # bit-exact arrays, start_ns, end_reason, hand


def read_quietly(path, **kwargs) -> TrajectorySet:
    """read_bag that fails the test on any warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_bag(path, **kwargs)


def step_messages(traj: Trajectory) -> list[tuple[str, int, object]]:
    """The hand's messages of one episode, as write_bag publishes them: (topic, stamp, message)."""
    out = []
    for k, state in enumerate(traj.states):
        stamp = traj.start_ns + k * CONTROL_PERIOD_NS
        angles = None if traj.actuator_angles is None else traj.actuator_angles[k]
        out.append((POSE, stamp, ma.object_pose_msg(state[:2], stamp)))
        out.append((JOINTS, stamp, ma.joint_state_msg(state[2:], angles, stamp)))
        if k < len(traj):
            out.append((ACTION, stamp, ma.applied_action_msg(traj.actions[k], stamp)))
    return out


def write_messages(path: Path, messages, types=ma.HAND_TOPICS, custom=None) -> Path:
    """A bag of arbitrary messages, written with rosbags directly (log time = the given stamp)."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for key, value in (custom or {}).items():
            writer.set_custom_data(key, value)
        conns = {t: writer.add_connection(t, types[t], typestore=ma.TYPESTORE) for t in types}
        for topic, stamp, msg in messages:
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    return path


@pytest.fixture(scope="module")
def episode(make_set) -> Trajectory:
    """One 60-transition episode with actuator angles."""
    return make_set((60,), angles=True)[0]


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_is_exact(tmp_path, small_set, storage):
    path = write_bag(tmp_path / "bag", small_set, storage=storage)
    assert path == tmp_path / "bag"
    assert_same(read_quietly(path), small_set)


F32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


@st.composite
def trajectory_sets(draw) -> TrajectorySet:
    hand = draw(st.text(max_size=12).filter(lambda s: "\x85" not in s))
    episodes = []
    for _ in range(draw(st.integers(1, 3))):
        steps = draw(st.integers(MIN_EPISODE_STEPS, MIN_EPISODE_STEPS + 4))
        episodes.append(
            Trajectory(
                states=draw(arrays(np.float32, (steps + 1, 4), elements=F32)),
                actions=draw(arrays(np.float32, (steps, 2), elements=F32)),
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
    assert info["metadata"] == {"operator": "ada", HAND_KEY: "sim_a"}
    assert info["recovered_prefix"] is False


# ------------------------------------------------------------------ writing rules


def test_assign_start_times_lays_episodes_end_to_end(small_set):
    placed = assign_start_times(small_set, t0_ns=5, gap_ns=EPISODE_GAP_NS)
    assert placed[0].start_ns == 5
    for before, after in zip(placed, placed[1:]):
        assert after.start_ns == before.start_ns + len(before) * CONTROL_PERIOD_NS + EPISODE_GAP_NS
    assert [np.array_equal(a.states, b.states) for a, b in zip(placed, small_set)] == [True] * 3
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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_failed_write_leaves_nothing(tmp_path, small_set, monkeypatch):
    calls = []

    def fail_on_second(writer, connections, traj):
        calls.append(traj)
        if len(calls) == 2:
            raise RuntimeError("disk full")

    monkeypatch.setattr(bag_io, "_write_episode", fail_on_second)
    with pytest.raises(RuntimeError, match="disk full"):
        write_bag(tmp_path / "bag", small_set)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ bags not written by write_bag


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
    for recorded, original, start in zip(got, data, first_states):
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


# ------------------------------------------------------------------ bad bags


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


def test_gap_raises_unless_allowed_then_splits(tmp_path, episode):
    gone = {episode.start_ns + k * CONTROL_PERIOD_NS for k in range(20, 24)}  # a 0.5 s hole
    path = write_messages(tmp_path / "bag", [m for m in step_messages(episode) if m[1] not in gone])
    with pytest.raises(BagError, match="skips 500 ms .* allow_gaps=True"):
        read_bag(path)
    with pytest.warns(UserWarning, match="skips 500 ms"):
        first, second = read_bag(path, allow_gaps=True)
    assert np.array_equal(first.states, episode.states[:20]) and np.array_equal(first.actions, episode.actions[:19])
    assert second.start_ns == episode.start_ns + 24 * CONTROL_PERIOD_NS
    assert np.array_equal(second.states, episode.states[24:]) and np.array_equal(second.actions, episode.actions[24:])


# ------------------------------------------------------------------ partial data: whole steps salvaged


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
    for traj, (first, last) in zip(got, fragments):
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


def test_stamps_closer_than_half_a_period(tmp_path, episode):
    messages = step_messages(episode)
    stamp = episode.start_ns + 3 * CONTROL_PERIOD_NS + 20_000_000
    messages.insert(3 * 3 + 3, (JOINTS, stamp, ma.joint_state_msg([1.0, 1.0], [0.0, 0.0], stamp)))
    with pytest.raises(BagError, match="20 ms apart"):
        read_bag(write_messages(tmp_path / "bag", messages))


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


# ------------------------------------------------------------------ damaged MCAP files


@pytest.fixture(scope="module")
def big_bag(tmp_path_factory, make_set) -> tuple[Path, TrajectorySet]:
    """A bag of about three 1 MiB MCAP chunks (rosbags' chunk size)."""
    data = make_set((450,) * 14, seed=7)
    return write_bag(tmp_path_factory.mktemp("big") / "bag", data), data


def damaged_copy(tmp_path: Path, bag: Path, size: int | None = None, drop_yaml: bool = False) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(bag, copy)
    mcap = copy / "bag.mcap"
    if size is not None:
        mcap.write_bytes(mcap.read_bytes()[:size])
    if drop_yaml:
        (copy / "metadata.yaml").unlink()
    return copy


def assert_prefix_of(got: TrajectorySet, original: TrajectorySet, with_custom_data: bool) -> None:
    """Recovered episodes are the originals in order, only the last possibly cut short; without
    custom_data (a killed writer never wrote it) end reasons and hands are unknown."""
    assert [t.start_ns for t in got] == [t.start_ns for t in original[: len(got)]]
    for traj, whole in zip(got, original):
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


def test_missing_metadata_yaml_on_an_intact_bag(tmp_path, small_set):
    copy = damaged_copy(tmp_path, write_bag(tmp_path / "bag", small_set), drop_yaml=True)
    with pytest.warns(UserWarning, match="metadata.yaml is missing"):
        assert_same(read_bag(copy), small_set)  # custom_data comes from the MCAP metadata record


def test_garbled_metadata_yaml(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.warns(UserWarning, match="metadata.yaml is unreadable"):
        assert_same(read_bag(bag), small_set)


def test_corrupt_sqlite3_bag(tmp_path, small_set):
    bag = write_bag(tmp_path / "bag", small_set, storage="sqlite3")
    (bag / "bag.db3").write_bytes(b"SQLite format 3\x00" + bytes(200))
    with pytest.raises(BagError, match="rosbags cannot read it") as err:
        read_bag(bag)
    assert str(bag) in str(err.value)


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


# ------------------------------------------------------------------ hostile bags: one-line errors, no hang, no writes

REPO = Path(__file__).resolve().parents[1]
TARGET = REPO / "bags" / "target_small"


def fixture_copy(tmp_path: Path, edit=None) -> Path:
    """The target fixture bag copied; ``edit(info)`` changes its rosbag2_bagfile_information in place."""
    bag = Path(shutil.copytree(TARGET, tmp_path / "target_small"))
    if edit is not None:
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())
        edit(meta["rosbag2_bagfile_information"])
        (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return bag


def nested(depth: int) -> list:
    value: list = []
    for _ in range(depth):
        value = [value]
    return value


def refusal(bag: Path, function=read_bag) -> str:
    """The one-line BagError ``function`` raises for ``bag``."""
    with pytest.raises(BagError) as err:
        function(bag)
    text = str(err.value)
    assert text.startswith(f"{bag}: ") and "\n" not in text, text
    return text


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


@pytest.mark.parametrize("where", ["bag", "storage file", "metadata.yaml", "bare file"])
@pytest.mark.parametrize("function", ["read_bag", "bag_info", "verify_bag"])
def test_fifos_are_refused_before_opening(where, function):
    """A FIFO blocks whoever opens it for reading; each run goes through the fuzz worker, whose alarm ends a hang."""
    with DecoderWorker(f"t42_transfer.data.bag_io:{function}", timeout_s=10.0) as worker:
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


# ------------------------------------------------------------------ t42 bag info --verify


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
