"""The transfer server node on the in-process bus: summaries, progress, busy, refusals, atomic saves."""

from __future__ import annotations

import json
import math
import shutil
import threading
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

import t42_transfer.models.checkpoint as checkpoint
from msg_adapters import DIAGNOSTIC_ARRAY, diagnostic_array, status_report
from t42_transfer.data.bag_io import read_bag, write_bag
from t42_transfer.models.checkpoint import FORMAT, load_model, read_metadata, save_model
from t42_transfer.models.residual import CumulativeResidualModel
from t42_transfer.models.training import TrainConfig, train_transition_model
from t42_transfer.nodes.transfer_server import (
    MODEL_TOPIC,
    STATUS_NAME,
    STRING,
    TRANSFER_SERVICE,
    TRIGGER,
    TransferServer,
    TransferServerParams,
)
from t42_transfer.planning.workspace import Workspace
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport
from t42_transfer.ros.transport import deserialize, serialize
from t42_transfer.transfer.methods import METHODS
from t42_transfer.transfer.online import CURRENT_MODEL, STATE_FILE, config_with_overrides, hold_out

REPO = Path(__file__).resolve().parents[1]
TINY = {"cumulative_residual": {"train": {"epochs": 2}}}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


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


def add_synthetic_bag(bag_dir: Path, make_set, name: str, lengths=(30, 30, 30), seed: int = 5) -> Path:
    return write_bag(bag_dir / name, make_set(lengths, seed=seed, hand="target"))


class Rig:
    """A transfer server and a tester node (Trigger client, diagnostics and model-update subscribers)."""

    def __init__(self, tmp_path: Path, source: Path, **params: object) -> None:
        self.bag_dir, self.model_dir = tmp_path / "bags", tmp_path / "models"
        self.bag_dir.mkdir(exist_ok=True)
        self.bus = InProcessBus(clock=FakeClock(1_000_000_000))
        self.tester = InProcessTransport(self.bus, "tester")
        self.diagnostics: list = []
        self.updates: list[str] = []
        self.tester.subscribe("/diagnostics", DIAGNOSTIC_ARRAY, qos.QoSProfile(depth=10_000), self.diagnostics.append)
        self.tester.subscribe(MODEL_TOPIC, STRING, qos.TRANSIENT_LOCAL, lambda m: self.updates.append(m.data))
        self.node = InProcessTransport(self.bus, "transfer_server")
        settings = {"source_model": str(source), "model_dir": str(self.model_dir), "bag_dir": str(self.bag_dir),
                    "config": TINY, "progress_period_s": 0.02, **params}
        self.server = TransferServer(self.node, TransferServerParams(**settings))
        self.client = self.tester.client(TRANSFER_SERVICE, TRIGGER)

    def call(self):
        response = self.client.call(self.client.Request())
        self.spin()
        return response

    def spin(self) -> None:
        self.tester.spin_once()

    def statuses(self):
        return [status_report(a, STATUS_NAME) for a in self.diagnostics]

    def stages(self) -> list[str]:
        """Stages in order of arrival, repeats collapsed."""
        out: list[str] = []
        for report in self.statuses():
            if not out or out[-1] != report.values["stage"]:
                out.append(report.values["stage"])
        return out

    def model_files(self) -> list[str]:
        return sorted(p.name for p in self.model_dir.iterdir()) if self.model_dir.exists() else []


def test_transfer_answers_with_summary_saves_and_announces(tmp_path, source_model):
    rig = Rig(tmp_path, source_model)
    bag = add_target_bag(rig.bag_dir)
    response = rig.call()
    assert response.success, response.message
    model_path = rig.model_dir / "transferred_000.safetensors"
    for part in ("cumulative_residual", "episodes", "transitions", "held-out", "divergence", "mm^2", str(model_path)):
        assert part in response.message
    assert rig.updates == [str(model_path)]
    assert rig.model_files() == [CURRENT_MODEL, STATE_FILE, "transferred_000.safetensors"]
    model, meta = load_model(rig.model_dir / CURRENT_MODEL)
    assert isinstance(model, CumulativeResidualModel) and meta["method"] == "cumulative_residual"
    assert meta["data"]["bags"] == [str(bag.resolve())]
    merged = Workspace.from_metadata(meta)
    source = Workspace.from_metadata(read_metadata(source_model))
    assert (merged.lower <= source.lower).all() and (merged.upper >= source.upper).all()
    assert read_metadata(model_path)["data"] == meta["data"]
    result = rig.server.last_result
    assert (result.episodes, result.held_out_episodes) == (3, 1)

    assert rig.stages() == ["loading", "training", "evaluating", "saving", "done"]
    last = rig.statuses()[-1]
    assert last.level == "OK" and last.message == response.message
    assert last.values["method"] == "cumulative_residual" and last.values["bags"] == bag.name
    assert last.values["epochs"] == "2" and last.values["model"] == str(model_path)
    assert float(last.values["elapsed_s"]) >= 0.0


