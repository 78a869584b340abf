"""ROS graph participation over ``ros_discovery_info``, as rmw_dds_common does it (Jazzy).

ROS tools learn which *nodes* exist (``ros2 node list``, ``ros2 node info``) not from
DDS discovery, which only knows participants and endpoints, but from the topic
``ros_discovery_info`` (no ``rt`` prefix; type
``rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_``; RELIABLE, TRANSIENT_LOCAL,
KEEP_LAST 1).  Each participant publishes its GID and, per node, the GIDs of the
node's readers and writers.  A GID is the 16-byte DDS GUID of the entity (prefix 12
bytes + entity id 4), as rmw_cyclonedds_cpp fills ``rmw_gid_t``.

:class:`ParticipantInfoWriter` publishes for one node per participant (this project's
transport makes one participant per node) and republishes on every added endpoint.
:class:`GraphReader` / :func:`nodes` read what other participants publish; readers
ignore their own participant's samples, as rmw does.  Participants that leave are not
pruned (rmw does that from DCPSParticipant disposals): enough for tests and tools
that look once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np
from cyclonedds.core import InstanceState, Policy, Qos, SampleState, ViewState
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from cyclonedds._clayer import ddspy_take, ddspy_write

from t42_transfer.ros.dds_types import dds_class
from t42_transfer.ros.naming import typestore_for, user_data_typehash

DISCOVERY_TOPIC = "ros_discovery_info"
INFO_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"
_ANY = SampleState.Any | ViewState.Any | InstanceState.Any


def gid(entity: Any) -> bytes:
    """The 16-byte GID of a Cyclone entity (participant, reader, writer): its DDS GUID."""
    return entity.guid.bytes


@dataclass(frozen=True)
class NodeInfo:
    """One node as another participant announces it."""

    namespace: str
    name: str
    participant_gid: bytes
    reader_gids: tuple[bytes, ...]
    writer_gids: tuple[bytes, ...]

    @property
    def fqn(self) -> str:
        """``/ns/name`` as ``ros2 node list`` prints it."""
        return self.namespace.rstrip("/") + "/" + self.name


def entities_info(participant_gid: bytes, namespace: str, name: str,
                  readers: Iterable[bytes], writers: Iterable[bytes]) -> Any:
    """The ParticipantEntitiesInfo (typestore object) of one participant with one node."""
    types = typestore_for(INFO_TYPE).types
    Gid = types["rmw_dds_common/msg/Gid"]

    def g(data: bytes) -> Any:
        if len(data) != 16:
            raise ValueError(f"a GID is 16 bytes, got {len(data)}")
        return Gid(data=np.frombuffer(data, dtype=np.uint8).copy())

    node = types["rmw_dds_common/msg/NodeEntitiesInfo"](
        node_namespace=namespace, node_name=name,
        reader_gid_seq=[g(r) for r in readers], writer_gid_seq=[g(w) for w in writers])
    return types[INFO_TYPE](gid=g(participant_gid), node_entities_info_seq=[node])


def _topic(participant: DomainParticipant) -> Topic:
    return Topic(participant, DISCOVERY_TOPIC, dds_class(INFO_TYPE))


def _qos(reader: bool) -> Qos:
    """rmw's discovery QoS: RELIABLE, TRANSIENT_LOCAL, KEEP_LAST 1 writer.

    The topic is keyless, i.e. one instance for all participants, so the reader keeps
    all samples and ignores its own participant's, as rmw's does.
    """
    return Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepAll if reader else Policy.History.KeepLast(1),
        Policy.DataRepresentation(use_cdrv0_representation=True),
        Policy.Userdata(data=user_data_typehash(INFO_TYPE).encode()),
        *([Policy.IgnoreLocal.Participant] if reader else []),
    )


class ParticipantInfoWriter:
    """Announces one node of ``participant`` with its endpoints on ``ros_discovery_info``."""

    def __init__(self, participant: DomainParticipant, node_name: str, namespace: str = "/") -> None:
        self.participant, self.node_name, self.namespace = participant, node_name, namespace
        self.topic = _topic(participant)
        self.writer = DataWriter(participant, self.topic, qos=_qos(reader=False))
        self.readers: list[bytes] = []
        self.writers: list[bytes] = []
        self.publish()

    def add(self, readers: Iterable[Any] = (), writers: Iterable[Any] = ()) -> None:
        """Add DDS readers/writers of the node and republish."""
        self.readers += [gid(r) for r in readers]
        self.writers += [gid(w) for w in writers]
        self.publish()

    def message(self) -> Any:
        return entities_info(gid(self.participant), self.namespace, self.node_name, self.readers, self.writers)

    def publish(self) -> None:
        data = bytes(typestore_for(INFO_TYPE).serialize_cdr(self.message(), INFO_TYPE))
        if ddspy_write(self.writer._ref, data) < 0:
            raise RuntimeError(f"dds write on {DISCOVERY_TOPIC} failed")

    def entities(self) -> list[Any]:
        """The DDS entities to delete, children first."""
        return [self.writer, self.topic]


def _node_infos(msg: Any) -> list[NodeInfo]:
    participant = bytes(msg.gid.data)
    return [
        NodeInfo(n.node_namespace, n.node_name, participant,
                 tuple(bytes(g.data) for g in n.reader_gid_seq), tuple(bytes(g.data) for g in n.writer_gid_seq))
        for n in msg.node_entities_info_seq
    ]


class GraphReader:
    """Collects the latest ParticipantEntitiesInfo of every other participant."""

    def __init__(self, participant: DomainParticipant) -> None:
        self.topic = _topic(participant)
        self.reader = DataReader(participant, self.topic, qos=_qos(reader=True))
        self._latest: dict[bytes, list[NodeInfo]] = {}

    def poll(self) -> list[NodeInfo]:
        """Take what arrived and return the nodes known so far."""
        ts = typestore_for(INFO_TYPE)
        while True:
            samples = ddspy_take(self.reader._ref, _ANY, 64)
            if isinstance(samples, int):
                raise RuntimeError(f"dds take on {DISCOVERY_TOPIC} failed ({samples})")
            for data, info in samples:
                if info.valid_data:
                    msg = ts.deserialize_cdr(bytes(data), INFO_TYPE)
                    self._latest[bytes(msg.gid.data)] = _node_infos(msg)
            if len(samples) < 64:
                return [node for infos in self._latest.values() for node in infos]

    def close(self) -> None:
        for entity in (self.reader, self.topic):
            try:
                entity.__del__()
            except Exception:  # already gone with its participant
                pass


def nodes(participant: DomainParticipant, timeout_s: float = 2.0, wait_for: str | None = None) -> list[NodeInfo]:
    """Nodes other participants announce, gathered for ``timeout_s``.

    With ``wait_for`` (a node name or ``/ns/name``) it returns as soon as that node is
    seen, so a test need not sit out the whole timeout.
    """
    reader = GraphReader(participant)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            found = reader.poll()
            if wait_for is not None and any(wait_for in (n.name, n.fqn) for n in found):
                return found
            if time.monotonic() >= deadline:
                return found
            time.sleep(0.02)
    finally:
        reader.close()


def node_names(source: Any, timeout_s: float = 2.0, wait_for: str | None = None) -> list[str]:
    """Sorted ``/ns/name`` of the nodes others announce (``ros2 node list`` minus this one).

    ``source`` is a DomainParticipant or anything with a ``participant`` (a transport).
    """
    participant = getattr(source, "participant", source)
    return sorted({n.fqn for n in nodes(participant, timeout_s, wait_for)})
