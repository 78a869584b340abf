"""The planner node on real rclpy, in-process, with the mock driver stepped by hand."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from ros_rig import Rosout, Tester
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from t42_interfaces.msg import ModelUpdated
from t42_interfaces.msg import PlanResult as PlanResultMsg
from toys import Toy, ToyHand
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    goal_msg,
    joint_state_msg,
    joint_trajectory_to_actions,
    names,
    object_pose_msg,
    object_xy_mm,
    path_xy_mm,
    stamp_to_ns,
    status_message,
)
from msg_adapters.plan_result import PlanResult, plan_result
from msg_adapters.transfer import model_updated_msg
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, CONTROL_PERIOD_NS, FRAME_ID
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.models.checkpoint import save_model
from t42_transfer.nodes.mock_driver import MockDriver
from t42_transfer.nodes.planner_node import PlannerNode
from t42_transfer.nodes.planner_params import PlannerNodeParams
from t42_transfer.nodes.planner_parts import Goal, Refused, hand_state, load_planner_model, unsent
from t42_transfer.planning import Plan, Planner, Workspace
from t42_transfer.planning.execution import execute
from t42_transfer.ros.qos import profile

pytestmark = pytest.mark.usefixtures("one_torch_thread")

GRASP = SimulatedHand("target")
GRASP.reset(0)
START_XY = GRASP.state[:2].copy()
"""Where the mock driver (seed 0) holds the object after its first grasp."""
BOX = Workspace.box(START_XY[0] - 40, START_XY[0] + 40, START_XY[1] - 40, START_XY[1] + 40)
SMALL = dict(samples=200, refine_iterations=0, horizon=20, horizon_search=True, tolerance_m=0.003,
             max_state_age_s=5.0)
"""Fast unrefined plans that stop at the first predicted reach (the node's mechanics, not the plans' quality); a
generous state age, since a loaded 2-core machine may take a while between tick and plan."""
SLOW_TIMER = 1e-3
"""The driver's rate_factor that keeps its own timer (100 s period) out of hand-stepped tests."""


def toy_file(path: Path, method: str = "toy", gain: float = 1.0, workspace: Workspace | None = BOX,
             action_unit_rad: float = ACTION_UNIT_RAD) -> Path:
    extra = {"workspace": workspace.to_dict()} if workspace is not None else None
    return save_model(Toy(gain=gain), path, method=method, extra=extra, action_unit_rad=action_unit_rad)


class Rig(Tester):
    """Mock driver (stepped by hand), planner node and a tester node on the test's own domain."""

    def __init__(self, ros, model: Path | str = "", driver: bool = True, **params: Any) -> None:
        super().__init__(ros)
        self.driver = ros.add(MockDriver, {"rate_factor": SLOW_TIMER}) if driver else None
        self.results: list[dict] = []
        """Each t42/plan_result as a dict of :class:`~msg_adapters.plan_result.PlanResult`'s fields (mm)."""
        self.messages: list[PlanResultMsg] = []
        """The t42/plan_result messages as they came."""
        self.tester.create_subscription(PlanResultMsg, names.PLAN_RESULT, self._on_result, 10)
        self.trajectories: list[JointTrajectory] = self.listen(JointTrajectory, names.HAND_TRAJECTORY, 10)
        self.paths: list[PathMsg] = self.listen(PathMsg, names.PLANNED_PATH, 10)
        self.goal_pub = self.tester.create_publisher(PointStamped, names.GOAL, 10)
        self.model_pub = self.tester.create_publisher(ModelUpdated, names.MODEL_UPDATED, profile(names.LATCHED))
        self.setter = self.tester.create_client(SetParameters, "planner/set_parameters")
        self.planner: PlannerNode | None = None
        self.start_planner(model, **params)

    def _on_result(self, msg: PlanResultMsg) -> None:
        self.messages.append(msg)
        self.results.append(asdict(plan_result(msg)))

    def start_planner(self, model: Path | str = "", **params: Any) -> None:
        self.planner = self.ros.add(PlannerNode, {"model": str(model), **params})
        hand = (names.OBJECT_POSE, names.JOINT_STATES)
        assert self.ros.spin_until(lambda: self.goal_pub.get_subscription_count() == 1
                                   and self.model_pub.get_subscription_count() == 1, 10.0), "discovery"
        assert self.wait_graph(
            publishers=dict.fromkeys((names.PLAN_RESULT, names.PLANNED_PATH, names.HAND_TRAJECTORY), 1)
            | (dict.fromkeys(hand, 1) if self.driver is not None else {}),
            subscribers={names.HAND_TRAJECTORY: (self.driver is not None) + 1, **dict.fromkeys(hand, 1)},
        ), "discovery"

    def tick(self, n: int = 1) -> None:
        """``n`` driver steps, each taken in by the planner before the next."""
        for _ in range(n):
            before = self.planner.state_stamp_ns
            self.driver.tick()
            assert self.ros.spin_until(lambda before=before: self.planner.state_stamp_ns != before, 5.0), \
                "state not delivered"

    def now_ns(self) -> int:
        return self.tester.get_clock().now().nanoseconds

    def publish_goal(self, xy: np.ndarray | list[float], frame_id: str = FRAME_ID) -> None:
        msg = goal_msg(np.asarray(xy, np.float32), self.now_ns(), RCLPY)
        msg.header.frame_id = frame_id
        self.goal_pub.publish(msg)

    def wait_results(self, count: int) -> None:
        """Spin until ``count`` results arrived and the planner is idle; then check no extra result follows."""
        assert self.ros.spin_until(lambda: len(self.results) >= count and self.planner.idle, 20.0), \
            f"{len(self.results)} of {count} plan results"
        self.ros.spin_for(0.05)
        assert len(self.results) == count, self.results

    def goal(self, xy: np.ndarray | list[float], frame_id: str = FRAME_ID) -> dict:
        """Send a goal and wait for its one result."""
        expected = len(self.results) + 1
        self.publish_goal(xy, frame_id)
        self.wait_results(expected)
        return self.results[-1]

    def announce(self, path: Path | str) -> None:
        self.model_pub.publish(model_updated_msg(0, str(path), "test", 1))

    def set(self, **values: Any) -> list:
        """``ros2 param set`` on the planner: the SetParametersResult of each value."""
        msgs = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        request = SetParameters.Request(parameters=msgs)
        return list(self.ros.call(self.setter, request).results)


