"""The bag player on real rclpy in this process: order, bytes, timing, filter, pause, loop, rate, /clock, bad input."""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from bag_builders import (
    BAR,
    BROKEN_TOPIC,
    FOO,
    IDL_TOPIC,
    broken_definition_bag,
    fixture_message_count,
    idl_topic_bag,
    step_messages,
)
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from ros_rig import Rosout
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosgraph_msgs.msg import Clock

from msg_adapters import HAND_TOPICS, TYPESTORE, object_pose_msg, rclpy_class, stamp_to_ns
from t42_transfer.cli import main
from t42_transfer.data.errors import BagError
from t42_transfer.nodes.player import BagPlayer, PlayerParams
from t42_transfer.ros.qos import recording

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "target_small"
POSE = "/hand/object_pose"


def bag_messages(bag: Path = BAG) -> list[tuple[str, int, bytes]]:
    with AnyReader([bag]) as reader:
        return [(conn.topic, log_ns, bytes(raw)) for conn, log_ns, raw in reader.messages()]


class Sink:
    """The test's node: raw subscriptions to the hand topics recording (steady time, topic, bytes)."""

    def __init__(self, ros: Any, topics: Any = HAND_TOPICS) -> None:
        self.node = ros.node("sink")
        self.got: list[tuple[float, str, bytes]] = []
        for topic in topics:
            self.node.create_subscription(rclpy_class(HAND_TOPICS[topic]), topic,
                                          lambda data, t=topic: self.got.append((time.monotonic(), t, data)),
                                          recording(10_000), raw=True)


def add_player(ros: Any, bag: Path = BAG, **params: Any) -> BagPlayer:
    player = ros.add(BagPlayer, params={"bag": str(bag), "start_paused": True, **params})
    assert player.wait_for_subscribers(10.0), "the sink never matched"
    return player


@pytest.mark.parametrize("rate", [20.0, 50.0])
def test_messages_come_out_in_order_with_their_bytes_and_spacing(ros: Any, rate: float) -> None:
    expected = bag_messages()
    sink = Sink(ros)
    player = add_player(ros, rate=rate)
    ros.spin_for(0.2)
    assert sink.got == [] and player.published == 0  # paused
    player.resume()
    duration_s = (expected[-1][1] - expected[0][1]) / 1e9 / rate
    assert ros.spin_until(lambda: len(sink.got) == len(expected), duration_s * 2 + 10)
    assert ros.spin_until(lambda: player.finished, 5.0)  # its thread marks the end after the last publish
    assert player.published == len(expected)
    for topic in HAND_TOPICS:  # per topic: the bag's bytes in the bag's order
        assert [d for _, t, d in sink.got if t == topic] == [d for t, _, d in expected if t == topic]
    # timing: never early, and the whole bag takes its duration / rate
    first_at, first_log = sink.got[0][0], expected[0][1]
    got_at = {d: at for at, _, d in sink.got}
    early = [(log_ns - first_log) / 1e9 / rate - (got_at[d] - first_at) for _, log_ns, d in expected]
    assert max(early) < 0.1  # receive times: the executor may deliver the first message late
    assert duration_s * 0.95 < sink.got[-1][0] - first_at < duration_s * 1.5 + 0.5


def test_topic_filter_pause_resume_and_loop(ros: Any) -> None:
    poses = [m for m in bag_messages() if m[0] == POSE]
    sink = Sink(ros, [POSE])
    player = add_player(ros, rate=50.0, topics=[POSE])
    assert set(player.topic_publishers) == {POSE}
    player.resume()
    assert ros.spin_until(lambda: len(sink.got) >= 20, 10.0)
    player.pause()
    ros.spin_for(0.1)
    held = len(sink.got)
    assert held < len(poses)
    ros.spin_for(0.5)  # longer than the rest of the bag at 50x
    assert len(sink.got) == held and not player.finished
    player.resume()
    assert ros.spin_until(lambda: player.finished, 10.0)
    ros.spin_for(0.1)
    assert [d for _, _, d in sink.got] == [d for _, _, d in poses]

    # 50x as above: at 200x a loaded machine's sink fell more than the publisher's history (depth 10, the
    # recorded QoS, as rosbag2 plays) behind, and a reliable keep-last writer drops what it overwrote.
    looping = add_player(ros, rate=50.0, topics=[POSE], loop=True)
    looping.resume()
    assert ros.spin_until(lambda: looping.loops >= 2, 10.0)
    assert not looping.finished
    looping.close()
    ros.spin_for(0.1)
    second = [d for _, _, d in sink.got[len(poses):]]
    assert second[: 2 * len(poses)] == [d for _, _, d in poses] * 2


