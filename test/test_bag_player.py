"""The bag player on the in-process bus with a fake clock: order, timing, bytes, controls, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from msg_adapters import HAND_TOPICS
from t42_transfer.cli import main
from t42_transfer.data.errors import BagError
from t42_transfer.nodes.player import BagPlayer, PlayerParams, play_bag
from t42_transfer.ros import qos
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "target_small"
T0_NS = 7_000_000_000
TICK_NS = 1_000_000


def bag_messages(bag: Path = BAG) -> list[tuple[str, int, bytes]]:
    with AnyReader([bag]) as reader:
        return [(conn.topic, log_ns, bytes(raw)) for conn, log_ns, raw in reader.messages()]


class Rig:
    """A player node and a sink node recording (clock, topic, bytes) per message."""

    def __init__(self, **params: object) -> None:
        self.clock = FakeClock(T0_NS)
        bus = InProcessBus(clock=self.clock)
        self.node, self.sink = InProcessTransport(bus, "player"), InProcessTransport(bus, "sink")
        self.got: list[tuple[int, str, bytes]] = []
        for topic, msgtype in HAND_TOPICS.items():
            self.sink.subscribe(topic, msgtype, qos.QoSProfile(depth=10_000),
                                lambda data, t=topic: self.got.append((self.clock(), t, data)), raw=True)
        self.player = BagPlayer(self.node, PlayerParams(params.pop("bag", BAG), **params))

    def run(self, ticks: int) -> None:
        for _ in range(ticks):
            self.clock.advance(ns=TICK_NS)
            self.node.spin_once()
            self.sink.spin_once()


@pytest.mark.parametrize("rate", [1.0, 2.5])
def test_messages_come_out_in_order_with_their_spacing_and_bytes(rate: float) -> None:
    expected = bag_messages()
    first = expected[0][1]
    rig = Rig(rate=rate)
    duration_ticks = (expected[-1][1] - first) / rate / TICK_NS
    rig.run(int(duration_ticks) + 5)
    assert rig.player.done and rig.player.published == len(expected)
    assert [(t, d) for _, t, d in rig.got] == [(t, d) for t, _, d in expected]  # order and bytes
    for (sent_at, _, _), (_, log_ns, _) in zip(rig.got, expected):
        due = T0_NS + round((log_ns - first) / rate)
        assert due <= sent_at < due + TICK_NS or sent_at == T0_NS + TICK_NS  # the first tick is 1 ms in
    rig.run(100)
    assert len(rig.got) == len(expected)


def test_topic_filter_pause_resume_and_loop() -> None:
    expected = bag_messages()
    poses = [m for m in expected if m[0] == "/hand/object_pose"]
    rig = Rig(topics=("/hand/object_pose",), start_paused=True, rate=10.0)
    assert set(rig.player.publishers) == {"/hand/object_pose"}
    rig.run(1000)
    assert rig.got == [] and rig.player.paused
    rig.player.resume()
    start = rig.clock()
    rig.run(100)  # 1 s of a 10x playback: the first 10 s of the bag
    played = len(rig.got)
    assert 0 < played < len(poses)
    rig.player.pause()
    rig.run(2000)
    assert len(rig.got) == played
    rig.player.resume()
    rig.run(5000)
    assert rig.player.done and [d for _, _, d in rig.got] == [d for _, _, d in poses]
    assert rig.got[-1][0] - start >= (poses[-1][1] - poses[0][1]) / 10 + 2000 * TICK_NS  # paused time did not count

    looping = Rig(topics=("/hand/object_pose",), rate=100.0, loop=True)
    looping.run(2 * 420 + 50)  # two passes of the 42 s bag at 100x
    assert looping.player.loops == 2 and not looping.player.done
    assert [d for _, _, d in looping.got[: 2 * len(poses)]] == [d for _, _, d in poses] * 2
    looping.player.close()


def test_publishers_offer_the_recorded_qos_unless_overridden() -> None:
    rig = Rig(qos={"/hand/joint_states": qos.SENSOR_DATA})
    assert rig.player.publishers["/hand/object_pose"].qos == qos.DEFAULT  # what the bag recorded
    assert rig.player.publishers["/hand/joint_states"].qos == qos.SENSOR_DATA
    rig.player.close()


def test_play_bag_spins_until_done_on_the_wall_clock() -> None:
    bus = InProcessBus()
    with InProcessTransport(bus, "player") as node:
        assert play_bag(node, BAG, rate=200.0, timeout_s=20.0) == len(bag_messages())


def test_bad_input_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    node = InProcessTransport(InProcessBus(clock=FakeClock()), "player")
    for rate in (0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rate"):
            PlayerParams(BAG, rate=rate)
    with pytest.raises(BagError, match="does not exist"):
        BagPlayer(node, PlayerParams(tmp_path / "missing"))
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "notes.txt").write_text("not a bag")
    with pytest.raises(BagError, match="cannot be played"):
        BagPlayer(node, PlayerParams(junk))
    killed = tmp_path / "killed"
    shutil.copytree(BAG, killed)
    (killed / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="t42 bag repair"):
        BagPlayer(node, PlayerParams(killed))
    with pytest.raises(BagError, match="has no topic /nope"):
        BagPlayer(node, PlayerParams(BAG, topics=("/nope",)))

    assert main(["bag", "play", str(BAG), "--rate", "0"]) == 2
    assert "rate must be" in capsys.readouterr().err
    assert main(["bag", "play", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
