"""The real-hand chain with a source model in the paper authors' action unit, on the simulated hand's driver: the
explorer records in that unit, the transfer reads the bags in it and keeps it, the planner sends its steps."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from geometry_msgs.msg import PointStamped
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import RCLPY, goal_msg, joint_trajectory_to_actions, names
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.bag import read_bag
from t42_transfer.hand.collect import RandomPolicy
from t42_transfer.models.checkpoint import UNIT_KEY, read_metadata, save_model
from t42_transfer.models.network import Normalisation, TransitionModel
from t42_transfer.models.training import TrainConfig
from t42_transfer.nodes.explorer import Explorer
from t42_transfer.nodes.mock_driver import MockDriver
from t42_transfer.nodes.planner_node import PlannerNode
from t42_transfer.nodes.recorder import Recorder
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.online import OnlineTransferSpec, run_transfer

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

SIM = {"use_sim_time": True}
EPISODES, STEPS = 4, 40


def test_an_authors_unit_source_is_transferred_on_bags_recorded_in_its_unit_and_plans_its_own_steps(
        ros, tmp_path: Path) -> None:
    driver = ros.add(MockDriver, {"hand": "target", "rate_factor": 10.0, "seed": 7, "sim_time": True,
                                  "max_command_age_s": 300.0})
    recorder = ros.add(Recorder, {"out_dir": str(tmp_path / "bags"), "mode": "episode", "start_immediately": False,
                                  **SIM})
    explorer = ros.add(Explorer, {"rate_factor": 10.0, "timeout_margin_s": 30.0, "episodes": EPISODES,
                                  "steps": STEPS, "seed": 3, "action_unit_rad": AUTHORS_ACTION_UNIT_RAD,
                                  "record_start_service": "recorder/start", "record_stop_service": "recorder/stop",
                                  **SIM})
    assert ros.spin_until(lambda: explorer.finished, 120.0), f"not finished: {explorer.completed}"
    assert ros.spin_until(lambda: not recorder.recording and not recorder.waiting_changes, 10.0)
    assert len(recorder.bags) == EPISODES, recorder.bags
    # The bags hold the actuators' steps: read in the authors' unit they are the actions sampled in it.
    for k, bag in enumerate(recorder.bags):
        (episode,) = read_bag(bag, AUTHORS_ACTION_UNIT_RAD)
        moved = episode.actions[np.abs(episode.actions).sum(axis=1) > 0]
        sampled = RandomPolicy(hold_max=5, limit=1.0).sample(np.random.default_rng(3 + k), STEPS)
        np.testing.assert_allclose(moved, sampled, atol=1e-5)

    still = TransitionModel(Normalisation.identity(), hidden=16, dropout=0.0)
    with torch.no_grad():
        for p in still.net.parameters():
            p.zero_()  # predicts no change: what the hand does with its actions comes from the bags
    source = save_model(still, tmp_path / "authors.safetensors", method="source",
                        action_unit_rad=AUTHORS_ACTION_UNIT_RAD)  # in the authors' unit, as their imports are
    fast = TrainConfig(epochs=40, patience=None, lr=3e-3)
    config = dataclasses.replace(TransferConfig(), naive_finetune=dataclasses.replace(
        TransferConfig().naive_finetune, train=fast))
    spec = OnlineTransferSpec(source_model=source, model_dir=tmp_path / "models", bag_dir=tmp_path / "bags",
                              method="naive_finetune", config=config)
    result = run_transfer(spec)
    assert result.episodes + result.held_out_episodes == EPISODES and not result.skipped_bags, result.summary()
    assert read_metadata(result.model_path)[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD

    # A full-length plan, any within 20 mm accepted: the units are under test here, not the aim.
    planner = ros.add(PlannerNode, {"model": str(result.model_path), "samples": 200, "refine_iterations": 0,
                                    "horizon": 20, "horizon_search": False, "tolerance_m": 0.02,
                                    "max_state_age_s": 300.0, **SIM})
    tester = ros.node("tester")
    trajectories: list[JointTrajectory] = []
    statuses: list[str] = []
    tester.create_subscription(JointTrajectory, names.HAND_TRAJECTORY, trajectories.append, 10)
    tester.create_subscription(String, names.HAND_STATUS, lambda m: statuses.append(m.data), 10)
    goals = tester.create_publisher(PointStamped, names.GOAL, 10)
    assert ros.call(tester.create_client(Trigger, names.HAND_RESET), Trigger.Request(), 30.0).success  # a new grasp
    grasped = planner.state_stamp_ns or 0
    assert ros.spin_until(lambda: (planner.state_stamp_ns or 0) > grasped and goals.get_subscription_count(), 20.0)
    start = driver.hand.state[:2].astype(np.float32)
    before = len(statuses)
    goals.publish(goal_msg(start + np.float32([2.0, 0.0]), 0, RCLPY))  # (stamp 0: now, on whichever clock)
    assert ros.spin_until(lambda: trajectories, 30.0), "no trajectory sent"
    angles = driver.hand.actuator_angles
    steps = np.diff(np.vstack([angles, [p.positions for p in trajectories[0].points]]), axis=0)
    assert 0 < np.abs(steps).max() <= AUTHORS_ACTION_UNIT_RAD * (1 + 1e-6)  # the model's steps, not 0.025 rad
    np.testing.assert_allclose(joint_trajectory_to_actions(trajectories[0], angles),
                               steps / ACTION_UNIT_RAD, atol=1e-5)
    ros.spin_for(1.0)
    assert not [s for s in statuses[before:] if s.startswith("refused")], statuses[before:]
