"""Cyclone DDS backend: generated IDL types match rosbags' CDR; pub/sub in and across processes."""

from __future__ import annotations

import os
import random
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="cyclonedds (cyclonedds-python) is not installed")

from msg_adapters.hand import TYPESTORE  # noqa: E402
from t42_transfer.ros import dds_types  # noqa: E402
from t42_transfer.ros.cyclone import CycloneTransport, discovery_config  # noqa: E402
from t42_transfer.ros.naming import dds_type_name, type_hash  # noqa: E402
from t42_transfer.ros.qos import DEFAULT, SENSOR_DATA, TRANSIENT_LOCAL  # noqa: E402
from t42_transfer.ros.transport import serialize  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
T = TYPESTORE.types


def _header(frame: str = "world") -> object:
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=12, nanosec=345), frame_id=frame)


def _messages() -> dict[str, object]:
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=0.1, y=-0.2, z=0.3),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.6, w=0.8),
    )
    point = T["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=np.array([0.5, -0.25]), velocities=np.array([], dtype=np.float64),
        accelerations=np.array([], dtype=np.float64), effort=np.array([1.5]),
        time_from_start=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=100_000_000),
    )
    return {
        "std_msgs/msg/String": T["std_msgs/msg/String"](data="hi"),
        "geometry_msgs/msg/PoseStamped": T["geometry_msgs/msg/PoseStamped"](header=_header(), pose=pose),
        "sensor_msgs/msg/JointState": T["sensor_msgs/msg/JointState"](
            header=_header("h"), name=["actuator_1", "actuator_2"], position=np.array([0.1, 0.2]),
            velocity=np.array([], dtype=np.float64), effort=np.array([0.01, -0.02])),
        "trajectory_msgs/msg/JointTrajectory": T["trajectory_msgs/msg/JointTrajectory"](
            header=_header(), joint_names=["a", "bcd"], points=[point, point]),
        "sensor_msgs/msg/Image": T["sensor_msgs/msg/Image"](
            header=_header(), height=1, width=3, encoding="mono8", is_bigendian=0, step=3,
            data=np.array([1, 2, 255], dtype=np.uint8)),
    }


@pytest.mark.parametrize("msgtype", sorted(_messages()))
def test_generated_types_serialise_like_rosbags(msgtype: str) -> None:
    msg = _messages()[msgtype]
    expected = bytes(TYPESTORE.serialize_cdr(msg, msgtype))
    obj = dds_types.to_dds(msgtype, msg)
    assert type(obj).__idl_typename__ == dds_type_name(msgtype)
    assert obj.serialize() == expected
    assert expected[:4] == b"\x00\x01\x00\x00"
    back = dds_types.from_dds(msgtype, dds_types.dds_class(msgtype).deserialize(expected))
    assert bytes(TYPESTORE.serialize_cdr(back, msgtype)) == expected


def test_uint8_fields_are_octets() -> None:
    from cyclonedds.idl import types as t

    cls = dds_types.dds_class("sensor_msgs/msg/Image")
    ann = cls.__annotations__
    assert ann["is_bigendian"] is t.byte
    assert ann["data"] == t.sequence[t.byte]
    assert dds_types.dds_class("std_msgs/msg/Header").__idl_typename__ == "std_msgs::msg::dds_::Header_"


def test_discovery_config_defaults_to_localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    xml = discovery_config()
    assert "<AllowMulticast>false</AllowMulticast>" in xml and '<Peer Address="127.0.0.1"/>' in xml
    assert discovery_config("SUBNET") is None
    with pytest.raises(ValueError):
        discovery_config("EVERYWHERE")


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return random.randint(100, 200)


