"""ROS graph over ros_discovery_info: what a node announces and what another participant reads."""

from __future__ import annotations

import random
import time

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="cyclonedds (cyclonedds-python) is not installed")

from cyclonedds.core import Policy  # noqa: E402

from t42_transfer.ros import dds_types, graph  # noqa: E402
from t42_transfer.ros.cyclone import CycloneTransport  # noqa: E402
from t42_transfer.ros.naming import type_hash, typestore_for  # noqa: E402
from t42_transfer.ros.qos import DEFAULT  # noqa: E402

INFO = graph.INFO_TYPE


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    """A random domain per test, localhost discovery, so concurrent runs do not meet."""
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return random.randint(100, 200)


def test_entities_info_serialises_like_the_dds_type() -> None:
    participant, reader, writer = bytes(range(16)), bytes(range(16, 32)), bytes(range(32, 48))
    msg = graph.entities_info(participant, "/", "hand", [reader], [writer])
    data = bytes(typestore_for(INFO).serialize_cdr(msg, INFO))
    obj = dds_types.dds_class(INFO).deserialize(data)
    assert type(obj).__idl_typename__ == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
    assert bytes(obj.gid.data) == participant
    (node,) = obj.node_entities_info_seq
    assert (node.node_namespace, node.node_name) == ("/", "hand")
    assert [bytes(g.data) for g in node.reader_gid_seq] == [reader]
    assert [bytes(g.data) for g in node.writer_gid_seq] == [writer]
    assert dds_types.to_dds(INFO, msg).serialize() == data
    with pytest.raises(ValueError):
        graph.entities_info(b"short", "/", "hand", [], [])


def test_another_participant_sees_the_node_and_its_endpoints(domain_id: int) -> None:
    with CycloneTransport("hand_driver", domain_id) as a, CycloneTransport("observer", domain_id) as b:
        pub = a.publisher("/hand/joint_states", "sensor_msgs/msg/JointState", DEFAULT)
        a.subscribe("/hand/command", "std_msgs/msg/String", DEFAULT, lambda msg: None)
        a.service("/hand/reset", "std_srvs/srv/Trigger", lambda req: None)
        client = a.client("/recorder/start", "std_srvs/srv/Trigger")

        assert graph.node_names(b, timeout_s=5, wait_for="/hand_driver") == ["/hand_driver"]
        (node,) = graph.nodes(b.participant, timeout_s=2, wait_for="hand_driver")

        service = a._services[0]
        assert node.fqn == "/hand_driver"
        assert node.participant_gid == a.participant.guid.bytes
        assert node.participant_gid[12:] == b"\x00\x00\x01\xc1"  # entity id of a participant
        assert set(node.writer_gids) == {graph.gid(e) for e in (pub.writer, service.writer, client.writer)}
        assert set(node.reader_gids) == {graph.gid(e) for e in (a._subscriptions[0].reader, service.reader,
                                                                client.reader)}
        assert all(g[:12] == node.participant_gid[:12] for g in node.writer_gids + node.reader_gids)

        writer = a.graph.writer
        assert writer.topic.name == "ros_discovery_info"
        assert writer.topic.typename == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
        qos = writer.get_qos()
        assert Policy.Durability.TransientLocal in qos and Policy.History.KeepLast(1) in qos
        assert Policy.Userdata(data=f"typehash={type_hash(INFO)};".encode()) in qos


def test_new_endpoints_are_republished(domain_id: int) -> None:
    with CycloneTransport("talker", domain_id) as a, CycloneTransport("observer", domain_id) as b:
        reader = graph.GraphReader(b.participant)
        try:
            deadline = time.monotonic() + 5
            seen = reader.poll()
            while not seen and time.monotonic() < deadline:
                time.sleep(0.02)
                seen = reader.poll()
            assert [(n.name, n.writer_gids) for n in seen] == [("talker", ())]

            pub = a.publisher("/chatter", "std_msgs/msg/String", DEFAULT)
            deadline = time.monotonic() + 5
            while reader.poll()[0].writer_gids == () and time.monotonic() < deadline:
                time.sleep(0.02)
            assert reader.poll()[0].writer_gids == (graph.gid(pub.writer),)
        finally:
            reader.close()


def test_own_participant_is_not_listed(domain_id: int) -> None:
    with CycloneTransport("alone", domain_id) as a:
        assert graph.node_names(a, timeout_s=0.3) == []
        assert np.frombuffer(a.graph.message().gid.data, dtype=np.uint8).tobytes() == graph.gid(a.participant)
