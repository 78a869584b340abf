"""Nodes as real processes: `t42 node`, `t42 up`, and the registry / setup.py / launch file agreeing.

Each process test uses its own ROS_DOMAIN_ID (the ``ros_domain`` fixture) and LOCALHOST discovery.
"""

from __future__ import annotations

import os
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
from rclpy.node import Node
from ros_rig import assert_one_line_errors, unbuffered_env

from t42_transfer.cli import main
from t42_transfer.nodes.registry import NODES
from t42_transfer.ros.launcher import PACKAGE, launch_nodes, namespace_args, node_sections

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "t42_suite.launch.py"
SUITE = REPO / "configs" / "suite.yaml"
T42 = [sys.executable, "-m", "t42_transfer.cli"]
ROS_LOG = re.compile(r"^\[(INFO|WARN|ERROR|DEBUG|FATAL)\] \[\d+\.\d{9}\] \[[A-Za-z0-9_.]+\]: ")


def _stop(proc: subprocess.Popen[str], sig: int = signal.SIGINT, timeout_s: float = 10.0) -> tuple[int, float, str]:
    """Send ``sig``; (exit code, seconds to exit, all output)."""
    sent = time.monotonic()
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=timeout_s)
    return proc.returncode, time.monotonic() - sent, out


# ------------------------------------------------------------------ registry, setup.py, launch file
def _setup_kwargs() -> dict[str, Any]:
    """What setup.py gives setuptools.setup, run as a build runs it (from the repository)."""
    captured: dict[str, Any] = {}
    original, cwd = setuptools.setup, os.getcwd()
    try:
        setuptools.setup = lambda **kwargs: captured.update(kwargs)  # type: ignore[assignment]
        os.chdir(REPO)
        runpy.run_path(str(REPO / "setup.py"))
    finally:
        setuptools.setup, _ = original, os.chdir(cwd)
    return captured


def _console_scripts() -> dict[str, str]:
    pairs = (line.split("=", 1) for line in _setup_kwargs()["entry_points"]["console_scripts"])
    return {name.strip(): target.strip() for name, target in pairs}


SUITE_PARAMS = sorted([*REPO.glob("configs/suite*.yaml"), *REPO.glob("configs/hardware_*.yaml")])
"""The node suite's params files: the package installs them for the launch file."""


def test_registry_and_setup_py_agree() -> None:
    scripts = _console_scripts()
    assert scripts.pop("t42") == "t42_transfer.cli:main"
    assert scripts == {name: "t42_transfer.ros.runner:main" for name in NODES}
    for name, spec in NODES.items():
        assert issubclass(spec.node_class(), Node), name
        assert spec.finishes == hasattr(spec.node_class(), "finished"), name  # the launch file reads `finishes`


def test_setup_py_installs_the_launch_file_and_every_suite_params_file() -> None:
    kwargs = _setup_kwargs()
    installed = {(directory, Path(f).name) for directory, files in kwargs["data_files"] for f in files}
    share = "share/" + PACKAGE
    assert kwargs["name"] == PACKAGE
    assert (share + "/launch", LAUNCH.name) in installed
    assert len(SUITE_PARAMS) >= 4 and SUITE in SUITE_PARAMS
    for params in [*SUITE_PARAMS, REPO / "configs" / "foxglove_layout.json"]:
        assert (share + "/config", params.name) in installed, params.name
    assert not any(name.startswith("real_") for _, name in installed), "experiment configs are not params files"


@pytest.mark.parametrize("params", SUITE_PARAMS, ids=lambda p: p.name)
def test_launch_starts_the_nodes_of_its_params_file_as_t42_up_does(params: Path) -> None:
    scripts = _console_scripts()
    for namespace, expected_ns in (("", ""), ("left", "/left"), ("/right/", "/right")):
        nodes = launch_nodes(params, namespace)
        assert [n["executable"] for n in nodes] == [n["name"] for n in nodes] == node_sections(params)
        for node in nodes:
            assert node["package"] == PACKAGE and node["executable"] in scripts
            assert node["parameters"] == [str(params)] and node["namespace"] == expected_ns
            # the same remappings as t42 up gives a node of that namespace (after its __ns:=)
            remaps = [arg for old, new in node["remappings"] for arg in ("-r", f"{old}:={new}")]
            assert remaps == namespace_args(namespace)[2:]
            assert remaps == (["-r", f"/clock:={expected_ns}/clock"] if expected_ns else [])
    drivers = {n["executable"] for n in launch_nodes(params)} & {"mock_driver", "dynamixel_driver"}
    assert drivers == ({"dynamixel_driver"} if params.name.startswith("hardware_") else {"mock_driver"})


