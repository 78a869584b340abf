"""The transfer server's ``t42/transfer`` action through a plain rclpy ActionClient, in-process.

The client side (:class:`TransferClient`) uses only rclpy, t42_interfaces and action_msgs, as a ROS user's
script would; the server and its files come from the rig of test_transfer_server."""

from __future__ import annotations

import json
import math
import time
from typing import Any

import pytest
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from std_srvs.srv import Trigger
from t42_interfaces.action import Transfer  # (a broken interface build fails, never skips)
from test_transfer_server import Rig, add_synthetic_bag, add_target_bag, config_file, gated_method

from t42_transfer.models.checkpoint import read_metadata
from t42_transfer.transfer.online import CURRENT_MODEL, STATE_FILE

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.executor_threads(4)]

FOUR_EPOCHS = "l2_finetune: {train: {epochs: 4, patience: null}}\n"
ENDLESS = "l2_finetune: {train: {epochs: 100000, patience: null}}\n"
"""Training that would take minutes: only a cancel ends it in time."""


class TransferClient:
    """A user's Transfer client on its own rclpy node: send a goal, collect its feedback, wait for its result."""

    def __init__(self, ros: Any, node: Any, name: str = "t42/transfer") -> None:
        self.ros, self.node = ros, node
        self.client = ActionClient(node, Transfer, name)
        assert ros.spin_until(self.client.server_is_ready, 10.0), f"no {name} action server"

    def send(self, method: str = "", bags: list[str] | None = None, feedback: list | None = None) -> Any:
        """Send a goal; its (accepted) goal handle."""
        sent = self.client.send_goal_async(
            Transfer.Goal(method=method, bags=[str(b) for b in bags or []]),
            feedback_callback=None if feedback is None else (lambda m: feedback.append(m.feedback)))
        assert self.ros.spin_until(sent.done, 10.0), "no goal response"
        handle = sent.result()
        assert handle.accepted
        return handle

    def result(self, handle: Any, timeout_s: float = 120.0) -> Any:
        """The goal's status and result, once it ended."""
        future = handle.get_result_async()
        assert self.ros.spin_until(future.done, timeout_s), "no result"
        return future.result()


@pytest.fixture
def user(ros: Any) -> Any:
    """A node of the test's own, as a user's script makes it."""
    return ros.node("user")


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def test_a_goal_with_a_method_and_bags_gets_epoch_feedback_and_a_filled_result(ros, tmp_path, source_model,
                                                                                make_set, user):
    # the server's own method is direct: the goal's l2_finetune must be the one run
    rig = Rig(ros, tmp_path, source_model, method="direct", config=config_file(tmp_path / "four.yaml", FOUR_EPOCHS))
    named = add_target_bag(rig.bag_dir)
    add_synthetic_bag(rig.bag_dir, make_set, "episode_001")  # closed, new, but not named: not used
    missing = tmp_path / "nowhere" / "episode_404"
    client = TransferClient(ros, user)
    feedback: list = []
    got = client.result(client.send("l2_finetune", [str(named), str(missing)], feedback))

    assert got.status == GoalStatus.STATUS_SUCCEEDED, got.result.message
    result = got.result
    model = rig.model_dir / "transferred_000.safetensors"
    assert result.success and result.model_path == str(model) and model.is_file()
    assert "l2_finetune" in result.message and str(model) in result.message and "\n" not in result.message
    assert finite(result.model_divergence_steps, result.model_mse_mm2, result.source_divergence_steps,
                  result.source_mse_mm2, result.hold_still_divergence_steps, result.hold_still_mse_mm2)
    assert list(result.candidates) == [] and list(result.candidate_scores) == []  # not auto
    assert list(result.skipped_bags) == [str(missing)] and list(result.skipped_reasons) == ["does not exist"]
    meta = read_metadata(model)
    saved = meta["extra"]["evaluation"]  # the scores the result reports are the saved model's
    assert (result.model_divergence_steps, result.model_mse_mm2) == (saved["divergence_steps"],
                                                                     saved["position_mse_mm2"])
    assert meta["method"] == "l2_finetune" and meta["data"]["bags"] == [str(named.resolve())]
    assert ros.spin_until(lambda: rig.updates == [str(model)], 5.0), rig.updates
    assert rig.announcements[-1].method == "l2_finetune"

    phases = [f.phase for f in feedback]
    assert phases[0] == "loading" and phases[-1] == "saving" and "evaluating" in phases
    epochs = [f for f in feedback if f.epoch > 0]
    assert [f.epoch for f in epochs] == [1, 2, 3, 4]
    assert all(f.epochs == 4 and f.phase == "training: L2 fine-tune" and finite(f.train_loss) for f in epochs)
    assert all(f.epoch == f.epochs == 0 for f in feedback if not f.phase.startswith("training"))