@pytest.fixture
def toy(tmp_path: Path) -> Path:
    return toy_file(tmp_path / "toy.safetensors")


@pytest.fixture
def rig(ros, toy: Path) -> Rig:
    return Rig(ros, toy, **SMALL)


# --------------------------------------------------------------------------- accepted plans
def test_goal_gives_a_trajectory_the_driver_executes_and_its_predicted_path(ros, rig: Rig) -> None:
    driver_log = Rosout(ros, "mock_driver")
    rig.tick()
    goal = START_XY + [6.0, -4.0]
    before = rig.now_ns()
    result = rig.goal(goal)
    assert result["accepted"] and result["status"] == "ok", result
    assert result["method"] == "toy" and result["samples_evaluated"] == 200 and result["planning_time_s"] > 0
    assert np.allclose(result["goal_mm"], goal) and np.allclose(result["start_mm"], START_XY, atol=0.5)
    assert result["predicted_error_mm"] <= 3.0
    (msg,) = rig.messages  # on the wire: a t42_interfaces PlanResult in metres in t42_base, stamped when published
    assert msg.header.frame_id == FRAME_ID and before <= stamp_to_ns(msg.header.stamp) <= rig.now_ns()
    assert msg.has_goal and [msg.goal.x, msg.goal.y] == [v / 1000 for v in result["goal_mm"]]
    assert msg.predicted_error_m == pytest.approx(result["predicted_error_mm"] / 1000)
    assert before <= stamp_to_ns(msg.goal_stamp) <= stamp_to_ns(msg.header.stamp)  # the goal it answers
    assert ros.spin_until(lambda: rig.trajectories and rig.paths, 5.0)
    (traj,), (path,) = rig.trajectories, rig.paths
    steps = result["horizon"]
    assert 1 <= steps <= 20 and len(traj.points) == steps and len(path.poses) == steps + 1
    stamp = stamp_to_ns(traj.header.stamp)
    assert before <= stamp <= rig.now_ns() and stamp_to_ns(path.header.stamp) == stamp
    pose_stamps = [stamp_to_ns(p.header.stamp) for p in path.poses]
    assert pose_stamps == [stamp + k * CONTROL_PERIOD_NS for k in range(steps + 1)]
    predicted = path_xy_mm(path)
    actions = joint_trajectory_to_actions(traj, rig.driver.hand.actuator_angles)
    assert np.all(np.abs(actions) <= 1.0 + 1e-5)
    assert np.allclose(predicted[1:], predicted[0] + np.cumsum(actions, 0), atol=1e-3)  # the toy's prediction
    assert np.linalg.norm(predicted[-1] - goal) <= 3.0

    assert ros.spin_until(lambda: rig.driver.pending_actions == steps, 5.0)
    rig.tick(steps)
    assert rig.driver.pending_actions == 0
    ros.spin_for(0.1)
    assert driver_log.warnings() == []
    late = rig.listen(PathMsg, names.PLANNED_PATH, profile(names.LATCHED))  # a viewer opened now
    assert ros.spin_until(lambda: late, 5.0) and late == [path]  # gets the plan's path (latched)


