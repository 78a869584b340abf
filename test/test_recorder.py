"""The recorder node on real rclpy in this process: bytes unchanged, step boundaries, services, episodes, bad input."""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Writer
from std_msgs.msg import String
from std_srvs.srv import Trigger

from msg_adapters import (
    APPLIED_ACTION_TOPIC,
    HAND_TOPICS,
    JOINT_STATES_TOPIC,
    OBJECT_POSE_TOPIC,
    TYPESTORE,
    applied_action_msg,
    joint_state_msg,
    names,
    object_pose_msg,
    rclpy_class,
    stamp_to_ns,
    status_message,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import RECORD_QOS, JazzyWriter, bag_info, read_bag
from t42_transfer.data.errors import BagError
from t42_transfer.nodes.mock_driver import MockDriver
from t42_transfer.nodes.recorder import Recorder, RecorderParams
from t42_transfer.nodes.recorder_params import next_bag_path
from t42_transfer.ros.qos import recording

POSE, JOINTS, ACTION = OBJECT_POSE_TOPIC, JOINT_STATES_TOPIC, APPLIED_ACTION_TOPIC
HAND_STEPS = {t for hand in HAND_TOPICS for t in (hand, "/left" + hand)}


def now_ns() -> int:
    """A stamp near the recorder's ROS time, on a whole control period."""
    return time.time_ns() // CONTROL_PERIOD_NS * CONTROL_PERIOD_NS


class Hand:
    """The test's node: the hand topics (CDR from rosbags, published as bytes), hand/status, the Trigger clients."""

    def __init__(self, ros: Any, recorder: Recorder, ns: str = "", remapped: dict[str, str] | None = None) -> None:
        self.ros, self.recorder = ros, recorder
        self.node: Node = ros.node("hand_tester")
        qos = recording(1000)  # a burst must not overflow the writer's history before the reader acks
        where = {t: (remapped or {}).get(t, ns + t) for t in (*HAND_TOPICS, "/hand/status")}  # where each goes
        self.pubs = {t: self.node.create_publisher(rclpy_class(m), where[t], qos) for t, m in HAND_TOPICS.items()}
        self.status_pub = self.node.create_publisher(String, where["/hand/status"], 10)
        rec_name = recorder.get_fully_qualified_name()
        self.clients = {name: self.node.create_client(Trigger, f"{rec_name}/{name}")
                        for name in ("start", "stop", "split")}
        self.sent: dict[str, list[bytes]] = {t: [] for t in HAND_TOPICS}
        recorded = [self.pubs["/" + t] for t in recorder.params.topics if "/" + t in self.pubs]
        assert ros.spin_until(lambda: all(p.get_subscription_count() for p in recorded)
                              and self.status_pub.get_subscription_count(), 10.0), "the recorder never matched"

    def call(self, name: str) -> Trigger.Response:
        return self.ros.call(self.clients[name], Trigger.Request())

    def publish(self, topic: str, data: bytes, wait: bool = True) -> None:
        """Publish CDR ``data`` on ``topic``; with ``wait``, spin until the recorder handled it."""
        before = self.recorder.received
        self.pubs[topic].publish(data)
        self.sent[topic].append(data)
        if wait:
            assert self.ros.spin_until(lambda: self.recorder.received > before, 10.0), f"{topic} never arrived"

    def status(self, text: str) -> None:
        self.status_pub.publish(String(data=text))
        self.ros.spin_for(0.2)

    def step(self, stamp: int, xy: Any = (1.0, 2.0), loads: Any = (3.0, 4.0), angles: Any = None,
             action: Any = (0.5, -0.5), topics: tuple[str, ...] = (POSE, JOINTS, ACTION)) -> None:
        """Publish the messages of the step stamped ``stamp`` (``action=None``: none) at once, as a driver does.

        Returns once the recorder handled them (in whatever order its queues gave them).
        """
        msgs = {POSE: object_pose_msg(xy, stamp), JOINTS: joint_state_msg(loads, angles, stamp)}
        if action is not None:
            msgs[ACTION] = applied_action_msg(action, stamp)
        sent = [t for t in topics if t in msgs]
        before = self.recorder.received
        for topic in sent:
            self.publish(topic, cdr(topic, msgs[topic]), wait=False)
        assert self.ros.spin_until(lambda: self.recorder.received >= before + len(sent), 10.0), f"{sent} never arrived"

    def episode(self, start_ns: int, steps: int, seed: int = 0, last_state: bool = True) -> dict[str, np.ndarray]:
        """Publish ``steps`` transitions (and the final state if ``last_state``); the arrays read_bag should give."""
        rng = np.random.default_rng(seed)
        # a random walk of a held object (steps of about 1 mm): a jump over 8 mm would be a drop
        xy = (rng.uniform(-20, 20, size=2) + np.cumsum(rng.normal(0.0, 1.0, size=(steps + 1, 2)), axis=0)).astype(
            np.float32)
        loads = rng.uniform(-200, 200, size=(steps + 1, 2)).astype(np.float32)
        angles = rng.uniform(0, 1, size=(steps + 1, 2)).astype(np.float32)
        actions = rng.uniform(-1, 1, size=(steps, 2)).astype(np.float32)
        for k in range(steps + 1 if last_state else steps):
            self.step(start_ns + k * CONTROL_PERIOD_NS, xy[k], loads[k], angles[k], actions[k] if k < steps else None)
        return {"states": np.column_stack([xy, loads]), "actions": actions, "angles": angles}

    def settle(self, timeout_s: float = 10.0) -> None:
        """Spin until no bag change waits for a step (a final state waits ``step_hold_s``)."""
        assert self.ros.spin_until(lambda: self.recorder.waiting_changes == 0, timeout_s), "a bag change never happened"


def cdr(topic: str, msg: Any) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, HAND_TOPICS[topic]))


