"""``t42 view --bag``: a recorded bag over the Foxglove protocol, driven by a client's play, pause, speed and seek
(Python websockets speaking the protocol: @foxglove/ws-protocol 0.8.0 has no playback control)."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest
from bag_builders import BROKEN_TOPIC, FOO, IDL_TOPIC, broken_definition_bag, fixture_copy, idl_topic_bag
from foxglove_probe import SUBPROTOCOLS
from fuzz_harness import DecoderWorker
from ros_rig import REPO, stop
from rosbags.highlevel import AnyReader

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.wire import CONTROL_PERIOD_NS
from t42_transfer.data.bag import write_bag
from t42_transfer.view.bag_server import BagServer

PLAY, PAUSE = 0, 1
PLAYING, PAUSED, ENDED = 0, 1, 3


class Client:
    """A minimal Foxglove protocol client (v1 spec): JSON ops, binary message data, time and playback state."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.server: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.messages: list[tuple[int, bytes]] = []
        """(log time, CDR) of subscription 1's messages."""
        self.others: list[tuple[int, int, bytes]] = []
        """(subscription id, log time, CDR) of the other subscriptions' messages."""
        self.states: list[tuple[int, int, float, bool, str]] = []
        """(status, current time, speed, did seek, request id) of each PlaybackState."""
        self.times: list[int] = []
        self.read(0.5)

    def read(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                frame = self.ws.recv(timeout=0.02)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    self.server = msg
                elif msg["op"] == "advertise":
                    self.channels.update({c["topic"]: c for c in msg["channels"]})
            elif frame[0] == 1:
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                if sub == 1:
                    self.messages.append((log_time, frame[13:]))
                else:
                    self.others.append((sub, log_time, frame[13:]))
            elif frame[0] == 2:
                self.times.append(struct.unpack_from("<Q", frame, 1)[0])
            else:  # PlaybackState: status, current time, speed, did seek, request id
                status, current, speed, seek, n = struct.unpack_from("<BQfBI", frame, 1)
                self.states.append((status, current, speed, bool(seek), frame[19:19 + n].decode()))

    def subscribe(self, topic: str, sub: int = 1) -> None:
        subscription = {"id": sub, "channelId": self.channels[topic]["id"]}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [subscription]}))

    def control(self, command: int, speed: float = 1.0, seek_ns: int | None = None, request_id: str = "r") -> None:
        payload = struct.pack("<BfBQI", command, speed, seek_ns is not None, seek_ns or 0, len(request_id))
        self.ws.send(b"\x03" + payload + request_id.encode())


@pytest.fixture
def bag(tmp_path, small_set):
    return write_bag(tmp_path / "bag", small_set)


def _poses(bag) -> list[tuple[int, np.ndarray]]:
    with AnyReader([bag], default_typestore=ma.TYPESTORE) as reader:
        conns = [c for c in reader.connections if c.topic == ma.OBJECT_POSE_TOPIC]
        return [(t, ma.object_xy_mm(reader.deserialize(raw, c.msgtype))) for c, t, raw in reader.messages(conns)]


def test_a_client_plays_pauses_and_seeks_a_bag(bag):
    from websockets.sync.client import connect

    poses = _poses(bag)
    server = BagServer(bag, port=0)
    try:
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            _drive(Client(ws), poses)
    finally:
        server.close()


def test_a_topic_of_a_type_defined_in_idl_is_offered_with_its_idl(tmp_path, small_set):
    """Foxglove decodes a channel by its schema encoding: an IDL definition sent as ros2msg would not parse."""
    from websockets.sync.client import connect

    bag, _ = idl_topic_bag(tmp_path / "idl_bag", small_set)
    server = BagServer(bag, port=0)
    try:
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            channels = Client(ws).channels
    finally:
        server.close()
    idl, pose = channels[IDL_TOPIC], channels[ma.OBJECT_POSE_TOPIC]
    assert idl["schemaName"] == FOO and idl["schemaEncoding"] == "ros2idl" and f"IDL: {FOO}" in idl["schema"]
    assert "module my_msgs" in idl["schema"] and pose["schemaEncoding"] == "ros2msg"


