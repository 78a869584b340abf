"""Recorder and player as processes over ROS 2 (rclpy, Fast DDS): lossless replay, and a SIGKILLed recorder's bag.

"Byte-identical" here means: per topic, the same CDR payloads in the same order,
and the same topics, types and counts.  Log times are receive times of the
re-recording, so they differ from the original bag's.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import pytest
from bag_builders import fixture_message_count
from ros_rig import REPO, start_node, stop
from rosbags.highlevel import AnyReader

from msg_adapters import (
    HAND_TOPICS,
    TYPESTORE,
    applied_action_msg,
    joint_state_msg,
    object_pose_msg,
    rclpy_class,
)
from t42_transfer.cli import main
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import read_bag
from t42_transfer.ros.qos import recording

BAG = REPO / "bags" / "target_small"


def payloads(bag: Path) -> tuple[dict[str, str], dict[str, list[bytes]]]:
    """Types and, per topic, the payloads in log-time order."""
    with AnyReader([bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        got: dict[str, list[bytes]] = {topic: [] for topic in types}
        for conn, _, raw in reader.messages():
            got[conn.topic].append(bytes(raw))
    return types, got


def wait_for(condition: Any, timeout_s: float, what: str, log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} within {timeout_s} s; recorder log:\n{log.read_text()[-3000:]}")
        time.sleep(0.05)


def test_replayed_bag_is_recorded_byte_identical(ros_domain: int, tmp_path: Path) -> None:
    types, original = payloads(BAG)
    out, log = tmp_path / "out", tmp_path / "recorder.log"
    recorder = start_node("recorder", "-p", f"out_dir:={out}", log=log)
    try:
        wait_for(lambda: (out / "recording_000").is_dir(), 30.0, "the recorder did not start", log)
        player = subprocess.run(
            [sys.executable, "-m", "t42_transfer.cli", "bag", "play", str(BAG), "--rate", "20",
             "--wait-subscribers", "30"], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert player.returncode == 0, player.stderr
        assert f"published {fixture_message_count(BAG)} messages on 3 topics" in player.stdout
        assert "not every topic" not in player.stderr
        time.sleep(1.0)  # the bag's last state waits step_hold_s for an action that never comes
    finally:
        codes = stop([recorder])
    assert codes == [0], log.read_text()[-3000:]
    bag = out / "recording_000"
    got_types, got = payloads(bag)
    assert got_types == types
    assert {t: len(m) for t, m in got.items()} == {t: len(m) for t, m in original.items()}
    assert got == original
    assert len(read_bag(bag)) == len(read_bag(BAG))


def test_sigkilled_recorder_leaves_a_bag_that_repairs_clean(ros: Any, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    out, log = tmp_path / "out", tmp_path / "recorder.log"
    recorder = start_node("recorder", "-p", f"out_dir:={out}", "-p", "flush_period_s:=0.3", log=log)
    sent: dict[str, list[bytes]] = {topic: [] for topic in HAND_TOPICS}
    mcap = out / "recording_000" / "recording_000.mcap"
    try:
        node = ros.node("hand")
        pubs = {t: node.create_publisher(rclpy_class(m), t, recording(1000)) for t, m in HAND_TOPICS.items()}
        wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 30.0,
                 "the recorder's subscriptions never matched", log)
        time.sleep(1.0)  # the recorder's side matches on its own
        sizes, k, t0 = [], 0, time.time_ns() // CONTROL_PERIOD_NS * CONTROL_PERIOD_NS
        while len(set(sizes)) < 5:  # publish through a few flushes, then kill
            assert k < 3000, f"the recorder did not flush; log:\n{log.read_text()[-3000:]}"
            stamp = t0 + k * CONTROL_PERIOD_NS
            for topic, msg in (
                ("/hand/object_pose", object_pose_msg([k % 17, -3.0], stamp)),
                ("/hand/joint_states", joint_state_msg([10.0 + k % 5, -20.0], None, stamp)),
                ("/hand/applied_action", applied_action_msg([0.5, -0.5], stamp)),
            ):
                data = bytes(TYPESTORE.serialize_cdr(msg, HAND_TOPICS[topic]))
                pubs[topic].publish(data)
                sent[topic].append(data)
            k += 1
            time.sleep(0.01)
            if mcap.exists() and mcap.stat().st_size > 100:
                sizes.append(mcap.stat().st_size)
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(10)
    finally:
        stop([recorder])
    bag = out / "recording_000"
    assert not (bag / "metadata.yaml").exists()  # killed: rosbags writes it only on close

    with pytest.warns(UserWarning, match="recovered the readable prefix"):
        prefix = read_bag(bag)
    assert len(prefix) == 1 and prefix.num_transitions >= 10

    assert main(["bag", "repair", str(bag)]) == 0
    assert f"{bag}: repaired" in capsys.readouterr().out
    _, got = payloads(bag)
    counts = {topic: len(m) for topic, m in got.items()}
    assert sum(counts.values()) >= 3 * prefix.num_transitions
    assert got == {topic: sent[topic][: counts[topic]] for topic in sent}  # nothing lost before the cut
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data = read_bag(bag)
    assert data.num_transitions >= prefix.num_transitions
