"""The planner's ``t42/reach`` action under abuse: 100 goals a second, a client that leaves mid-goal, and a new
model announced while a goal runs (a transfer finishing).  Each gets a result or a clear rejection, and the node
serves the next goal as before.  The client side uses only rclpy, t42_interfaces and message packages."""

from __future__ import annotations

import time
from typing import Any

import pytest
from action_msgs.msg import GoalStatus, GoalStatusArray
from geometry_msgs.msg import Point, PointStamped
from rclpy.action import ActionClient
from t42_interfaces.action import Reach  # (a broken interface build fails, never skips)
from t42_interfaces.msg import ModelUpdated
from test_planner_node import SMALL, START_XY, toy_file
from test_reach_action import VERDICTS, ReachRig

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TERMINAL = {GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_ABORTED, GoalStatus.STATUS_CANCELED}


def goal(dx_mm: float, frame_id: str = "t42_base") -> Any:
    target = PointStamped(point=Point(x=float(START_XY[0] + dx_mm) / 1000, y=float(START_XY[1]) / 1000))
    target.header.frame_id = frame_id
    return Reach.Goal(target=target)


@pytest.fixture
def rig(ros: Any, tmp_path: Any) -> ReachRig:
    return ReachRig(ros, toy_file(tmp_path / "toy.safetensors"), **SMALL)


def test_100_goals_a_second_each_get_a_response_and_a_result(ros, rig: ReachRig) -> None:
    rig.tick()
    sent, start = [], time.monotonic()
    for k in range(100):  # paced at 100 a second, the executor spinning between them
        sent.append(rig.client.send_goal_async(goal(2.0 + k % 3, "t42_base" if k % 7 else "map")))
        ros.spin_until(lambda k=k: time.monotonic() - start >= (k + 1) * 0.01, 0.05)
    assert ros.spin_until(lambda: all(s.done() for s in sent), 30.0), \
        f"{sum(not s.done() for s in sent)} of 100 goals never got a response"
    handles = [s.result() for s in sent]
    futures = [h.get_result_async() for h in handles if h.accepted]
    for future in futures:
        rig.run_until(future, 40)
    results = [f.result() for f in futures]
    assert len(results) + sum(not h.accepted for h in handles) == 100
    assert all(r.result.verdict in VERDICTS | {"refused"} for r in results)
    aborted = [r for r in results if r.status == GoalStatus.STATUS_ABORTED]
    assert all(r.result.reason for r in aborted), "an aborted goal without its reason"
    assert sum("frame" in r.result.reason for r in aborted) >= 14  # the 15 goals in "map", one maybe pre-empted first
    rig.tick()
    after = rig.client.send_goal_async(goal(2.0))
    assert ros.spin_until(after.done, 10.0) and after.result().accepted
    assert rig.run_until(after.result().get_result_async()).result.verdict in VERDICTS


def test_a_client_that_leaves_mid_goal_does_not_stop_the_planner(ros, rig: ReachRig) -> None:
    rig.tick()
    statuses: list = rig.listen(GoalStatusArray, "t42/reach/_action/status", 10)
    leaver = ros.node("leaver")
    client = ActionClient(leaver, Reach, "t42/reach")
    assert ros.spin_until(client.server_is_ready, 10.0)
    sent = client.send_goal_async(goal(4.0))
    assert ros.spin_until(sent.done, 10.0) and sent.result().accepted
    rig.wait_sent()
    ros.executor.remove_node(leaver)
    ros.nodes.remove(leaver)
    client.destroy()
    leaver.destroy_node()
    orphan = bytes(sent.result().goal_id.uuid)

    def ended() -> bool:  # as the action's status topic tells anyone listening
        return any(bytes(s.goal_info.goal_id.uuid) == orphan and s.status in TERMINAL
                   for m in statuses for s in m.status_list)

    for _ in range(60):  # the orphaned goal runs to its end with no client left to tell
        if ros.spin_until(ended, 0.05):
            break
        rig.tick()
    assert ended(), "the goal of a client that left never ended"
    after = rig.send(START_XY + [2.0, 0.0])  # a new goal pre-empts the orphaned one and runs to its verdict
    assert rig.run_until(after.get_result_async()).result.verdict in VERDICTS


def test_a_model_announced_while_a_goal_runs_leaves_the_goal_a_result(ros, rig: ReachRig, tmp_path: Any) -> None:
    rig.tick()
    handle = rig.send(START_XY + [4.0, 0.0])
    rig.wait_sent()
    newer = toy_file(tmp_path / "newer.safetensors")
    update = ModelUpdated(path=str(newer), method="direct", episodes=3)
    update.stamp = rig.tester.get_clock().now().to_msg()
    rig.model_pub.publish(update)  # the transfer server's announcement
    loaded = rig.planner.model
    assert ros.spin_until(lambda: str(rig.planner.model.path) == str(newer), 10.0), "the new model never loaded"
    assert loaded is not None and loaded.path != str(newer)
    got = rig.run_until(handle.get_result_async())
    assert got.result.verdict in VERDICTS | {"refused"} and (got.status == GoalStatus.STATUS_SUCCEEDED
                                                             or got.result.reason)
    after = rig.send(START_XY + [2.0, 0.0])
    assert rig.run_until(after.get_result_async()).result.verdict in VERDICTS
