"""A stock ROS 2 graph uses the suite: a plain rclpy script (test/stock_user.py, importing nothing of
ours) against ``t42 up``; and two suites (two simulated hands) side by side under two namespaces."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from ros_rig import REPO, start_node, stop

from t42_transfer.planning import PlannerConfig
from t42_transfer.ros.launcher import namespace_args

STOCK_USER = Path(__file__).with_name("stock_user.py")
T42 = [sys.executable, "-u", "-m", "t42_transfer.cli"]


def suite_file(root: Path, source: Path, seed: int = 0) -> Path:
    """A params file for the suite and the explorer, everything under ``root``, tiny sizes.

    The driver runs faster than real time, so it is the graph's clock (``sim_time``) and every
    other node runs with ``use_sim_time``: stamps stay one control period apart.
    """
    methods = root / "transfer_methods.yaml"
    methods.write_text(yaml.safe_dump({"naive_finetune": {"train": {"epochs": 2}}}))

    def node(**params: Any) -> dict[str, Any]:
        return {"ros__parameters": params}

    config = {  # "/**/name": the node under any namespace
        "mock_driver": node(hand="target", rate_factor=5.0, seed=seed, sim_time=True, max_command_age_s=5.0),
        "recorder": node(out_dir=str(root / "bags"), mode="episode", start_immediately=False, use_sim_time=True),
        "transfer_server": node(source_model=str(source), model_dir=str(root / "models"),
                                bag_dir=str(root / "bags"), method="naive_finetune", config=str(methods),
                                min_episodes=2, use_sim_time=True),
        "planner": node(model=str(root / "models" / "current.safetensors"), samples=128, horizon=10,
                        tolerance_m=0.01, max_state_age_s=5.0, use_sim_time=True),
        "explorer": node(episodes=3, steps=30, seed=seed + 1, rate_factor=5.0, use_sim_time=True,
                         record_start_service="recorder/start", record_stop_service="recorder/stop"),
    }
    path = root / "suite.yaml"
    path.write_text(yaml.safe_dump({f"/**/{name}": section for name, section in config.items()}, sort_keys=False))
    return path


class Suite:
    """``t42 up`` of a params file (optionally under a namespace), its output in a log file."""

    def __init__(self, params: Path, namespace: str = "") -> None:
        self.params, self.namespace = params, namespace
        self.log = params.with_suffix(f".{namespace.strip('/') or 'root'}.log")
        cmd = [*T42, "up", str(params), "--only", "mock_driver,recorder,transfer_server,planner",
               "--stop-timeout", "10"]
        if namespace:
            cmd += ["--namespace", namespace]
        with self.log.open("w") as out:
            self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=out, stderr=subprocess.STDOUT,
                                         env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def start_explorer(self) -> subprocess.Popen:
        """The explorer (its section of the params file) as a process."""
        args = ["--params-file", str(self.params), *namespace_args(self.namespace)]
        log = self.params.with_suffix(f".explorer.{self.namespace.strip('/') or 'root'}.log")
        return start_node("explorer", *args, log=log)

    def explore(self, timeout_s: float = 180.0) -> int:
        """Run the explorer to completion; its exit code."""
        return explore_all([self], timeout_s)[0]

    def output(self) -> str:
        return self.log.read_text()

    def stop(self) -> int:
        return stop([self.proc], timeout_s=60.0)[0]


def explore_all(suites: list[Suite], timeout_s: float = 180.0) -> list[int]:
    """Run the suites' explorers at the same time (each hand on its own graph or namespace); their exit codes."""
    procs = [suite.start_explorer() for suite in suites]
    try:
        return [proc.wait(timeout=timeout_s) for proc in procs]
    finally:
        stop(procs)