def test_a_model_of_the_authors_unit_is_sent_as_the_actuator_steps_it_planned(ros, tmp_path: Path) -> None:
    """The authors' models learnt 0.00388 rad a step at an action of 1; the wire carries the suite's 0.025."""
    rig = Rig(ros, toy_file(tmp_path / "authors.safetensors", action_unit_rad=AUTHORS_ACTION_UNIT_RAD), **SMALL)
    rig.tick()
    assert rig.goal(START_XY + [6.0, -4.0])["accepted"]
    assert ros.spin_until(lambda: rig.trajectories and rig.paths, 5.0)
    (traj,), (path,) = rig.trajectories, rig.paths
    sent = joint_trajectory_to_actions(traj, rig.driver.hand.actuator_angles)
    planned = sent * (ACTION_UNIT_RAD / AUTHORS_ACTION_UNIT_RAD)
    assert np.abs(planned).max() > 0.5 and np.all(np.abs(planned) <= 1.0 + 1e-4)
    predicted = path_xy_mm(path)  # the toy moves the object by its actions, in its own unit
    np.testing.assert_allclose(predicted[1:], predicted[0] + np.cumsum(planned, 0), atol=1e-3)


def test_a_model_whose_actions_step_further_than_a_driver_takes_is_not_loaded(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"its actions step up to 0\.05 rad \(unit 0\.05 rad\), more than a driver "
                                         r"takes \(0\.0375 rad\)"):
        load_planner_model(toy_file(tmp_path / "far.safetensors", action_unit_rad=0.05))
    assert load_planner_model(toy_file(tmp_path / "edge.safetensors", action_unit_rad=0.0375)).action_unit_rad == 0.0375


def test_closing_the_node_stops_a_plan_under_way_and_publishes_nothing_of_it(ros, tmp_path: Path) -> None:
    """Ctrl-C during a long plan: the node stops at the plan's next chunk, not after the whole plan."""
    from toys import SlowToy

    from t42_transfer.nodes.planner_node import JOIN_TIMEOUT_S

    slow = save_model(SlowToy(step_s=0.05), tmp_path / "slow.safetensors", method="slow",
                      extra={"workspace": BOX.to_dict()})
    rig = Rig(ros, slow, **{**SMALL, "samples": 2000, "refine_iterations": 9})  # 20 chunks of 1 s: a 20 s plan
    rig.tick()
    rig.publish_goal(START_XY + [6.0, -4.0])
    assert ros.spin_until(lambda: not rig.planner.idle, 5.0)
    ros.spin_for(0.5)  # the plan is under way
    began = time.monotonic()
    rig.planner.close()
    assert time.monotonic() - began < JOIN_TIMEOUT_S  # joined: not waited out, and not the 20 s of the plan
    ros.spin_for(0.5)
    assert rig.results == [] and rig.trajectories == []


def test_candidates_are_off_by_default_and_k_paths_with_the_plan_first_when_asked(ros, rig: Rig) -> None:
    from t42_interfaces.msg import PlanCandidates

    from msg_adapters.planning import candidates_xy_mm

    got: list = rig.listen(PlanCandidates, names.PLAN_CANDIDATES, 10)
    assert rig.wait_graph(publishers={names.PLAN_CANDIDATES: 1})
    rig.tick()
    rig.goal(START_XY + [6.0, -4.0])
    ros.spin_for(0.3)
    assert got == []  # off by default: nothing published
    assert rig.planner.set_parameters([Parameter("candidates", value=4)])[0].successful
    assert not rig.planner.set_parameters([Parameter("candidates", value=-1)])[0].successful
    rig.paths.clear()
    rig.goal(START_XY + [-5.0, 3.0])
    assert ros.spin_until(lambda: got and rig.paths, 5.0), "no candidates published with the plan"
    (msg,) = got
    paths = candidates_xy_mm(msg)
    assert msg.header.frame_id == FRAME_ID and msg.header.stamp == rig.paths[-1].header.stamp
    assert len(paths) == 4 and np.array_equal(paths[0], path_xy_mm(rig.paths[-1]))  # the plan's own first
    assert all(np.allclose(p[0], paths[0][0]) for p in paths)  # all from the start planned from


def test_a_model_announced_before_the_node_starts_is_loaded_from_the_latched_topic(ros, toy: Path) -> None:
    tester = ros.node("announcer")
    announcer = tester.create_publisher(ModelUpdated, names.MODEL_UPDATED, profile(names.LATCHED))
    announcer.publish(ModelUpdated(path=str(toy), method="toy", episodes=3))
    rig = Rig(ros, "", **SMALL)
    assert ros.spin_until(lambda: rig.planner.model is not None, 10.0)
    assert rig.planner.model.path == str(toy)
    rig.tick()
    assert rig.goal(START_XY + [3.0, 3.0])["accepted"]


# --------------------------------------------------------------------------- refusals
def test_goal_before_any_hand_state_is_refused(rig: Rig) -> None:
    result = rig.goal(START_XY)
    assert not result["accepted"] and result["status"] == "no_state"
    assert "no object pose or joint states" in result["reason"]
    assert rig.trajectories == [] and rig.paths == []