def test_rate_changes_while_playing(ros: Any) -> None:
    sink = Sink(ros, [POSE])
    player = add_player(ros, rate=2.0, topics=[POSE])  # 21 s at this rate
    player.resume()
    assert ros.spin_until(lambda: len(sink.got) >= 3, 10.0)
    bag_time = player.bag_now_ns()
    result = player.set_parameters([Parameter("rate", value=400.0)])[0]
    assert result.successful
    assert player.bag_now_ns() >= bag_time  # bag time carries on from where it was
    assert ros.spin_until(lambda: player.finished, 3.0)
    refused = player.set_parameters([Parameter("rate", value=0.0)])[0]
    assert not refused.successful


def test_clock_publishes_the_bag_time(ros: Any) -> None:
    start = bag_messages()[0][1]
    clocks: list[int] = []
    ros.node("clock_sink").create_subscription(Clock, "/clock", lambda m: clocks.append(stamp_to_ns(m.clock)), 10,
                                               callback_group=ReentrantCallbackGroup())
    player = ros.add(BagPlayer, params={"bag": str(BAG), "start_paused": True, "rate": 10.0, "clock_hz": 50.0,
                                        "topics": [POSE]})
    ros.spin_for(0.3)
    paused = list(clocks)
    assert paused and set(paused) == {start}  # paused: the bag's first instant, standing still
    player.resume()
    began = time.monotonic()
    ros.spin_for(1.0)
    player.pause()
    elapsed = time.monotonic() - began
    paused_at = player.bag_now_ns()
    assert 0.7 * elapsed * 10 * 1e9 < paused_at - start <= 1.05 * elapsed * 10 * 1e9  # 10x the time it played
    assert ros.spin_until(lambda: clocks[-1] == paused_at, 5.0)  # /clock says where the bag stands
    after = clocks[len(paused):]
    assert after == sorted(after) and len(set(after)) > 10 and start <= after[0]


def test_publishers_offer_the_recorded_qos(ros: Any, tmp_path: Path) -> None:
    infinite = QosTime(9223372036, 854775807)
    latched = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                  infinite, infinite, QosLiveliness.AUTOMATIC, infinite, False)
    bag = tmp_path / "latched"
    with Writer(bag, version=9) as writer:
        conn = writer.add_connection(POSE, HAND_TOPICS[POSE], typestore=TYPESTORE, offered_qos_profiles=[latched])
        writer.write(conn, 1, bytes(TYPESTORE.serialize_cdr(object_pose_msg((1.0, 2.0), 1), HAND_TOPICS[POSE])))
        writer.add_connection("/other", HAND_TOPICS[POSE], typestore=TYPESTORE)  # no offered QoS recorded
    player = ros.add(BagPlayer, params={"bag": str(bag), "start_paused": True})
    pose_qos = player.topic_publishers[POSE].qos_profile
    assert pose_qos.durability == DurabilityPolicy.TRANSIENT_LOCAL and pose_qos.depth == 1
    other = player.topic_publishers["/other"].qos_profile
    assert other.reliability == ReliabilityPolicy.RELIABLE and other.depth == 10  # ROS's default


def test_a_topic_whose_message_package_is_missing_is_left_out_with_a_warning(ros: Any, tmp_path: Path) -> None:
    """As ros2 bag play: a ``ros2 bag record -a`` bag holds /tf, and a pip-installed ROS has no tf2_msgs."""
    tf_type = "tf2_msgs/msg/TFMessage"
    bag = tmp_path / "with_tf"
    with Writer(bag, version=9) as writer:
        tf = writer.add_connection("/tf", tf_type, typestore=TYPESTORE)
        writer.write(tf, 1, bytes(TYPESTORE.serialize_cdr(TYPESTORE.types[tf_type](transforms=[]), tf_type)))
        pose = writer.add_connection(POSE, HAND_TOPICS[POSE], typestore=TYPESTORE)
        writer.write(pose, 2, bytes(TYPESTORE.serialize_cdr(object_pose_msg((1.0, 2.0), 2), HAND_TOPICS[POSE])))
    log = Rosout(ros, "bag_player")
    player = ros.add(BagPlayer, params={"bag": str(bag)})
    assert set(player.topic_publishers) == {POSE}
    assert ros.spin_until(lambda: player.finished and any("not playing /tf" in m.msg for m in log.lines), 10.0)
    assert player.published == 1
    with pytest.raises(BagError, match="/tf has type tf2_msgs/msg/TFMessage, whose message package is not"):
        ros.add(BagPlayer, params={"bag": str(bag), "topics": ["/tf"]})