def stock_user(mode: str, namespace: str = "", timeout_s: float = 600.0) -> dict[str, Any]:
    """Run the plain rclpy script; what it saw (it prints one JSON object)."""
    proc = subprocess.run([sys.executable, str(STOCK_USER), mode, namespace], capture_output=True, text=True,
                          timeout=timeout_s, cwd=STOCK_USER.parent, env=dict(os.environ, PYTHONPATH=""))
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert lines, proc.stdout + proc.stderr
    result = json.loads(lines[-1])
    assert proc.returncode == 0 and "error" not in result, (result, proc.stderr[-3000:])
    return result


def test_stock_user_script_imports_nothing_of_ours() -> None:
    text = STOCK_USER.read_text()
    assert "t42_transfer" not in text and "msg_adapters" not in text and "ros_rig" not in text


def test_a_stock_rclpy_script_uses_the_suite(tmp_path: Path, source_model: Path, ros_domain: int) -> None:
    suite = Suite(suite_file(tmp_path, source_model))
    try:
        seen = stock_user("graph")
        assert {"/mock_driver", "/recorder", "/transfer_server", "/planner"} <= set(seen["nodes"])
        params = seen["parameters"]
        assert {"rate_factor", "hand", "seed", "use_sim_time"} <= set(params["mock_driver"])
        assert {"samples", "refine_iterations", "replan_every", "piece_timeout_s", "tolerance_m",
                "use_sim_time"} <= set(params["planner"])
        assert "source_model" in params["transfer_server"] and "out_dir" in params["recorder"]
        ok, reason = seen["bad_set"]
        assert not ok and reason and seen["after_bad_set"] == 5.0  # refused, old value kept
        assert seen["good_set"][0] and seen["after_good_set"] == 10.0
        assert not seen["planner_bad_samples"][0] and seen["planner_bad_samples"][1]
        assert seen["planner_good_samples"][0] and seen["planner_samples"] == 64
        assert not seen["planner_bad_replan"][0] and seen["planner_good_replan"][0]  # MPC off, as the demo runs
        assert seen["planner_refine"] == PlannerConfig.refine_iterations  # the planner's own default, unset here
        assert seen["pose"]["frame_id"] and 0.0 < abs(seen["pose"]["y_m"]) < 0.5  # metres, not mm
        assert seen["joint_state"]["name"] == ["actuator_1", "actuator_2"] and len(seen["joint_state"]["effort"]) == 2
        assert seen["reset"][0] and "grasped" in seen["reset"][1]
        assert set(seen["rosout"]) == {"mock_driver", "recorder", "transfer_server", "planner"}
        assert "rejected" in seen["rosout_warning"] and "non-finite" in seen["rosout_warning"]

        assert suite.explore() == 0, suite.output()
        assert len(list((tmp_path / "bags").glob("episode_*"))) >= 3

        seen = stock_user("transfer")
        success, message, seconds = seen["transfer"]
        assert success, (message, suite.output()[-4000:])
        assert "naive_finetune" in message and (tmp_path / "models" / "current.safetensors").is_file()
        # the Transfer goal named the method and the bags the recorder announced; feedback came per epoch
        assert seen["transfer_goal"] == {"method": "naive_finetune", "bags": 3, "status": 4}  # SUCCEEDED
        assert sorted(p for p, episodes, _ in seen["bags_closed"] if episodes) == \
            [str(b) for b in sorted((tmp_path / "bags").glob("episode_*"))]
        # every epoch's feedback in order, the last included (the server's last feedback leads its result)
        assert [(f[1], f[2]) for f in seen["transfer_feedback"] if f[1]] == [(1, 2), (2, 2)]
        assert seen["transfer_result"]["model_path"].endswith(".safetensors") and not seen["transfer_result"][
            "skipped_bags"] and math.isfinite(seen["transfer_result"]["model_divergence_steps"])
        # a Reach goal: feedback, then a result with the verdict and both paths; the driver ran the plan
        reach = seen["reach"]
        assert reach["verdict"] in ("hit", "miss", "no_progress", "incomplete"), reach
        assert reach["feedback"] and reach["predicted"] == seen["trajectory"]["points"] + 1 and reach["executed"] >= 2
        assert seen["plan_result"] == {"accepted": True, "status": "ok", "frame_id": "t42_base",
                                       "horizon": seen["trajectory"]["points"]}
        assert seen["trajectory"]["joint_names"] == ["actuator_1", "actuator_2"]
        assert 1 <= seen["trajectory"]["points"] <= 10
        assert seen["path"]["poses"] == seen["trajectory"]["points"] + 1 and seen["path"]["frame_id"]
        # a Reach goal cancelled while the hand moved: CANCELED; in the order the driver applied them, the goal's
        # moving steps (no more than the result's executed path holds, and one more in flight to the driver when
        # the cancel took effect), then the hand held still
        cancel = seen["cancel"]
        assert cancel["canceled"] and cancel["verdict"] == "incomplete" and "cancelled" in cancel["reason"], cancel
        moving = cancel["moving"]
        first = moving.index(True)
        run = moving[first:].index(False) if False in moving[first:] else len(moving) - first
        assert 1 <= cancel["steps_at_cancel"] < 10 and 1 <= run <= cancel["executed"] + 1, cancel
        assert not any(moving[first + run:]) and len(moving) - first - run >= 4, cancel
    finally:
        code = suite.stop()
    assert code == 0, suite.output()[-4000:]


