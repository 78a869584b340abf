"""The planner's ``t42/reach`` action through a plain rclpy ActionClient, in-process, with the mock driver stepped
by hand (the rig of test_planner_node).  The client side uses only rclpy, t42_interfaces and message packages."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from geometry_msgs.msg import Point, PointStamped
from rclpy.action import ActionClient
from sensor_msgs.msg import JointState
from t42_interfaces.action import Reach  # (a broken interface build fails, never skips)
from test_planner_node import SMALL, START_XY, Rig, toy_file

pytestmark = pytest.mark.usefixtures("one_torch_thread")

VERDICTS = {"hit", "miss", "no_progress", "incomplete"}


class ReachRig(Rig):
    """The planner rig plus a Reach client and the driver's applied actions."""

    def __init__(self, ros: Any, model: Any, **params: Any) -> None:
        super().__init__(ros, model, **params)
        self.client = ActionClient(self.tester, Reach, "t42/reach")
        self.applied: list[JointState] = self.listen(JointState, "hand/applied_action")
        assert ros.spin_until(self.client.server_is_ready, 10.0), "no t42/reach server"
        assert self.wait_graph(publishers={"hand/applied_action": 1}), "discovery"

    def send(self, xy_mm: Any, frame_id: str = "t42_base", steps: int = 0, tolerance_m: float = 0.0,
             feedback: list | None = None) -> Any:
        """Send a goal (``xy_mm``: the object's target in mm); the accepted goal handle."""
        target = PointStamped(point=Point(x=float(xy_mm[0]) / 1000, y=float(xy_mm[1]) / 1000))
        target.header.frame_id = frame_id
        sent = self.client.send_goal_async(Reach.Goal(target=target, tolerance_m=tolerance_m, steps=steps),
                                           feedback_callback=None if feedback is None else
                                           (lambda m: feedback.append(m.feedback)))
        assert self.ros.spin_until(sent.done, 10.0), "no goal response"
        handle = sent.result()
        assert handle.accepted
        return handle

    def run_until(self, future: Any, max_ticks: int = 60) -> Any:
        """Tick the driver until ``future`` is done; its result."""
        for _ in range(max_ticks):
            if self.ros.spin_until(future.done, 0.05):
                return future.result()
            self.tick()
        assert self.ros.spin_until(future.done, 5.0), "no result"
        return future.result()

    def wait_sent(self) -> None:
        """Until the driver holds the plan sent last."""
        assert self.ros.spin_until(lambda: self.driver.pending_actions > 0, 20.0), "no trajectory reached the driver"


@pytest.fixture
def rig(ros: Any, tmp_path: Any) -> ReachRig:
    return ReachRig(ros, toy_file(tmp_path / "toy.safetensors"), **SMALL)


def test_a_goal_gets_feedback_and_a_result_with_its_verdict_and_paths(ros, rig: ReachRig) -> None:
    rig.tick()
    feedback: list = []
    goal = START_XY + [6.0, -4.0]
    handle = rig.send(goal, feedback=feedback)
    rig.wait_sent()
    steps = rig.driver.pending_actions
    got = rig.run_until(handle.get_result_async())
    result = got.result
    assert result.verdict in VERDICTS and result.success == (result.verdict == "hit"), result
    assert got.status == (GoalStatus.STATUS_SUCCEEDED if result.success else GoalStatus.STATUS_ABORTED)
    assert result.success or result.reason.startswith(result.verdict)
    executed = [(p.pose.position.x * 1000, p.pose.position.y * 1000) for p in result.executed.poses]
    assert result.executed.header.frame_id == result.predicted.header.frame_id == "t42_base"
    assert len(executed) == steps + 1  # the start, then the state after each step
    assert result.final_error_m == pytest.approx(np.linalg.norm(np.subtract(executed[-1], goal)) / 1000, abs=1e-6)
    assert np.linalg.norm(np.subtract(executed[-1], executed[0])) > 1.0  # the object moved
    assert np.allclose(executed[0], START_XY, atol=1.0)  # where the plan started (the grasp settles a little)
    assert len(result.predicted.poses) == steps + 1
    assert len(feedback) >= math.ceil(steps / 10) and feedback[-1].step == steps
    assert [f.step for f in feedback] == sorted(f.step for f in feedback)
    assert feedback[-1].error_m == pytest.approx(result.final_error_m, abs=1e-6)
    assert math.isfinite(feedback[0].predicted_final_error_m)
    assert rig.results and rig.results[-1]["accepted"]  # t42/plan_result keeps being published