def test_goal_before_the_model_exists_is_refused_until_it_is_announced(ros, tmp_path: Path) -> None:
    later = tmp_path / "later.safetensors"
    rig = Rig(ros, later, **SMALL)
    log = Rosout(ros, "planner")
    rig.tick()
    result = rig.goal(START_XY + [3.0, 0.0])
    assert result["status"] == "no_model" and "/t42/model_updated" in result["reason"]
    assert ros.spin_until(lambda: any("refused goal" in w for w in log.warnings()), 5.0)
    rig.announce(toy_file(later, method="late"))
    assert ros.spin_until(lambda: rig.planner.model is not None, 10.0)
    rig.tick()
    result = rig.goal(START_XY + [3.0, 0.0])
    assert result["accepted"] and result["method"] == "late"
    assert ros.spin_until(lambda: len(rig.trajectories) == 1, 5.0)


def test_goal_outside_the_workspace_is_refused(rig: Rig) -> None:
    rig.tick()
    result = rig.goal(START_XY + [100.0, 0.0])
    assert result["status"] == "goal_outside_workspace" and "outside the trained workspace" in result["reason"]
    x, y = START_XY + [100.0, 0.0]  # the goal and the workspace's extent (BOX: 40 mm each way), in mm
    extent = f"x {START_XY[0] - 40:.1f} to {START_XY[0] + 40:.1f} mm, y {START_XY[1] - 40:.1f} to"
    assert f"goal (x {x:.1f} mm, y {y:.1f} mm)" in result["reason"] and extent in result["reason"], result["reason"]
    assert result["horizon"] == 0 and result["predicted_error_mm"] is None
    assert rig.trajectories == [] and rig.paths == []


def test_unreachable_goal_is_refused_with_its_predicted_error(ros, tmp_path: Path) -> None:
    rig = Rig(ros, toy_file(tmp_path / "slow.safetensors", gain=0.1), **SMALL)
    rig.tick()
    result = rig.goal(START_XY + [20.0, 0.0])
    assert result["status"] == "unreachable" and result["predicted_error_mm"] > 3.0
    assert rig.trajectories == [] and rig.paths == []


@pytest.mark.parametrize("frame_id, x, why", [("map", 0.0, "frame 'map'"), (FRAME_ID, math.nan, "non-finite")])
def test_bad_goals_are_refused_and_the_node_keeps_planning(ros, rig: Rig, frame_id: str, x: float,
                                                           why: str) -> None:
    rig.tick()
    msg = goal_msg([0.0, 80.0], rig.now_ns(), RCLPY)
    msg.header.frame_id = frame_id
    msg.point.x = x
    rig.goal_pub.publish(msg)
    rig.wait_results(1)
    result = rig.results[0]
    assert result["status"] == "bad_goal" and why in result["reason"] and result["goal_mm"] is None
    assert rig.trajectories == []
    assert rig.goal(START_XY + [2.0, 2.0])["accepted"]
    assert ros.spin_until(lambda: len(rig.trajectories) == 1, 5.0)


@pytest.mark.parametrize("stamp_ns, why", [(1, "goal is stale"), (2_147_000_000 * 10**9, "in the future")],
                         ids=["1970", "2038"])
def test_goals_stamped_long_ago_or_ahead_are_refused_and_an_unset_stamp_means_now(rig: Rig, stamp_ns: int,
                                                                                   why: str) -> None:
    rig.tick()
    rig.goal_pub.publish(goal_msg(START_XY + [2.0, 2.0], stamp_ns, RCLPY))
    rig.wait_results(1)
    result = rig.results[0]
    assert result["status"] == "bad_goal" and why in result["reason"] and "limit 30.000 s" in result["reason"]
    assert result["goal_stamp_ns"] == stamp_ns and rig.trajectories == []  # the result names the goal it answers
    rig.goal_pub.publish(goal_msg(START_XY + [2.0, 2.0], 0, RCLPY))  # Foxglove's publish panel leaves it unset
    rig.wait_results(2)
    assert rig.results[1]["accepted"], rig.results[1]


def test_stale_hand_state_is_refused(ros, toy: Path) -> None:
    rig = Rig(ros, toy, **{**SMALL, "max_state_age_s": 0.2})
    rig.tick()
    ros.spin_for(0.3)  # the driver stops publishing
    result = rig.goal(START_XY + [2.0, 2.0])
    assert result["status"] == "stale_state" and "limit 0.200 s" in result["reason"]
    assert rig.trajectories == []
    rig.tick()  # the driver is back
    assert rig.goal(START_XY + [2.0, 2.0])["accepted"]