def _topics_in(bags: list[Path]) -> set[str]:
    from rosbags.rosbag2 import Reader

    topics: set[str] = set()
    for bag in bags:
        with Reader(bag) as reader:
            topics |= {c.topic for c in reader.connections}
    return topics


def test_two_hands_on_one_graph_keep_to_their_namespaces(tmp_path: Path, source_model: Path, ros) -> None:
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory

    from t42_transfer.models.checkpoint import read_metadata

    roots = {ns: tmp_path / ns.strip("/") for ns in ("/left", "/right")}
    suites = {}
    for k, (ns, root) in enumerate(roots.items()):
        root.mkdir()
        suites[ns] = Suite(suite_file(root, source_model, seed=100 * k), ns)
    probe = ros.node("two_hands_probe")
    trajectories: dict[str, list] = {ns: [] for ns in roots}
    for ns in roots:
        probe.create_subscription(JointTrajectory, f"{ns}/hand/trajectory", trajectories[ns].append, 10)
    try:
        # Each suite is whole on the graph (the recorder and planner hear the driver) before anything is explored:
        # an explorer started at once recorded 0 messages while discovery was still under way on a busy machine.
        assert ros.spin_until(lambda: all(probe.count_subscribers(f"{ns}/hand/joint_states") >= 2
                                          and probe.count_publishers(f"{ns}/hand/joint_states") >= 1
                                          and probe.count_subscribers(f"{ns}/hand/status") >= 2 for ns in roots),
                              60.0), [s.output()[-3000:] for s in suites.values()]
        # Both hands explore, then both transfer, at the same time: each keeps to its own namespace meanwhile.
        assert explore_all(list(suites.values())) == [0, 0], [s.output()[-3000:] for s in suites.values()]
        for ns, root in roots.items():
            bags = sorted((root / "bags").glob("episode_*"))
            assert len(bags) >= 3, ns
            # the explorer has exited; the recorder may still be closing its last bag (metadata.yaml comes last)
            assert ros.spin_until(lambda bags=bags: all((b / "metadata.yaml").is_file() for b in bags), 30.0), \
                [bag for bag in bags if not (bag / "metadata.yaml").is_file()]
            other = "/right" if ns == "/left" else "/left"
            topics = _topics_in(bags)
            assert f"{ns}/hand/object_pose" in topics and not any(t.startswith(other) for t in topics), topics
        clients = {ns: probe.create_client(Trigger, f"{ns}/t42/transfer_now") for ns in roots}
        for ns, client in clients.items():
            assert client.wait_for_service(timeout_sec=60.0), (ns, suites[ns].output()[-3000:])
        calls = {ns: client.call_async(Trigger.Request()) for ns, client in clients.items()}
        assert ros.spin_until(lambda: all(c.done() for c in calls.values()), 300.0), \
            [s.output()[-3000:] for s in suites.values()]
        for ns, root in roots.items():
            answer = calls[ns].result()
            assert answer.success, (ns, answer.message, suites[ns].output()[-3000:])
            meta = read_metadata(root / "models" / "current.safetensors")
            assert str(root / "bags") in json.dumps(meta), "each server trains on its own bags"
        # a goal to the left planner moves only the left hand
        from geometry_msgs.msg import PointStamped, PoseStamped

        poses: list = []
        probe.create_subscription(PoseStamped, "/left/hand/object_pose", poses.append, 10)
        goal_pub = probe.create_publisher(PointStamped, "/left/t42/goal", 10)
        assert ros.spin_until(lambda: poses and goal_pub.get_subscription_count() == 1, 30.0)
        ros.spin_for(1.0)
        explored = {ns: len(trajectories[ns]) for ns in roots}  # the explorers' episodes
        goal = PointStamped()
        goal.header = poses[-1].header
        goal.point.x, goal.point.y = poses[-1].pose.position.x + 0.004, poses[-1].pose.position.y + 0.004
        goal_pub.publish(goal)
        assert ros.spin_until(lambda: len(trajectories["/left"]) > explored["/left"], 120.0), \
            suites["/left"].output()[-3000:]
        ros.spin_for(1.0)
        assert len(trajectories["/right"]) == explored["/right"]  # nothing reached the right hand
    finally:  # both stopped at once: each suite's nodes shut down beside the other's
        codes = stop([suite.proc for suite in suites.values()], timeout_s=60.0)
    assert codes == [0, 0], [s.output()[-3000:] for s in suites.values()]


