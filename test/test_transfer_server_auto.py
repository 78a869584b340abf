"""The transfer server's automatic transfers: after N new closed bags (recorder/bag_closed), one transfer by itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger
from t42_interfaces.msg import BagClosed
from test_recorder import Hand, add_recorder, now_ns
from test_transfer_server import Rig, add_synthetic_bag, add_target_bag, gated_method

from msg_adapters import names, status_message
from msg_adapters.events import SNAPSHOT, BagClosedEvent, bag_closed_msg
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import read_bag
from t42_transfer.models.checkpoint import read_metadata
from t42_transfer.ros.qos import profile

pytestmark = [pytest.mark.usefixtures("one_torch_thread"), pytest.mark.executor_threads(4)]


class Recorder:
    """The test as a recorder: announces bags it wrote on recorder/bag_closed."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.pub = rig.tester.create_publisher(BagClosed, names.BAG_CLOSED, profile(names.EVENTS))
        assert rig.wait_graph(subscribers={names.BAG_CLOSED: 1}), "the transfer server never subscribed"

    def closed(self, bag: Path, reason: str = "split") -> None:
        event = BagClosedEvent(str(bag), len(read_bag(bag)), 1, 1, 2, reason)
        self.pub.publish(bag_closed_msg(event))
        self.rig.ros.spin_for(0.3)


def test_two_closed_bags_start_one_transfer_that_announces_a_model(ros: Any, tmp_path: Path, source_model: Path,
                                                                   make_set: Any) -> None:
    rig = Rig(ros, tmp_path, source_model, auto_transfer_after_bags=2)
    rec = Recorder(rig)
    first, second = add_target_bag(rig.bag_dir), add_synthetic_bag(rig.bag_dir, make_set, "episode_001")
    rec.closed(first)
    assert not rig.reports and rig.server.new_bags == 1  # one bag: nothing yet
    rec.closed(second)
    model = rig.model_dir / "transferred_000.safetensors"
    assert ros.spin_until(lambda: rig.updates == [str(model)], 60.0), rig.updates
    assert ros.spin_until(lambda: rig.ends(), 5.0) and rig.stages() == ["loading", "training", "evaluating",
                                                                          "saving", "done"]
    (ok, message), = rig.server.auto_results
    assert ok and str(model) in message and rig.reports[-1].message == message  # as a call would answer
    assert read_metadata(model)["data"]["bags"] == [str(first.resolve()), str(second.resolve())]
    assert rig.server.new_bags == 0
    ros.spin_for(0.5)
    assert len(rig.server.auto_results) == 1 and len(rig.updates) == 1  # one transfer for two bags


def test_snapshot_bags_do_not_count(ros: Any, tmp_path: Path, source_model: Path, make_set: Any) -> None:
    """A snapshot bag repeats steps the recorder's own bags hold: it starts no transfer."""
    rig = Rig(ros, tmp_path, source_model, auto_transfer_after_bags=1)
    rec = Recorder(rig)
    rec.closed(add_synthetic_bag(rig.bag_dir, make_set, "episode_000"), reason=SNAPSHOT)
    ros.spin_for(0.5)
    assert rig.server.new_bags == 0 and not rig.server.auto_results and not rig.updates
    rec.closed(rig.bag_dir / "episode_000")  # the same bag closed as a recording: it counts
    assert ros.spin_until(lambda: len(rig.updates) == 1, 60.0), rig.updates


def test_off_by_default_nothing_happens(ros: Any, tmp_path: Path, source_model: Path, make_set: Any) -> None:
    rig = Rig(ros, tmp_path, source_model)
    rec = Recorder(rig)
    for i in range(3):
        rec.closed(add_synthetic_bag(rig.bag_dir, make_set, f"episode_00{i}"))
    ros.spin_for(1.0)
    assert not rig.reports and not rig.updates and not rig.server.auto_results and rig.server.new_bags == 0
    assert not rig.model_dir.exists() or not any(rig.model_dir.iterdir())
    # switched on while running: it counts from then on
    rig.server.set_parameters([Parameter("auto_transfer_after_bags", value=1)])
    rec.closed(rig.bag_dir / "episode_000")
    assert ros.spin_until(lambda: len(rig.updates) == 1, 60.0), rig.updates


def test_bags_closed_during_a_transfer_run_one_more_after_it(ros: Any, tmp_path: Path, source_model: Path,
                                                             make_set: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    entered, release = gated_method(monkeypatch)
    rig = Rig(ros, tmp_path, source_model, method="slow", auto_transfer_after_bags=1)
    rec = Recorder(rig)
    add_target_bag(rig.bag_dir)
    assert rig.client.wait_for_service(timeout_sec=10.0)
    call = rig.client.call_async(Trigger.Request())
    try:
        assert ros.spin_until(entered.is_set, 60.0) and rig.server.busy
        entered.clear()
        rec.closed(add_synthetic_bag(rig.bag_dir, make_set, "episode_001"))  # two triggers while it trains: one run
        rec.closed(add_synthetic_bag(rig.bag_dir, make_set, "episode_002", lengths=(30, 30, 31)))
        assert not rig.server.auto_results and not entered.is_set()  # it waits for the call's transfer
    finally:
        release.set()
    assert ros.spin_until(call.done, 60.0) and call.result().success
    assert ros.spin_until(lambda: len(rig.updates) == 2, 60.0), rig.updates
    ros.spin_for(0.5)
    assert [ok for ok, _ in rig.server.auto_results] == [True] and len(rig.updates) == 2
    second = read_metadata(rig.model_dir / "transferred_001.safetensors")["data"]["bags"]
    assert [Path(b).name for b in second] == ["episode_001", "episode_002"]  # the bags new since the call's


def test_a_recorder_in_episode_mode_and_the_server_transfer_after_two_episodes(ros: Any, tmp_path: Path,
                                                                              source_model: Path) -> None:
    """The real recorder node closes two episode bags into the server's bag_dir: one transfer on both."""
    rig = Rig(ros, tmp_path, source_model, auto_transfer_after_bags=2)
    rec = add_recorder(ros, rig.bag_dir, mode="episode", step_hold_s=1.0)
    hand = Hand(ros, rec)
    t0 = now_ns()
    hand.episode(t0, 20, seed=1)
    hand.status(status_message(names.DROPPED, "episode 0 ended", t0 + 20 * CONTROL_PERIOD_NS))
    hand.settle()
    start = t0 + 10 * 10**9
    hand.episode(start, 20, seed=2)
    hand.status(status_message(names.RESET, "episode 1 grasped", start + 20 * CONTROL_PERIOD_NS))
    hand.settle()
    model = rig.model_dir / "transferred_000.safetensors"
    assert ros.spin_until(lambda: rig.updates == [str(model)], 60.0), (rig.updates, rig.server.auto_results)
    bags = read_metadata(model)["data"]["bags"]
    assert [Path(b).name for b in bags] == ["episode_000", "episode_001"] and rig.server.auto_results[0][0]