def test_the_launch_file_runs_launch_nodes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ROS's launch packages are not among the wheels: the launch file is run against stand-ins of their four
    names, which record what it asks of them."""
    import types

    share = tmp_path / "share"

    class Recorded:
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorded):
        def perform(self, context: dict[str, str]) -> str:
            return context[self.args[0]]

    stand_ins = {
        "launch": {"LaunchContext": dict, "LaunchDescription": Recorded},
        "launch.actions": {"DeclareLaunchArgument": Recorded, "OpaqueFunction": Recorded},
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration},
        "launch_ros.actions": {"Node": Recorded},
        "ament_index_python.packages": {"get_package_share_directory": lambda package: str(share / package)},
    }
    for module, attributes in stand_ins.items():
        monkeypatch.setitem(sys.modules, module, types.SimpleNamespace(**attributes))
    description = runpy.run_path(str(LAUNCH))["generate_launch_description"]()
    declared = {a.args[0]: a.kwargs["default_value"] for a in description.args[0][:-1]}
    assert declared == {"params_file": str(share / PACKAGE / "config" / "suite.yaml"), "namespace": ""}
    opaque = description.args[0][-1]
    real = REPO / "configs" / "hardware_real.yaml"
    started = opaque.kwargs["function"]({"params_file": str(real), "namespace": "/left"})
    assert [node.kwargs for node in started] == launch_nodes(real, "/left")
    assert "dynamixel_driver" in [node.kwargs["executable"] for node in started]


def test_node_list_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["node", "--list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in NODES)
    assert main(["node", "no_such_node"]) == 2
    assert f"available: {', '.join(NODES)}" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(NODES))
def test_node_help_lists_every_parameter_the_node_declares(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    """What ``ros2 param describe`` says of the running node, before it runs: each declared parameter, its type,
    default and description (the class the node declares is the one listed)."""
    import dataclasses

    assert main(["node", name, "--help"]) == 0
    out = capsys.readouterr().out
    node_cls = NODES[name].node_class()
    fields = [f for f in dataclasses.fields(node_cls.params_class) if f.init]
    listed = re.findall(r"^  (\w+) \((\w+)", out, flags=re.M)
    assert [n for n, _ in listed] == [f.name for f in fields] and fields, out
    for field in fields:
        description = field.metadata["t42_param"].description
        assert f"  {field.name} (" in out and description[:40] in out, field.name
    assert all(kind in ("bool", "integer", "double", "string", "bool_array", "integer_array", "double_array",
                        "string_array") for _, kind in listed), listed


def test_t42_node_and_t42_up_import_neither_torch_nor_mujoco() -> None:
    """Every node process starts as ``t42 node``: what only other commands need stays out of it."""
    code = ("import sys\nfrom t42_transfer.cli import main\nassert main(['node', '--list']) == 0\n"
            "try:\n    main(['up', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('torch', 'mujoco') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[]", proc.stdout


# ------------------------------------------------------------------ one node process
def _run_driver_until_poses(ros, *ros_args: str) -> tuple[list[Any], int, float, str]:
    from geometry_msgs.msg import PoseStamped

    poses: list[Any] = []
    ros.node("pose_probe").create_subscription(PoseStamped, "/arm/hand/object_pose", poses.append, 10)
    proc = subprocess.Popen(
        [*T42, "node", "mock_driver", "--ros-args", "-p", "rate_factor:=5.0", "-r", "__ns:=/arm", *ros_args],
        cwd=REPO, env=unbuffered_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        ros.spin_until(lambda: len(poses) >= 3 or proc.poll() is not None, 40.0)
    finally:
        code, took, out = _stop(proc)
    return poses, code, took, out


def test_t42_node_mock_driver_publishes_under_remaps_and_stops_on_sigint(ros) -> None:
    poses, code, took, out = _run_driver_until_poses(ros, "-r", "__node:=hand_sim")
    assert len(poses) >= 3, out
    assert poses[-1].header.frame_id and poses[-1].header.stamp.sec > 0
    assert code == 0, (code, took, out)  # within _stop's 10 s
    lines = out.splitlines()
    assert lines and all(ROS_LOG.match(line) for line in lines), out
    assert "[arm.hand_sim]: shut down cleanly" in lines[-1]


def test_t42_node_log_level_is_rclpys(ros) -> None:
    poses, code, _, out = _run_driver_until_poses(ros, "--log-level", "warn")
    assert len(poses) >= 3 and code == 0, out
    assert "[INFO]" not in out, out


def test_a_parameter_the_node_does_not_have_is_named_in_a_warning(ros) -> None:
    """rclpy ignores an override the node never declares: a typo would run on the default without a word."""
    poses, code, _, out = _run_driver_until_poses(ros, "-p", "rate_factr:=2.0")
    assert len(poses) >= 3 and code == 0, out
    warned = [line for line in out.splitlines() if line.startswith("[WARN]") and "rate_factr" in line]
    assert len(warned) == 1 and "not parameters of this node" in warned[0], out
    assert "rate_factor" not in warned[0]  # only what the node lacks is named


def test_t42_node_bad_arguments_are_one_line_errors(ros_domain) -> None:
    cases = (
        (["mock_driver", "--ros-args", "-p", "rate_factor:=-2.0"], "rate_factor"),
        (["mock_driver", "--ros-args", "-p", "rate_factor:=fast"], "rate_factor"),
        (["mock_driver", "extra"], "unexpected arguments extra"),
        (["mock_driver", "--ros-args", "--params-file", "/nonexistent.yaml"], "ros-args"),
        (["no_such_node"], "unknown node"),
        # a parameter's former name (rclpy would drop it unread): the planner's tolerance is now in metres
        (["planner", "--ros-args", "-p", "tolerance_mm:=5.0"], "'tolerance_mm' is now 'tolerance_m'"),
    )
    assert_one_line_errors(cases)


# ------------------------------------------------------------------ t42 up
def _suite_copy(tmp_path: Path, **recorder: Any) -> Path:
    config = yaml.safe_load(SUITE.read_text())
    config["/**/mock_driver"]["ros__parameters"]["rate_factor"] = 5.0
    config["/**/recorder"]["ros__parameters"].update(recorder)
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_t42_up_runs_the_suite_and_stops_it_cleanly(tmp_path: Path, ros_domain: int) -> None:
    from rosbags.rosbag2 import Reader

    out_dir = tmp_path / "recordings"
    config = _suite_copy(tmp_path, out_dir=str(out_dir))
    proc = subprocess.Popen([*T42, "up", str(config), "--only", "mock_driver,recorder", "--stop-timeout", "10"],
                            cwd=tmp_path,
                            env=unbuffered_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and proc.poll() is None and not any(out_dir.glob("episode_*/*.mcap")):
            time.sleep(0.2)
        time.sleep(2.0)  # a second of messages at 50 Hz
    finally:
        code, took, out = _stop(proc, timeout_s=30)
    assert code == 0, (took, out)  # within 30 s
    assert "[t42 up] started mock_driver" in out and "[t42 up] started recorder" in out
    assert "[mock_driver] [INFO]" in out and "[recorder] [INFO]" in out
    bags = sorted(out_dir.glob("episode_*"))
    assert bags, out
    assert all((bag / "metadata.yaml").is_file() for bag in bags), "the recorder closed its bags"
    with Reader(bags[0]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts.get("/hand/object_pose", 0) > 0, (counts, out)


def test_t42_up_fails_when_a_child_dies(tmp_path: Path, ros_domain: int) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("in the way")
    config = _suite_copy(tmp_path, out_dir=str(not_a_dir))
    started = time.monotonic()
    proc = subprocess.run([*T42, "up", str(config), "--only", "mock_driver,recorder"], cwd=tmp_path,
                          env=unbuffered_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert re.search(r"recorder exited with code [1-9]\d* unexpectedly \(it failed to start\): stopping the others",
                     proc.stdout), proc.stdout
    assert "[mock_driver]" in proc.stdout and time.monotonic() - started < 60


class Lines:
    """A process's output lines as they come (a thread reads them)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        import threading

        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(proc.stdout.readline, "")), daemon=True)
        self._reader.start()

    def reading(self) -> bool:
        """Whether the output has not ended yet."""
        return self._reader.is_alive()

    def pids(self, name: str) -> list[int]:
        """Every pid ``t42 up`` started ``name`` with, in order."""
        return [int(m.group(1)) for line in list(self.lines)
                if (m := re.match(rf"\[t42 up\] started {name} \(pid (\d+)\)", line))]

    def wait(self, condition: Any, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.1)
        return True


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_t42_up_restarts_a_killed_node_alone_and_the_others_keep_running(tmp_path: Path, ros_domain: int) -> None:
    """SIGKILL of the recorder, then of the driver, then of the planner: each comes back within 15 s while the
    others keep their pids."""
    from t42_transfer.ros.launcher import MIN_UPTIME_S

    suite = ("mock_driver", "recorder", "planner")
    config = _suite_copy(tmp_path, out_dir=str(tmp_path / "recordings"))
    proc = subprocess.Popen([*T42, "up", str(config), "--only", ",".join(suite), "--stop-timeout", "10"],
                            cwd=tmp_path, env=unbuffered_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    out = Lines(proc)
    try:
        assert out.wait(lambda: all(out.pids(n) for n in suite), 30.0), out.lines
        time.sleep(MIN_UPTIME_S + 0.5)  # running a while: not a node that failed to start
        for victim in ("recorder", "mock_driver", "planner"):
            kept = {n: out.pids(n)[-1] for n in suite if n != victim}
            os.kill(out.pids(victim)[-1], signal.SIGKILL)
            assert out.wait(lambda victim=victim: len(out.pids(victim)) == 2, 15.0), out.lines
            again = out.pids(victim)[-1]
            assert out.wait(lambda again=again: _alive(again), 5.0) and proc.poll() is None
            assert {n: out.pids(n)[-1] for n in kept} == kept and all(_alive(p) for p in kept.values())
            assert any(f"{victim} exited with code -9" in line and "restarting it in 1 s (1 of 5)" in line
                       for line in out.lines), out.lines
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=40)
    assert code == 0, out.lines[-20:]


