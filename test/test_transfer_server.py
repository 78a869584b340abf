"""The transfer server node on real rclpy, in-process: summaries, progress, busy, refusals, atomic saves."""

from __future__ import annotations

import json
import math
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import torch
from bag_builders import ACTION, JOINTS, step_messages, write_messages
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.parameter import Parameter
from ros_rig import Tester
from safetensors.torch import save_file
from std_srvs.srv import Trigger
from t42_interfaces.msg import ModelUpdated

import t42_transfer.models.checkpoint as checkpoint
from msg_adapters import DiagnosticReport, names, status_report
from t42_transfer.data.bag import assign_start_times, read_bag, write_bag
from t42_transfer.models.checkpoint import FORMAT, load_model, read_metadata, save_model
from t42_transfer.models.residual import CumulativeResidualModel
from t42_transfer.models.training import TrainConfig, train_transition_model
from t42_transfer.nodes.transfer_server import SHUTTING_DOWN, TransferServer
from t42_transfer.nodes.transfer_status import STATUS_NAME
from t42_transfer.planning.workspace import Workspace
from t42_transfer.ros.qos import profile
from t42_transfer.transfer.methods import METHODS
from t42_transfer.transfer.online import (
    CURRENT_MODEL,
    STATE_FILE,
    config_from_file,
    config_with_overrides,
    hold_out,
)

REPO = Path(__file__).resolve().parents[1]
TINY = "l2_finetune: {train: {epochs: 2}}\n"
"""Method settings (a config file) that train in seconds."""

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.executor_threads(4)]


@pytest.fixture(scope="module")
def source_model(tmp_path_factory: pytest.TempPathFactory, one_torch_thread: None) -> Path:
    """A source model trained for 1 epoch on the source fixture bag, with its workspace."""
    data = read_bag(REPO / "bags" / "source_small")
    model, _ = train_transition_model(data, TrainConfig(epochs=1))
    path = tmp_path_factory.mktemp("source") / "source.safetensors"
    return save_model(model, path, method="source", extra={"workspace": Workspace.from_trajectories(data).to_dict()})


def add_target_bag(bag_dir: Path, name: str = "episode_000") -> Path:
    """The target fixture bag (4 episodes) copied into ``bag_dir``."""
    return Path(shutil.copytree(REPO / "bags" / "target_small", bag_dir / name))


def add_synthetic_bag(bag_dir: Path, make_set: Any, name: str, lengths: tuple[int, ...] = (30, 30, 30)) -> Path:
    return write_bag(bag_dir / name, make_set(lengths, seed=5, hand="target"))


def config_file(path: Path, text: str = TINY) -> str:
    path.write_text(text)
    return str(path)


def server_params(tmp_path: Path, source: Path, **params: Any) -> dict[str, Any]:
    return {"source_model": str(source), "model_dir": str(tmp_path / "models"), "bag_dir": str(tmp_path / "bags"),
            "config": config_file(tmp_path / "tiny.yaml"), "progress_period_s": 0.02, **params}


class Rig(Tester):
    """A transfer server and the test's node (Trigger client, diagnostics and model-update subscribers)."""

    def __init__(self, ros: Any, tmp_path: Path, source: Path, namespace: str = "", **params: Any) -> None:
        super().__init__(ros, namespace=namespace)
        self.bag_dir, self.model_dir = tmp_path / "bags", tmp_path / "models"
        self.bag_dir.mkdir(exist_ok=True)
        self.reports: list[DiagnosticReport] = []
        self.updates: list[str] = []
        self.tester.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_diagnostics, 10_000)
        self.announcements: list[ModelUpdated] = []
        self.tester.create_subscription(ModelUpdated, names.MODEL_UPDATED, self._on_model, profile(names.LATCHED))
        self.server = ros.add(TransferServer, server_params(tmp_path, source, **params), namespace=namespace)
        self.client = self.tester.create_client(Trigger, names.TRANSFER_NOW)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """The server's statuses; other nodes' (a recorder's, on the same topic) are not the server's."""
        if any(status.name == STATUS_NAME for status in msg.status):
            self.reports.append(status_report(msg, STATUS_NAME))

    def _on_model(self, msg: ModelUpdated) -> None:
        self.announcements.append(msg)
        self.updates.append(msg.path)

    def call(self, timeout_s: float = 120.0) -> Trigger.Response:
        """One call that runs (not busy); returns once its final status (done or failed) arrived too."""
        ends = len(self.ends())
        response = self.ros.call(self.client, Trigger.Request(), timeout_s)
        assert self.ros.spin_until(lambda: len(self.ends()) > ends, 5.0), "no final status on diagnostics"
        return response

    def ends(self) -> list[DiagnosticReport]:
        return [r for r in self.reports if r.values["stage"] in ("done", "failed")]

    def stages(self) -> list[str]:
        """Stages in order of arrival, repeats collapsed."""
        out: list[str] = []
        for report in self.reports:
            if not out or out[-1] != report.values["stage"]:
                out.append(report.values["stage"])
        return out

    def model_files(self) -> list[str]:
        return sorted(p.name for p in self.model_dir.iterdir()) if self.model_dir.exists() else []


