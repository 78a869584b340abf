"""The recorder's bags with the suite's own types, read by an independent reader (rosbags with a typestore built from
the bag's schemas alone, and mcap-ros2-support, in a process that cannot import t42_interfaces or this project), and
its snapshot mode (~/snapshot, status triggers, the last S seconds exactly), on real rclpy in-process."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from t42_interfaces.msg import ModelUpdated, PlanResult
from test_recorder import ACTION, JOINTS, POSE, Hand, add_recorder, now_ns, raw_messages, steps_in
from test_recorder_events import Events

from msg_adapters import STRING, TYPESTORE, names, status_message
from msg_adapters.events import SNAPSHOT
from t42_transfer.conventions import ACTION_UNIT_RAD, CONTROL_PERIOD_NS, CONTROL_PERIOD_S
from t42_transfer.data.bag import bag_info, read_bag, verify_bag
from t42_transfer.nodes.player import BagPlayer
from t42_transfer.nodes.recorder_params import RecorderParams

READER = Path(__file__).with_name("independent_reader.py")


def stamp(ns: int) -> Time:
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def plan_results(t0: int) -> list[PlanResult]:
    """An accepted plan and a refusal (no prediction: NaN, no start)."""
    accepted = PlanResult(header=Header(stamp=stamp(t0 + 1), frame_id="t42_base"), accepted=True, status="ok",
                          reason="", has_goal=True, goal=Point(x=0.012, y=0.1155, z=0.0), goal_stamp=stamp(t0),
                          has_start=True, start=Point(x=0.0031, y=0.1092, z=0.0), predicted_error_m=0.0021,
                          horizon=40, samples_evaluated=1000, planning_time_s=0.25,
                          model="/models/transferred_003.safetensors", method="fine_tune", replan_every=5)
    refused = PlanResult(header=Header(stamp=stamp(t0 + 2), frame_id="t42_base"), accepted=False,
                         status="goal_outside_workspace", reason="the goal is 41 mm outside the trained workspace",
                         has_goal=True, goal=Point(x=0.2, y=-0.05, z=0.0), goal_stamp=stamp(t0 + 2),
                         has_start=False, predicted_error_m=math.nan, horizon=0, samples_evaluated=0,
                         planning_time_s=0.0, model="", method="", replan_every=0)
    return [accepted, refused]


def independent_read(bag: Path, cwd: Path) -> dict[str, Any]:
    done = subprocess.run([sys.executable, str(READER), str(bag)], cwd=cwd, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_an_independent_reader_decodes_every_typed_message_of_a_recorded_bag(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path / "bags", step_hold_s=1.0)  # default topics: the hand's and both events
    hand = Hand(ros, rec)
    pubs = {PlanResult: hand.node.create_publisher(PlanResult, names.PLAN_RESULT, 10),
            ModelUpdated: hand.node.create_publisher(ModelUpdated, names.MODEL_UPDATED, 10)}
    assert ros.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values()), 10.0)
    t0 = now_ns()
    expected = hand.episode(t0, 15)
    assert ros.spin_until(lambda: rec.current_count == 47, 5.0)  # events go only into a bag holding steps
    results = plan_results(t0)
    model = ModelUpdated(stamp=stamp(t0 + 3), path="/work/models/left/transferred_003.safetensors",
                         method="residual", episodes=12)
    for msg in results:
        pubs[PlanResult].publish(msg)
    pubs[ModelUpdated].publish(model)
    text = status_message(names.TRAJECTORY_DONE, "40 points applied", t0 + 15 * CONTROL_PERIOD_NS)
    hand.status(text)
    assert ros.spin_until(lambda: rec.current_count == 47 + 4, 5.0), rec.current_count
    assert hand.call("stop").success
    bag = tmp_path / "bags" / "recording_000"

    got = independent_read(bag, tmp_path)
    hand_types = {POSE: "geometry_msgs/msg/PoseStamped", JOINTS: "sensor_msgs/msg/JointState",
                  ACTION: "sensor_msgs/msg/JointState"}
    assert got["schemas"] == {**{t: ["MSG", m] for t, m in hand_types.items()},
                              "/hand/status": ["MSG", "std_msgs/msg/String"],
                              "/t42/plan_result": ["MSG", "t42_interfaces/msg/PlanResult"],
                              "/t42/model_updated": ["MSG", "t42_interfaces/msg/ModelUpdated"]}
    # both readers decode the same values (NaN included: compared as JSON text)
    assert json.dumps(got["rosbags"], sort_keys=True) == json.dumps(got["mcap_ros2"], sort_keys=True)
    msgs = got["mcap_ros2"]
    ok, no = msgs["/t42/plan_result"]
    assert ok["header"] == {"stamp": {"sec": (t0 + 1) // 10**9, "nanosec": (t0 + 1) % 10**9}, "frame_id": "t42_base"}
    assert (ok["accepted"], ok["status"], ok["has_goal"], ok["has_start"]) == (True, "ok", True, True)
    assert (ok["goal"], ok["start"]) == ({"x": 0.012, "y": 0.1155, "z": 0.0}, {"x": 0.0031, "y": 0.1092, "z": 0.0})
    assert ok["goal_stamp"] == {"sec": t0 // 10**9, "nanosec": t0 % 10**9}
    assert (ok["predicted_error_m"], ok["horizon"], ok["samples_evaluated"], ok["planning_time_s"]) == \
        (0.0021, 40, 1000, 0.25)
    assert (ok["model"], ok["method"], ok["replan_every"]) == ("/models/transferred_003.safetensors", "fine_tune", 5)
    assert (no["accepted"], no["status"], no["has_start"]) == (False, "goal_outside_workspace", False)
    assert no["reason"] == "the goal is 41 mm outside the trained workspace" and math.isnan(no["predicted_error_m"])
    assert msgs["/t42/model_updated"] == [{"stamp": {"sec": (t0 + 3) // 10**9, "nanosec": (t0 + 3) % 10**9},
                                           "path": "/work/models/left/transferred_003.safetensors",
                                           "method": "residual", "episodes": 12}]
    assert msgs["/hand/status"] == [{"data": text}]
    poses = msgs[POSE]
    assert [p["header"]["stamp"] for p in poses] == [{"sec": (t0 + k * CONTROL_PERIOD_NS) // 10**9,
                                                       "nanosec": (t0 + k * CONTROL_PERIOD_NS) % 10**9}
                                                      for k in range(16)]
    np.testing.assert_allclose([p["pose"]["position"]["x"] * 1000 for p in poses], expected["states"][:, 0],
                               rtol=1e-6)
    np.testing.assert_allclose([j["effort"] for j in msgs[JOINTS]][3], expected["states"][3, 2:] * 0.0041, rtol=1e-6)
    np.testing.assert_allclose([a["velocity"] for a in msgs[ACTION]],
                               expected["actions"] * ACTION_UNIT_RAD / CONTROL_PERIOD_S, rtol=1e-6)

    # our own reader still reads it: the events are no steps
    (episode,) = read_bag(bag)
    np.testing.assert_array_equal(episode.actions, expected["actions"])
    info = bag_info(bag)
    assert info["topics"]["/t42/plan_result"] == {"type": "t42_interfaces/msg/PlanResult", "count": 2}
    assert info["episodes"] == 1 and verify_bag(bag) == []

    # the bag offers each topic as its publishers do, so a player republishes the latched ones latched: the
    # planner's latched reader of t42/model_updated matches no volatile writer
    player = ros.add(BagPlayer, params={"bag": str(bag), "start_paused": True})
    offers = {topic: pub.qos_profile for topic, pub in player.topic_publishers.items()}
    latched = {"/hand/status": 100, "/t42/model_updated": 1, "/t42/plan_result": 10_000}
    assert {t: q.depth for t, q in offers.items() if q.durability == DurabilityPolicy.TRANSIENT_LOCAL} == latched
    assert all(offers[t].durability == DurabilityPolicy.VOLATILE for t in hand_types)


def test_snapshot_mode_writes_exactly_the_last_seconds_on_the_service_and_on_a_drop(ros: Any, tmp_path: Path) -> None:
    rec = add_recorder(ros, tmp_path, start_immediately=False, snapshot_s=2.0, step_hold_s=1.0,
                       snapshot_on=[names.DROPPED, names.RESET])
    hand = Hand(ros, rec)
    events = Events(hand)
    client = hand.node.create_client(Trigger, names.private_of("recorder", names.RECORDER_SNAPSHOT))

    def snapshot() -> Trigger.Response:
        return ros.call(client, Trigger.Request())

    empty = snapshot()
    assert not empty.success and "no whole step" in empty.message
    t0 = now_ns()
    expected = hand.episode(t0, 60, last_state=False)  # 6 s of steps, nothing recorded continuously
    taken = snapshot()
    first = tmp_path / "snapshots" / "snapshot_000"
    assert taken.success and str(first) in taken.message, taken.message
    assert [s for s, _ in steps_in(first)] == [t0 + k * CONTROL_PERIOD_NS for k in range(40, 60)]  # (t - 2 s, t]
    (episode,) = read_bag(first)
    np.testing.assert_array_equal(episode.states, expected["states"][40:60])
    np.testing.assert_array_equal(episode.actions, expected["actions"][40:59])
    buffer = rec.snapshots.buffer
    assert len(buffer.steps) == 20 and buffer.forgotten_steps == 40  # memory: old steps are dropped

    # a drop: the snapshot waits for the final state the status names (it waits step_hold_s for an action)
    for k in range(60, 79):
        hand.step(t0 + k * CONTROL_PERIOD_NS, angles=(0.1, 0.2), action=(0.1 * (k % 5), -0.2))
    end = t0 + 79 * CONTROL_PERIOD_NS
    hand.step(end, xy=(7.0, 8.0), angles=(0.1, 0.2), action=None)  # the final state ...
    dropped = status_message(names.DROPPED, "episode 0 ended", end)
    hand.status(dropped)  # ... then the status naming it, as a driver publishes them
    assert rec.snapshots.bags == [first]
    hand.status(status_message(names.RESET, "episode 1 grasped", end))  # the same border: no second bag
    assert ros.spin_until(lambda: len(events.got) >= 2, 10.0)
    ros.spin_for(0.5)
    second = tmp_path / "snapshots" / "snapshot_001"
    assert rec.snapshots.bags == [first, second] and rec.bags == []  # nothing but snapshots was written
    assert [s for s, _ in steps_in(second)] == [t0 + k * CONTROL_PERIOD_NS for k in range(60, 80)]
    (episode,) = read_bag(second)  # the bag holds the final state; a reader leaves out the state the object fell into
    assert len(episode) == 18 and episode.end_reason == names.DROPPED and tuple(episode.states[-1, :2]) != (7.0, 8.0)
    got = events.wait(2, ros)
    assert [(e.path, e.reason, e.episodes) for e in got] == [(str(first), SNAPSHOT, 1), (str(second), SNAPSHOT, 1)]
    statuses = raw_messages(second)["/" + names.HAND_STATUS]
    assert TYPESTORE.deserialize_cdr(statuses[0], STRING).data == dropped
    assert got[1].messages == 20 * 3 - 1 + len(statuses)  # 20 steps (the final state has no action), the statuses
    assert sorted(p.name for p in tmp_path.iterdir()) == ["snapshots"]  # no bag among the continuous ones

    # off: the buffer goes, the service says why
    assert rec.set_parameters([Parameter("snapshot_s", value=0.0)])[0].successful
    off = snapshot()
    assert not off.success and "snapshot mode is off" in off.message and rec.snapshots.buffer is None


def test_recorder_params_record_both_events_by_default_and_refuse_bad_values(tmp_path: Path) -> None:
    params = RecorderParams(out_dir=tmp_path)
    assert params.topics == (names.OBJECT_POSE, names.JOINT_STATES, names.APPLIED_ACTION, names.PLAN_RESULT,
                             names.MODEL_UPDATED)
    assert params.snapshot_s == 0.0 and params.snapshot_on == names.SPLIT_EVENTS
    with pytest.raises(ValueError, match="must name a hand topic"):
        RecorderParams(out_dir=tmp_path, topics=(names.PLAN_RESULT,))  # events are written only beside steps
    for field, value in (("snapshot_s", -1.0), ("snapshot_s", math.inf), ("snapshot_max_mb", 0.0)):
        with pytest.raises(ValueError, match=field):
            RecorderParams(out_dir=tmp_path, **{field: value})