# --------------------------------------------------------------------------- concurrency
def test_state_is_tracked_during_a_long_plan_and_the_latest_goal_wins(ros, rig: Rig,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    rig.tick()
    planning, release = threading.Event(), threading.Event()
    original = Planner.plan

    def held_plan(self: Planner, *args: Any, **kwargs: Any) -> Any:  # the first plan waits for release
        if not planning.is_set():
            planning.set()
            assert release.wait(20.0)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Planner, "plan", held_plan)
    first, waiting, latest = START_XY + [3.0, 0.0], START_XY + [0.0, 3.0], START_XY + [-3.0, 0.0]
    rig.publish_goal(first)
    assert ros.spin_until(planning.is_set, 10.0)
    stamp = rig.planner.state_stamp_ns
    rig.tick(3)  # the planner keeps taking in the hand state while it plans
    assert rig.planner.state_stamp_ns > stamp and not rig.planner.idle
    rig.publish_goal(waiting)
    rig.publish_goal(latest)
    assert ros.spin_until(lambda: len(rig.results) == 1, 10.0)  # the waiting goal is replaced at once
    assert rig.results[0]["status"] == "superseded" and np.allclose(rig.results[0]["goal_mm"], waiting)
    assert rig.results[0]["reason"] == "a newer goal arrived"
    release.set()
    rig.wait_results(3)
    by_goal = {tuple(np.round(r["goal_mm"], 3)): r for r in rig.results}
    discarded, served = by_goal[tuple(np.round(first, 3))], by_goal[tuple(np.round(latest, 3))]
    assert discarded["status"] == "superseded" and "plan was discarded" in discarded["reason"]
    assert not discarded["accepted"] and served["accepted"] and rig.results[-1] is served
    assert ros.spin_until(lambda: len(rig.trajectories) == 1, 5.0)
    ros.spin_for(0.1)
    assert len(rig.trajectories) == 1 and len(rig.paths) == 1
    assert np.linalg.norm(path_xy_mm(rig.paths[0])[-1] - latest) <= 3.0


# --------------------------------------------------------------------------- model updates
def test_announced_model_replaces_the_old_and_bad_announcements_keep_it(ros, rig: Rig, tmp_path: Path) -> None:
    log = Rosout(ros, "planner")
    rig.tick()
    assert rig.goal(START_XY + [2.0, 0.0])["method"] == "toy"
    new = toy_file(tmp_path / "new.safetensors", method="new")
    rig.announce(new)
    assert ros.spin_until(lambda: rig.planner.model.path == str(new), 10.0)
    assert rig.goal(START_XY + [2.0, 0.0])["method"] == "new"

    (tmp_path / "broken.safetensors").write_bytes(b"not a model")
    no_workspace = toy_file(tmp_path / "bare.safetensors", method="bare", workspace=None)
    for bad, why in ((tmp_path / "missing.safetensors", "does not exist"),
                     (tmp_path / "broken.safetensors", "not a readable model file"),
                     (no_workspace, "stores no workspace")):
        log.lines.clear()
        rig.announce(bad)
        assert ros.spin_until(lambda: any("could not load model" in w for w in log.warnings()), 10.0), bad
        (warning,) = log.warnings()
        assert why in warning and "keeping model" in warning and "new.safetensors" in warning
        assert rig.planner.model.path == str(new)
    rig.tick()
    assert rig.goal(START_XY + [2.0, 0.0])["method"] == "new"


# --------------------------------------------------------------------------- parameters
def test_parameter_changes_apply_to_the_next_plan_and_bad_values_are_refused(rig: Rig) -> None:
    rig.tick()
    assert rig.goal(START_XY + [6.0, 0.0])["accepted"]
    (ok,) = rig.set(samples=50)
    assert ok.successful and rig.planner.params.samples == 50
    assert rig.goal(START_XY + [2.0, 0.0])["samples_evaluated"] == 50
    (ok,) = rig.set(refine_iterations=2)
    assert ok.successful
    assert rig.goal(START_XY + [2.0, 0.0])["samples_evaluated"] == 50 + 2 * (50 - 5)  # the 10 % elites kept a round
    (ok,) = rig.set(refine_iterations=0)
    (ok,) = rig.set(horizon=2)  # at most about 1.4 mm per step: 6 mm is out of reach now
    assert ok.successful
    rig.tick()
    short = rig.goal(START_XY + [6.0, 0.0])
    assert short["status"] == "unreachable" and short["horizon"] <= 2

    before = rig.planner.params
    for name, value, why in (("samples", 0, "range"), ("samples", "many", "type"),
                             ("tolerance_m", 0.0, "tolerance_mm must be positive"),
                             ("tolerance_m", math.inf, "finite"), ("max_state_age_s", -1.0, "range"),
                             ("model", "other.safetensors", "read-only"), ("torch_threads", 2, "read-only"),
                             ("rerank", -1, "range")):
        (refused,) = rig.set(**{name: value})
        assert not refused.successful and why in refused.reason, (name, refused.reason)
    assert rig.planner.params == before
    described = rig.planner.describe_parameter("samples")
    assert described.description and described.integer_range[0].from_value == 1
    assert rig.planner.describe_parameter("model").read_only
    assert rig.planner.params.torch_threads == 1 and torch.get_num_threads() == 1  # the node set it at start


def test_bad_startup_parameters_are_one_line_errors(ros) -> None:
    with pytest.raises(ValueError, match="max_state_age_s"):
        ros.add(PlannerNode, {"max_state_age_s": math.nan})