def add_recorder(ros: Any, out: Path, namespace: str | None = None, **params: Any) -> Recorder:
    kwargs = {"namespace": namespace} if namespace else {}
    return ros.add(Recorder, params={"out_dir": str(out), **params}, **kwargs)


def raw_messages(bag: Path) -> dict[str, list[bytes]]:
    """Payloads per topic in log-time order; checks each connection's type and Jazzy type hash."""
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        got: dict[str, list[bytes]] = {c.topic: [] for c in reader.connections}
        for conn in reader.connections:
            assert conn.digest == TYPESTORE.hash_rihs01(conn.msgtype)
        for conn, _, data in reader.messages():
            got[conn.topic].append(bytes(data))
    return got


def steps_in(bag: Path) -> list[tuple[int, set[str]]]:
    """The bag's (stamp, topics) groups in stamp order."""
    groups: dict[int, set[str]] = {}
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        for conn, _, data in reader.messages(connections=[c for c in reader.connections if c.topic in HAND_STEPS]):
            stamp = stamp_to_ns(TYPESTORE.deserialize_cdr(data, conn.msgtype).header.stamp)
            groups.setdefault(stamp, set()).add(conn.topic.removeprefix("/left"))
    return sorted(groups.items())


def check_episode(traj: Any, expected: dict[str, np.ndarray], start_ns: int) -> None:
    assert traj.start_ns == start_ns
    np.testing.assert_array_equal(traj.states, expected["states"])
    np.testing.assert_array_equal(traj.actions, expected["actions"])
    np.testing.assert_array_equal(traj.actuator_angles, expected["angles"])


# step_hold_s is 1 s where a test waits for a final state: long enough that a loaded machine does not
# split a step the test publishes message by message
WHOLE = {POSE, JOINTS, ACTION}
STATE = {POSE, JOINTS}


# --------------------------------------------------------------------------- recording
def test_a_late_step_is_recorded_with_the_drivers_word_for_it_and_read_as_data(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path / "bags", step_hold_s=1.0)
    hand = Hand(ros, rec)
    t0 = now_ns()
    stamps = [t0 + k * CONTROL_PERIOD_NS + (350_000_000 if k >= 10 else 0) for k in range(21)]  # step 10: 450 ms
    for k, stamp in enumerate(stamps):
        hand.step(stamp, xy=(float(k), 0.0), action=(0.5, -0.5) if k < 20 else None)
        if k == 10:  # as a driver says it: after the step, with the step's stamp
            hand.status(status_message(names.LATE, "450 ms after the step before", stamp))
    hand.status(status_message(names.RESET, "episode 1", None))  # any other word goes in too
    assert ros.spin_until(lambda: rec.current_count == 21 + 21 + 20 + 2, 5.0)
    assert hand.call("stop").success
    (traj,) = read_bag(tmp_path / "bags" / "recording_000")
    assert len(traj) == 20 and traj.late_steps.tolist() == [9] and traj.step_ns[9] == 450_000_000
    assert traj.states[:, 0].tolist() == [float(k) for k in range(21)]