def test_a_topic_no_client_could_decode_is_left_out_with_a_warning(tmp_path, small_set):
    """A topic whose stored definition does not parse and whose type this machine does not know either: the bag is
    served without it (it stopped with a KeyError traceback), as ``t42 bag play`` leaves such a topic out."""
    import warnings

    from websockets.sync.client import connect

    bag, _ = broken_definition_bag(tmp_path / "bag", small_set)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        server = BagServer(bag, port=0)
    try:
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            client = Client(ws)
            client.subscribe(ma.OBJECT_POSE_TOPIC)
            client.control(PLAY, speed=50.0)
            deadline = time.monotonic() + 10.0
            while not client.messages and time.monotonic() < deadline:
                client.read(0.05)
    finally:
        server.close()
    why = "neither the bag nor this machine defines its type"
    assert f"{bag}: not serving {BROKEN_TOPIC} (my_msgs/msg/Bar): {why}" in [str(w.message) for w in said]
    assert BROKEN_TOPIC not in client.channels and ma.OBJECT_POSE_TOPIC in client.channels
    assert client.messages  # the hand topics play past the topics left out


def _drive(client: Client, poses: list[tuple[int, np.ndarray]]) -> None:
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray

    assert {"playbackControl", "time"} <= set(client.server["capabilities"])
    channel = client.channels[ma.OBJECT_POSE_TOPIC]
    assert channel["encoding"] == "cdr" and channel["schemaEncoding"] == "ros2msg"
    assert "MSG: geometry_msgs/Point" in channel["schema"]
    assert set(client.channels) == {ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC,
                                    "/" + names.VIEW_MARKERS}
    client.subscribe(ma.OBJECT_POSE_TOPIC)
    client.subscribe("/" + names.VIEW_MARKERS, 2)
    client.read(0.5)
    assert client.messages == []  # it starts paused

    client.control(PLAY, speed=4.0, request_id="play")
    client.read(1.0)
    assert client.states and client.states[0][0] == PLAYING and client.states[0][4] == "play"
    assert client.states[0][2] == pytest.approx(4.0)
    heard = list(client.messages)
    assert len(heard) >= 10  # 1 s at 4x: ~40 steps of 0.1 s
    for log_time, data in heard:
        msg = deserialize_message(data, PoseStamped)
        xy = next(p for t, p in poses if t == log_time)
        assert ma.object_xy_mm(msg).tolist() == xy.tolist()
    assert [t for t, _ in heard] == [t for t, _ in poses[:len(heard)]]  # in order, from the first

    # The scene's markers, drawn at each step: the object where the bag has it at that step.
    markers = [(t, deserialize_message(data, MarkerArray)) for _, t, data in client.others]
    assert len(markers) >= 10
    for log_time, array in markers:
        obj = next(m for m in array.markers if m.ns == "object")
        xy = next(p for t, p in poses if t <= log_time and log_time - t < CONTROL_PERIOD_NS)  # the step's pose
        assert (obj.pose.position.x * 1000, obj.pose.position.y * 1000) == pytest.approx(xy.tolist(), abs=1e-3)

    client.control(PAUSE, speed=4.0, request_id="pause")
    client.read(0.3)
    paused_at = len(client.messages)
    client.read(0.7)
    assert len(client.messages) == paused_at
    assert client.states[-1][0] == PAUSED and client.states[-1][4] == "pause"

    target = poses[-10][0]  # seek near the end, then play to it
    client.control(PLAY, speed=4.0, seek_ns=target, request_id="seek")
    client.read(1.5)
    after = client.messages[paused_at:]
    assert after and after[0][0] == target
    assert [t for t, _ in after] == [t for t, _ in poses[-10:]]
    assert any(s[3] and s[4] == "seek" for s in client.states)
    assert client.states[-1][0] == ENDED
    assert client.times and max(client.times) >= target


def test_t42_view_bag_serves_until_ctrl_c_and_refuses_a_missing_bag(bag, tmp_path):
    from t42_transfer.cli import main

    handlers = [signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)]
    assert main(["view", "--bag", str(tmp_path / "none")]) == 2
    assert [signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)] == handlers  # none left behind
    log = tmp_path / "serve.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-u", "-m", "t42_transfer.cli", "view", "--bag", str(bag),
                                 "--port", "0"], cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "on ws://127.0.0.1:" not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.2)
        assert "3 topics" in log.read_text()
    finally:
        assert stop([proc]) == [0], log.read_text()


@pytest.mark.parametrize("target", ["t42_transfer.view.bag_scene:bag_scene_inputs",
                                    "t42_transfer.view.bag_server:BagServer"])
def test_a_fifo_where_a_bag_file_belongs_is_refused_before_opening(target):
    """Opening a FIFO blocks forever (``t42 view --bag`` hung, deaf to SIGTERM): the worker's alarm fails a hang."""
    with DecoderWorker(target, timeout_s=10.0) as worker:
        for name in ("metadata.yaml", "target_small.mcap"):
            bag = fixture_copy(worker.new_case_dir())
            (bag / name).unlink()
            os.mkfifo(bag / name)
            verdict = worker.check_path(bag)
            assert verdict.outcome == "refused" and f"{name} is a FIFO" in verdict.detail, verdict