def test_diagnostics_follow_the_training_epochs(tmp_path, source_model):
    rig = Rig(tmp_path, source_model, config={"cumulative_residual": {"train": {"epochs": 4, "patience": None}}})
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    training = [r for r in rig.statuses() if r.values["stage"] == "training"]
    epochs = [int(r.values["epoch"]) for r in training]
    assert epochs == sorted(epochs) and set(epochs) == {0, 1, 2, 3, 4}
    trained = [r for r in training if int(r.values["epoch"]) > 0]
    assert all(r.values["phase"] == "residual" and r.values["epochs"] == "4" for r in trained)
    assert all(math.isfinite(float(r.values["train_loss"])) for r in trained)
    assert trained[-1].message == "training residual: epoch 4/4"


def test_bags_are_used_once(tmp_path, source_model, make_set):
    rig = Rig(tmp_path, source_model)
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
    assert rig.updates[-1] == str(rig.model_dir / "transferred_001.safetensors")


def test_a_restarted_server_announces_the_latest_model(tmp_path, source_model):
    rig = Rig(tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    assert rig.call().success
    rig.node.close()
    late = Rig(tmp_path, source_model)
    late.spin()
    assert late.updates == [str(rig.model_dir / "transferred_000.safetensors")]


def test_second_call_while_running_is_answered_busy(tmp_path, source_model, monkeypatch):
    entered, release = threading.Event(), threading.Event()

    def slow(source, target, cfg, seed, on_epoch=None):
        entered.set()
        assert release.wait(5.0)
        return METHODS["direct"](source, target, cfg, seed, on_epoch)

    monkeypatch.setitem(METHODS, "slow", slow)
    rig = Rig(tmp_path, source_model, method="slow")
    add_target_bag(rig.bag_dir)
    first: list = []
    caller = threading.Thread(target=lambda: first.append(rig.client.call(rig.client.Request())))
    caller.start()
    try:
        assert entered.wait(5.0)
        assert rig.server.busy
        second = rig.client.call(rig.client.Request())
        assert not second.success and second.message.startswith("busy") and "training" in second.message
        threading.Event().wait(0.15)  # a few progress periods
        rig.spin()
        training = [r for r in rig.statuses() if r.values["stage"] == "training"]
        assert len(training) >= 3, "progress is re-published while training"
        elapsed = [float(r.values["elapsed_s"]) for r in training]
        assert elapsed == sorted(elapsed)
    finally:
        release.set()
        caller.join(10.0)
    assert first and first[0].success, first
    assert not rig.server.busy
    rig.spin()
    assert rig.stages()[-1] == "done"


def _corrupt_bag(bag_dir: Path) -> Path:
    bag = bag_dir / "episode_000"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    (bag / "episode_000_0.mcap").write_bytes(b"\x89MCAP0\r\n not really an mcap file")
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
    "no bags": (lambda rig, tmp, src, make_set: None, "no new bags"),
    "too little data": (lambda rig, tmp, src, make_set: add_synthetic_bag(rig.bag_dir, make_set, "e", (30,)),
                        "too little data"),
    "corrupt bag": (lambda rig, tmp, src, make_set: _corrupt_bag(rig.bag_dir), "unreadable bag"),
}
BAD_SOURCES = {
    "missing source": (lambda tmp, src: tmp / "missing.safetensors", "does not exist"),
    "residual source": (_residual_source, "plain transition model"),
    "wrong state layout": (_wrong_layout_source, "state layout"),
}