def test_works_under_a_namespace_with_remapped_names(ros) -> None:
    ros.add(PlannerNode, {"model": ""}, namespace="/left", cli_args=["--ros-args", "-r", "t42/goal:=aim"])
    tester = ros.node("ns_tester")
    results: list[dict] = []
    tester.create_subscription(PlanResultMsg, "/left/t42/plan_result",
                               lambda m: results.append(asdict(plan_result(m))), 10)
    goals = tester.create_publisher(PointStamped, "/left/aim", 10)
    assert ros.spin_until(lambda: goals.get_subscription_count() == 1
                          and tester.count_publishers("/left/t42/plan_result") == 1, 10.0)
    goals.publish(goal_msg(START_XY, tester.get_clock().now().nanoseconds, RCLPY))
    assert ros.spin_until(lambda: results, 10.0)
    assert results[0]["status"] == "no_model" and "/left/t42/model_updated" in results[0]["reason"]


# --------------------------------------------------------------------------- pure parts
def test_hand_state_joins_pose_and_loads_and_checks_freshness() -> None:
    xy, loads, angles = np.float32([1, 2]), np.float32([3, 4]), np.float32([0.1, 0.2])
    state = hand_state((100, xy), (100, loads, angles), 150, 100)
    assert state.state.dtype == np.float32 and state.state.tolist() == [1, 2, 3, 4]
    assert state.angles is angles
    with pytest.raises(Refused, match="no joint states"):
        hand_state((100, xy), None, 150, 100)
    with pytest.raises(Refused, match="no actuator angles"):
        hand_state((100, xy), (100, loads, None), 150, 100)
    for now in (201, -1):
        with pytest.raises(Refused, match="limit") as err:
            hand_state((100, xy), (100, loads, angles), now, 100)
        assert err.value.status == "stale_state"


@pytest.mark.parametrize("kwargs", [{"samples": 0}, {"horizon": 0}, {"tolerance_m": -0.001},
                                    {"tolerance_m": math.inf}, {"max_state_age_s": math.inf},
                                    {"max_state_age_s": 0.0}])
def test_params_validate_planner_fields(kwargs: dict) -> None:
    assert PlannerNodeParams(samples=5, horizon=3, tolerance_m=0.001).planner_config.samples == 5
    with pytest.raises(ValueError):
        PlannerNodeParams(**kwargs)


def test_the_planner_parameters_reach_the_planners_config() -> None:
    given = dict(samples=5, refine_iterations=2, horizon=3, horizon_search=True, seed=4, candidates=2,
                 warm_start=True)
    config = PlannerNodeParams(**given, tolerance_m=0.0015).planner_config  # type: ignore[arg-type]
    assert {name: getattr(config, name) for name in given} == given
    assert config.tolerance_mm == pytest.approx(1.5)  # the parameter in metres (REP 103), the planner in mm
    assert PlannerNodeParams(rerank=30).planner_config.rerank == 30
    with pytest.raises(ValueError, match="rerank chooses the answer of a fixed-length plan"):
        PlannerNodeParams(rerank=30, horizon_search=True)


# --------------------------------------------------------------------------- closed loop
def test_closed_loop_with_a_model_trained_on_target_data_moves_the_object_towards_the_goal(ros,
                                                                                           tmp_path: Path) -> None:
    from t42_transfer.data.bag import read_bag
    from t42_transfer.models.training import TrainConfig, train_transition_model
    from t42_transfer.planning.sampling import sample_actions

    data = read_bag(Path(__file__).resolve().parents[1] / "bags" / "target_small")
    model = train_transition_model(data, TrainConfig(epochs=5, patience=None))[0]
    workspace = Workspace.from_trajectories(data)
    path = save_model(model, tmp_path / "target.safetensors", method="target_only",
                      extra={"workspace": workspace.to_dict()})
    # The goal: where the true hand puts the object from the driver's grasp after 10 random steps (13.6 mm away).
    hand = SimulatedHand("target")
    hand.reset(0)
    for action in sample_actions("piecewise", 1, 10, torch.Generator().manual_seed(6))[0].numpy():
        hand.step_info(action.astype(np.float64))
    goal = hand.state[:2].copy()
    assert not hand.done and workspace.contains_xy(torch.as_tensor(goal, dtype=torch.float32))

    rig = Rig(ros, path, samples=300, horizon=30, horizon_search=True, tolerance_m=0.005, max_state_age_s=5.0)
    rig.tick()
    start = rig.driver.hand.state[:2].copy()
    result = rig.goal(goal)
    assert result["accepted"], result
    assert ros.spin_until(lambda: rig.driver.pending_actions == result["horizon"], 5.0)
    rig.tick(result["horizon"] + 1)
    final = rig.driver.hand.state[:2]
    assert rig.driver.running and rig.driver.pending_actions == 0
    assert np.linalg.norm(final - goal) < np.linalg.norm(start - goal), (start, final, goal)