def test_cancel_stops_the_hand_at_the_next_step_and_ends_canceled_with_the_partial_path(ros, rig: ReachRig) -> None:
    rig.tick()
    handle = rig.send(START_XY + [8.0, 0.0], steps=20)
    rig.wait_sent()
    rig.tick(3)
    assert np.any(np.asarray(rig.applied[-1].velocity) != 0.0)  # the hand is moving
    cancel = handle.cancel_goal_async()
    assert ros.spin_until(cancel.done, 5.0) and len(cancel.result().goals_canceling) == 1
    assert ros.spin_until(lambda: rig.driver.pending_actions == 0, 2.0), "the driver still runs the plan"
    before = len(rig.applied)
    rig.tick()
    assert ros.spin_until(lambda: len(rig.applied) > before, 2.0)
    assert np.all(np.asarray(rig.applied[-1].velocity) == 0.0)  # zero from the first step after the cancel
    got = rig.run_until(handle.get_result_async(), 5)
    assert got.status == GoalStatus.STATUS_CANCELED
    assert got.result.verdict == "incomplete" and "cancelled" in got.result.reason
    assert 3 <= len(got.result.executed.poses) <= 4  # the start and the 2 steps measured (3rd: if it came first)
    assert len(got.result.predicted.poses) == 21


def test_a_newer_goal_pre_empts_the_running_one_action_or_topic(ros, rig: ReachRig) -> None:
    rig.tick()
    first = rig.send(START_XY + [8.0, 0.0], steps=20)
    rig.wait_sent()
    rig.tick(2)
    second = rig.send(START_XY + [0.0, 5.0], steps=20)
    got = rig.run_until(first.get_result_async(), 5)
    assert got.status == GoalStatus.STATUS_ABORTED and "pre-empted by a newer goal" in got.result.reason
    assert got.result.verdict == "incomplete"
    assert ros.spin_until(lambda: len(rig.trajectories) >= 3, 20.0), "the newer goal's plan"
    assert [len(t.points) for t in rig.trajectories][1:] == [0, 20]  # the hand stopped, then the newer plan
    rig.tick(2)
    rig.publish_goal(START_XY + [-3.0, 0.0])  # t42/goal, as Foxglove's publish panel sends it
    got = rig.run_until(second.get_result_async(), 5)
    assert got.status == GoalStatus.STATUS_ABORTED and "pre-empted" in got.result.reason
    rig.wait_results(3)  # plan_result for all three
    assert all(r["accepted"] for r in rig.results)


@pytest.mark.parametrize("frame_id, x, why", [("map", 0.01, "frame 'map'"), ("t42_base", math.nan, "non-finite")])
def test_a_goal_in_another_frame_or_with_nan_is_aborted_with_the_reason(ros, rig: ReachRig, frame_id: str,
                                                                           x: float, why: str) -> None:
    rig.tick()
    handle = rig.send([x * 1000, 80.0], frame_id=frame_id)
    got = rig.run_until(handle.get_result_async(), 1)
    assert got.status == GoalStatus.STATUS_ABORTED and got.result.verdict == "refused"
    assert why in got.result.reason and not got.result.success
    rig.wait_results(1)
    assert rig.results[0]["status"] == "bad_goal" and rig.trajectories == []
    outside = rig.send(START_XY + [100.0, 0.0])  # outside the model's workspace: refused as t42/goal refuses it
    got = rig.run_until(outside.get_result_async(), 1)
    assert got.result.verdict == "refused" and "outside the trained workspace" in got.result.reason


def test_a_burst_of_20_goals_each_gets_a_result_and_the_node_survives(ros, rig: ReachRig) -> None:
    rig.tick()
    sent = []
    for k in range(20):
        target = PointStamped(point=Point(x=float(START_XY[0] + 2.0 + k % 3) / 1000, y=float(START_XY[1]) / 1000))
        target.header.frame_id = "t42_base" if k % 5 else "map"  # some bad ones too
        sent.append(rig.client.send_goal_async(Reach.Goal(target=target)))
    assert ros.spin_until(lambda: all(s.done() for s in sent), 20.0), "goal responses"
    handles = [s.result() for s in sent]
    results = [h.get_result_async() for h in handles if h.accepted]
    for future in results:
        rig.run_until(future, 40)
    statuses = [f.result().status for f in results]
    assert len(statuses) + sum(not h.accepted for h in handles) == 20
    assert all(f.result().result.verdict in VERDICTS | {"refused"} for f in results)
    assert statuses.count(GoalStatus.STATUS_ABORTED) >= 15  # 4 bad ones, the rest pre-empted
    assert all(f.result().result.reason for f in results if f.result().status == GoalStatus.STATUS_ABORTED)
    rig.tick()
    after = rig.send(START_XY + [2.0, 0.0])
    assert rig.run_until(after.get_result_async()).result.verdict in VERDICTS