@pytest.mark.parametrize("case", sorted(BAD_REQUESTS))
def test_bad_data_is_refused_and_the_node_serves_on(tmp_path, source_model, make_set, case):
    rig = Rig(tmp_path, source_model)
    setup, reason = BAD_REQUESTS[case]
    setup(rig, tmp_path, source_model, make_set)
    response = rig.call()
    assert not response.success and reason in response.message, response.message
    if case == "corrupt bag":
        assert "episode_000" in response.message
    assert rig.model_files() == []
    assert rig.stages()[-1] == "failed" and rig.statuses()[-1].level == "WARN"
    assert rig.statuses()[-1].message == response.message
    for bag in list(rig.bag_dir.iterdir()):
        shutil.rmtree(bag)
    add_target_bag(rig.bag_dir, "episode_009")
    assert rig.call().success


@pytest.mark.parametrize("case", sorted(BAD_SOURCES))
def test_unusable_source_model_is_refused(tmp_path, source_model, case):
    make_path, reason = BAD_SOURCES[case]
    rig = Rig(tmp_path, make_path(tmp_path, source_model))
    add_target_bag(rig.bag_dir)
    response = rig.call()
    assert not response.success and "source model unusable" in response.message and reason in response.message
    assert rig.model_files() == [] and rig.updates == []
    assert rig.call().message == response.message, "the node still serves"


@pytest.mark.parametrize("failing_save", [1, 2], ids=["numbered model", "current model"])
def test_a_crash_while_saving_keeps_the_old_current_model(tmp_path, source_model, make_set, monkeypatch, failing_save):
    rig = Rig(tmp_path, source_model)
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
    assert rig.statuses()[-1].level == "ERROR" and rig.stages()[-1] == "failed"
    monkeypatch.setattr(checkpoint, "save_file", real_save)
    retry = rig.call()
    assert retry.success and "transferred_001" in retry.message, "the unrecorded bag is offered again"


def test_params_are_checked(tmp_path):
    base = {"source_model": "s.safetensors", "model_dir": str(tmp_path), "bag_dir": str(tmp_path)}
    TransferServerParams(**base)
    for bad, word in (
        ({"bag_dir": ""}, "bag_dir"),
        ({"method": "nope"}, "method"),
        ({"config": {"cumulative_residual": {"train": {"epochs": 1.5}}}}, "epochs"),
        ({"config": {"nope": {}}}, "nope"),
        ({"holdout_fraction": 1.0}, "holdout_fraction"),
        ({"min_episodes": 1}, "min_episodes"),
        ({"service": "t42/transfer"}, "absolute"),
    ):
        with pytest.raises(ValueError, match=word):
            TransferServerParams(**{**base, **bad})
    cfg = config_with_overrides({"cumulative_residual": {"alpha": 1, "train": {"patience": None}}})
    assert cfg.cumulative_residual.alpha == 1.0 and cfg.cumulative_residual.train.patience is None


@pytest.mark.parametrize("episodes, fraction, held", [(10, 0.25, 2), (4, 0.25, 1), (2, 0.9, 1), (3, 0.1, 1)])
def test_hold_out_takes_whole_episodes(make_set, episodes, fraction, held):
    data = make_set([10 + i for i in range(episodes)])
    train, test = hold_out(data, fraction, seed=3)
    assert len(test) == held and len(train) == episodes - held
    assert sorted(len(t) for t in (*train, *test)) == sorted(len(t) for t in data)
    assert [len(t) for t in hold_out(data, fraction, seed=3)[1]] == [len(t) for t in test]


def test_diagnostics_round_trip():
    msg = diagnostic_array(STATUS_NAME, "WARN", "refused", {"stage": "failed", "epoch": 3, "ok": False}, 5_000_000_001)
    back = deserialize(DIAGNOSTIC_ARRAY, serialize(DIAGNOSTIC_ARRAY, msg))
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (5, 1)
    report = status_report(back, STATUS_NAME)
    assert report.level == "WARN" and report.message == "refused"
    assert report.values == {"stage": "failed", "epoch": "3", "ok": "false"}
    with pytest.raises(KeyError):
        status_report(back, "another node")
    with pytest.raises(ValueError, match="level"):
        diagnostic_array(STATUS_NAME, "FINE", "", {}, 0)