def test_auto_reports_every_candidate_and_its_score(ros, tmp_path, source_model, user):
    settings = "auto: {candidates: [direct, l2_finetune]}\nl2_finetune: {train: {epochs: 2}}\n"
    rig = Rig(ros, tmp_path, source_model, config=config_file(tmp_path / "auto.yaml", settings))
    add_target_bag(rig.bag_dir)
    client = TransferClient(ros, user)
    feedback: list = []
    got = client.result(client.send("auto", feedback=feedback))  # no bags: those closed since the last transfer
    assert got.status == GoalStatus.STATUS_SUCCEEDED, got.result.message
    assert list(got.result.candidates) == ["direct", "l2_finetune"]
    assert len(got.result.candidate_scores) == 2 and finite(*got.result.candidate_scores)
    assert "auto picked" in got.result.message
    assert any(f.phase == "training: l2_finetune: L2 fine-tune" for f in feedback)
    assert json.loads((rig.model_dir / STATE_FILE).read_text())["transfers"][0]["method"] == "auto"


def test_a_cancelled_goal_stops_training_and_keeps_the_previous_model(ros, tmp_path, source_model, user):
    from t42_transfer.nodes.planner_node import PlannerNode

    rig = Rig(ros, tmp_path, source_model, method="direct", config=config_file(tmp_path / "endless.yaml", ENDLESS))
    bag = add_target_bag(rig.bag_dir)
    assert rig.call().success  # the previous model (direct: no training)
    assert ros.spin_until(lambda: len(rig.updates) == 1, 5.0)
    planner = ros.add(PlannerNode, {"samples": 50, "horizon": 5})  # plans with what t42/model_updated announces
    assert ros.spin_until(lambda: planner.model is not None and planner.model.path == rig.updates[0], 10.0)
    files = {p.name: p.read_bytes() for p in rig.model_dir.iterdir()}
    client = TransferClient(ros, user)
    feedback: list = []
    handle = client.send("l2_finetune", [str(bag)], feedback)  # the bag was used: named, it is used again
    assert ros.spin_until(lambda: any(f.epoch >= 1 for f in feedback), 60.0), "no training epoch"
    cancel = handle.cancel_goal_async()
    assert ros.spin_until(cancel.done, 5.0) and len(cancel.result().goals_canceling) == 1
    got = client.result(handle, 30.0)
    assert got.status == GoalStatus.STATUS_CANCELED
    assert not got.result.success and got.result.model_path == ""
    assert "cancelled while training" in got.result.message and "previous model stays" in got.result.message
    assert max(f.epoch for f in feedback) < 1000
    ros.spin_for(0.5)
    assert {p.name: p.read_bytes() for p in rig.model_dir.iterdir()} == files  # current, numbered, state: as they were
    assert len(rig.updates) == 1 and planner.model.path == rig.updates[0]  # nothing announced: the old model in use
    assert ros.spin_until(lambda: rig.stages()[-1] == "cancelled", 5.0) and rig.reports[-1].level == "OK"
    # the server serves on; the bag, not recorded by the cancelled goal, is taken again
    again = client.result(client.send("direct", [str(bag)]))
    assert again.status == GoalStatus.STATUS_SUCCEEDED
    assert again.result.model_path == str(rig.model_dir / "transferred_001.safetensors")
    assert read_metadata(rig.model_dir / CURRENT_MODEL)["method"] == "direct"
    assert ros.spin_until(lambda: planner.model.path == again.result.model_path, 10.0), "the planner takes the new one"


def test_a_goal_while_a_transfer_runs_is_aborted_busy_and_the_service_too(ros, tmp_path, source_model,
                                                                          monkeypatch, user):
    entered, release = gated_method(monkeypatch)
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    client = TransferClient(ros, user)
    first = client.send("slow")
    try:
        assert ros.spin_until(entered.is_set, 60.0)
        busy = client.result(client.send(), 5.0)  # answered while the first transfer's training is held
        assert busy.status == GoalStatus.STATUS_ABORTED and not busy.result.success
        assert busy.result.message.startswith("busy: a slow transfer is training"), busy.result.message
        assert busy.result.model_path == "" and math.isnan(busy.result.model_divergence_steps)
        answer = ros.call(rig.client, Trigger.Request(), 5.0)  # the service meanwhile: busy too
        assert not answer.success and answer.message.startswith("busy")
        assert first.status == GoalStatus.STATUS_EXECUTING  # the first runs on
    finally:
        release.set()
    got = client.result(first)
    assert got.status == GoalStatus.STATUS_SUCCEEDED and "slow" in got.result.message
    assert not rig.call().success  # the service works on after the goal (no new bags now)


def test_an_unknown_method_is_aborted_with_the_reason_and_nothing_runs(ros, tmp_path, source_model, user):
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    client = TransferClient(ros, user)
    got = client.result(client.send("nope"), 5.0)
    assert got.status == GoalStatus.STATUS_ABORTED and not got.result.success
    assert got.result.message.startswith("unknown transfer method 'nope'") and "l2_finetune" in got.result.message
    assert rig.reports == [] and rig.model_files() == []
    named_nothing = client.result(client.send("direct", [str(tmp_path / "missing"), str(tmp_path / "gone")]))
    assert named_nothing.status == GoalStatus.STATUS_ABORTED and "too little data" in named_nothing.result.message
    assert len(named_nothing.result.skipped_bags) == 2 == len(named_nothing.result.skipped_reasons)
    empty = client.result(client.send("direct", [str(tmp_path / "missing"), " "]))  # not read as the server's "."
    assert empty.status == GoalStatus.STATUS_ABORTED and empty.result.message.startswith("bags[1] is an empty path")
    bag = add_target_bag(rig.bag_dir, "episode_001")
    twice = client.result(client.send("direct", [str(bag), str(rig.bag_dir / ".." / rig.bag_dir.name / bag.name)]))
    assert twice.status == GoalStatus.STATUS_ABORTED and "named more than once" in twice.result.message, \
        twice.result.message  # its episodes would be trained on and held out at once
    assert rig.model_files() == []


