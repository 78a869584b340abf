"""The recorder node on the in-process transport with a fake clock."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from msg_adapters import (
    APPLIED_ACTION_TOPIC,
    HAND_TOPICS,
    JOINT_STATE,
    JOINT_STATES_TOPIC,
    OBJECT_POSE_TOPIC,
    POSE_STAMPED,
    TYPESTORE,
    applied_action_msg,
    joint_state_msg,
    object_pose_msg,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag_io import read_bag
from t42_transfer.nodes.mock_driver import RESET_SERVICE, MockDriver, MockDriverParams
from t42_transfer.nodes.recorder import (
    SPLIT_SERVICE,
    START_SERVICE,
    STATUS_TOPIC,
    STOP_SERVICE,
    STRING,
    TRIGGER,
    Recorder,
    RecorderParams,
    next_bag_path,
)
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport
from t42_transfer.ros.transport import serialize

T0_NS = 1_000_000_000
_String = TYPESTORE.types[STRING]


class Rig:
    """A recorder node and a tester node (hand publishers, status publisher, Trigger clients) on one bus."""

    def __init__(self, out_dir: Path, **params: object) -> None:
        self.clock = FakeClock(T0_NS)
        self.bus = InProcessBus(clock=self.clock)
        self.tester = InProcessTransport(self.bus, "tester")
        self.node = InProcessTransport(self.bus, "recorder")
        self.pubs = {topic: self.tester.publisher(topic, msgtype, qos.DEFAULT) for topic, msgtype in HAND_TOPICS.items()}
        self.status = self.tester.publisher(STATUS_TOPIC, STRING, qos.TRANSIENT_LOCAL)
        self.clients = {name: self.tester.client(name, TRIGGER) for name in (START_SERVICE, STOP_SERVICE, SPLIT_SERVICE)}
        self.recorder = Recorder(self.node, RecorderParams(out_dir, **params))
        self.sent: dict[str, list[tuple[int, bytes]]] = {topic: [] for topic in HAND_TOPICS}
        """What the tester published per topic: (clock at publish, CDR bytes)."""

    def call(self, name: str):
        client = self.clients[name]
        return client.call(client.Request())

    def publish(self, topic: str, msg: object) -> None:
        data = serialize(HAND_TOPICS[topic], msg)
        self.pubs[topic].publish_raw(data)
        self.sent[topic].append((self.clock(), data))

    def step(self, k: int, start_ns: int, xy, loads, angles, action) -> None:
        """Publish state ``k`` (and its action unless None) stamped ``start_ns + k * 0.1 s`` at that time; spin."""
        stamp = start_ns + k * CONTROL_PERIOD_NS
        self.clock.advance(ns=stamp - self.clock())
        self.publish(OBJECT_POSE_TOPIC, object_pose_msg(xy, stamp))
        self.publish(JOINT_STATES_TOPIC, joint_state_msg(loads, angles, stamp))
        if action is not None:
            self.publish(APPLIED_ACTION_TOPIC, applied_action_msg(action, stamp))
        self.node.spin_once()

    def episode(self, start_ns: int, steps: int, seed: int = 0, last_state: bool = True) -> dict[str, np.ndarray]:
        """Publish one episode of ``steps`` transitions (its final state only if ``last_state``).

        Returns its arrays as read_bag should give them.
        """
        rng = np.random.default_rng(seed)
        xy = rng.uniform(-20, 20, size=(steps + 1, 2)).astype(np.float32)
        loads = rng.uniform(-200, 200, size=(steps + 1, 2)).astype(np.float32)
        angles = rng.uniform(0, 1, size=(steps + 1, 2)).astype(np.float32)
        actions = rng.uniform(-1, 1, size=(steps, 2)).astype(np.float32)
        for k in range(steps + 1 if last_state else steps):
            self.step(k, start_ns, xy[k], loads[k], angles[k], actions[k] if k < steps else None)
        return {"states": np.column_stack([xy, loads]), "actions": actions, "angles": angles}

    def close(self) -> None:
        self.recorder.close()
        self.node.close()
        self.tester.close()


def raw_messages(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    got: dict[str, list[tuple[int, bytes]]] = {topic: [] for topic in HAND_TOPICS}
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        for conn in reader.connections:
            assert conn.msgtype == HAND_TOPICS[conn.topic]
            assert conn.digest == TYPESTORE.hash_rihs01(conn.msgtype)
        for conn, log_ns, data in reader.messages():
            got[conn.topic].append((log_ns, bytes(data)))
    return got


def check_episode(traj, expected: dict[str, np.ndarray], start_ns: int) -> None:
    assert traj.start_ns == start_ns
    np.testing.assert_array_equal(traj.states, expected["states"])
    np.testing.assert_array_equal(traj.actions, expected["actions"])
    np.testing.assert_array_equal(traj.actuator_angles, expected["angles"])


def test_records_bytes_unchanged_and_read_bag_gives_the_trajectory(tmp_path: Path) -> None:
    rig = Rig(tmp_path / "bags")
    bag = tmp_path / "bags" / "recording_000"
    assert rig.recorder.current_bag == bag
    expected = rig.episode(T0_NS, 20)
    assert rig.recorder.current_count == 21 + 21 + 20

    reply = rig.call(STOP_SERVICE)
    assert reply.success and str(bag) in reply.message
    assert not rig.recorder.recording and rig.recorder.bags == [bag]
    assert (bag / "metadata.yaml").is_file() and (bag / "recording_000.mcap").is_file()

    assert raw_messages(bag) == rig.sent  # same bytes, logged at the receive time
    data = read_bag(bag)
    assert len(data) == 1
    check_episode(data.trajectories[0], expected, T0_NS)
    assert "offered_qos_profiles" in (bag / "metadata.yaml").read_text()
    rig.close()


def test_services_start_stop_split_make_the_expected_bags(tmp_path: Path) -> None:
    out = tmp_path / "out"
    rig = Rig(out, start_immediately=False, prefix="run")
    assert not rig.recorder.recording and not out.joinpath("run_000").exists()
    assert not rig.call(STOP_SERVICE).success
    assert not rig.call(SPLIT_SERVICE).success

    reply = rig.call(START_SERVICE)
    assert reply.success and str(out / "run_000") in reply.message
    assert not rig.call(START_SERVICE).success  # already recording
    rig.episode(T0_NS, 3)
    reply = rig.call(SPLIT_SERVICE)
    assert reply.success and str(out / "run_000") in reply.message and str(out / "run_001") in reply.message
    rig.episode(T0_NS + 10 * 10**9, 3)
    assert rig.call(SPLIT_SERVICE).success
    assert rig.call(STOP_SERVICE).success
    assert not rig.call(STOP_SERVICE).success
    rig.episode(T0_NS + 20 * 10**9, 3)  # not recording: nothing written
    assert rig.call(START_SERVICE).success
    rig.close()  # closes run_003

    names = sorted(p.name for p in out.iterdir())
    assert names == ["run_000", "run_001", "run_002", "run_003"]
    assert rig.recorder.bags == [out / n for n in names]
    assert all((out / n / "metadata.yaml").is_file() for n in names)
    counts = [sum(len(v) for v in raw_messages(out / n).values()) for n in names]
    assert counts == [11, 11, 0, 0]


def test_bags_are_never_overwritten(tmp_path: Path) -> None:
    (tmp_path / "rec_004").mkdir()
    (tmp_path / "other_009").mkdir()
    (tmp_path / "rec_x").mkdir()
    assert next_bag_path(tmp_path, "rec") == tmp_path / "rec_005"
    assert next_bag_path(tmp_path / "missing", "rec") == tmp_path / "missing" / "rec_000"
    rig = Rig(tmp_path, prefix="rec")
    assert rig.recorder.current_bag == tmp_path / "rec_005"
    rig.close()
    assert (tmp_path / "rec_004").exists() and not any((tmp_path / "rec_004").iterdir())


def test_episode_mode_splits_on_status(tmp_path: Path) -> None:
    rig = Rig(tmp_path, mode="episode")
    rig.status.publish(_String(data="reset: episode 0 grasped (seed 0)"))  # empty bag: no split
    rig.node.spin_once()
    assert rig.recorder.current_bag == tmp_path / "episode_000"
    first = rig.episode(T0_NS, 16, seed=1)
    rig.status.publish(_String(data="hello world"))  # other words do not split
    rig.status.publish(_String(data="reset_failed: grasp failed"))
    rig.node.spin_once()
    assert rig.recorder.current_bag == tmp_path / "episode_000"
    rig.status.publish(_String(data="dropped: episode 0 ended after 16 steps"))
    rig.node.spin_once()
    # a state stamped up to the status's receive time still belongs to the episode (topics are unordered)
    assert rig.recorder.current_bag == tmp_path / "episode_000"
    rig.status.publish(_String(data="reset: episode 1 grasped (seed 1)"))  # right after the end: one split
    rig.node.spin_once()
    start = T0_NS + 5 * 10**9
    second = rig.episode(start, 18, seed=2, last_state=False)
    assert rig.recorder.bags == [tmp_path / "episode_000"]
    assert rig.recorder.current_bag == tmp_path / "episode_001"
    # the end status queued together with the final state, in one spin: the state stays in episode_001
    final_stamp = start + 18 * CONTROL_PERIOD_NS
    rig.clock.advance(ns=final_stamp - rig.clock())
    rig.publish(OBJECT_POSE_TOPIC, object_pose_msg(second["states"][-1, :2], final_stamp))
    rig.publish(JOINT_STATES_TOPIC, joint_state_msg(second["states"][-1, 2:], second["angles"][-1], final_stamp))
    rig.status.publish(_String(data="overload: episode 1 ended"))
    rig.node.spin_once()
    assert rig.recorder.current_bag == tmp_path / "episode_001"
    third = rig.episode(start + 5 * 10**9, 15, seed=3)
    rig.close()

    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_000", "episode_001", "episode_002"]
    for name, expected, t0 in (("episode_000", first, T0_NS), ("episode_001", second, start),
                               ("episode_002", third, start + 5 * 10**9)):
        data = read_bag(tmp_path / name)
        assert len(data) == 1
        check_episode(data.trajectories[0], expected, t0)


def test_recording_mode_ignores_status(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    rig.episode(T0_NS, 2)
    rig.status.publish(_String(data="dropped"))
    rig.node.spin_once()
    assert rig.recorder.current_bag == tmp_path / "recording_000"
    rig.close()


def test_bad_messages_never_crash_the_recorder(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rig = Rig(tmp_path, mode="episode")
    with caplog.at_level(logging.WARNING):
        # bytes of another type, and no CDR at all, on a hand topic and on the status topic
        rig.pubs[JOINT_STATES_TOPIC].publish_raw(serialize(STRING, _String(data="hello")))
        rig.pubs[OBJECT_POSE_TOPIC].publish_raw(b"\x00\x01\x00\x00garbage")
        rig.pubs[APPLIED_ACTION_TOPIC].publish_raw(b"")
        rig.status.publish_raw(b"\x00\x01")
        assert rig.node.spin_once() == 4
    assert rig.recorder.dropped == 3
    assert rig.recorder.current_count == 0
    text = caplog.text
    assert JOINT_STATES_TOPIC in text and OBJECT_POSE_TOPIC in text and STATUS_TOPIC in text
    assert "not a sensor_msgs/msg/JointState" in text
    expected = rig.episode(T0_NS, 15)  # still recording
    rig.close()
    check_episode(read_bag(tmp_path / "episode_000").trajectories[0], expected, T0_NS)


def test_write_failure_is_logged_not_raised(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rig = Rig(tmp_path)
    bag = rig.recorder._bag
    assert bag is not None

    def broken(*args: object) -> None:
        raise OSError("disk full")

    bag.writer.write = broken  # type: ignore[method-assign]
    with caplog.at_level(logging.ERROR):
        rig.step(0, T0_NS, (1.0, 2.0), (3.0, 4.0), None, (0.5, -0.5))
    assert rig.recorder.dropped == 3 and "disk full" in caplog.text
    rig.close()


def test_params_are_checked(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"):
        RecorderParams(tmp_path, mode="bogus")
    with pytest.raises(ValueError, match="prefix"):
        RecorderParams(tmp_path, prefix="../up")
    with pytest.raises(ValueError, match="topics"):
        RecorderParams(tmp_path, topics={})
    with pytest.raises(KeyError):
        RecorderParams(tmp_path, topics={"/hand/x": "nope_msgs/msg/Nope"})
    with pytest.raises(ValueError):
        RecorderParams(tmp_path, topics={"bad topic": JOINT_STATE})
    with pytest.raises(ValueError, match="flush_period_s"):
        RecorderParams(tmp_path, flush_period_s=0)
    with pytest.raises(ValueError, match="queue_depth"):
        RecorderParams(tmp_path, queue_depth=0)
    params = RecorderParams(tmp_path, topics={OBJECT_POSE_TOPIC: POSE_STAMPED})
    assert params.bag_prefix == "recording" and params.topics == {OBJECT_POSE_TOPIC: POSE_STAMPED}


def test_the_open_chunk_reaches_the_file_every_flush_period(tmp_path: Path) -> None:
    rig = Rig(tmp_path, flush_period_s=0.5)
    bag = rig.recorder.current_bag
    assert bag is not None
    mcap = bag / f"{bag.name}.mcap"
    rig.episode(T0_NS, 3, last_state=False)  # 0.3 s: still in memory
    before = mcap.stat().st_size
    rig.episode(T0_NS + 3 * CONTROL_PERIOD_NS, 3)  # the clock passes 0.5 s: the timer flushes
    assert mcap.stat().st_size > before
    sub = rig.node._subscriptions[0]
    assert sub.qos == qos.QoSProfile(depth=1000)  # a deep RELIABLE queue, not ROS's default 10
    rig.close()


def test_records_the_mock_driver_one_bag_per_episode(tmp_path: Path) -> None:
    clock = FakeClock(T0_NS)
    bus = InProcessBus(clock=clock)
    rec_node = InProcessTransport(bus, "recorder")
    recorder = Recorder(rec_node, RecorderParams(tmp_path, mode="episode"))
    drv_node = InProcessTransport(bus, "mock_driver")
    driver = MockDriver(drv_node, MockDriverParams())
    tester = InProcessTransport(bus, "tester")
    reset = tester.client(RESET_SERVICE, TRIGGER)

    def run(ticks: int) -> None:
        for _ in range(ticks):
            clock.advance(0.1)
            drv_node.spin_once()
            rec_node.spin_once()

    run(20)
    assert reset.call(reset.Request()).success
    rec_node.spin_once()  # the reset status splits
    clock.advance(2.0)
    run(20)
    driver.close()
    recorder.close()
    assert recorder.bags == [tmp_path / "episode_000", tmp_path / "episode_001"]
    for bag in recorder.bags:
        data = read_bag(bag)
        assert len(data) == 1 and len(data.trajectories[0]) >= 15
    for node in (rec_node, drv_node, tester):
        node.close()