@pytest.mark.parametrize("episode", [1, 2])
def test_a_late_second_step_keeps_its_word_while_the_first_step_waits(ros: Any, tmp_path: Path,
                                                                      episode: int) -> None:
    """In episode mode a bag's first step waits for a status that would split before it (half ``step_hold_s``).
    The driver's ``late`` for the second step can come in that time, while the bag holds no step yet: it must
    still go into the bag with the steps it qualifies, in the first bag and in one a reset split off."""
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=2.0)  # the first step waits 1 s
    hand = Hand(ros, rec)
    start = now_ns()
    if episode == 2:
        hand.episode(start, 5, seed=1, last_state=False)
        start += 5 * CONTROL_PERIOD_NS
        hand.status(status_message(names.RESET, "episode 2 grasped (seed 2)", start - CONTROL_PERIOD_NS))
        assert ros.spin_until(lambda: rec.waiting_changes == 0 and rec.current_count == 0, 5.0)
    stamps = [start, start + 250_000_000, *(start + (2 + k) * CONTROL_PERIOD_NS + 50_000_000 for k in range(1, 17))]
    hand.step(stamps[0], xy=(0.0, 0.0))
    hand.step(stamps[1], xy=(1.0, 0.0))  # 250 ms after the first
    hand.status(status_message(names.LATE, "250.0 ms after the step before", stamps[1]))
    assert rec.current_count == 0  # (the case: the first step still waits, so no step is in the bag yet)
    for k, stamp in enumerate(stamps[2:], start=2):
        hand.step(stamp, xy=(float(k), 0.0), action=(0.5, -0.5) if k < len(stamps) - 1 else None)
    hand.settle()
    rec.close()
    bag = sorted(p for p in tmp_path.iterdir() if p.is_dir())[-1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no episode split for want of the late word
        (traj,) = read_bag(bag)
    assert traj.start_ns == stamps[0] and len(traj) == len(stamps) - 1  # 17 transitions: one episode is 15 or more
    assert traj.late_steps.tolist() == [0] and traj.step_ns[0] == 250_000_000


def _an_episode_with_step_ten_by(ros: Any, tmp_path: Path, step_ten: Any) -> tuple[Recorder, Any]:
    """Record 21 steps (step_hold_s 0.5 s), ``step_ten(hand, recorder, stamp)`` publishing the eleventh; check
    every step went into the bag whole (the last a final state); the recorder and the episode read back."""
    rec = add_recorder(ros, tmp_path / "bags", step_hold_s=0.5)
    hand = Hand(ros, rec)
    t0 = now_ns()
    stamps = [t0 + k * CONTROL_PERIOD_NS for k in range(21)]
    for k, stamp in enumerate(stamps):
        if k == 10:
            step_ten(hand, rec, stamp)
        else:
            hand.step(stamp, xy=(float(k), 0.0), action=(0.5, -0.5) if k < 20 else None)
    assert ros.spin_until(lambda: rec.current_count == 21 + 21 + 20, 5.0), rec.current_count
    assert hand.call("stop").success
    assert steps_in(tmp_path / "bags" / "recording_000") == [(s, WHOLE) for s in stamps[:20]] + [(stamps[20], STATE)]
    (traj,) = read_bag(tmp_path / "bags" / "recording_000")
    assert traj.states[:, 0].tolist() == [float(k) for k in range(21)]
    assert len(traj) == 20 and traj.actions.tolist() == [[0.5, -0.5]] * 20
    return rec, traj


def test_a_driver_stalled_between_the_messages_of_a_step_loses_nothing(ros: Any, tmp_path: Path) -> None:
    """The soak's lost step: a step's pose, then the driver stalls longer than step_hold_s (and half of it with
    nothing heard) before its joint states and action. The step waits for its state, whole, and nothing drops."""

    def stall_after_the_pose(hand: Hand, rec: Recorder, stamp: int) -> None:
        hand.step(stamp, xy=(10.0, 0.0), topics=(POSE,))
        ros.spin_for(1.2)  # the stall: below HOLD_CAP step_hold_s (2 s), past the silence rule's 0.75 s
        hand.step(stamp, xy=(10.0, 0.0), topics=(JOINTS, ACTION))

    rec, _ = _an_episode_with_step_ten_by(ros, tmp_path, stall_after_the_pose)
    assert rec.dropped == 0 and rec.late_kept == 0


def test_an_action_after_its_step_went_out_joins_it_in_the_open_bag(ros: Any, tmp_path: Path) -> None:
    """A stall between a step's state and its action: the state goes out on silence (it could be an episode's
    final state), then the action comes. It joins its step in the bag still open; a duplicate is dropped."""

    def stall_before_the_action(hand: Hand, rec: Recorder, stamp: int) -> None:
        hand.step(stamp, xy=(10.0, 0.0), topics=(POSE, JOINTS))
        assert ros.spin_until(lambda: rec.current_count == 10 * 3 + 2, 3.0), "the state went out on silence"
        hand.step(stamp, xy=(10.0, 0.0), topics=(ACTION,))
        assert rec.late_kept == 1 and rec.dropped == 0
        hand.step(stamp, xy=(10.0, 0.0), topics=(ACTION,))  # the same action again: a duplicate
        assert rec.late_kept == 1 and rec.dropped == 1

    _an_episode_with_step_ten_by(ros, tmp_path, stall_before_the_action)


def test_records_bytes_unchanged_and_read_bag_gives_the_trajectory(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path / "bags", step_hold_s=1.0)
    hand = Hand(ros, rec)
    bag = tmp_path / "bags" / "recording_000"
    assert rec.current_bag == bag
    t0 = now_ns()
    expected = hand.episode(t0, 20)
    assert ros.spin_until(lambda: rec.current_count == 21 + 21 + 20, 5.0)  # the final state after step_hold_s

    reply = hand.call("stop")
    assert reply.success and str(bag) in reply.message and "62 messages" in reply.message
    assert not rec.recording and rec.bags == [bag]
    assert (bag / "metadata.yaml").is_file() and (bag / "recording_000.mcap").is_file()

    assert raw_messages(bag) == hand.sent  # the same bytes, per topic in order
    data = read_bag(bag)
    assert len(data) == 1
    check_episode(data.trajectories[0], expected, t0)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["ros_distro"] == "jazzy"
    assert all(t["topic_metadata"]["offered_qos_profiles"] for t in meta["topics_with_message_count"])
    assert rec.dropped == 0


def test_under_a_namespace_topics_are_recorded_by_their_full_names(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, namespace="/left", step_hold_s=1.0, topics=["hand/object_pose",
                                                                                  "hand/joint_states",
                                                                                  "hand/applied_action"])
    hand = Hand(ros, rec, ns="/left")
    assert hand.clients["stop"].srv_name == "/left/recorder/stop"
    t0 = now_ns()
    expected = hand.episode(t0, 16)
    hand.call("stop")
    hand.settle()
    bag = rec.bags[0]
    assert set(raw_messages(bag)) == {"/left" + t for t in HAND_TOPICS}
    check_episode(read_bag(bag).trajectories[0], expected, t0)


def test_remapped_hand_topics_are_recorded_under_their_new_names_and_read_back(ros: Any, tmp_path: Path) -> None:
    """``-r hand/object_pose:=pose`` (as on driver, recorder and explorer alike): the bag holds /pose, and read_bag
    finds the episode through the names the recorder wrote down (by name alone it found no object pose)."""
    rec = ros.add(Recorder, params={"out_dir": str(tmp_path), "step_hold_s": 1.0},
                  cli_args=["--ros-args", "-r", "hand/object_pose:=pose", "-r", "hand/status:=events/hand"])
    hand = Hand(ros, rec, remapped={POSE: "/pose", "/hand/status": "/events/hand"})
    t0 = now_ns()
    expected = hand.episode(t0, 16)
    hand.call("stop")
    hand.settle()
    bag = rec.bags[0]
    assert set(raw_messages(bag)) == {"/pose", JOINTS, ACTION}
    check_episode(read_bag(bag).trajectories[0], expected, t0)
    assert bag_info(bag)["hand_topics"] == {POSE: "/pose", JOINTS: JOINTS, ACTION: ACTION,
                                            "/hand/status": "/events/hand"}


def test_a_bag_of_two_namespaces_is_refused(tmp_path: Path) -> None:
    bag = tmp_path / "two"
    with Writer(bag, version=9) as writer:
        for ns in ("/left", "/right"):
            for topic, msgtype in HAND_TOPICS.items():
                conn = writer.add_connection(ns + topic, msgtype, typestore=TYPESTORE,
                                             offered_qos_profiles=[RECORD_QOS])
                writer.write(conn, 1, cdr(topic, joint_state_msg((1.0, 2.0), None, 1)) if topic != POSE
                             else cdr(topic, object_pose_msg((1.0, 2.0), 1)))
    with pytest.raises(BagError, match=r"2 namespaces: /left \(.*\); /right"):
        read_bag(bag)


def test_only_the_chosen_topics_are_recorded(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, topics=["hand/object_pose"])
    hand = Hand(ros, rec)
    t0 = now_ns()
    hand.step(t0, topics=(POSE,))  # a pose alone is a whole step here
    assert rec.current_count == 1
    rec.close()
    assert list(raw_messages(rec.bags[0])) == [POSE]


# --------------------------------------------------------------------------- step boundaries
def test_bags_begin_and_end_at_step_boundaries(ros: Any, tmp_path: Path) -> None:
    """Start, split and stop requested mid-step: every bag holds whole steps only."""
    rec = add_recorder(ros, tmp_path, start_immediately=False, step_hold_s=30.0)
    hand = Hand(ros, rec)
    t = [now_ns() + k * CONTROL_PERIOD_NS for k in range(10)]

    hand.step(t[0], topics=(JOINTS, ACTION))  # not recording: this step is not recorded
    hand.step(t[1], topics=(POSE, JOINTS))  # the state of step 1, then start, then its action
    reply = hand.call("start")
    assert reply.success and "after the step in progress" in reply.message and not rec.recording
    hand.step(t[1], topics=(ACTION,))  # step 1 is complete (unrecorded, whole): the bag opens
    bag0 = rec.current_bag
    assert bag0 is not None and rec.current_count == 0 and rec.waiting_changes == 0
    hand.step(t[2], topics=(ACTION, POSE))  # an action may arrive before its state
    assert rec.current_count == 0
    hand.step(t[2], topics=(JOINTS,))
    assert rec.current_count == 3  # the bag begins with a whole step, not an orphan action

    hand.step(t[3], topics=(POSE, JOINTS))
    reply = hand.call("split")  # mid-step: after step 3
    assert reply.success and "after the step in progress" in reply.message
    assert rec.current_bag == bag0 and rec.waiting_changes == 1
    hand.step(t[3], topics=(ACTION,))  # step 3 completes in bag 0, then the bag changes
    assert rec.waiting_changes == 0 and rec.bags == [bag0]
    bag1 = rec.current_bag
    hand.step(t[4])
    hand.step(t[5], topics=(POSE,))
    reply = hand.call("stop")
    assert reply.success and rec.current_bag == bag1
    assert not hand.call("stop").success  # a stop already waits
    hand.step(t[5], topics=(ACTION, JOINTS))  # step 5 completes: bag 1 closes
    assert not rec.recording and rec.bags == [bag0, bag1]
    hand.step(t[6])  # not recording

    assert hand.call("start").success
    hand.step(t[7], topics=(ACTION,))  # an action whose state was lost ...
    rec.set_parameters([Parameter("step_hold_s", value=0.5)])
    dropped = rec.dropped
    assert ros.spin_until(lambda: rec.dropped == dropped + 1, 5.0)  # ... cannot begin a bag
    hand.step(t[8])
    hand.step(t[8], topics=(JOINTS,))  # a duplicate: its step was written
    assert rec.dropped == dropped + 2
    hand.step(t[9], action=None)  # a final state: written once step_hold_s passed
    assert ros.spin_until(lambda: rec.current_count == 5, 5.0)
    rec.close()
    bag2 = rec.bags[-1]

    assert steps_in(bag0) == [(t[2], WHOLE), (t[3], WHOLE)]
    assert steps_in(bag1) == [(t[4], WHOLE), (t[5], WHOLE)]
    assert steps_in(bag2) == [(t[8], WHOLE), (t[9], STATE)]


def test_services_start_stop_split_make_the_expected_bags(ros: Any, tmp_path: Path) -> None:
    out = tmp_path / "out"
    rec = add_recorder(ros, out, start_immediately=False, prefix="run", step_hold_s=1.0)
    hand = Hand(ros, rec)
    assert not rec.recording and not out.joinpath("run_000").exists()
    assert not hand.call("stop").success
    assert not hand.call("split").success

    reply = hand.call("start")
    assert reply.success and str(out / "run_000") in reply.message
    assert not hand.call("start").success  # already recording
    t0 = now_ns()
    hand.episode(t0, 3)
    assert hand.call("split").success
    hand.settle()  # the final state of the episode is written after step_hold_s, then the split happens
    assert rec.bags == [out / "run_000"] and rec.current_bag == out / "run_001"
    hand.episode(t0 + 10 * 10**9, 3)
    assert hand.call("split").success
    hand.settle()
    assert hand.call("stop").success
    assert not hand.call("stop").success
    hand.episode(t0 + 20 * 10**9, 3)  # not recording: nothing written
    reply = hand.call("start")  # after the step in progress: the final state, which waits step_hold_s
    assert reply.success
    rec.close()  # a start still waiting opens no bag: it would close it empty at once
    waited = "after the step in progress" in reply.message  # (else the start was carried out: a loaded machine)

    names = sorted(p.name for p in out.iterdir())
    assert names == ["run_000", "run_001", "run_002"] + ([] if waited else ["run_003"])
    assert rec.bags == [out / n for n in names]
    assert all((out / n / "metadata.yaml").is_file() for n in names)
    counts = [sum(len(v) for v in raw_messages(out / n).values()) for n in names]
    assert counts == [11, 11, 0] + ([] if waited else [0])


def test_bags_are_never_overwritten(ros: Any, tmp_path: Path) -> None:
    (tmp_path / "rec_004").mkdir()
    (tmp_path / "other_009").mkdir()
    (tmp_path / "rec_x").mkdir()
    assert next_bag_path(tmp_path, "rec") == tmp_path / "rec_005"
    assert next_bag_path(tmp_path / "missing", "rec") == tmp_path / "missing" / "rec_000"
    rec = add_recorder(ros, tmp_path, prefix="rec")
    assert rec.current_bag == tmp_path / "rec_005"
    rec.close()
    assert (tmp_path / "rec_004").exists() and not any((tmp_path / "rec_004").iterdir())


# --------------------------------------------------------------------------- episodes
def test_episode_mode_splits_on_status(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0)
    hand = Hand(ros, rec)
    hand.status("reset: episode 0 grasped (seed 0)")  # empty bag: no split
    assert rec.current_bag == tmp_path / "episode_000"
    t0 = now_ns()
    first = hand.episode(t0, 16, seed=1)
    hand.status("hello world")  # other words do not split
    hand.status("reset_failed: grasp failed")
    assert rec.current_bag == tmp_path / "episode_000" and rec.waiting_changes == 0
    hand.status("dropped: episode 0 ended after 16 steps")
    hand.status("reset: episode 1 grasped (seed 1)")  # right after the end: one split
    hand.settle()
    assert rec.bags == [tmp_path / "episode_000"] and rec.current_bag == tmp_path / "episode_001"

    start = max(now_ns(), t0 + 16 * CONTROL_PERIOD_NS) + 2 * 10**9
    second = hand.episode(start, 18, seed=2, last_state=False)
    # the end status published together with the final state: the state stays in episode_001
    final = start + 18 * CONTROL_PERIOD_NS
    hand.publish(POSE, cdr(POSE, object_pose_msg(second["states"][-1, :2], final)), wait=False)
    hand.publish(JOINTS, cdr(JOINTS, joint_state_msg(second["states"][-1, 2:], second["angles"][-1], final)),
                 wait=False)
    hand.status("overload: episode 1 ended")
    hand.settle()
    assert rec.bags[-1] == tmp_path / "episode_001" and rec.current_bag == tmp_path / "episode_002"
    third_start = max(now_ns(), final) + 2 * 10**9
    third = hand.episode(third_start, 15, seed=3)
    hand.status("reset: episode 3 grasped (seed 3)")  # a reset alone also splits
    hand.settle()
    hand.episode(third_start + 10 * 10**9, 15, seed=4)
    rec.close()

    assert sorted(p.name for p in tmp_path.iterdir()) == [f"episode_00{i}" for i in range(4)]
    for name, expected, t in (("episode_000", first, t0), ("episode_001", second, start),
                              ("episode_002", third, third_start)):
        data = read_bag(tmp_path / name)
        assert len(data) == 1
        check_episode(data.trajectories[0], expected, t)


def test_a_status_naming_its_last_step_splits_there_even_when_it_arrives_late(ros: Any, tmp_path: Path) -> None:
    """Topics are not ordered against each other: the driver's reset status may reach the recorder after
    the new episode's first steps. Its ``[last step ...]`` puts the border where it belongs, and two
    resets in quick succession (short episodes) make two borders, not one."""
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=2.0)  # steps wait 1 s for a late status
    hand = Hand(ros, rec)
    t0 = now_ns()
    first = hand.episode(t0, 16, seed=1, last_state=False)
    second_start = t0 + 16 * CONTROL_PERIOD_NS
    second = hand.episode(second_start, 16, seed=2, last_state=False)
    third_start = second_start + 16 * CONTROL_PERIOD_NS
    hand.step(third_start, angles=(0.5, 0.5))  # the third episode began ...
    hand.status(status_message("reset", "episode 1 grasped (seed 1)", second_start - CONTROL_PERIOD_NS))
    hand.status(status_message("reset", "episode 2 grasped (seed 2)", third_start - CONTROL_PERIOD_NS))  # ... late
    hand.status(status_message("reset", "episode 2 grasped (seed 2)", third_start - CONTROL_PERIOD_NS))  # same border
    hand.episode(third_start + CONTROL_PERIOD_NS, 15, seed=3)
    hand.settle()
    rec.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_000", "episode_001", "episode_002"]
    for name, expected, start in (("episode_000", first, t0), ("episode_001", second, second_start)):
        data = read_bag(tmp_path / name)
        assert len(data) == 1
        traj = data.trajectories[0]  # last_state=False: each ends with its last action's state missing
        assert traj.start_ns == start
        np.testing.assert_array_equal(traj.states, expected["states"][:-1])
        np.testing.assert_array_equal(traj.actions, expected["actions"][:-1])
    assert steps_in(tmp_path / "episode_002")[0][0] == third_start  # the early step moved to its episode
    assert len(read_bag(tmp_path / "episode_002")) == 1