def test_t42_up_no_respawn_stops_everything_when_a_node_dies(tmp_path: Path, ros_domain: int) -> None:
    config = _suite_copy(tmp_path, out_dir=str(tmp_path / "recordings"))
    proc = subprocess.Popen([*T42, "up", str(config), "--only", "mock_driver,recorder", "--no-respawn"],
                            cwd=tmp_path, env=unbuffered_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    out = Lines(proc)
    try:
        assert out.wait(lambda: out.pids("mock_driver") and out.pids("recorder"), 30.0), out.lines
        time.sleep(1.0)
        os.kill(out.pids("recorder")[-1], signal.SIGKILL)
        assert proc.wait(timeout=40) == 1
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert out.wait(lambda: any("recorder exited with code -9 unexpectedly (no respawn): stopping the others" in line
                                for line in out.lines), 5.0), out.lines
    assert len(out.pids("recorder")) == 1


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGKILL], ids=["SIGHUP", "SIGKILL"])
def test_t42_up_stops_its_nodes_on_a_hangup_and_they_stop_should_it_be_killed(tmp_path: Path, ros_domain: int,
                                                                             sig: int) -> None:
    """SIGHUP (the terminal or ssh session closed) ended `t42 up` at once and left its nodes running orphaned, a
    driver holding its servos; now it stops them as Ctrl-C does.  Killed (SIGKILL, a crash), it cannot: each node
    then gets SIGTERM from the kernel (PR_SET_PDEATHSIG) and stops."""
    from t42_transfer.ros.runner import RUNNING

    config = _suite_copy(tmp_path, out_dir=str(tmp_path / "recordings"))
    proc = subprocess.Popen([*T42, "up", str(config), "--only", "mock_driver"], cwd=tmp_path, env=unbuffered_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = Lines(proc)
    try:
        assert out.wait(lambda: any(line.startswith("[mock_driver]") and RUNNING in line for line in out.lines),
                        30.0), out.lines
        (child,) = out.pids("mock_driver")
        proc.send_signal(sig)
        code = proc.wait(timeout=30)
        assert out.wait(lambda: not _alive(child), 10.0), f"mock_driver (pid {child}) still runs"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in out.pids("mock_driver"):  # (a node that outlived it: not left running after the test)
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        out.wait(lambda: proc.stdout.closed or not out.reading(), 5.0)
        proc.stdout.close()
    if sig == signal.SIGHUP:
        assert code == 0 and any("[t42 up] stopping" in line for line in out.lines), out.lines
        assert out.wait(lambda: any("[mock_driver]" in line and "shut down cleanly" in line for line in out.lines),
                        2.0), out.lines


def test_t42_up_rejects_unknown_sections_and_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("mock_driver: {ros__parameters: {}}\nplanner_x: {ros__parameters: {}}\n")
    assert main(["up", str(config)]) == 2
    assert "no registered node named planner_x" in capsys.readouterr().err
    assert main(["up", str(SUITE), "--only", "mock_driver,nope"]) == 2
    assert "--only nope: not in" in capsys.readouterr().err


def test_quick_announcements_unless_a_profile_or_another_middleware_was_chosen(tmp_path) -> None:
    from t42_transfer.ros.runner import FASTDDS_PROFILE_ENV, announce_often, keep_discovery_local

    env: dict[str, str] = {}
    assert keep_discovery_local(env) == "LOCALHOST"
    profile = Path(env[FASTDDS_PROFILE_ENV])
    text = profile.read_text()
    assert "<leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>" in text
    assert 'is_default_profile="true"' in text
    mine = {FASTDDS_PROFILE_ENV: str(tmp_path / "mine.xml")}
    assert announce_often(mine) == str(tmp_path / "mine.xml")  # the user's profile is kept
    other = {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"}
    assert announce_often(other) is None and FASTDDS_PROFILE_ENV not in other


def test_each_node_spins_on_the_executor_it_asks_for() -> None:
    import rclpy

    from t42_transfer.ros.runner import make_executor

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        kinds = {name: type(make_executor(spec.node_class(), context)).__name__ for name, spec in NODES.items()}
    finally:
        context.try_shutdown()
    assert kinds["dynamixel_driver"] == "EventsExecutor"  # its CPU per step is benchmarked (bench_driver)
    assert kinds["transfer_server"] == "MultiThreadedExecutor"  # a long transfer beside its other callbacks
    assert kinds["recorder"] == kinds["mock_driver"] == "SingleThreadedExecutor"



_FROZEN_BEFORE_SPINNING = """
import gc, os, signal, threading, time
import t42_transfer.ros.runner as runner

first_spin = {}
make_executor = runner.make_executor

def watched(node_cls, context):  # the node's executor, noting the heap at its first spin
    executor = make_executor(node_cls, context)
    spin_once = executor.spin_once

    def first(*args, **kwargs):
        first_spin.setdefault("frozen", gc.get_freeze_count())
        first_spin.setdefault("tracked", len(gc.get_objects()))
        return spin_once(*args, **kwargs)

    executor.spin_once = first
    return executor

runner.make_executor = watched

def stop_when_spinning():
    while "frozen" not in first_spin:
        time.sleep(0.05)
    os.kill(os.getpid(), signal.SIGINT)  # run_node's own handler: a clean stop

threading.Thread(target=stop_when_spinning, daemon=True).start()
code = runner.run_node("mock_driver", ["--ros-args", "-r", "__node:=frozen_hand"])
print("exit", code, "frozen", first_spin.get("frozen"), "tracked", first_spin.get("tracked"))
"""


def test_a_node_freezes_what_its_start_left_before_it_spins(ros_domain: int) -> None:
    """A full collection of the ~300k objects the imports leave stops every thread of a node for 150-250 ms
    (runner.freeze_heap): by a node's first spin they are frozen, and it stops on SIGINT as before.  (In a process
    of its own: run_node's exit watchdog and signals belong to a node's process, not to pytest's.)"""
    done = subprocess.run([sys.executable, "-c", _FROZEN_BEFORE_SPINNING], env=unbuffered_env(), cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    said = re.search(r"^exit (\d+) frozen (\d+) tracked (\d+)$", done.stdout, re.MULTILINE)
    assert done.returncode == 0 and said, done.stdout[-2000:] + done.stderr[-2000:]
    code, frozen, tracked = (int(g) for g in said.groups())
    assert code == 0
    assert frozen > 10 * tracked, (frozen, tracked)  # the start-up's objects, out of every later collection