def test_transfer_answers_with_summary_saves_and_announces(ros, tmp_path, source_model):
    rig = Rig(ros, tmp_path, source_model)
    bag = add_target_bag(rig.bag_dir)
    response = rig.call()
    assert response.success, response.message
    model_path = rig.model_dir / "transferred_000.safetensors"
    for part in ("l2_finetune", "episodes", "transitions", "held-out", "divergence", "mm^2", str(model_path)):
        assert part in response.message
    assert "\n" not in response.message
    assert ros.spin_until(lambda: rig.updates == [str(model_path)], 5.0), rig.updates
    announced = rig.announcements[-1]
    assert (announced.method, announced.episodes) == ("l2_finetune", 3)
    assert abs(announced.stamp.sec - time.time()) < 60
    assert rig.model_files() == [CURRENT_MODEL, STATE_FILE, "transferred_000.safetensors"]
    model, meta = load_model(rig.model_dir / CURRENT_MODEL)
    assert type(model) is type(load_model(source_model)[0]) and meta["method"] == "l2_finetune"
    assert meta["data"]["bags"] == [str(bag.resolve())]
    merged = Workspace.from_metadata(meta)
    source = Workspace.from_metadata(read_metadata(source_model))
    assert (merged.lower <= source.lower).all() and (merged.upper >= source.upper).all()
    assert read_metadata(model_path)["data"] == meta["data"]
    result = rig.server.last_result
    assert (result.episodes, result.held_out_episodes) == (3, 1)

    assert rig.stages() == ["loading", "training", "evaluating", "saving", "done"]
    last = rig.reports[-1]
    assert last.level == "OK" and last.message == response.message
    assert last.values["method"] == "l2_finetune" and last.values["bags"] == bag.name
    assert last.values["epochs"] == "2" and last.values["model"] == str(model_path)
    assert float(last.values["elapsed_s"]) >= 0.0


def test_diagnostics_follow_the_training_epochs(ros, tmp_path, source_model):
    settings = config_file(tmp_path / "four.yaml", "l2_finetune: {train: {epochs: 4, patience: null}}\n")
    rig = Rig(ros, tmp_path, source_model, config=settings)
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    training = [r for r in rig.reports if r.values["stage"] == "training"]
    epochs = [int(r.values["epoch"]) for r in training]
    assert epochs == sorted(epochs) and set(epochs) == {0, 1, 2, 3, 4}
    trained = [r for r in training if int(r.values["epoch"]) > 0]
    assert all(r.values["phase"] == "L2 fine-tune" and r.values["epochs"] == "4" for r in trained)
    assert all(math.isfinite(float(r.values["train_loss"])) for r in trained)
    assert trained[-1].message == "training L2 fine-tune: epoch 4/4"
    ends = len(rig.ends())  # how it ended is said again each second, for a monitor that joins late
    assert ros.spin_until(lambda: len(rig.ends()) > ends, 2.5) and rig.reports[-1].values["stage"] == "done"