def test_a_closed_loop_goal_replans_every_k_steps_and_reports_each_step(ros, rig: ReachRig) -> None:
    rig.tick()
    feedback: list = []
    target = PointStamped(point=Point(x=float(START_XY[0] + 6.0) / 1000, y=float(START_XY[1] - 4.0) / 1000))
    target.header.frame_id = "t42_base"
    sent = rig.client.send_goal_async(Reach.Goal(target=target, steps=15, replan_every=5),
                                      feedback_callback=lambda m: feedback.append(m.feedback))
    assert ros.spin_until(sent.done, 10.0) and sent.result().accepted
    got = rig.run_until(sent.result().get_result_async())
    assert [len(t.points) for t in rig.trajectories] == [5, 5, 5]  # three pieces, each planned from the state
    executed = len(got.result.executed.poses)  # 15 steps, the start, and the steps held while replanning
    assert got.result.verdict in VERDICTS and 16 <= executed <= 16 + 2 * 3
    assert len(got.result.predicted.poses) == 6  # the last plan: the 5 steps left, from where it started
    assert [f.step for f in feedback] == list(range(executed))  # every step, none skipped
    assert rig.results[-1]["replan_every"] == 5 and rig.results[-1]["horizon"] == 15


def test_goals_end_right_after_many_trajectories_and_episode_ends_have_been_heard(ros, tmp_path: Any) -> None:
    """The planner tells a piece's trajectory_done, and an episode's end, by what came since it was sent: after more
    than the ten it keeps (a demo explores twelve episodes first) a goal still ends when its plan has run, not after
    piece_timeout_s with no state, and a drop still ends it."""
    from std_msgs.msg import String

    from msg_adapters import names, status_message
    from t42_transfer.ros.qos import profile

    rig = ReachRig(ros, toy_file(tmp_path / "toy.safetensors"), **{**SMALL, "piece_timeout_s": 3.0})
    status = rig.tester.create_publisher(String, names.HAND_STATUS, profile(names.EVENTS))
    assert rig.wait_graph(subscribers={names.HAND_STATUS: 1}), "discovery"
    for k in range(12):  # earlier episodes' trajectories and drops
        status.publish(String(data=status_message(names.TRAJECTORY_DONE, f"episode {k}", 1_000 + k)))
        status.publish(String(data=status_message(names.DROPPED, f"episode {k}", 1_000 + k)))
    rig.ros.spin_for(0.3)
    rig.tick()
    got = rig.run_until(rig.send(START_XY + [6.0, -4.0]).get_result_async())
    assert got.result.verdict in VERDICTS - {"incomplete"}, got.result.reason  # judged on the state after the plan
    handle = rig.send(START_XY + [0.0, 6.0], steps=20, tolerance_m=0.02)  # a fixed 20-step plan, executed
    rig.wait_sent()
    rig.tick(2)
    status.publish(String(data=status_message(names.DROPPED, "the object fell", rig.now_ns())))
    got = rig.run_until(handle.get_result_async(), 5)
    assert got.status == GoalStatus.STATUS_ABORTED and "the episode ended (dropped)" in got.result.reason


def test_an_open_loop_plan_is_waited_for_its_length_and_one_that_overruns_stops_the_hand(ros, tmp_path: Any) -> None:
    """An open-loop plan is one piece: it was given piece_timeout_s from its sending whatever its length (a
    400-step plan at 10 Hz ended `incomplete` after 30 s), and the hand ran the rest of it with no goal."""
    import time

    rig = ReachRig(ros, toy_file(tmp_path / "toy.safetensors"), **{**SMALL, "piece_timeout_s": 2.0})
    rig.tick()
    handle = rig.send(START_XY + [6.0, -4.0], steps=40, tolerance_m=0.02)
    rig.wait_sent()
    future, start = handle.get_result_async(), time.monotonic()
    while rig.driver.pending_actions:  # the hand at about its 10 Hz: 4 s for the plan, twice piece_timeout_s
        rig.tick()
        rig.ros.spin_for(0.06)
    assert time.monotonic() - start > 2.0  # (else this tells nothing)
    got = rig.run_until(future, 5)
    assert got.result.verdict != "incomplete", got.result.reason
    rig.tick()  # a fresh state to plan from
    handle = rig.send(START_XY + [6.0, 0.0], steps=20, tolerance_m=0.03)  # a hand that stalls mid-plan
    rig.wait_sent()
    rig.tick(2)
    future = handle.get_result_async()
    assert rig.ros.spin_until(future.done, 15.0), "no result"  # after 2 s of plan and piece_timeout_s
    assert future.result().result.verdict == "incomplete", future.result().result.reason
    assert rig.ros.spin_until(lambda: rig.driver.pending_actions == 0, 5.0), "the hand was left running the plan"