def test_a_bag_with_a_topic_of_an_idl_type_plays(ros: Any, tmp_path: Path, small_set: Any) -> None:
    """``ros2 bag record -a`` where a vendor's package defines a message in IDL: rosbag2 stores its definition with
    ``#include`` lines, which rosbags' IDL parser refuses, and the whole bag was refused ("Could not parse").  The
    hand's topics play; the vendor's, its package not installed here, is left out with the warning."""
    bag, _ = idl_topic_bag(tmp_path / "bag", small_set)
    log = Rosout(ros, "bag_player")
    player = ros.add(BagPlayer, params={"bag": str(bag), "rate": 1000.0})
    assert set(player.topic_publishers) == set(HAND_TOPICS)
    assert ros.spin_until(lambda: player.finished and any(f"not playing {IDL_TOPIC} ({FOO})" in m.msg
                                                          for m in log.lines), 20.0)
    assert player.published == sum(len(step_messages(traj)) for traj in small_set)


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_topic_whose_stored_definition_does_not_parse_is_left_out(ros: Any, tmp_path: Path, small_set: Any,
                                                                    capsys: pytest.CaptureFixture[str],
                                                                    storage: StoragePlugin) -> None:
    """``ros2 bag record -a`` where one topic's stored definition does not parse: the whole bag was refused ("Could
    not parse").  It is named once in a warning saying why; the hand's topics play, the one of a package not
    installed here is left out with the player's warning; asked for by name, it is refused; ``t42 bag play``
    picks topics from it as from any bag."""
    bag, _ = broken_definition_bag(tmp_path / "bag", small_set, storage)
    hand = sum(len(step_messages(traj)) for traj in small_set)
    log = Rosout(ros, "bag_player")
    said = f"{BROKEN_TOPIC} ({BAR}) is not decodable from the bag: its stored definition cannot be parsed"
    with pytest.warns(UserWarning, match=re.escape(said)) as warned:
        player = ros.add(BagPlayer, params={"bag": str(bag), "rate": 1000.0})
    assert len(warned) == 1
    assert set(player.topic_publishers) == set(HAND_TOPICS)
    assert ros.spin_until(lambda: player.finished and any(f"not playing {BROKEN_TOPIC} ({BAR})" in m.msg
                                                          for m in log.lines), 20.0)
    assert player.published == hand
    with pytest.warns(UserWarning, match=re.escape(said)), \
            pytest.raises(BagError, match=f"{BROKEN_TOPIC} has type {BAR}, whose message package is not installed"):
        ros.add(BagPlayer, params={"bag": str(bag), "topics": [BROKEN_TOPIC]})
    with pytest.warns(UserWarning, match=re.escape(said)):
        assert main(["bag", "play", str(bag), "--rate", "1000", "--wait-subscribers", "0", "--topics", POSE]) == 0
    poses = sum(topic == POSE for traj in small_set for topic, _, _ in step_messages(traj))
    assert f"{bag}: published {poses} messages on 1 topics" in capsys.readouterr().out


def test_bad_input_is_refused(ros: Any, tmp_path: Path, small_set: Any) -> None:
    for rate in (0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rate"):
            PlayerParams(BAG, rate=rate)
    with pytest.raises(ValueError, match="clock_hz"):
        PlayerParams(BAG, clock_hz=-1.0)
    with pytest.raises(ValueError, match="absolute"):
        PlayerParams(BAG, topics=("hand/object_pose",))
    with pytest.raises(BagError, match="does not exist"):
        ros.add(BagPlayer, params={"bag": str(tmp_path / "missing")})
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "notes.txt").write_text("not a bag")
    with pytest.raises(BagError, match="is not a rosbag2 bag"):
        ros.add(BagPlayer, params={"bag": str(junk)})
    killed = tmp_path / "killed"
    shutil.copytree(BAG, killed)
    (killed / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="t42 bag repair"):
        ros.add(BagPlayer, params={"bag": str(killed)})
    from t42_transfer.data.bag import write_bag

    sqlite = write_bag(tmp_path / "sqlite", small_set, storage="sqlite3")
    (sqlite / "sqlite.db3").write_bytes(b"SQLite format 3\x00" + bytes(200))  # repair takes MCAP bags only
    with pytest.raises(BagError, match="cannot be played") as refused:
        ros.add(BagPlayer, params={"bag": str(sqlite)})
    assert "repair" not in str(refused.value)
    with pytest.raises(BagError, match="has no topic /nope"):
        ros.add(BagPlayer, params={"bag": str(BAG), "topics": ["/nope"]})