def test_bags_are_used_once(ros, tmp_path, source_model, make_set):
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    again = rig.call()
    assert not again.success and "no new bags" in again.message
    new = add_synthetic_bag(rig.bag_dir, make_set, "episode_001")
    response = rig.call()
    assert response.success, response.message
    assert rig.server.last_result.bags == (new,)
    assert "from 1 bag(s)" in response.message
    state = json.loads((rig.model_dir / STATE_FILE).read_text())
    assert len(state["used_bags"]) == 2 and [t["model"] for t in state["transfers"]] == [
        "transferred_000.safetensors", "transferred_001.safetensors"]
    latest = str(rig.model_dir / "transferred_001.safetensors")
    assert ros.spin_until(lambda: rig.updates[-1:] == [latest], 5.0), rig.updates


def test_with_new_bags_only_false_every_bag_is_used_once_one_is_new(ros, tmp_path, source_model, make_set):
    rig = Rig(ros, tmp_path, source_model, new_bags_only=False)
    first = add_target_bag(rig.bag_dir)
    assert rig.call().success
    again = rig.call()
    assert not again.success and "no new bags" in again.message  # nothing new: nothing to learn
    new = add_synthetic_bag(rig.bag_dir, make_set, "episode_001")
    response = rig.call()
    assert response.success, response.message
    assert set(rig.server.last_result.bags) == {first, new} and "from 2 bag(s)" in response.message
    state = json.loads((rig.model_dir / STATE_FILE).read_text())
    assert len(state["used_bags"]) == 2  # recorded once each


def test_a_restarted_server_announces_the_latest_model_to_late_joiners(ros, tmp_path, source_model):
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    # Another server on the same model directory (in its own namespace, as this one still runs), and a late listener.
    late = Rig(ros, tmp_path, source_model, namespace="/again", share_dirs=True)
    expected = [str(rig.model_dir / "transferred_000.safetensors")]
    assert ros.spin_until(lambda: late.updates == expected, 5.0), late.updates
    first, again = rig.announcements[-1], late.announcements[-1]
    assert (again.method, again.episodes) == (first.method, first.episodes)
    assert abs(again.stamp.sec - first.stamp.sec) <= 2  # the state file's time of the save, in whole seconds
    assert late.server.get_fully_qualified_name() == "/again/transfer_server"


def gated_method(monkeypatch: pytest.MonkeyPatch, name: str = "slow") -> tuple[threading.Event, threading.Event]:
    """A transfer method ``name`` that trains as ``direct`` once released: (entered, release) events, so a test
    holds a transfer running for as long as it needs."""
    entered, release = threading.Event(), threading.Event()

    def slow(source, target, cfg, seed, on_epoch=None):
        entered.set()
        assert release.wait(30.0)
        return METHODS["direct"](source, target, cfg, seed, on_epoch)

    monkeypatch.setitem(METHODS, name, slow)
    return entered, release


def test_second_call_while_training_is_answered_busy_without_waiting(ros, tmp_path, source_model, monkeypatch):
    entered, release = gated_method(monkeypatch)
    rig = Rig(ros, tmp_path, source_model, method="slow")
    add_target_bag(rig.bag_dir)
    assert rig.client.wait_for_service(timeout_sec=10.0)
    first = rig.client.call_async(Trigger.Request())
    try:
        assert ros.spin_until(entered.is_set, 60.0)
        assert rig.server.busy
        second = ros.call(rig.client, Trigger.Request(), timeout_s=5.0)  # answered while training is held
        assert not second.success and second.message.startswith("busy") and "slow" in second.message
        assert "training" in second.message
        before = len(rig.reports)
        assert ros.spin_until(lambda: sum(r.values["stage"] == "training" for r in rig.reports[before:]) >= 3, 5.0), \
            "progress is re-published while training"
        elapsed = [float(r.values["elapsed_s"]) for r in rig.reports if r.values["stage"] == "training"]
        assert elapsed == sorted(elapsed)
        assert not first.done()
    finally:
        release.set()
    assert ros.spin_until(first.done, 60.0)
    assert first.result().success, first.result().message
    assert "slow" in first.result().message and not rig.server.busy
    assert ros.spin_until(lambda: rig.stages()[-1] == "done", 5.0)