def t42_reach(rig: ReachRig, *argv: str, interrupt_after_ticks: int | None = None) -> tuple[int, str, str]:
    """Run ``t42 reach *argv`` as a process while the rig's driver steps (``interrupt_after_ticks``: SIGINT once
    the plan reached the driver and the hand took so many steps of it); (exit code, stdout, stderr)."""
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "reach", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline, moving = time.monotonic() + 90.0, 0
    # No ticks before the plan: the goal is planned from the rig's state however long the process takes to start
    # (ticking meanwhile moved the hand a load-dependent number of steps, and a toy plan refused a goal once).
    assert all(r.successful for r in rig.set(max_state_age_s=600.0))
    plans = len(rig.results)
    while proc.poll() is None and time.monotonic() < deadline:
        if rig.driver.pending_actions > 0 or len(rig.results) > plans:
            rig.tick()
        moving += rig.driver.pending_actions > 0
        if moving == interrupt_after_ticks:
            proc.send_signal(signal.SIGINT)
            interrupt_after_ticks = None  # once
        rig.ros.spin_until(lambda: proc.poll() is not None, 0.05)
    if proc.poll() is None:
        proc.kill()
    out, err = proc.communicate()
    return proc.returncode, out, err


def test_t42_reach_follows_a_goal_to_its_verdict_as_ros2_action_send_goal_does(ros, rig: ReachRig) -> None:
    """The command a pip-only install has for the action: feedback lines, the verdict, exit 0 only on a hit."""
    rig.tick()
    x, y = (START_XY + [6.0, -4.0]) / 1000
    # a 10 mm tolerance: the rig's small unrefined search, under load, once predicted 4.3 mm for a 3 mm one and
    # refused the goal; this test is about the command, not the plan
    code, out, err = t42_reach(rig, f"{x:.6f}", f"{y:.6f}", "--steps", "20", "--tolerance", "0.01")
    lines = out.splitlines()
    assert lines and all(line.startswith("step ") for line in lines[:-1]) and len(lines) >= 3, (out, err)
    verdict = re.fullmatch(r"/t42/reach: (hit|miss|no_progress|incomplete)(: .+)?; final error \d+\.\d mm after "
                           r"2[1-9] measured positions", lines[-1])
    assert verdict and not (verdict[2] or "").startswith(f": {verdict[1]}"), lines[-1]  # the word said once
    assert code == (0 if lines[-1].startswith("/t42/reach: hit") else 1), (code, err)
    assert rig.results[-1]["accepted"] and rig.results[-1]["horizon"] == 20  # the goal's steps, as sent
    assert [len(t.points) for t in rig.trajectories] == [20]


def test_ctrl_c_on_t42_reach_cancels_the_goal_and_the_hand_holds(ros, rig: ReachRig) -> None:
    rig.tick()
    x, y = (START_XY + [8.0, 0.0]) / 1000
    code, out, err = t42_reach(rig, f"{x:.6f}", f"{y:.6f}", "--steps", "40", "--tolerance", "0.01",
                               interrupt_after_ticks=3)  # (the tolerance: as above)
    assert code == 130 and err == "t42: interrupted: goal cancelled (the hand holds from its next step)\n", (out, err)
    assert ros.spin_until(lambda: rig.driver.pending_actions == 0, 2.0), "the driver still runs the plan"


def test_t42_reach_says_a_refusal_in_one_line_with_its_reason(ros, rig: ReachRig) -> None:
    rig.tick()
    x, y = (START_XY + [100.0, 0.0]) / 1000  # outside the model's workspace
    code, out, err = t42_reach(rig, f"{x:.6f}", f"{y:.6f}")
    assert code == 1 and out.count("\n") == 1, (out, err)
    assert out.startswith("/t42/reach: refused: goal_outside_workspace: goal (x "), out
    assert "is outside the trained workspace (x " in out and "final error" not in out, out


def test_t42_reach_without_a_planner_is_one_line(ros, rig: ReachRig) -> None:
    code, out, err = t42_reach(rig, "0.0", "0.05", "--action", "/left/t42/reach", "--wait", "1")
    assert code == 2 and out == "" and err.count("\n") == 1, (out, err)
    assert "/left/t42/reach: no such action server on the graph after 1 s" in err, err