def test_recording_mode_ignores_status(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path)
    hand = Hand(ros, rec)
    hand.episode(now_ns(), 2, last_state=False)
    hand.status("dropped")
    assert rec.current_bag == tmp_path / "recording_000" and rec.waiting_changes == 0


def test_records_the_mock_driver_one_bag_per_episode(ros: Any, tmp_path: Path) -> None:
    """The driver (sim time, 10x) and the recorder: a reset between episodes splits exactly between them."""
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0)
    driver = ros.add(MockDriver, params={"rate_factor": 10.0, "sim_time": True})
    tester = ros.node("reset_client")
    reset = tester.create_client(Trigger, "/hand/reset")
    assert ros.spin_until(lambda: rec.current_count >= 60, 20.0)
    assert ros.call(reset, Trigger.Request()).success
    assert ros.spin_until(lambda: len(rec.bags) == 1 and rec.current_count >= 60, 20.0)
    driver.close()
    rec.close()
    assert rec.bags == [tmp_path / "episode_000", tmp_path / "episode_001"]
    for bag in rec.bags:
        data = read_bag(bag)
        assert len(data) == 1 and len(data.trajectories[0]) >= 19
        assert steps_in(bag)[0][1] == WHOLE


# --------------------------------------------------------------------------- bad input, params, flushing
def test_bad_messages_never_crash_the_recorder(ros: Any, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0)
    hand = Hand(ros, rec)
    # bytes of another type, and no CDR at all, on hand topics and on the status topic
    hand.publish(JOINTS, bytes(TYPESTORE.serialize_cdr(TYPESTORE.types["std_msgs/msg/String"](data="hi"),
                                                       "std_msgs/msg/String")))
    hand.publish(POSE, b"\x00\x01\x00\x00garbage")
    hand.publish(ACTION, b"\x00\x01")
    hand.status_pub.publish(b"\x00\x01")
    ros.spin_for(0.3)
    assert rec.dropped == 3 and rec.current_count == 0
    err = capfd.readouterr().err
    assert JOINTS in err and POSE in err and "hand/status" in err
    assert "not a sensor_msgs/msg/JointState" in err
    t0 = now_ns()
    expected = hand.episode(t0, 15)  # still recording
    rec.close()
    check_episode(read_bag(tmp_path / "episode_000").trajectories[0], expected, t0)


