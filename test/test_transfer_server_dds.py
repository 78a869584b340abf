"""The transfer server node over Cyclone DDS: a long transfer runs while a second call is answered busy and diagnostics flow."""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds", reason="cyclonedds (cyclonedds-python) is not installed")

from msg_adapters import DIAGNOSTIC_ARRAY, status_report  # noqa: E402
from t42_transfer.nodes.transfer_server import (  # noqa: E402
    STATUS_NAME,
    TRANSFER_SERVICE,
    TRIGGER,
    TransferServer,
    TransferServerParams,
)
from t42_transfer.ros import qos  # noqa: E402
from t42_transfer.ros.cyclone import CycloneTransport  # noqa: E402
from t42_transfer.transfer.methods import METHODS  # noqa: E402
from test_transfer_server import TINY, add_target_bag, source_model  # noqa: E402,F401  (fixture)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    """A random domain per test, localhost discovery, so concurrent runs do not meet."""
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return random.randint(100, 200)


def test_busy_answer_and_diagnostics_while_a_transfer_runs(tmp_path: Path, source_model: Path,
                                                           monkeypatch: pytest.MonkeyPatch, domain_id: int) -> None:
    entered, release = threading.Event(), threading.Event()

    def slow(source, target, cfg, seed, on_epoch=None):
        entered.set()
        assert release.wait(30.0)
        return METHODS["direct"](source, target, cfg, seed, on_epoch)

    monkeypatch.setitem(METHODS, "slow", slow)
    bag_dir = tmp_path / "bags"
    bag_dir.mkdir()
    add_target_bag(bag_dir)
    params = TransferServerParams(source_model=str(source_model), model_dir=str(tmp_path / "models"),
                                  bag_dir=str(bag_dir), method="slow", config=TINY, progress_period_s=0.05)
    with CycloneTransport("transfer_server", domain_id) as node, CycloneTransport("tester", domain_id) as tester:
        server = TransferServer(node, params)
        reports: list[Any] = []
        tester.subscribe("/diagnostics", DIAGNOSTIC_ARRAY, qos.QoSProfile(depth=10_000),
                         lambda msg: reports.append(status_report(msg, STATUS_NAME)))
        client = tester.client(TRANSFER_SERVICE, TRIGGER)
        stop = threading.Event()
        spinner = threading.Thread(target=lambda: node.spin(until=stop.is_set), daemon=True)
        spinner.start()
        first: list[Any] = []
        caller = threading.Thread(target=lambda: first.append(client.call(client.Request(), timeout_s=60.0)))
        caller.start()
        try:
            assert entered.wait(30.0)
            start = time.monotonic()
            second = client.call(client.Request(), timeout_s=5.0)
            assert time.monotonic() - start < 1.0
            assert not second.success and second.message.startswith("busy") and "training" in second.message
            assert tester.spin(until=lambda: sum(r.values["stage"] == "training" for r in reports) >= 3,
                               timeout_s=10.0), "progress is published on /diagnostics while training"
            assert server.busy and first == []
        finally:
            release.set()
            caller.join(60.0)
            stop.set()
            spinner.join(5.0)
        assert first and first[0].success, first
        assert "slow" in first[0].message and not server.busy
        assert tester.spin(until=lambda: reports[-1].values["stage"] == "done", timeout_s=5.0)