def test_replan_every_k_sends_k_steps_at_a_time_each_planned_from_the_measured_state(ros, toy: Path) -> None:
    rig = Rig(ros, toy, **{**SMALL, "horizon": 15, "horizon_search": False, "replan_every": 5})
    poses = rig.listen(PoseStamped, names.OBJECT_POSE)
    assert rig.wait_graph(subscribers={names.OBJECT_POSE: 2}), "discovery"
    rig.tick()
    rig.publish_goal(START_XY + [6.0, -4.0])
    assert ros.spin_until(lambda: rig.results, 20.0)
    result = rig.results[0]
    assert result["accepted"] and result["horizon"] == 15 and result["replan_every"] == 5, result
    assert not rig.planner.idle  # the closed loop runs until its last piece is sent
    for piece in range(3):
        assert ros.spin_until(lambda piece=piece: len(rig.trajectories) == piece + 1 and len(rig.paths) == piece + 1,
                              10.0), piece
        traj, path = rig.trajectories[-1], rig.paths[-1]
        assert len(traj.points) == 5
        assert len(path.poses) == 15 - 5 * piece + 1  # the whole rest is planned, its first 5 steps sent
        assert np.allclose(path_xy_mm(path)[0], object_xy_mm(poses[-1]), atol=1e-3)  # from the measured state
        assert ros.spin_until(lambda: rig.driver.pending_actions == 5, 5.0)
        rig.tick(6)  # the piece, then the step that publishes the state after it
    assert ros.spin_until(lambda: rig.planner.idle, 5.0)
    ros.spin_for(0.3)
    assert len(rig.trajectories) == 3 and len(rig.results) == 1  # one result per goal, replans or not


@pytest.mark.parametrize("warm_start", [True, False])
def test_a_warm_replan_of_one_sequence_sends_on_its_first_plan(ros, toy: Path, warm_start: bool) -> None:
    """The node hands each replan the rest of its plan: a one-sequence warm search can only return that rest,
    so every replanned path moves as the first plan's rest does (the toy moves by its actions); cold, it does
    not.  (A wide tolerance: one random sequence must be accepted.)"""
    rig = Rig(ros, toy, **{**SMALL, "samples": 1, "horizon": 15, "horizon_search": False, "replan_every": 5,
                           "tolerance_m": 0.05, "warm_start": warm_start})
    assert rig.wait_graph(subscribers={names.OBJECT_POSE: 1}), "discovery"
    rig.tick()
    rig.publish_goal(START_XY + [6.0, -4.0])
    assert ros.spin_until(lambda: rig.results, 20.0) and rig.results[0]["accepted"], rig.results
    for piece in range(3):
        assert ros.spin_until(lambda piece=piece: len(rig.trajectories) == len(rig.paths) == piece + 1, 10.0), piece
        assert ros.spin_until(lambda: rig.driver.pending_actions == 5, 5.0)
        rig.tick(6)
    first, *replans = (np.diff(path_xy_mm(path), axis=0) for path in rig.paths)
    assert [len(moves) for moves in replans] == [10, 5]
    followed = [np.allclose(moves, first[5 * (i + 1):], atol=1e-3) for i, moves in enumerate(replans)]
    assert followed == [warm_start] * 2


def test_a_refused_replan_keeps_the_rest_of_the_previous_plan_as_execute_does(ros, toy: Path) -> None:
    """The node and :func:`execute` share one MPC rule: a replan without a safe sequence sends on the old plan."""
    k, horizon = 5, 15
    rig = Rig(ros, toy, driver=False, **{**SMALL, "horizon": horizon, "horizon_search": False, "replan_every": k})
    state_pub = rig.tester.create_publisher(PoseStamped, names.OBJECT_POSE, 10)
    joints_pub = rig.tester.create_publisher(JointState, names.JOINT_STATES, 10)
    status_pub = rig.tester.create_publisher(String, names.HAND_STATUS, profile(names.EVENTS))
    assert ros.spin_until(lambda: state_pub.get_subscription_count() == joints_pub.get_subscription_count()
                          == status_pub.get_subscription_count() == 1, 10.0), "discovery"
    angles = np.zeros(2, np.float32)

    def publish_state(xy: np.ndarray, stamp: int) -> None:
        state_pub.publish(object_pose_msg(xy.astype(np.float32), stamp, RCLPY))
        joints_pub.publish(joint_state_msg(np.zeros(2, np.float32), angles, stamp, RCLPY))

    start_stamp = rig.now_ns()
    publish_state(START_XY, start_stamp)
    assert ros.spin_until(lambda: rig.planner.state_stamp_ns == start_stamp, 5.0)
    rig.publish_goal(START_XY + [6.0, -4.0])
    # the path goes out just after the trajectory: wait for it too (an IndexError at rig.paths[0], 1 run in 2)
    assert ros.spin_until(lambda: rig.results and rig.trajectories and rig.paths, 20.0)
    assert rig.results[0]["accepted"], rig.results[0]
    first = np.diff(path_xy_mm(rig.paths[0]), axis=0)  # the toy moves (x, y) by the action: its actions
    assert len(first) == horizon

    # the piece ran: the hand is now far outside the model's workspace, so every replan is refused
    status_pub.publish(String(data=status_message(names.TRAJECTORY_DONE, "piece", start_stamp)))
    publish_state(START_XY + [100.0, 0.0], start_stamp + 1)
    assert ros.spin_until(lambda: len(rig.trajectories) == 2, 10.0), "no second piece"
    sent = joint_trajectory_to_actions(rig.trajectories[1], angles)
    assert np.allclose(sent, first[k:2 * k], atol=1e-3)  # the old plan's next piece, not holding still

    # the same rule in execute(): the first plan, then replans refused
    plans = iter([first, *[np.zeros((0, 2))] * 2])
    hand = ToyHand(1.0, np.concatenate([START_XY, [0.0, 0.0]]))
    run = execute(hand, lambda state, left, _: _plan_of(next(plans)), horizon, k)
    assert np.allclose(run.actions, first, atol=1e-6) and run.completed and len(run.plans) == 3