def test_closing_the_node_cancels_a_running_transfer_and_waits_for_it(ros, tmp_path, source_model, monkeypatch):
    """A transfer left running when the node closes would be cut off wherever it was by the process's exit: closing
    cancels it at its next epoch and returns once it stopped, with nothing saved."""
    from t42_transfer.models.training import Progress

    epochs: list[int] = []

    def endless(source, target, cfg, seed, on_epoch=None):
        while True:  # stops only when on_epoch raises (the transfer cancelled)
            epochs.append(len(epochs) + 1)
            on_epoch(Progress("endless", len(epochs), 10**6, 1.0, None))
            time.sleep(0.005)

    monkeypatch.setitem(METHODS, "endless", endless)
    rig = Rig(ros, tmp_path, source_model, method="endless")
    add_target_bag(rig.bag_dir)
    assert rig.client.wait_for_service(timeout_sec=10.0)
    rig.client.call_async(Trigger.Request())
    assert ros.spin_until(lambda: len(epochs) >= 3, 60.0)
    rig.server.close()
    stopped_at = len(epochs)
    time.sleep(0.2)
    assert len(epochs) == stopped_at, "the transfer ran on after the node closed"
    assert not rig.server.busy and rig.model_files() == []


def test_stopping_the_node_during_a_goal_ends_it_and_its_client_gets_the_result(ros, tmp_path, source_model,
                                                                                 monkeypatch):
    """As ``t42 node`` stops the node (SIGTERM, Ctrl-C): close() from the thread that spun it, then the node is
    destroyed.  The goal's client still gets its result (ABORTED, the shutdown reason), sent before the node left."""
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient
    from t42_interfaces.action import Transfer

    from t42_transfer.models.training import Progress

    def endless(source, target, cfg, seed, on_epoch=None):
        for epoch in range(1, 10**6):  # stops only when on_epoch raises (the transfer cancelled)
            on_epoch(Progress("endless", epoch, 10**6, 1.0, None))
            time.sleep(0.005)

    monkeypatch.setitem(METHODS, "endless", endless)
    rig = Rig(ros, tmp_path, source_model, method="endless")
    add_target_bag(rig.bag_dir)
    client = ActionClient(rig.tester, Transfer, names.TRANSFER)
    assert ros.spin_until(client.server_is_ready, 10.0)
    sent = client.send_goal_async(Transfer.Goal())
    assert ros.spin_until(sent.done, 10.0) and sent.result().accepted
    result = sent.result().get_result_async()
    assert ros.spin_until(lambda: sum(r.values["stage"] == "training" for r in rig.reports) >= 3, 60.0)
    rig.server.close()
    rig.server.destroy_node()  # (t42 node shuts its executor down first; the test's spins on for the client)
    ros.nodes.remove(rig.server)
    assert ros.spin_until(result.done, 5.0), "the goal of a stopped server got no result"
    assert result.result().status == GoalStatus.STATUS_ABORTED
    assert result.result().result.message == SHUTTING_DOWN and not result.result().result.success
    assert rig.model_files() == []


def _corrupt_bag(bag_dir: Path, name: str = "episode_000") -> Path:
    bag = bag_dir / name
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    (bag / f"{name}_0.mcap").write_bytes(b"\x89MCAP0\r\n not really an mcap file")
    return bag


def _truncated_bag(bag_dir: Path) -> Path:
    """The target bag cut short in its first chunk, as a recorder killed early leaves it."""
    bag = add_target_bag(bag_dir)
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:200])
    return bag


def _residual_source(tmp_path: Path, source_model: Path) -> Path:
    """A transferred (residual) model: not a start for a transfer.  Two loads, as safetensors refuses shared tensors."""
    model = CumulativeResidualModel(load_model(source_model)[0], load_model(source_model)[0], 0.3, 0.9)
    return save_model(model, tmp_path / "residual.safetensors", method="cumulative_residual")


def _wrong_layout_source(tmp_path: Path, source_model: Path) -> Path:
    path = tmp_path / "layout.safetensors"
    meta = {"format": FORMAT, "state_layout": ["x_mm", "y_mm"]}
    save_file({"w": torch.zeros(1)}, str(path), metadata={"t42_transfer": json.dumps(meta)})
    return path


