"""Recorder and player across processes over Cyclone DDS: lossless replay, and a SIGKILLed recorder's bag.

"Byte-identical" here means: per topic, the same CDR payloads in the same order,
and the same topics, types and counts.  Log times are receive times of the
re-recording, so they differ from the original bag's (and the interleaving of
topics may differ by the ms it takes to deliver each).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
import warnings
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds", reason="cyclonedds (cyclonedds-python) is not installed")

from rosbags.highlevel import AnyReader  # noqa: E402

from msg_adapters import HAND_TOPICS, applied_action_msg, joint_state_msg, object_pose_msg  # noqa: E402
from t42_transfer.conventions import CONTROL_PERIOD_NS  # noqa: E402
from t42_transfer.data.bag_io import read_bag  # noqa: E402
from t42_transfer.data.bag_repair import repair_bag  # noqa: E402
from t42_transfer.nodes.player import BagPlayer, PlayerParams, wait_for_subscribers  # noqa: E402
from t42_transfer.ros import qos  # noqa: E402
from t42_transfer.ros.cyclone import CycloneTransport  # noqa: E402
from t42_transfer.ros.transport import serialize  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "target_small"

RECORDER_SCRIPT = textwrap.dedent(
    """
    import sys
    from t42_transfer.nodes.recorder import Recorder, RecorderParams
    from t42_transfer.ros.cyclone import CycloneTransport

    out, expected, flush_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])

    class Node(CycloneTransport):
        def service(self, name, srvtype, handler):
            try:
                super().service(name, srvtype, handler)
            except NotImplementedError:  # a backend without services: these tests do not call them
                pass

    class Reporting(Recorder):
        def flush(self):
            super().flush()
            print("flushed", self.current_count, flush=True)

    with Node("recorder") as node:
        rec = Reporting(node, RecorderParams(out, flush_period_s=flush_s))
        print("ready", flush=True)
        node.spin(until=lambda: expected and rec.current_count >= expected, timeout_s=90)
        rec.close()
        print("closed", rec.bags[-1] if rec.bags else "", flush=True)
    """
)


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return random.randint(100, 200)


class RecorderProcess:
    """The recorder in a subprocess; its stdout lines are collected by a thread."""

    def __init__(self, out: Path, domain_id: int, expected: int = 0, flush_s: float = 1.0) -> None:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONPATH=str(REPO))
        self.proc = subprocess.Popen([sys.executable, "-c", RECORDER_SCRIPT, str(out), str(expected), str(flush_s)],
                                     cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.strip())

    def wait_line(self, prefix: str, timeout_s: float = 30.0) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            found = [line for line in self.lines if line.startswith(prefix)]
            if found:
                return found[-1]
            if self.proc.poll() is not None and not self._reader.is_alive():
                break
            time.sleep(0.02)
        raise AssertionError(f"no {prefix!r} from the recorder; stderr: {self.stderr()}")

    def flushed(self) -> list[int]:
        return [int(line.split()[1]) for line in list(self.lines) if line.startswith("flushed")]

    def stderr(self) -> str:
        if self.proc.poll() is None:
            return "(still running)"
        assert self.proc.stderr is not None
        return self.proc.stderr.read()[-3000:]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        self._reader.join(10)
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()


def payloads(bag: Path) -> tuple[dict[str, str], dict[str, list[bytes]]]:
    """Types and, per topic, the payloads in log-time order."""
    with AnyReader([bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        got: dict[str, list[bytes]] = {topic: [] for topic in types}
        for conn, _, raw in reader.messages():
            got[conn.topic].append(bytes(raw))
    return types, got


def test_replayed_bag_is_recorded_byte_identical(tmp_path: Path, domain_id: int) -> None:
    types, original = payloads(BAG)
    total = sum(len(m) for m in original.values())
    recorder = RecorderProcess(tmp_path / "out", domain_id, expected=total)
    try:
        recorder.wait_line("ready")
        with CycloneTransport("player", domain_id) as node:
            player = BagPlayer(node, PlayerParams(BAG, rate=20.0, start_paused=True))
            assert wait_for_subscribers(player, 30.0), "the recorder's readers never matched"
            node.spin(timeout_s=0.5)  # let the readers match the writers too
            player.resume()
            assert node.spin(until=lambda: player.done, timeout_s=60.0)
            player.close()
        closed = recorder.wait_line("closed", 60.0)
    finally:
        recorder.kill()
    bag = Path(closed.split(maxsplit=1)[1])
    got_types, got = payloads(bag)
    assert got_types == types
    assert {t: len(m) for t, m in got.items()} == {t: len(m) for t, m in original.items()}
    assert got == original
    assert len(read_bag(bag)) == len(read_bag(BAG))


def test_sigkilled_recorder_leaves_a_bag_that_repairs_clean(tmp_path: Path, domain_id: int) -> None:
    out = tmp_path / "out"
    recorder = RecorderProcess(out, domain_id, flush_s=0.5)
    sent: dict[str, list[bytes]] = {topic: [] for topic in HAND_TOPICS}
    try:
        recorder.wait_line("ready")
        with CycloneTransport("hand", domain_id) as node:
            pubs = {topic: node.publisher(topic, msgtype, qos.DEFAULT) for topic, msgtype in HAND_TOPICS.items()}
            deadline = time.monotonic() + 30
            while not all(p.writer.get_matched_subscriptions() for p in pubs.values()):
                assert time.monotonic() < deadline, "the recorder's readers never matched"
                time.sleep(0.02)
            time.sleep(0.5)
            k, t0 = 0, 1_000_000_000
            while len([n for n in recorder.flushed() if n > 0]) < 4:  # publish through a few flushes, then kill
                assert k < 5000, f"the recorder did not flush; stderr: {recorder.stderr()}"
                stamp = t0 + k * CONTROL_PERIOD_NS
                for topic, msg in (
                    ("/hand/object_pose", object_pose_msg([k % 17, -3.0], stamp)),
                    ("/hand/joint_states", joint_state_msg([10.0 + k % 5, -20.0], None, stamp)),
                    ("/hand/applied_action", applied_action_msg([0.5, -0.5], stamp)),
                ):
                    data = serialize(HAND_TOPICS[topic], msg)
                    pubs[topic].publish_raw(data)
                    sent[topic].append(data)
                k += 1
                time.sleep(0.01)
            flushed = recorder.flushed()[-1]
            recorder.proc.send_signal(signal.SIGKILL)
            recorder.proc.wait(10)
    finally:
        recorder.kill()
    bag = out / "recording_000"
    assert not (bag / "metadata.yaml").exists()  # killed: rosbags writes it only on close

    with pytest.warns(UserWarning, match="recovered the readable prefix"):
        prefix = read_bag(bag)
    assert len(prefix) == 1 and prefix.num_transitions >= flushed // 3 - 2

    report = repair_bag(bag)
    assert report.repaired and report.message_count >= flushed
    assert report.message_count <= sum(len(m) for m in sent.values())
    _, got = payloads(bag)
    assert got == {topic: sent[topic][: report.counts[topic]] for topic in sent}  # nothing lost before the cut
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data = read_bag(bag)
    assert data.num_transitions >= prefix.num_transitions