def _pids(log: str, name: str) -> list[int]:
    return [int(m.group(1)) for m in re.finditer(rf"\[t42 up\] started {name} \(pid (\d+)\)", log)]


@pytest.mark.slow
def test_after_the_recorder_driver_and_planner_are_killed_and_respawned_a_full_round_passes(
        tmp_path: Path, source_model: Path, ros_domain: int) -> None:
    """``t42 up`` brings each SIGKILLed node back within 15 s while the others keep their pids; then a stock
    user explores, transfers and plans a goal on the suite as if nothing had happened."""
    suite = Suite(suite_file(tmp_path, source_model))
    nodes = ("mock_driver", "recorder", "transfer_server", "planner")
    try:
        deadline = time.monotonic() + 60.0
        while not all(_pids(suite.output(), n) for n in nodes) or "SIGINT or SIGTERM stops" not in suite.output():
            assert time.monotonic() < deadline and suite.proc.poll() is None, suite.output()[-3000:]
            time.sleep(0.2)
        time.sleep(6.0)  # running a while, not failing to start
        for victim in ("recorder", "mock_driver", "planner"):
            kept = {n: _pids(suite.output(), n)[-1] for n in nodes if n != victim}
            os.kill(_pids(suite.output(), victim)[-1], signal.SIGKILL)
            deadline = time.monotonic() + 15.0
            while len(_pids(suite.output(), victim)) < 2:
                assert time.monotonic() < deadline, suite.output()[-3000:]
                time.sleep(0.2)
            assert {n: _pids(suite.output(), n)[-1] for n in kept} == kept
        time.sleep(5.0)  # the restarted ones join the graph
        assert suite.explore() == 0, suite.output()[-3000:]
        seen = stock_user("transfer")
        assert seen["transfer"][0], (seen, suite.output()[-4000:])
        assert seen["trajectory"]["points"] >= 1 and seen["path"]["poses"] == seen["trajectory"]["points"] + 1
    finally:
        code = suite.stop()
    assert code == 0, suite.output()[-4000:]