def test_write_failure_is_logged_not_raised(ros: Any, tmp_path: Path, capfd: pytest.CaptureFixture[str],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    rec = add_recorder(ros, tmp_path)
    hand = Hand(ros, rec)
    assert rec.recording

    def broken(*args: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(JazzyWriter, "write", broken)  # the storage layer: rosbags' writer
    hand.step(now_ns())
    assert rec.dropped == 3 and "disk full" in capfd.readouterr().err


def test_params_are_checked(ros: Any, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"):
        RecorderParams(tmp_path, mode="bogus")
    with pytest.raises(ValueError, match="prefix"):
        RecorderParams(tmp_path, prefix="../up")
    with pytest.raises(ValueError, match="topics must name"):
        RecorderParams(tmp_path, topics=())
    with pytest.raises(ValueError, match="not recordable"):
        RecorderParams(tmp_path, topics=("/hand/object_pose",))  # relative names only
    with pytest.raises(ValueError, match="repeat"):
        RecorderParams(tmp_path, topics=("hand/object_pose", "hand/object_pose"))
    with pytest.raises(ValueError, match="flush_period_s"):
        RecorderParams(tmp_path, flush_period_s=0)
    with pytest.raises(ValueError, match="queue_depth"):
        RecorderParams(tmp_path, queue_depth=0)
    assert RecorderParams(tmp_path).bag_prefix == "recording"

    with pytest.raises(ValueError, match="missing required parameter 'out_dir'"):
        ros.add(Recorder)
    with pytest.raises(ValueError, match="mode must be one of"):
        add_recorder(ros, tmp_path, mode="sometimes")
    with pytest.raises(ValueError, match="out_dir"):
        (tmp_path / "file").write_text("")
        add_recorder(ros, tmp_path / "file" / "bags")
    rec = add_recorder(ros, tmp_path)
    refused = rec.set_parameters([Parameter("mode", value="bogus")])[0]
    assert not refused.successful and "mode must be one of" in refused.reason
    assert not rec.set_parameters([Parameter("out_dir", value="/elsewhere")])[0].successful  # read-only
    assert rec.set_parameters([Parameter("mode", value="episode")])[0].successful
    assert rec.params.mode == "episode"


def test_the_open_chunk_reaches_the_file_every_flush_period(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, flush_period_s=30.0)
    hand = Hand(ros, rec)
    bag = rec.current_bag
    assert bag is not None
    mcap = bag / f"{bag.name}.mcap"
    t0 = now_ns()
    for k in range(3):
        hand.step(t0 + k * CONTROL_PERIOD_NS)
    ros.spin_for(0.3)
    before = mcap.stat().st_size
    assert before < 100  # only the MCAP header: the chunk is in memory
    rec.set_parameters([Parameter("flush_period_s", value=0.1)])  # takes effect at run time
    assert ros.spin_until(lambda: mcap.stat().st_size > before + 300, 5.0)
    for sub in rec.subscriptions:
        if sub.topic_name in ("/" + t for t in ("hand/object_pose", "hand/joint_states", "hand/applied_action")):
            assert sub.qos_profile.depth == 1000  # a deep RELIABLE queue, not ROS's default 10


def test_two_recorders_in_two_namespaces_with_one_relative_out_dir_keep_apart(ros, tmp_path, monkeypatch):
    """Two suites from one working directory: recordings/left and recordings/right, never one shared folder."""
    from t42_transfer.nodes.recorder import Recorder

    monkeypatch.chdir(tmp_path)
    left = ros.add(Recorder, {"out_dir": "recordings", "mode": "recording"}, namespace="/left")
    right = ros.add(Recorder, {"out_dir": "recordings", "mode": "recording"}, namespace="/right")
    assert (left.out_dir, right.out_dir) == (tmp_path / "recordings/left", tmp_path / "recordings/right")
    ok, said = left.stop()  # a bag announced by its absolute path: a listener elsewhere finds it
    assert ok and str(tmp_path / "recordings/left/recording_000") in said, said
    assert sorted(p.name for p in (tmp_path / "recordings").iterdir()) == [  # each folder claimed by its suite
        ".left.t42_namespace", ".right.t42_namespace", "left", "right"]
    left.close()
    right.close()


@pytest.fixture
def small_disk(tmp_path: Path):
    """A 512 KiB file system of its own (tmpfs); skipped where mounting is not allowed."""
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({done.stderr.strip() or done.returncode}): the disk-full "
                    "case needs a file system that fills up")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def _fill(directory: Path) -> Path:
    filler = directory / "filler"
    with filler.open("wb", buffering=0) as out:  # unbuffered: nothing left to flush when it closes
        try:
            while True:
                out.write(b"\0" * 4096)
        except OSError:
            pass
    return filler


def test_a_full_disk_is_reported_once_and_recording_resumes_when_space_returns(ros, small_disk):
    from diagnostic_msgs.msg import DiagnosticArray
    from ros_rig import Rosout

    from msg_adapters import names, status_report
    from t42_transfer.data.bag import read_bag
    from t42_transfer.nodes.recorder import STATUS_NAME

    rec = add_recorder(ros, small_disk / "bags", mode="recording", resume_free_mb=0.2, flush_period_s=0.2)
    hand = Hand(ros, rec)
    log = Rosout(ros, rec.get_name())
    reports: list = []
    hand.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, reports.append, 100)
    t0 = now_ns()
    hand.episode(t0, 20)
    hand.settle()
    assert hand.call("split").success
    hand.settle()
    first = rec.bags[0]
    filler = _fill(small_disk)
    hand.episode(t0 + 40 * CONTROL_PERIOD_NS, 150, seed=1)  # far more than the disk holds
    def level_reports(level: str) -> int:
        return sum(status_report(r, STATUS_NAME).level == level for r in reports)

    assert ros.spin_until(lambda: level_reports("ERROR"), 5.0)
    said = level_reports("ERROR")  # and said again each second while it lasts, for a monitor that joins late
    assert ros.spin_until(lambda: level_reports("ERROR") > said, 2.5)
    errors = [m for m in log.lines if m.level >= 40 and m.name.endswith(rec.get_name())]
    assert 1 <= len(errors) <= 3, [m.msg for m in errors]  # said once, not once per message
    split = hand.call("split")
    assert not split.success and "failed" in split.message
    assert len(read_bag(first)[0]) == 20  # what was written before the disk filled is intact
    oks = level_reports("OK")  # none comes while writing fails: a new one says it resumed
    filler.unlink()
    assert ros.spin_until(lambda: level_reports("OK") > oks, 5.0)
    hand.episode(t0 + 300 * CONTROL_PERIOD_NS, 20, seed=2)
    hand.settle()
    assert hand.call("stop").success
    hand.settle()
    assert len(read_bag(rec.bags[-1])[0]) == 20  # a new bag records once there is room
    rec.close()


def _error_reports(hand: Hand) -> list[str]:
    """The recorder's ERROR messages on diagnostics, as they come."""
    from diagnostic_msgs.msg import DiagnosticArray

    from msg_adapters import status_report
    from t42_transfer.nodes.recorder import STATUS_NAME

    errors: list[str] = []

    def on_report(msg: DiagnosticArray) -> None:
        report = status_report(msg, STATUS_NAME)
        if report is not None and report.level == "ERROR":
            errors.append(report.message)

    hand.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, on_report, 100)
    return errors