def _spin_until(nodes: list[CycloneTransport], cond, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for node in nodes:
            node.spin_once(0.02)
        if cond():
            return True
    return False


def test_pubsub_between_two_transports(domain_id: int) -> None:
    msgs = _messages()
    with CycloneTransport("talker", domain_id) as talker, CycloneTransport("listener", domain_id) as listener:
        raw: list[bytes] = []
        typed: list[object] = []
        listener.subscribe("/hand/joint_states", "sensor_msgs/msg/JointState", DEFAULT, raw.append, raw=True)
        listener.subscribe("/chatter", "std_msgs/msg/String", SENSOR_DATA, typed.append)
        js = talker.publisher("/hand/joint_states", "sensor_msgs/msg/JointState", DEFAULT)
        chat = talker.publisher("/chatter", "std_msgs/msg/String", SENSOR_DATA)

        sent = serialize("sensor_msgs/msg/JointState", msgs["sensor_msgs/msg/JointState"])
        assert _spin_until([listener], lambda: js.writer.get_matched_subscriptions() != [], 10)

        def ping() -> bool:
            js.publish_raw(sent)
            chat.publish(msgs["std_msgs/msg/String"])
            listener.spin_once(0.05)
            return bool(raw) and bool(typed)

        assert _spin_until([listener], ping, 10)
        assert raw[0] == sent
        assert typed[0].data == "hi"

        sub = listener._subscriptions[0]
        assert sub.reader.topic.name == "rt/hand/joint_states"
        assert sub.reader.topic.typename == "sensor_msgs::msg::dds_::JointState_"
        qos = sub.reader.get_qos()
        from cyclonedds.core import Policy
        assert Policy.Userdata(data=f"typehash={type_hash('sensor_msgs/msg/JointState')};".encode()) in qos
        assert Policy.Reliability.Reliable(max_blocking_time=100_000_000) in qos
        assert Policy.History.KeepLast(10) in qos
        assert Policy.Userdata(data=b"enclave=/;") in listener.participant.get_qos()


def test_transient_local_reaches_late_reader(domain_id: int) -> None:
    with CycloneTransport("latch", domain_id) as a, CycloneTransport("late", domain_id) as b:
        pub = a.publisher("/latched", "std_msgs/msg/String", TRANSIENT_LOCAL)
        pub.publish(T["std_msgs/msg/String"](data="kept"))
        got: list[object] = []
        b.subscribe("/latched", "std_msgs/msg/String", TRANSIENT_LOCAL, got.append)
        assert _spin_until([b], lambda: bool(got), 10)
        assert got[0].data == "kept"


def test_timer_and_closed_transport(domain_id: int) -> None:
    node = CycloneTransport("ticker", domain_id)
    ticks: list[int] = []
    node.timer(0.02, lambda: ticks.append(node.now_ns()))
    node.spin(until=lambda: len(ticks) >= 3, timeout_s=2.0)
    assert len(ticks) >= 3
    node.close()
    assert node.closed
    with pytest.raises(RuntimeError):
        node.spin_once()


PUBLISHER_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from t42_transfer.ros.cyclone import CycloneTransport
    from t42_transfer.ros.qos import DEFAULT
    payload = bytes.fromhex(sys.argv[1])
    with CycloneTransport("remote_talker") as node:
        pub = node.publisher("/hand/object_pose", "geometry_msgs/msg/PoseStamped", DEFAULT)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            if pub.writer.get_matched_subscriptions():
                break
            time.sleep(0.02)
        for _ in range(50):
            pub.publish_raw(payload)
            time.sleep(0.05)
    """
)


def test_pubsub_across_processes(domain_id: int) -> None:
    msg = _messages()["geometry_msgs/msg/PoseStamped"]
    sent = serialize("geometry_msgs/msg/PoseStamped", msg)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONPATH=str(REPO))
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    env.pop("CYCLONEDDS_URI", None)
    got: list[bytes] = []
    with CycloneTransport("local_listener", domain_id) as node:
        node.subscribe("/hand/object_pose", "geometry_msgs/msg/PoseStamped", DEFAULT, got.append, raw=True)
        proc = subprocess.Popen([sys.executable, "-c", PUBLISHER_SCRIPT, sent.hex()], cwd=REPO, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            ok = node.spin(until=lambda: bool(got), timeout_s=20.0)
        finally:
            proc.kill()
            out, err = proc.communicate()
        assert ok, f"nothing received; publisher stderr: {err.decode()[-2000:]}"
    assert got[0] == sent