def test_cli_plays_a_bag_and_refuses_bad_input(ros_domain: int, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bag", "play", str(BAG), "--rate", "400", "--wait-subscribers", "0", "--clock"]) == 0
    out = capsys.readouterr()
    assert f"{BAG}: published {fixture_message_count(BAG)} messages on 3 topics" in out.out
    assert "not every topic had a subscriber" in out.err and "(none on /hand/" in out.err, out.err

    for argv, problem in (
        (["--rate", "0"], "rate must be"),
        (["--rate", "-2"], "rate must be"),
        (["--clock", "-1"], "clock_hz must be"),
    ):
        assert main(["bag", "play", str(BAG), *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("t42: error:") and problem in err and "Traceback" not in err
    assert main(["bag", "play", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and err.count("\n") == 1
    (tmp_path / "notabag").mkdir()
    assert main(["bag", "play", str(tmp_path / "notabag")]) == 2
    err = capsys.readouterr().err
    assert "is not a rosbag2 bag" in err and err.count("\n") == 1


def test_cli_remaps_a_topic_as_ros2_bag_play_does(ros: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """A bag recorded at the root played into a namespace: ``--remap /hand/object_pose:=/left/hand/object_pose``."""
    import threading

    moved = "/left" + POSE
    got: list[bytes] = []
    ros.node("sink").create_subscription(rclpy_class(HAND_TOPICS[POSE]), moved, got.append, recording(10_000),
                                         raw=True)
    codes: list[int] = []
    play = threading.Thread(target=lambda: codes.append(main(
        ["bag", "play", str(BAG), "--rate", "400", "--topics", POSE, "--remap", f"{POSE}:={moved}",
         "--wait-subscribers", "10"])))
    play.start()
    while play.is_alive():
        ros.spin_for(0.1)
    ros.spin_for(0.3)
    assert codes == [0]
    assert got == [raw for topic, _, raw in bag_messages() if topic == POSE]
    assert "not every topic had a subscriber" not in capsys.readouterr().err  # the sink matched the moved topic
    for rule in ("nocolon", ":=/x", "/a:=", "/a:=/b:=/c"):
        with pytest.raises(SystemExit) as exit_:
            main(["bag", "play", str(BAG), "--remap", rule])
        assert exit_.value.code == 2 and "a remapping is OLD:=NEW" in capsys.readouterr().err


def test_cli_a_remapping_to_a_name_ros_refuses_is_one_line_naming_the_rule(
        ros_domain: int, capsys: pytest.CaptureFixture[str]) -> None:
    """OLD:=NEW in form, but rcl cannot parse it (a token starting with a digit): an RCLError traceback before."""
    assert main(["bag", "play", str(BAG), "--remap", f"{POSE}:=/1bad", "--wait-subscribers", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("t42: error: bad --remap: ") and f"-r {POSE}:=/1bad" in err and err.count("\n") == 1, err


def test_cli_play_stops_on_sigterm_as_on_ctrl_c(ros: Any) -> None:
    """A launch file or supervisor stops a player with SIGTERM: it closes cleanly and says what it published."""
    import signal
    import subprocess
    import sys

    from ros_rig import stop, unbuffered_env

    got: list[bytes] = []
    ros.node("sink").create_subscription(rclpy_class(HAND_TOPICS[POSE]), POSE, got.append, recording(10_000),
                                         raw=True)
    proc = subprocess.Popen([sys.executable, "-m", "t42_transfer.cli", "bag", "play", str(BAG), "--loop",
                             "--topics", POSE, "--wait-subscribers", "10"], cwd=REPO, env=unbuffered_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert ros.spin_until(lambda: len(got) >= 5, 60.0), "the player never played"
    finally:
        codes = stop([proc], timeout_s=10.0, sig=signal.SIGTERM)
    out, err = proc.communicate()
    assert codes == [0], (codes, err)
    assert f"{BAG}: published" in out and "Traceback" not in err, (out, err)