def _plan_of(actions: np.ndarray) -> Plan:
    """A plan of ``actions`` (none: refused, as the planner refuses when no sequence is safe)."""
    ok = len(actions) > 0
    return Plan(ok, "ok" if ok else "no_safe_sequence", "", actions.astype(np.float32),
                np.zeros((len(actions) + 1, 4), np.float32), 0.0 if ok else math.inf, np.zeros(2, np.float32))


def test_run_time_sizes_are_bounded_as_the_cli_bounds_them(rig: Rig) -> None:
    """``samples`` 1e12 once passed and then failed to allocate 8e14 bytes at the next goal."""
    (ok,) = rig.set(horizon=100)
    assert ok.successful
    before = rig.planner.params
    for change, why in (({"samples": 10**12}, "range"), ({"horizon": 10**6}, "range"),
                        ({"samples": 500_000}, "sampled steps")):  # x the horizon of 100
        (refused,) = rig.set(**change)
        assert not refused.successful and why in refused.reason, (change, refused.reason)
    assert rig.planner.params == before
    rig.tick()
    assert rig.goal(START_XY + [2.0, 0.0])["accepted"]


def test_a_plan_stopped_before_its_first_piece_went_out_gets_a_result_saying_why() -> None:
    goal, planned = Goal(np.array([1.0, 2.0]), 7), PlanResult(True, "ok", "", [1.0, 2.0], 7, horizon=10)
    cancelled = unsent(goal, planned, cancelled=True, episode_ended=True)
    ended = unsent(goal, planned, cancelled=False, episode_ended=True)
    newer = unsent(goal, planned, cancelled=False, episode_ended=False)
    assert [(r.status, r.reason) for r in (cancelled, ended, newer)] == [
        (names.SUPERSEDED, "cancelled while it was planned"),
        ("episode_ended", "the episode ended before the plan was sent (reset the hand)"),
        (names.SUPERSEDED, "a newer goal arrived while it was planned; the plan was discarded")]
    assert all(not r.accepted and r.goal_stamp_ns == 7 and r.horizon == 10 for r in (cancelled, ended, newer))


def test_a_burst_of_2000_goals_gets_2000_results(ros, toy: Path) -> None:
    """Each goal is planned, superseded by a newer one, or refused, and says so (1645 of 2000 got nothing; then,
    on a busy machine, 1-3: a goal planned and superseded before its first piece went out)."""
    rig = Rig(ros, toy, **SMALL)
    results: list[dict] = []
    rig.tester.create_subscription(PlanResultMsg, names.PLAN_RESULT,
                                   lambda m: results.append(asdict(plan_result(m))), profile(names.RESULTS))
    rig.tick()
    ros.spin_for(0.3)
    results.clear()
    goals = rig.tester.create_publisher(PointStamped, names.GOAL, profile(names.REQUESTS))
    assert ros.spin_until(lambda: goals.get_subscription_count() == 1, 10.0)
    start = rig.now_ns()
    for k in range(2000):
        goals.publish(goal_msg(START_XY + [2.0, 0.0], start + k, RCLPY))  # the stamp names the goal
        ros.executor.spin_once(timeout_sec=0.0)
    assert ros.spin_until(lambda: len(results) >= 2000, 60.0), \
        sorted(set(range(2000)) - {r["goal_stamp_ns"] - start for r in results})  # the goals without a result
    ros.spin_for(0.5)
    assert sorted(r["goal_stamp_ns"] for r in results) == [start + k for k in range(2000)]  # one each, no more
    assert all(r["accepted"] or (r["status"] and r["reason"]) for r in results)  # planned, or refused saying why
    assert any(r["status"] == names.SUPERSEDED for r in results)  # the burst outran the planner
