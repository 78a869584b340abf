"""The recorder's bag events (recorder/bag_closed) and its pause and resume services, on real rclpy in-process."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_srvs.srv import Trigger
from t42_interfaces.msg import BagClosed
from test_recorder import ACTION, JOINTS, POSE, Hand, add_recorder, now_ns, raw_messages, steps_in

from msg_adapters import names, status_message
from msg_adapters.events import SHUTDOWN, BagClosedEvent, bag_closed_event, bag_closed_msg
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import read_bag
from t42_transfer.ros.qos import profile


class Events:
    """The test's listener on recorder/bag_closed: each event, and what read_bag made of its bag when it arrived."""

    def __init__(self, hand: Hand, qos: Any = None) -> None:
        self.got: list[BagClosedEvent] = []
        self.read_then: list[int | str] = []
        hand.node.create_subscription(BagClosed, names.BAG_CLOSED, self._on_event,
                                      qos or profile(names.EVENT_READER))

    def _on_event(self, msg: BagClosed) -> None:
        event = bag_closed_event(msg)
        self.got.append(event)
        try:  # at the moment the event arrives
            self.read_then.append(len(read_bag(event.path)))
        except Exception as err:
            self.read_then.append(f"{type(err).__name__}: {err}")

    def wait(self, count: int, ros: Any, timeout_s: float = 10.0) -> list[BagClosedEvent]:
        assert ros.spin_until(lambda: len(self.got) >= count, timeout_s), self.got
        ros.spin_for(0.2)
        assert len(self.got) == count, self.got  # one event per bag
        return self.got


def metadata_span(bag: Path) -> tuple[int, int, int]:
    """(messages, first log time, last log time) as the bag's metadata.yaml says."""
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    start = info["starting_time"]["nanoseconds_since_epoch"]
    return info["message_count"], start, start + info["duration"]["nanoseconds"]


def check(event: BagClosedEvent, bag: Path, reason: str, steps: int, episodes: int) -> None:
    """``steps``: the hand messages in the bag (statuses come on top)."""
    per_topic = raw_messages(bag)
    status = len(per_topic.pop("/" + names.HAND_STATUS, []))
    assert sum(len(v) for v in per_topic.values()) == steps
    messages = steps + status
    assert (event.path, event.reason, event.messages, event.episodes) == (str(bag), reason, messages, episodes)
    if messages:
        assert metadata_span(bag) == (messages, event.start_ns, event.end_ns)
    else:
        assert event.start_ns == event.end_ns == 0