def test_out_dir_removed_while_recording_is_a_reported_write_failure_and_a_new_bag_records(ros, tmp_path):
    """``rm -rf out_dir`` under a recorder: the bag being written is lost. A split that cannot close it, and the
    next flush, which finds its file gone, say so (ERROR on diagnostics), and a new bag records at once."""
    import shutil

    out = tmp_path / "bags"
    rec = add_recorder(ros, out, step_hold_s=1.0, flush_period_s=30.0)
    hand = Hand(ros, rec)
    errors = _error_reports(hand)
    t0 = now_ns()
    hand.episode(t0, 3, last_state=False)
    shutil.rmtree(out)  # before a flush noticed: the split's close fails
    reply = hand.call("split")
    assert not reply.success and "closing" in reply.message and "failed" in reply.message
    assert ros.spin_until(lambda: any("closing" in e for e in errors), 5.0), errors
    assert rec.current_bag == out / "recording_000" and rec.bags == []  # a new bag, out_dir made again

    hand.episode(t0 + 10 * CONTROL_PERIOD_NS, 3, last_state=False)
    shutil.rmtree(out)  # now the flush finds the file gone
    rec.set_parameters([Parameter("flush_period_s", value=0.1)])
    assert ros.spin_until(lambda: any("was removed" in e for e in errors), 5.0), errors
    assert ros.spin_until(lambda: rec.recording and out.is_dir(), 5.0)
    assert rec.write_failure is None
    start = t0 + 20 * CONTROL_PERIOD_NS
    expected = hand.episode(start, 16)
    assert hand.call("stop").success
    hand.settle()  # the final state is written after step_hold_s, then the bag closes
    assert rec.bags == [out / "recording_000"]
    check_episode(read_bag(rec.bags[0]).trajectories[0], expected, start)


