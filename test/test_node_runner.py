"""Nodes as real processes: `t42 node`, `t42 up`, and the registry / setup.py / launch file agreeing.

Each process test uses its own random ROS_DOMAIN_ID so concurrent test runs do not hear each other.
"""

from __future__ import annotations

import ast
import os
import random
import re
import runpy
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import setuptools
import yaml

from t42_transfer.cli import main
from t42_transfer.nodes.registry import NODES

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "t42_suite.launch.py"
SUITE = REPO / "configs" / "suite.yaml"
T42 = [sys.executable, "-m", "t42_transfer.cli"]
ROS_LOG = re.compile(r"^\[(INFO|WARN|ERROR|DEBUG|FATAL)\] \[\d+\.\d{9}\] \[[A-Za-z0-9_]+\]: ")


def _env(domain: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), T42_TRANSPORT="cyclone", PYTHONUNBUFFERED="1")
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    return env


def _stop(proc: subprocess.Popen[str], sig: int = signal.SIGINT, timeout_s: float = 10.0) -> tuple[int, float, str]:
    """Send ``sig``; (exit code, seconds to exit, all output)."""
    sent = time.monotonic()
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=timeout_s)
    return proc.returncode, time.monotonic() - sent, out


# ------------------------------------------------------------------ registry, setup.py, launch file
def _console_scripts() -> dict[str, str]:
    captured: dict[str, Any] = {}
    original, cwd = setuptools.setup, os.getcwd()
    try:
        setuptools.setup = lambda **kwargs: captured.update(kwargs)  # type: ignore[assignment]
        os.chdir(REPO)
        runpy.run_path(str(REPO / "setup.py"))
    finally:
        setuptools.setup, _ = original, os.chdir(cwd)
    pairs = (line.split("=", 1) for line in captured["entry_points"]["console_scripts"])
    return {name.strip(): target.strip() for name, target in pairs}


def test_registry_setup_py_and_launch_file_agree() -> None:
    scripts = _console_scripts()
    assert scripts.pop("t42") == "t42_transfer.cli:main"
    assert scripts == {name: "t42_transfer.nodes.registry:main" for name in NODES}
    for name, spec in NODES.items():
        assert spec.node_class().__name__ and spec.params_class().__name__, name

    tree = ast.parse(LAUNCH.read_text(), str(LAUNCH))
    compile(tree, str(LAUNCH), "exec")
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "Node"]
    assert len(calls) == 1 and {kw.value.value for kw in calls[0].keywords if kw.arg == "package"} == {"t42_transfer"}
    suite = [n for n in ast.walk(tree) if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", None) == "NODES"]
    executables = list(ast.literal_eval(suite[0].value))
    assert executables == ["mock_driver", "recorder", "transfer_server", "planner"]
    assert set(executables) <= set(scripts)
    assert set(yaml.safe_load(SUITE.read_text())) == set(executables), "the launch file runs the suite's nodes"


def test_node_list_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["node", "--list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in NODES)
    assert main(["node", "mock_driver", "--ros-args", "-p", "rate_factor:=fast"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("t42: error: mock_driver: parameter 'rate_factor'")
    assert main(["node", "recorder"]) == 2
    assert "missing required parameter(s) out_dir" in capsys.readouterr().err
    assert main(["node", "no_such_node"]) == 2
    assert "available: mock_driver, recorder" in capsys.readouterr().err


# ------------------------------------------------------------------ one node process
def test_t42_node_mock_driver_publishes_and_stops_on_sigint() -> None:
    from t42_transfer.ros import qos
    from t42_transfer.ros.cyclone import CycloneTransport

    domain = random.randint(1, 200)
    poses: list[Any] = []
    with CycloneTransport("pose_probe", domain_id=domain) as probe:
        probe.subscribe("/hand/object_pose", "geometry_msgs/msg/PoseStamped", qos.DEFAULT, poses.append)
        proc = subprocess.Popen(
            [*T42, "node", "mock_driver", "--ros-args", "-p", "rate_factor:=5", "-r", "__node:=hand_sim"],
            cwd=REPO, env=_env(domain), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        try:
            probe.spin(until=lambda: len(poses) >= 3 or proc.poll() is not None, timeout_s=40)
        finally:
            code, took, out = _stop(proc)
    assert len(poses) >= 3, out
    assert poses[-1].header.frame_id is not None and poses[-1].header.stamp.sec > 0
    assert code == 0 and took < 5.0, (code, took, out)
    lines = out.splitlines()
    assert lines and all(ROS_LOG.match(line) for line in lines), out
    assert "[hand_sim]: shut down cleanly" in lines[-1]


# ------------------------------------------------------------------ t42 up
def _suite_copy(tmp_path: Path, **recorder: Any) -> Path:
    config = yaml.safe_load(SUITE.read_text())
    config["mock_driver"]["ros__parameters"]["rate_factor"] = 5.0
    config["recorder"]["ros__parameters"].update(recorder)
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_t42_up_runs_the_suite_and_stops_it_cleanly(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader

    out_dir = tmp_path / "recordings"
    config = _suite_copy(tmp_path, out_dir=str(out_dir))
    proc = subprocess.Popen([*T42, "up", str(config), "--only", "mock_driver,recorder", "--stop-timeout", "10"], cwd=tmp_path,
                            env=_env(random.randint(1, 200)), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and proc.poll() is None and not any(out_dir.glob("episode_*/*.mcap")):
            time.sleep(0.2)
        time.sleep(2.0)  # a second of messages at 50 Hz
    finally:
        code, took, out = _stop(proc, timeout_s=30)
    assert code == 0 and took < 15, out
    assert "[t42 up] started mock_driver" in out and "[t42 up] started recorder" in out
    assert "[mock_driver] [INFO]" in out and "[recorder] [INFO]" in out
    bags = sorted(out_dir.glob("episode_*"))
    assert bags, out
    assert all((bag / "metadata.yaml").is_file() for bag in bags), "the recorder closed its bags"
    with Reader(bags[0]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts.get("/hand/object_pose", 0) > 0, (counts, out)


def test_t42_up_fails_when_a_child_dies(tmp_path: Path) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("in the way")
    config = _suite_copy(tmp_path, out_dir=str(not_a_dir))
    started = time.monotonic()
    proc = subprocess.run([*T42, "up", str(config), "--only", "mock_driver,recorder"], cwd=tmp_path, env=_env(random.randint(1, 200)),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert re.search(r"recorder exited with code [1-9]\d* unexpectedly: stopping the others", proc.stdout), proc.stdout
    assert "[mock_driver]" in proc.stdout and time.monotonic() - started < 60


def test_t42_up_rejects_unknown_sections_and_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("mock_driver: {ros__parameters: {}}\nplanner_x: {ros__parameters: {}}\n")
    assert main(["up", str(config)]) == 2
    assert "no registered node named planner_x" in capsys.readouterr().err
    assert main(["up", str(SUITE), "--only", "mock_driver,nope"]) == 2
    assert "--only nope: not in" in capsys.readouterr().err
