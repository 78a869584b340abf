"""The transfer server as a process (``t42 node transfer_server``): busy answers, live diagnostics, a latched model."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from ros_rig import REPO, start_node, stop
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from t42_interfaces.msg import ModelUpdated
from test_transfer_server import Rig, add_target_bag, config_file, source_model  # noqa: F401  (fixture)

from msg_adapters import DiagnosticReport, names, status_report
from t42_transfer.data.bag import read_bag
from t42_transfer.nodes.recorder import Recorder
from t42_transfer.nodes.transfer_server import SHUTTING_DOWN
from t42_transfer.nodes.transfer_status import STATUS_NAME
from t42_transfer.ros.qos import profile

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LONG = "l2_finetune: {train: {epochs: 800, patience: null}}\n"
"""Seconds of training on the fixture bag (a few ms an epoch): time for a second call meanwhile."""


# Slow suite (CI runs it): 12 s of training in a node process; the busy answer within a second and the progress on
# diagnostics are checked in the default suite in-process (test_transfer_server.py).
@pytest.mark.slow
def test_busy_answer_and_diagnostics_while_a_transfer_trains_then_success(ros, tmp_path: Path,
                                                                          source_model: Path) -> None:  # noqa: F811
    bag_dir, model_dir = tmp_path / "bags", tmp_path / "models"
    bag_dir.mkdir()
    add_target_bag(bag_dir)
    log = tmp_path / "server.log"
    server = start_node(
        "transfer_server", "-r", "__ns:=/left", "-p", f"source_model:={source_model}", "-p", f"model_dir:={model_dir}",
        "-p", f"bag_dir:={bag_dir}", "-p", f"config:={config_file(tmp_path / 'long.yaml', LONG)}",
        "-p", "progress_period_s:=0.05", log=log,
    )
    try:
        tester = ros.node("tester", namespace="/left")
        reports: list[DiagnosticReport] = []
        tester.create_subscription(DiagnosticArray, names.DIAGNOSTICS,
                                   lambda m: reports.append(status_report(m, STATUS_NAME)), 10_000)
        client = tester.create_client(Trigger, names.TRANSFER_NOW)
        assert tester.resolve_service_name(names.TRANSFER_NOW) == "/left/t42/transfer_now"
        assert client.wait_for_service(timeout_sec=60.0), log.read_text()
        first = client.call_async(Trigger.Request())
        assert ros.spin_until(lambda: any(r.values["stage"] == "training" for r in reports), 60.0), log.read_text()

        second = ros.call(client, Trigger.Request(), timeout_s=5.0)
        assert not first.done(), "a busy server answers while it trains, not after"
        assert not second.success and second.message.startswith("busy") and "training" in second.message
        seen = len(reports)
        assert ros.spin_until(lambda: sum(r.values["stage"] == "training" for r in reports[seen:]) >= 3, 10.0), \
            "progress is published on diagnostics while training"
        assert not first.done()

        assert ros.spin_until(first.done, 120.0), log.read_text()
        answer = first.result()
        assert answer.success, answer.message
        model = model_dir / "transferred_000.safetensors"
        assert str(model) in answer.message and model.is_file()
        assert ros.spin_until(lambda: reports[-1].values["stage"] == "done", 5.0)
        assert reports[-1].level == "OK" and reports[-1].message == answer.message

        # A listener joining afterwards still gets the announcement (latched).
        late = ros.node("late", namespace="/left")
        updates: list[str] = []
        late.create_subscription(ModelUpdated, names.MODEL_UPDATED, lambda m: updates.append(m.path),
                                 profile(names.LATCHED))
        assert ros.spin_until(lambda: updates == [str(model)], 10.0), updates
    finally:
        codes = stop([server])
    assert codes == [0], log.read_text()


@pytest.mark.executor_threads(4)
def test_sigterm_during_a_goal_ends_it_and_its_client_gets_the_result(ros, tmp_path: Path,
                                                                       source_model: Path) -> None:  # noqa: F811
    """SIGTERM (Ctrl-C, t42 up's restart) while a goal trains: the goal ends ABORTED with the shutdown reason, and
    the result reaches its client before the node leaves; the process exits 0 with nothing saved."""
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient
    from t42_interfaces.action import Transfer

    bag_dir, model_dir = tmp_path / "bags", tmp_path / "models"
    bag_dir.mkdir()
    add_target_bag(bag_dir)
    log = tmp_path / "server.log"
    server = start_node(
        "transfer_server", "-p", f"source_model:={source_model}", "-p", f"model_dir:={model_dir}",
        "-p", f"bag_dir:={bag_dir}", "-p", f"config:={config_file(tmp_path / 'long.yaml', LONG)}",
        "-p", "progress_period_s:=0.05", log=log,
    )
    try:
        tester = ros.node("tester")
        client = ActionClient(tester, Transfer, names.TRANSFER)
        assert ros.spin_until(client.server_is_ready, 60.0), log.read_text()
        feedback: list = []
        sent = client.send_goal_async(Transfer.Goal(), feedback_callback=lambda m: feedback.append(m.feedback))
        assert ros.spin_until(sent.done, 10.0) and sent.result().accepted, log.read_text()
        result = sent.result().get_result_async()
        assert ros.spin_until(lambda: sum(f.epoch > 0 for f in feedback) >= 3, 60.0), log.read_text()
        server.send_signal(signal.SIGTERM)
        assert ros.spin_until(result.done, 15.0), f"no result after SIGTERM: {log.read_text()}"
    finally:
        codes = stop([server], sig=signal.SIGTERM)
    assert codes == [0], log.read_text()
    got = result.result()
    assert got.status == GoalStatus.STATUS_ABORTED, got.result.message
    assert got.result.message == SHUTTING_DOWN and not got.result.success
    assert not model_dir.exists() or not any(model_dir.glob("*.safetensors"))
    assert "Failed to send result" not in log.read_text()


def test_a_bad_parameter_ends_the_process_with_one_line(ros_domain: int, tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "t42_transfer.cli", "node", "transfer_server", "--ros-args",
           "-p", "source_model:=s.safetensors", "-p", f"model_dir:={tmp_path}", "-p", f"bag_dir:={tmp_path}",
           "-p", "method:=nope"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("t42: error:")]
    assert len(errors) == 1 and "method must be one of" in errors[0], done.stderr


@pytest.mark.serial
@pytest.mark.executor_threads(4)
def test_a_driver_frozen_three_times_mid_episode_costs_no_bag(ros, tmp_path: Path,
                                                              source_model: Path) -> None:  # noqa: F811
    """SIGSTOP/SIGCONT of the mock driver for 0.35 s, three times mid-episode: each step after a stall is late, not
    lost; the driver says so, the recorder keeps its word in the bag, and the transfer reads every bag and trains on
    the 0.1 s steps around the late ones."""
    rig = Rig(ros, tmp_path, source_model)
    recorder = ros.add(Recorder, {"out_dir": str(rig.bag_dir), "mode": "episode"})
    log = tmp_path / "driver.log"
    driver = start_node("mock_driver", "-p", "seed:=4", log=log)
    try:
        joints = rig.listen(JointState, names.JOINT_STATES)
        reset = rig.tester.create_client(Trigger, names.HAND_RESET)
        assert ros.spin_until(lambda: len(joints) >= 10 and recorder.current_count > 0, 60.0), log.read_text()
        for _ in range(3):
            ros.spin_for(0.7)
            driver.send_signal(signal.SIGSTOP)
            time.sleep(0.35)
            driver.send_signal(signal.SIGCONT)
        ros.spin_for(1.0)
        for _ in range(2):  # two more episodes, one bag each
            assert ros.call(reset, Trigger.Request(), timeout_s=30.0).success
            ros.spin_for(2.5)
        recorder.close()
    finally:
        codes = stop([driver])
    assert codes == [0], log.read_text()[-3000:]
    bags = sorted(p for p in rig.bag_dir.iterdir() if p.is_dir())
    assert len(bags) == 3, bags
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing split, nothing dropped
        (stalled,) = read_bag(bags[0])
    # Each stall makes one late step of over 0.3 s; a busy machine may add shorter late steps of its own.
    assert (stalled.step_ns[stalled.late_steps] > 300_000_000).sum() >= 3, stalled.step_ns[stalled.late_steps]

    answer = rig.call()
    assert answer.success, answer.message
    assert "from 3 bag(s)" in answer.message and "skipped" not in answer.message, answer.message
    left_out = re.search(r"\((\d+) late steps left out\)", answer.message)  # no 0.1 s transitions: not trained on
    assert left_out and int(left_out.group(1)) >= len(stalled.late_steps), answer.message
    assert re.search(r"episode 0 \(start \d+ ns\): \d+ late step\(s\) \(the longest \d+ ms\) left out", answer.message)