BAD_REQUESTS = {
    "no bags": (lambda bag_dir, make_set: None, "no finished bags in"),  # none ever: not "all used already"
    "too little data": (lambda bag_dir, make_set: add_synthetic_bag(bag_dir, make_set, "e", (30,)), "too little data"),
    "corrupt bag": (lambda bag_dir, make_set: _corrupt_bag(bag_dir), "unreadable bag"),
    "truncated bag": (lambda bag_dir, make_set: _truncated_bag(bag_dir), "unreadable bag"),
}
BAD_SOURCES = {
    "missing source": (lambda tmp, src: tmp / "missing.safetensors", "does not exist"),
    "residual source": (_residual_source, "plain transition model"),
    "wrong state layout": (_wrong_layout_source, "state layout"),
}


@pytest.mark.parametrize("case", sorted(BAD_REQUESTS))
def test_bad_data_is_refused_in_one_line_and_the_node_serves_on(ros, tmp_path, source_model, make_set, case):
    rig = Rig(ros, tmp_path, source_model)
    setup, reason = BAD_REQUESTS[case]
    setup(rig.bag_dir, make_set)
    response = rig.call()
    assert not response.success and reason in response.message, response.message
    assert "\n" not in response.message
    if case.endswith(" bag"):
        assert "episode_000" in response.message
    assert rig.model_files() == []
    assert rig.stages()[-1] == "failed" and rig.reports[-1].level == "WARN"
    assert rig.reports[-1].message == response.message
    for bag in list(rig.bag_dir.iterdir()):
        shutil.rmtree(bag)
    add_target_bag(rig.bag_dir, "episode_009")
    assert rig.call().success


def test_an_unreadable_bag_is_skipped_named_and_offered_again(ros, tmp_path, source_model):
    rig = Rig(ros, tmp_path, source_model)
    good = add_target_bag(rig.bag_dir)
    bad = _corrupt_bag(rig.bag_dir, "episode_001")
    response = rig.call()
    assert response.success, response.message
    assert f"; skipped 1 unreadable bag(s): {bad}: " in response.message and "\n" not in response.message
    assert rig.server.last_result.bags == (good,) and "from 1 bag(s)" in response.message
    assert json.loads((rig.model_dir / STATE_FILE).read_text())["used_bags"] == [str(good.resolve())]
    again = rig.call()  # the bad bag is new still, and all there is
    assert not again.success and again.message.startswith("too little data: 0 episode(s) (0 transitions) in 0 "
                                                           "readable new bag(s)")
    assert f"skipped 1 unreadable bag(s): {bad}: " in again.message and rig.reports[-1].level == "WARN"


def test_a_bag_begun_mid_step_is_salvaged_not_refused(ros, tmp_path, source_model, make_set):
    """The issue's case: the recorder started between a step's state and its action, so the bag began with an
    /hand/applied_action lacking its /hand/joint_states; the whole bag was refused and /t42/transfer failed."""
    data = make_set((30, 30, 30), seed=5, hand="target")
    placed = assign_start_times(data)
    start = placed[0].start_ns
    messages = [m for traj in placed for m in step_messages(traj) if not (m[1] == start and m[0] != ACTION)]
    rig = Rig(ros, tmp_path, source_model)
    write_messages(rig.bag_dir / "episode_000", messages)
    response = rig.call()
    assert response.success, response.message
    result = rig.server.last_result
    assert result.episodes + result.held_out_episodes == 3  # the first episode from its second step on
    assert "skipped" not in response.message
    # the answer names what the reader dropped, and where
    assert f"while reading: {rig.bag_dir / 'episode_000'}: kept the whole steps only; dropped {ACTION} messages " \
           f"with no {JOINTS} within 50 ms: 1" in response.message, response.message


@pytest.mark.parametrize("case", sorted(BAD_SOURCES))
def test_unusable_source_model_is_refused(ros, tmp_path, source_model, case, capfd):
    make_path, reason = BAD_SOURCES[case]
    rig = Rig(ros, tmp_path, make_path(tmp_path, source_model))
    missing = [line for line in capfd.readouterr().err.splitlines()  # the node's log (stderr: see the camera's test)
               if "[WARN]" in line and "[transfer_server]" in line and "does not exist (yet)" in line]
    assert len(missing) == (case == "missing source"), missing  # at start, before any transfer is asked for
    add_target_bag(rig.bag_dir)
    response = rig.call()
    assert not response.success and "source model unusable" in response.message and reason in response.message
    assert rig.model_files() == [] and rig.updates == []
    assert rig.call().message == response.message, "the node still serves"