def test_a_bag_name_another_writer_took_is_passed_over_and_a_bag_that_does_not_open_is_a_write_failure(
        ros, tmp_path, monkeypatch):
    """Two recorders on one out_dir race for the next name (rosbags raises WriterError, no OSError, for a path
    that exists): the loser takes the next name and goes on recording. Any other failure to open a bag is a
    write failure, which ~/start ends."""
    import t42_transfer.data.bag.recording as recording
    import t42_transfer.nodes.recorder_bags as recorder_bags

    real_name, real_writer, race = recorder_bags.next_bag_path, recording.BagWriter, [False]

    def taken_first(out_dir, prefix):  # the other writer makes the directory between the choice and the open
        path = real_name(out_dir, prefix)
        if race[0]:
            race[0] = False
            path.mkdir()
        return path

    def broken(*args, **kwargs):
        raise RuntimeError("the storage plugin fails")

    monkeypatch.setattr(recorder_bags, "next_bag_path", taken_first)
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0, resume_free_mb=1e6)  # no resume on room
    hand = Hand(ros, rec)
    t0 = now_ns()
    hand.episode(t0, 3, last_state=False)
    race[0] = True
    hand.status(status_message("reset", "episode 1", t0 + 2 * CONTROL_PERIOD_NS))
    hand.settle()
    assert rec.current_bag == tmp_path / "episode_002" and rec.write_failure is None

    monkeypatch.setattr(recording, "BagWriter", broken)
    hand.episode(t0 + 3 * CONTROL_PERIOD_NS, 3, last_state=False)
    assert hand.call("split").success
    hand.settle()  # after the step in progress: the bag closes, the next does not open
    assert not rec.recording and "storage plugin fails" in (rec.write_failure or "")
    monkeypatch.setattr(recording, "BagWriter", real_writer)
    reply = hand.call("start")
    assert reply.success and rec.current_bag == tmp_path / "episode_003", reply.message
    start = t0 + 10 * CONTROL_PERIOD_NS
    expected = hand.episode(start, 16)
    rec.close()
    assert rec.bags[-1] == tmp_path / "episode_003"
    check_episode(read_bag(rec.bags[-1]).trajectories[0], expected, start)
