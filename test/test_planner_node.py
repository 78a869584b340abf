"""The planner node on the in-process bus, with the mock driver and a fake clock."""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path

from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from msg_adapters import (
    JOINT_TRAJECTORY,
    PATH,
    POINT_STAMPED,
    goal_msg,
    joint_trajectory_to_actions,
    path_xy_mm,
    stamp_to_ns,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS, FRAME_ID
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.models import LatentDynamics
from t42_transfer.models.checkpoint import save_model
from t42_transfer.nodes.mock_driver import MockDriver, MockDriverParams
from t42_transfer.nodes.planner_node import (
    GOAL_TOPIC,
    MODEL_UPDATED_TOPIC,
    PATH_TOPIC,
    RESULT_TOPIC,
    STRING,
    TRAJECTORY_TOPIC,
    PlannerNode,
    PlannerNodeParams,
    Refused,
    hand_state,
)
from t42_transfer.planning import Workspace
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport
from t42_transfer.ros.transport import message_class

pytestmark = pytest.mark.usefixtures("one_torch_thread")

START_NS = 1_000_000_000
GRASP = SimulatedHand("target")
GRASP.reset(0)
START_XY = GRASP.state[:2].copy()
"""Where the mock driver (seed 0) holds the object after its first grasp."""
BOX = Workspace.box(START_XY[0] - 40, START_XY[0] + 40, START_XY[1] - 40, START_XY[1] + 40)
SMALL = dict(samples=200, horizon=20, tolerance_mm=3.0)


class LinearHand(LatentDynamics):
    """Toy model: ``(x, y) += gain @ a`` mm per step, loads unchanged."""

    kind = "test_planner_node_linear"

    def __init__(self, gain: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("gain", torch.eye(2) * gain)

    def config(self) -> dict:
        return {}

    @classmethod
    def from_config(cls, config: dict) -> "LinearHand":
        return cls()

    def initial_latent(self, x0: Tensor) -> Tensor:
        return x0

    def latent_step(self, z: Tensor, action: Tensor) -> Tensor:
        return torch.cat([z[:, :2] + action @ self.gain.T, z[:, 2:]], -1)

    def observe(self, z: Tensor) -> Tensor:
        return z


def toy_file(path: Path, method: str = "toy", gain: float = 1.0, workspace: Workspace | None = BOX) -> Path:
    extra = {"workspace": workspace.to_dict()} if workspace is not None else None
    return save_model(LinearHand(gain), path, method=method, extra=extra)


class Rig:
    """Mock driver, planner node and a tester node on one bus; the driver steps on a fake clock."""

    def __init__(self, model: Path | str = "", **params: object) -> None:
        self.clock = FakeClock(START_NS)
        self.bus = InProcessBus(clock=self.clock)
        self.tester = InProcessTransport(self.bus, "tester")
        self.results: list[dict] = []
        self.trajectories: list = []
        self.paths: list = []
        self.tester.subscribe(RESULT_TOPIC, STRING, qos.DEFAULT, lambda m: self.results.append(json.loads(m.data)))
        self.tester.subscribe(TRAJECTORY_TOPIC, JOINT_TRAJECTORY, qos.DEFAULT, self.trajectories.append)
        self.tester.subscribe(PATH_TOPIC, PATH, qos.DEFAULT, self.paths.append)
        self.goal_pub = self.tester.publisher(GOAL_TOPIC, POINT_STAMPED)
        self.model_pub = self.tester.publisher(MODEL_UPDATED_TOPIC, STRING, qos.TRANSIENT_LOCAL)
        self.driver_node = InProcessTransport(self.bus, "mock_driver")
        self.driver = MockDriver(self.driver_node, MockDriverParams())
        self.planner_node = InProcessTransport(self.bus, "planner")
        self.node = PlannerNode(self.planner_node, PlannerNodeParams(model=str(model), **params))  # type: ignore[arg-type]

    def tick(self, n: int = 1) -> None:
        """``n`` driver steps; the planner takes in the state each publishes."""
        for _ in range(n):
            self.clock.advance(0.1)
            self.driver_node.spin_once()
            self.planner_node.spin_once()

    def announce(self, path: Path | str) -> None:
        self.model_pub.publish(message_class(STRING)(data=str(path)))
        self.planner_node.spin_once()

    def goal(self, xy: np.ndarray | list[float], frame_id: str = FRAME_ID) -> dict:
        """Send a goal and wait for its result."""
        msg = goal_msg(np.asarray(xy, np.float32), self.clock())
        msg.header.frame_id = frame_id
        return self.send(msg)

    def send(self, msg: object, results: int = 1) -> dict:
        expected = len(self.results) + results
        self.goal_pub.publish(msg)
        deadline = time.monotonic() + 10.0
        while (len(self.results) < expected or not self.node.idle) and time.monotonic() < deadline:
            self.planner_node.spin_once()
            self.tester.spin_once(0.01)
        self.tester.spin_once()
        assert len(self.results) == expected, "no plan result within 10 s"
        return self.results[-1]

    def close(self) -> None:
        self.node.close()
        self.driver.close()
        for node in (self.planner_node, self.driver_node, self.tester):
            node.close()


@pytest.fixture
def toy(tmp_path: Path) -> Path:
    return toy_file(tmp_path / "toy.safetensors")


@pytest.fixture
def rig(toy: Path):
    rig = Rig(toy, **SMALL)
    yield rig
    rig.close()


def driver_warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.endswith("mock_driver") and r.levelno >= logging.WARNING]


# --------------------------------------------------------------------------- accepted plans
def test_goal_gives_a_trajectory_the_driver_executes_and_its_predicted_path(rig: Rig, caplog) -> None:
    caplog.set_level(logging.INFO)
    rig.tick()
    goal = START_XY + [6.0, -4.0]
    result = rig.goal(goal)
    assert result["accepted"] and result["status"] == "ok", result
    assert result["method"] == "toy" and result["samples_evaluated"] == 200 and result["planning_time_s"] > 0
    assert np.allclose(result["goal_mm"], goal) and np.allclose(result["start_mm"], START_XY, atol=0.5)
    assert result["predicted_error_mm"] <= 3.0
    (traj,), (path,) = rig.trajectories, rig.paths
    steps = result["horizon"]
    assert 1 <= steps <= 20 and len(traj.points) == steps and len(path.poses) == steps + 1
    stamp = stamp_to_ns(traj.header.stamp)
    assert stamp == rig.clock() and stamp_to_ns(path.header.stamp) == stamp
    assert [stamp_to_ns(p.header.stamp) for p in path.poses] == [stamp + k * CONTROL_PERIOD_NS for k in range(steps + 1)]
    predicted = path_xy_mm(path)
    actions = joint_trajectory_to_actions(traj, rig.driver.hand.actuator_angles)
    assert np.all(np.abs(actions) <= 1.0 + 1e-5)
    assert np.allclose(predicted[1:], predicted[0] + np.cumsum(actions, 0), atol=1e-3)  # the toy's prediction
    assert np.linalg.norm(predicted[-1] - goal) <= 3.0

    rig.driver_node.spin_once()
    assert rig.driver.pending_actions == steps and not driver_warnings(caplog)
    rig.tick(steps)
    assert rig.driver.pending_actions == 0 and not driver_warnings(caplog)


def test_a_model_announced_before_the_node_starts_is_loaded_from_the_latched_topic(toy: Path) -> None:
    rig = Rig("", **SMALL)
    try:
        rig.node.close()
        rig.planner_node.close()
        rig.model_pub.publish(message_class(STRING)(data=str(toy)))
        rig.planner_node = InProcessTransport(rig.bus, "planner2")
        rig.node = PlannerNode(rig.planner_node, PlannerNodeParams(**SMALL))  # type: ignore[arg-type]
        rig.tick()
        assert rig.node.model is not None and rig.node.model.path == str(toy)
        assert rig.goal(START_XY + [3.0, 3.0])["accepted"]
    finally:
        rig.close()


# --------------------------------------------------------------------------- refusals
def test_goal_before_any_hand_state_is_refused(rig: Rig) -> None:
    result = rig.goal(START_XY)
    assert not result["accepted"] and result["status"] == "no_state"
    assert "no object pose or joint states" in result["reason"]
    assert rig.trajectories == [] and rig.paths == []


def test_goal_before_the_model_exists_is_refused_until_it_is_announced(tmp_path: Path, caplog) -> None:
    caplog.set_level(logging.INFO)
    later = tmp_path / "later.safetensors"
    rig = Rig(later, **SMALL)
    try:
        rig.tick()
        result = rig.goal(START_XY + [3.0, 0.0])
        assert result["status"] == "no_model" and MODEL_UPDATED_TOPIC in result["reason"]
        assert rig.trajectories == [] and any("refused goal" in r.getMessage() for r in caplog.records)
        rig.announce(toy_file(later, method="late"))
        rig.tick()
        result = rig.goal(START_XY + [3.0, 0.0])
        assert result["accepted"] and result["method"] == "late" and len(rig.trajectories) == 1
    finally:
        rig.close()


def test_goal_outside_the_workspace_is_refused(rig: Rig) -> None:
    rig.tick()
    result = rig.goal(START_XY + [100.0, 0.0])
    assert result["status"] == "goal_outside_workspace" and "outside the trained workspace" in result["reason"]
    assert result["horizon"] == 0 and result["predicted_error_mm"] is None
    assert rig.trajectories == [] and rig.paths == []


def test_unreachable_goal_is_refused_with_its_predicted_error(tmp_path: Path) -> None:
    rig = Rig(toy_file(tmp_path / "slow.safetensors", gain=0.1), **SMALL)
    try:
        rig.tick()
        result = rig.goal(START_XY + [20.0, 0.0])
        assert result["status"] == "unreachable" and result["predicted_error_mm"] > 3.0
        assert rig.trajectories == [] and rig.paths == []
    finally:
        rig.close()


@pytest.mark.parametrize("frame_id, xy, why", [("map", [0.0, 80.0], "frame 'map'"),
                                              (FRAME_ID, [math.nan, 80.0], "non-finite")])
def test_bad_goals_are_refused_and_the_node_keeps_planning(rig: Rig, frame_id: str, xy: list[float],
                                                           why: str) -> None:
    rig.tick()
    msg = goal_msg([0.0, 80.0], rig.clock())
    msg.header.frame_id = frame_id
    msg.point.x = xy[0] / 1000.0
    result = rig.send(msg)
    assert result["status"] == "bad_goal" and why in result["reason"] and result["goal_mm"] is None
    assert rig.trajectories == []
    assert rig.goal(START_XY + [2.0, 2.0])["accepted"] and len(rig.trajectories) == 1


def test_stale_hand_state_is_refused(rig: Rig) -> None:
    rig.tick()
    rig.clock.advance(1.0)  # the driver stops publishing
    result = rig.goal(START_XY + [2.0, 2.0])
    assert result["status"] == "stale_state" and "1.000 s" in result["reason"]


def test_an_older_goal_is_superseded_by_a_newer_one(rig: Rig) -> None:
    rig.tick()
    planner = rig.node._model.planner
    planning, release = threading.Event(), threading.Event()
    original = planner.plan

    def held_plan(*args: Any, **kwargs: Any) -> Any:  # the first plan waits until the second goal is queued
        planning.set()
        release.wait(10.0)
        return original(*args, **kwargs)

    planner.plan = held_plan
    before = len(rig.results)
    rig.goal_pub.publish(goal_msg(START_XY + [3.0, 0.0], rig.clock()))
    rig.planner_node.spin_once()
    assert planning.wait(10.0)
    planner.plan = original
    rig.goal_pub.publish(goal_msg(START_XY + [0.0, 3.0], rig.clock()))
    rig.planner_node.spin_once()
    release.set()
    deadline = time.monotonic() + 10.0
    while (len(rig.results) < before + 2 or not rig.node.idle) and time.monotonic() < deadline:
        rig.planner_node.spin_once()
        rig.tester.spin_once(0.01)
    rig.tester.spin_once()
    assert len(rig.results) == before + 2
    results = rig.results[-1]
    first, second = rig.results[-2:]
    assert first["status"] == "superseded" and not first["accepted"] and "newer goal" in first["reason"]
    assert results is second and second["accepted"] and np.allclose(second["goal_mm"], START_XY + [0.0, 3.0])
    assert len(rig.trajectories) == 1


# --------------------------------------------------------------------------- model updates
def test_announced_model_replaces_the_old_and_bad_announcements_keep_it(rig: Rig, tmp_path: Path, caplog) -> None:
    rig.tick()
    assert rig.goal(START_XY + [2.0, 0.0])["method"] == "toy"
    rig.announce(toy_file(tmp_path / "new.safetensors", method="new"))
    assert rig.goal(START_XY + [2.0, 0.0])["method"] == "new"

    (tmp_path / "broken.safetensors").write_bytes(b"not a model")
    no_workspace = toy_file(tmp_path / "bare.safetensors", method="bare", workspace=None)
    for bad, why in ((tmp_path / "missing.safetensors", "does not exist"),
                     (tmp_path / "broken.safetensors", "not a readable model file"),
                     (no_workspace, "stores no workspace")):
        caplog.clear()
        rig.announce(bad)
        rig.tick()
        (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert why in warning and "keeping model" in warning and "new.safetensors" in warning
        assert rig.goal(START_XY + [2.0, 0.0])["method"] == "new"


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


def test_params_validate_planner_fields_and_names() -> None:
    assert PlannerNodeParams(samples=5, horizon=3, tolerance_mm=1.0).planner_config.samples == 5
    with pytest.raises(ValueError):
        PlannerNodeParams(samples=0)
    with pytest.raises(ValueError):
        PlannerNodeParams(tolerance_mm=-1.0)
    with pytest.raises(ValueError):
        PlannerNodeParams(max_state_age_s=math.inf)
    with pytest.raises(ValueError):
        PlannerNodeParams(goal_topic="not a topic")


# --------------------------------------------------------------------------- closed loop
def test_closed_loop_with_a_model_trained_on_target_data_moves_the_object_towards_the_goal(tmp_path: Path) -> None:
    from t42_transfer.data.bag_io import read_bag
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

    rig = Rig(path, samples=300, horizon=30, tolerance_mm=5.0)
    try:
        rig.tick()
        start = rig.driver.hand.state[:2].copy()
        result = rig.goal(goal)
        assert result["accepted"], result
        rig.driver_node.spin_once()
        rig.tick(result["horizon"] + 1)
        final = rig.driver.hand.state[:2]
        assert rig.driver.running and rig.driver.pending_actions == 0
        assert np.linalg.norm(final - goal) < np.linalg.norm(start - goal), (start, final, goal)
    finally:
        rig.close()