@pytest.mark.parametrize("failing_save", [1, 2], ids=["numbered model", "current model"])
def test_a_crash_while_saving_keeps_the_old_current_model(ros, tmp_path, source_model, make_set, monkeypatch,
                                                          failing_save):
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    current = rig.model_dir / CURRENT_MODEL
    old_bytes, old_state = current.read_bytes(), (rig.model_dir / STATE_FILE).read_text()
    add_synthetic_bag(rig.bag_dir, make_set, "episode_001")

    real_save, calls = checkpoint.save_file, []

    def crashing_save(tensors, filename, metadata=None):
        calls.append(filename)
        if len(calls) == failing_save:
            Path(filename).write_bytes(b"half a safetensors fi")
            raise OSError("disk full")
        real_save(tensors, filename, metadata=metadata)

    monkeypatch.setattr(checkpoint, "save_file", crashing_save)
    response = rig.call()
    assert not response.success and "disk full" in response.message
    assert current.read_bytes() == old_bytes
    load_model(current)
    assert (rig.model_dir / STATE_FILE).read_text() == old_state
    assert rig.model_files() == [CURRENT_MODEL, STATE_FILE, "transferred_000.safetensors"]
    assert rig.reports[-1].level == "ERROR" and rig.stages()[-1] == "failed"
    monkeypatch.setattr(checkpoint, "save_file", real_save)
    retry = rig.call()
    assert retry.success and "transferred_001" in retry.message, "the unrecorded bag is offered again"


@pytest.mark.parametrize("bad, word", [
    ({"bag_dir": ""}, "bag_dir"),
    ({"method": "nope"}, "method"),
    ({"config": "cumulative_residual: {train: {epochs: 1.5}}\n"}, "epochs"),
    ({"config": "nope: {}\n"}, "nope"),
    ({"config": "l2_finetune: {train: {lr: -1}}\n"}, "transfer.l2_finetune.train.lr must be > 0, got -1"),
    ({"config": "[unclosed\n"}, "YAML"),
    ({"holdout_fraction": 1.0}, "holdout_fraction"),
    ({"min_episodes": 1}, "min_episodes"),
    ({"progress_period_s": 0.0}, "progress_period_s"),
])
def test_bad_parameters_are_refused_at_start(ros, tmp_path, bad, word):
    params = server_params(tmp_path, tmp_path / "s.safetensors", **bad)
    if "config" in bad:
        params["config"] = config_file(tmp_path / "bad.yaml", bad["config"])
    with pytest.raises(ValueError, match=word):
        ros.add(TransferServer, params)


def test_missing_required_parameters_are_named(ros):
    with pytest.raises(ValueError, match="source_model"):
        ros.add(TransferServer, {"model_dir": "m", "bag_dir": "b"})


def test_parameters_change_at_run_time_and_take_effect_with_the_next_call(ros, tmp_path, source_model):
    rig = Rig(ros, tmp_path, source_model)
    server = rig.server
    refused = {
        "method": server.set_parameters([Parameter("method", value="nope")])[0],
        "holdout": server.set_parameters([Parameter("holdout_fraction", value=1.0)])[0],
        "config": server.set_parameters([Parameter("config", value=str(tmp_path / "missing.yaml"))])[0],
        "read-only": server.set_parameters([Parameter("model_dir", value=str(tmp_path / "elsewhere"))])[0],
    }
    assert not any(r.successful for r in refused.values())
    assert "method must be one of" in refused["method"].reason
    assert "missing.yaml" in refused["config"].reason
    assert "read-only" in refused["read-only"].reason
    assert server.params.method == "l2_finetune" and server.params.holdout_fraction == 0.25

    other = tmp_path / "three.yaml"
    other.write_text("l2_finetune: {train: {epochs: 3, patience: null}}\n")
    assert server.set_parameters([Parameter("config", value=str(other))])[0].successful
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    assert rig.reports[-1].values["epochs"] == "3"


def test_explicit_bags_instead_of_a_directory(ros, tmp_path, source_model):
    bag = add_target_bag(tmp_path)
    rig = Rig(ros, tmp_path, source_model, bag_dir="", bags=[str(bag)])
    assert rig.call().success and rig.server.last_result.bags == (bag,)