def test_a_client_that_leaves_mid_goal_does_not_hurt_the_server(ros, tmp_path, source_model, monkeypatch, user):
    entered, release = gated_method(monkeypatch)
    rig = Rig(ros, tmp_path, source_model)
    add_target_bag(rig.bag_dir)
    leaver = ros.node("leaver")
    TransferClient(ros, leaver).send("slow", feedback=[])
    assert ros.spin_until(entered.is_set, 60.0)
    ros.executor.remove_node(leaver)
    ros.nodes.remove(leaver)
    leaver.destroy_node()
    ros.spin_for(0.3)
    release.set()
    model = rig.model_dir / "transferred_000.safetensors"
    assert ros.spin_until(lambda: rig.updates == [str(model)], 60.0), "the transfer finished and was announced"
    assert ros.spin_until(lambda: not rig.server.busy, 5.0)
    add_target_bag(rig.bag_dir, "episode_001")
    client = TransferClient(ros, user)
    got = client.result(client.send("direct"))
    assert got.status == GoalStatus.STATUS_SUCCEEDED, got.result.message


# ------------------------------------------------------------------ the adapters and the node's own words
def test_feedback_carries_the_stage_and_the_epoch_only_while_training():
    from msg_adapters.transfer import transfer_feedback

    loading = transfer_feedback("loading", {"method": "auto", "epoch": 3})
    assert (loading.phase, loading.epoch, loading.epochs) == ("loading", 0, 0) and math.isnan(loading.train_loss)
    start = transfer_feedback("training", {"epoch": 0, "epochs": 50, "episodes": 3})
    assert (start.phase, start.epoch, start.epochs) == ("training", 0, 50)
    epoch = transfer_feedback("training", {"phase": "residual", "epoch": 2, "epochs": 50, "train_loss": 0.5})
    assert (epoch.phase, epoch.epoch, epoch.train_loss) == ("training: residual", 2, 0.5) and math.isnan(epoch.val_loss)


def test_skipped_reasons_drop_the_bag_they_name_and_announcements_check_their_counts():
    from msg_adapters.transfer import model_announcement, model_updated_msg, skipped_pairs

    assert skipped_pairs([("/b/e1", "/b/e1: does not exist"), ("/b/e2", "odd")]) == (
        ("/b/e1", "does not exist"), ("/b/e2", "odd"))
    msg = model_updated_msg(1_500_000_000, " /m/transferred_000.safetensors", "residual", 7)
    assert model_announcement(msg) == (1_500_000_000, "/m/transferred_000.safetensors", "residual", 7)
    with pytest.raises(ValueError, match="uint32"):
        model_updated_msg(0, "/m", "x", 2**32)


def test_the_method_parameter_names_every_registered_method():
    import dataclasses

    from t42_transfer.nodes.transfer_server_params import TransferServerParams
    from t42_transfer.transfer.methods import METHODS

    (method,) = [f for f in dataclasses.fields(TransferServerParams) if f.name == "method"]
    description = method.metadata["t42_param"].description
    assert all(name in description for name in METHODS), description


def test_a_burst_of_goals_each_gets_a_result_and_one_transfer_runs(ros, tmp_path, source_model, user):
    rig = Rig(ros, tmp_path, source_model, method="direct")
    add_target_bag(rig.bag_dir)
    client = TransferClient(ros, user)
    sent, start = [], time.monotonic()
    for k in range(100):  # 100 goals a second, the executor spinning between them
        sent.append(client.client.send_goal_async(Transfer.Goal(method="" if k % 4 else "nope")))
        ros.spin_until(lambda k=k: time.monotonic() - start >= (k + 1) * 0.01, 0.05)
    assert ros.spin_until(lambda: all(s.done() for s in sent), 20.0), "goal responses"
    results = [s.result().get_result_async() for s in sent]
    assert ros.spin_until(lambda: all(r.done() for r in results), 60.0), sum(r.done() for r in results)
    ends = [(r.result().status, r.result().result.message) for r in results]
    assert all(s.result().accepted for s in sent)
    assert sum(status == GoalStatus.STATUS_SUCCEEDED for status, _ in ends) >= 1
    assert all(status == GoalStatus.STATUS_SUCCEEDED or message.startswith(("busy", "no new bags", "unknown"))
               for status, message in ends), ends
    assert [message.startswith("unknown") for _, message in ends] == [k % 4 == 0 for k in range(100)]