def test_start_split_stop_and_shutdown_each_announce_their_bag_readable(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, start_immediately=False, prefix="run", step_hold_s=1.0)
    hand = Hand(ros, rec)
    events = Events(hand)
    assert hand.call("start").success
    t0 = now_ns()
    hand.episode(t0, 15)  # MIN_EPISODE_STEPS transitions: 16 states, 15 actions
    assert hand.call("split").success
    hand.settle()
    check(events.wait(1, ros)[0], tmp_path / "run_000", "split", 47, 1)
    hand.episode(t0 + 10 * 10**9, 15)
    hand.episode(t0 + 20 * 10**9, 16)  # a second episode in the same bag
    assert ros.spin_until(lambda: rec.current_count == 47 + 50, 5.0)
    assert hand.call("stop").success
    check(events.wait(2, ros)[1], tmp_path / "run_001", "stop", 97, 2)
    assert hand.call("start").success
    rec.close()  # the node shuts down: its open (empty) bag is closed and announced before close returns
    check(events.wait(3, ros)[2], tmp_path / "run_002", SHUTDOWN, 0, 0)
    assert events.read_then[:2] == [1, 2]  # read_bag read each bag when its event arrived
    # a late joiner gets the recent events (latched, as hand/status)
    late = Events(hand, QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    assert [e.path for e in late.wait(3, ros)] == [str(tmp_path / f"run_00{i}") for i in range(3)]


def test_an_episode_mode_split_announces_the_bag_with_the_status_word(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0)
    hand = Hand(ros, rec)
    events = Events(hand)
    t0 = now_ns()
    hand.episode(t0, 16, seed=1)
    hand.status(status_message(names.DROPPED, "episode 0 ended", t0 + 16 * CONTROL_PERIOD_NS))
    hand.status(status_message(names.RESET, "episode 1 grasped", t0 + 16 * CONTROL_PERIOD_NS))  # same border
    hand.settle()
    start = t0 + 10 * 10**9
    hand.episode(start, 16, seed=2)
    hand.status(status_message(names.RESET, "episode 2 grasped", start + 16 * CONTROL_PERIOD_NS))
    hand.settle()
    got = events.wait(2, ros)
    # both statuses came before a step was written (each waits 0.5 s for a status): they went in after it, and the
    # reader leaves out the fall to the last state, as the drop says (15 transitions left: one episode)
    assert len(raw_messages(tmp_path / "episode_000")["/" + names.HAND_STATUS]) == 2
    check(got[0], tmp_path / "episode_000", names.DROPPED, 50, 1)
    check(got[1], tmp_path / "episode_001", names.RESET, 50, 1)
    assert events.read_then == [1, 1]


def test_pause_drops_steps_keeps_the_bag_and_resume_continues_in_it(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, start_immediately=False, step_hold_s=1.0)
    hand = Hand(ros, rec)
    events = Events(hand)
    client = {n: hand.node.create_client(Trigger, names.private_of("recorder", getattr(names, f"RECORDER_{n}")))
              for n in ("PAUSE", "RESUME")}

    def call(name: str) -> Trigger.Response:
        return ros.call(client[name], Trigger.Request())

    refused = call("PAUSE")
    assert not refused.success and "not recording" in refused.message
    assert hand.call("start").success
    assert (not (r := call("RESUME")).success) and r.message == "not paused"
    t0 = now_ns()
    for k in range(16):
        hand.step(t0 + k * CONTROL_PERIOD_NS)
    hand.step(t0 + 16 * CONTROL_PERIOD_NS, topics=(POSE, JOINTS))  # the step in progress ...
    paused = call("PAUSE")
    assert paused.success and f"after the step stamped {t0 + 16 * CONTROL_PERIOD_NS} ns" in paused.message
    again = call("PAUSE")
    assert not again.success and "already paused" in again.message
    hand.step(t0 + 16 * CONTROL_PERIOD_NS, topics=(ACTION,))  # ... is recorded whole
    for k in range(17, 22):  # dropped
        hand.step(t0 + k * CONTROL_PERIOD_NS)
    hand.status("hello: dropped too")
    assert rec.paused_dropped == 16 and rec.recording and not events.got
    resumed = call("RESUME")
    assert resumed.success and "16 messages dropped" in resumed.message and str(rec.current_bag) in resumed.message
    start = t0 + 3 * 10**9  # over 1 s after the last step recorded: a second episode to a reader
    expected = hand.episode(start, 15)
    assert ros.spin_until(lambda: rec.current_count == 51 + 47, 5.0)
    hand.step(t0 + 21 * CONTROL_PERIOD_NS)  # late, in the paused window: dropped
    assert rec.paused_dropped == 19
    assert call("PAUSE").success  # stop ends a pause
    assert hand.call("stop").success and not rec.paused
    bag = tmp_path / "recording_000"
    assert rec.bags == [bag] and [e.path for e in events.wait(1, ros)] == [str(bag)]
    stamps = [s for s, _ in steps_in(bag)]
    assert stamps == [t0 + k * CONTROL_PERIOD_NS for k in range(17)] + [start + k * CONTROL_PERIOD_NS
                                                                        for k in range(16)]
    data = read_bag(bag)
    assert [len(t) for t in data] == [16, 15] and (data.trajectories[1].actions == expected["actions"]).all()


def test_bag_closed_messages_carry_the_event_both_ways_and_refuse_bad_values() -> None:
    event = BagClosedEvent("/bags/episode_003", 2, 97, 1_700_000_000_123_456_789, 1_700_000_004_000_000_001, "reset")
    msg = bag_closed_msg(event)
    assert isinstance(msg, BagClosed) and (msg.start.sec, msg.start.nanosec) == (1_700_000_000, 123_456_789)
    assert bag_closed_event(msg) == event
    with pytest.raises(ValueError, match="non-negative"):
        bag_closed_msg(event._replace(messages=-1))
    with pytest.raises(ValueError, match="range"):
        bag_closed_msg(event._replace(end_ns=-5))


def test_what_the_reader_says_of_a_closed_bag_goes_to_rosout(ros: Any, tmp_path: Path,
                                                             recwarn: pytest.WarningsRecorder) -> None:
    """A bag of one short episode is announced with 0 episodes; why is on /rosout (info), not a warning printed
    by the recorder's process outside its log."""
    from ros_rig import Rosout

    log = Rosout(ros, "recorder")
    rec = add_recorder(ros, tmp_path, start_immediately=False, step_hold_s=1.0)
    hand = Hand(ros, rec)
    events = Events(hand)
    assert hand.call("start").success
    hand.episode(now_ns(), 5)  # fewer transitions than MIN_EPISODE_STEPS
    assert hand.call("stop").success
    assert events.wait(1, ros)[0].episodes == 0

    def said() -> list[str]:
        return [m.msg for m in log.lines if m.name.endswith("recorder") and m.msg.startswith("read back: ")]

    assert ros.spin_until(lambda: said(), 3.0), [m.msg for m in log.lines]
    assert "fewer than MIN_EPISODE_STEPS" in said()[0]
    # (the test's own listener reads the bag too, and warns here: only the recorder's reading must not)
    assert not [w for w in recwarn if w.filename.endswith("recorder_params.py")], [str(w) for w in recwarn]


def test_a_status_split_is_one_line_on_rosout(ros: Any, tmp_path: Path) -> None:
    """The bag closed and the next opened, with the status that caused it, once (each half was said again)."""
    from ros_rig import Rosout

    log = Rosout(ros, "recorder")
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=1.0)
    hand = Hand(ros, rec)
    t0 = now_ns()
    hand.episode(t0, 15, seed=1)
    hand.status(status_message(names.RESET, "episode 1 grasped", t0 + 15 * CONTROL_PERIOD_NS))
    hand.settle()

    def closing() -> list[str]:
        return [m.msg for m in log.lines if m.name.endswith("recorder") and "closed " in m.msg]

    assert ros.spin_until(lambda: closing(), 3.0), [m.msg for m in log.lines]
    ros.spin_for(0.3)
    (line,) = closing()
    assert line.startswith("status 'reset': closed ") and "; recording to " in line, line