def test_config_files_hold_nested_overrides(tmp_path):
    assert config_from_file("") == config_with_overrides({})
    assert config_from_file(config_file(tmp_path / "empty.yaml", "")) == config_with_overrides({})
    overrides = "cumulative_residual: {alpha: 1, train: {patience: null}}\n"
    cfg = config_from_file(config_file(tmp_path / "alpha.yaml", overrides))
    assert cfg.cumulative_residual.alpha == 1.0 and cfg.cumulative_residual.train.patience is None
    with pytest.raises(ValueError, match="must be a mapping"):
        config_from_file(config_file(tmp_path / "list.yaml", "[1, 2]\n"))
    with pytest.raises(ValueError, match="No such file"):
        config_from_file(tmp_path / "missing.yaml")


@pytest.mark.parametrize("episodes, fraction, held", [(10, 0.25, 2), (4, 0.25, 1), (2, 0.9, 1), (3, 0.1, 1)])
def test_hold_out_takes_whole_episodes(make_set, episodes, fraction, held):
    data = make_set([10 + i for i in range(episodes)])
    train, test = hold_out(data, fraction, seed=3)
    assert len(test) == held and len(train) == episodes - held
    assert sorted(len(t) for t in (*train, *test)) == sorted(len(t) for t in data)
    assert [len(t) for t in hold_out(data, fraction, seed=3)[1]] == [len(t) for t in test]


def test_a_parameter_dump_gives_every_parameter_its_value(ros, tmp_path, source_model):
    """``ros2 param dump``: list_parameters, then get_parameters of every name (an unset ``bags`` once emptied it)."""
    from rcl_interfaces.srv import GetParameters, ListParameters

    rig = Rig(ros, tmp_path, source_model)
    listed = ros.call(rig.tester.create_client(ListParameters, "transfer_server/list_parameters"),
                      ListParameters.Request()).result.names
    values = ros.call(rig.tester.create_client(GetParameters, "transfer_server/get_parameters"),
                      GetParameters.Request(names=listed)).values
    got = dict(zip(listed, values, strict=True))
    assert {"bags", "bag_dir", "method", "source_model", "model_dir"} <= set(got)
    assert all(v.type != 0 for v in got.values()), [n for n, v in got.items() if v.type == 0]  # none NOT_SET
    assert list(got["bags"].string_array_value) == [] and got["method"].string_value == "l2_finetune"
    assert rig.server.describe_parameter("bags").read_only  # still, though declared writable until it held []
    (refused,) = rig.server.set_parameters([Parameter("bags", value=["x"])])
    assert not refused.successful and "read-only" in refused.reason


def test_twenty_simultaneous_calls_are_all_answered(ros, tmp_path, source_model):
    """One runs, the others are told it is busy or run after it: none is left unanswered (10 of 20 were)."""
    rig = Rig(ros, tmp_path, source_model, method="direct")
    add_target_bag(rig.bag_dir)
    clients = [rig.tester.create_client(Trigger, names.TRANSFER_NOW) for _ in range(20)]
    assert ros.spin_until(lambda: all(c.service_is_ready() for c in clients), 10.0)
    futures = [c.call_async(Trigger.Request()) for c in clients]
    assert ros.spin_until(lambda: all(f.done() for f in futures), 60.0), sum(f.done() for f in futures)
    answers = [f.result() for f in futures]
    assert sum(a.success for a in answers) >= 1
    assert all(a.success or a.message.startswith(("busy", "no new bags")) for a in answers), \
        [a.message for a in answers]


def test_torch_threads_sets_the_process_threads_and_is_read_only(ros: Any, tmp_path: Path, source_model: Path) -> None:
    import torch
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    rig = Rig(ros, tmp_path, source_model, torch_threads=2)
    assert torch.get_num_threads() == 2  # (one_torch_thread restores the suite's count afterwards)
    client = rig.tester.create_client(SetParameters, "transfer_server/set_parameters")
    request = SetParameters.Request(parameters=[Parameter("torch_threads", value=1).to_parameter_msg()])
    answer = ros.call(client, request).results[0]
    assert not answer.successful and "read-only" in answer.reason.lower()
    assert torch.get_num_threads() == 2