def test_a_clock_restart_splits_the_bag_so_both_bags_read(ros: Any, tmp_path: Path) -> None:
    """The graph's clock (a sim-time driver) restarts behind its old time, as when ``t42 up`` respawns the driver,
    and the new driver's first step arrives before its first /clock: it is received at the old, later time. The
    bag is split before it and its messages are logged at their stamp, so read_bag reads both bags (one bag kept
    across the jump read as none); a pause after the restart draws its border on the new clock."""
    from rosgraph_msgs.msg import Clock

    from msg_adapters import RCLPY, ns_to_stamp
    from t42_transfer.data.bag.recording import CLOCK_RESTART

    rec = add_recorder(ros, tmp_path, use_sim_time=True, step_hold_s=1.0)
    hand = Hand(ros, rec)
    events = Events(hand)
    clock = hand.node.create_publisher(Clock, "/clock", 10)

    def tick(ns: int) -> None:
        clock.publish(Clock(clock=ns_to_stamp(ns, RCLPY)))
        assert ros.spin_until(lambda: rec.get_clock().now().nanoseconds == ns, 5.0), "/clock not heard"

    old, new = now_ns() + 60 * 10**9, now_ns()  # the old driver's clock ran ahead; the new one starts at the wall's
    for k in range(16):
        tick(old + k * CONTROL_PERIOD_NS)
        hand.step(old + k * CONTROL_PERIOD_NS)
    hand.step(new)  # before the new driver's first /clock
    for k in range(1, 16):
        tick(new + k * CONTROL_PERIOD_NS)
        hand.step(new + k * CONTROL_PERIOD_NS)
    assert rec.pause()[0]
    dropped = rec.paused_dropped
    hand.step(new + 16 * CONTROL_PERIOD_NS)
    assert rec.paused_dropped == dropped + 3
    rec.close()
    assert rec.bags == [tmp_path / "recording_000", tmp_path / "recording_001"]
    got = events.wait(2, ros)
    assert [e.reason for e in got] == [CLOCK_RESTART, SHUTDOWN]
    assert (got[1].start_ns, got[1].end_ns) == (new, new + 15 * CONTROL_PERIOD_NS)  # on the new clock only
    for bag, start in zip(rec.bags, (old, new), strict=True):
        (traj,) = read_bag(bag)
        assert traj.start_ns == start and len(traj) == 15


def test_shutting_down_with_a_split_waiting_leaves_no_empty_bag(ros: Any, tmp_path: Path) -> None:
    """An episode-ending status, then shutdown before the split was carried out: the bag closes with its steps,
    and no new bag is opened only to be closed empty (and announced)."""
    rec = add_recorder(ros, tmp_path, mode="episode", step_hold_s=10.0)  # steps wait 5 s for a status
    hand = Hand(ros, rec)
    events = Events(hand)
    t0 = now_ns()
    for k in range(16):
        hand.step(t0 + k * CONTROL_PERIOD_NS)
    hand.status(status_message(names.RESET, "episode 1 grasped", t0 + 15 * CONTROL_PERIOD_NS))
    assert rec.waiting_changes == 1  # the split waits for the last step
    rec.close()  # SIGINT now
    assert rec.bags == [tmp_path / "episode_000"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_000"]
    (event,) = events.wait(1, ros)
    assert (event.reason, event.episodes) == (SHUTDOWN, 1)


def test_use_sim_time_with_no_clock_is_warned_of(ros: Any, tmp_path: Path) -> None:
    """Every message would be logged at 0 ns: said (throttled) once it lasts NO_CLOCK_S, not silent (a driver's
    first steps before its first /clock are no cause)."""
    from ros_rig import Rosout

    from t42_transfer.nodes.recorder import NO_CLOCK_S

    log = Rosout(ros, "recorder")
    rec = add_recorder(ros, tmp_path, use_sim_time=True)
    hand = Hand(ros, rec)
    hand.step(now_ns())
    assert not [w for w in log.wait_warnings(1, 0.3) if "no /clock" in w]
    ros.spin_for(NO_CLOCK_S)
    hand.step(now_ns())
    hand.step(now_ns() + CONTROL_PERIOD_NS)
    warnings = [w for w in log.wait_warnings(1) if "no /clock" in w]
    assert len(warnings) == 1, log.warnings()
