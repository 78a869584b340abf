"""rosbag2 bags <-> TrajectorySet, in the hand wire format of :mod:`msg_adapters`.

A bag holds, per control step ``k`` of an episode, an object pose, a joint state
and (except after the last state) the applied action, all stamped
``start_ns + k * CONTROL_PERIOD_NS`` in the header and as log time.  Episodes lie
at least ``EPISODE_GAP_S`` apart, so the reader finds their borders from stamps
alone; ``custom_data`` restores what stamps cannot say (end reasons, hands).

The reader aligns the three topics by header stamp, not by log time or order,
which also makes bags of a real ``ros2 bag record`` readable.  The hand topics
may lie under one namespace (a recorder run with ``__ns:=/left`` writes
``/left/hand/object_pose``...): they are found by suffix; a bag holding the hand
topics of two namespaces is refused, as it mixes two hands.  A damaged MCAP
(cut off mid-write, writer killed) is scanned record by record and its readable
prefix returned with a warning; everything else that is wrong raises
:class:`BagError` naming the bag and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import tempfile
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterable, Mapping

import numpy as np
import yaml
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer

import msg_adapters as ma
from t42_transfer.conventions import CONTROL_PERIOD_NS, MIN_EPISODE_STEPS
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import END_REASONS, Trajectory, TrajectorySet

EPISODE_GAP_S = 1.0
"""A stamp gap at least this long separates episodes; shorter gaps are lost messages."""
EPISODE_GAP_NS = round(EPISODE_GAP_S * 1e9)
DEFAULT_T0_NS = 1_000_000_000
"""First stamp :func:`assign_start_times` gives; non-zero because zero stamps read as "unset"."""

HAND_KEY = "t42_transfer.hand"
EPISODES_KEY = "t42_transfer.episodes"
REPAIRED_KEY = "t42_transfer.repaired"
"""Set by :mod:`t42_transfer.data.bag_repair`: the bag is a killed writer's salvaged prefix (a cut last step is no error)."""

_INFINITE = QosTime(9223372036, 854775807)
RECORD_QOS = Qos(
    QosHistory.KEEP_LAST,
    10,
    QosReliability.RELIABLE,
    QosDurability.VOLATILE,
    _INFINITE,
    _INFINITE,
    QosLiveliness.AUTOMATIC,
    _INFINITE,
    False,
)
"""ROS default QoS, written as ``ros2 bag record`` writes a default publisher's offer."""

ROS_DISTRO = "jazzy"
"""What our bags' metadata says they were recorded with: Jazzy's CDR and type hashes (rosbags writes "rosbags")."""

_STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}
_HALF_PERIOD_NS = CONTROL_PERIOD_NS // 2
_MAX_STEP_NS = 3 * CONTROL_PERIOD_NS // 2
_WITHIN = f"within {_HALF_PERIOD_NS / 1e6:g} ms"
_POSE, _JOINTS, _ACTION = ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC
_HAND_SUFFIXES = tuple(ma.HAND_TOPICS)
_CONVERTERS: dict[str, Callable[[Any], Any]] = {
    _POSE: ma.object_xy_mm,
    _JOINTS: ma.joint_state_arrays,
    _ACTION: ma.applied_action,
}


# --------------------------------------------------------------------------- writing

_DISTRO_LINE = re.compile(r"^( {0,2})ros_distro: rosbags$", re.MULTILINE)
"""rosbags' ros_distro line at the top level of the bag information (metadata.yaml nests it 2 deep)."""


def _jazzy(text: str) -> str:
    return _DISTRO_LINE.sub(rf"\1ros_distro: {ROS_DISTRO}", text, count=1)


class JazzyWriter(Writer):
    """rosbags' ``Writer`` whose metadata (``metadata.yaml`` and the MCAP's own record) says ``ros_distro: jazzy``.

    rosbags 0.11 hard-codes ``rosbags``; ``ros2 bag info`` shows the distro, and the
    bytes are Jazzy's, so the metadata says so.
    """

    def close(self) -> None:
        storage = self.storage
        assert storage is not None, "close() of a writer that is not open"
        close_storage = storage.close
        storage.close = lambda version, text: close_storage(version, _jazzy(text))  # type: ignore[method-assign]
        super().close()
        tmp = self.metapath.with_suffix(".yaml.distro")
        tmp.write_text(_jazzy(self.metapath.read_text()))
        tmp.replace(self.metapath)


def assign_start_times(
    trajectories: Iterable[Trajectory], t0_ns: int = DEFAULT_T0_NS, gap_ns: int = 2 * EPISODE_GAP_NS
) -> list[Trajectory]:
    """Copies laid end to end from ``t0_ns``, ``gap_ns`` from one episode's last state to the next's first."""
    if gap_ns < EPISODE_GAP_NS:
        raise ValueError(f"gap_ns must be at least EPISODE_GAP_S ({EPISODE_GAP_NS} ns), got {gap_ns}")
    placed, start = [], int(t0_ns)
    for traj in trajectories:
        placed.append(dataclasses.replace(traj, start_ns=start))
        start += len(traj) * CONTROL_PERIOD_NS + gap_ns
    return placed


def write_bag(
    path: str | Path,
    data: TrajectorySet,
    *,
    storage: str = "mcap",
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write ``data`` as a new rosbag2 bag at ``path``; returns ``path``.

    The bag is built in a hidden directory beside ``path`` and renamed into place
    only once complete, so a failure never leaves a half bag that looks whole.
    ``metadata`` lands in rosbag2 ``custom_data`` next to the keys this module owns.
    """
    target = Path(path)
    if storage not in _STORAGES:
        raise ValueError(f"storage must be one of {sorted(_STORAGES)}, got {storage!r}")
    if target.exists() or target.is_symlink():
        raise FileExistsError(f"{target} exists already; bags are never overwritten")
    custom = _custom_data(data, metadata)
    _check_timeline(data.trajectories)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    try:
        bag = staging / target.name
        with JazzyWriter(bag, version=9, storage_plugin=_STORAGES[storage]) as writer:
            for key, value in custom.items():
                writer.set_custom_data(key, value)
            connections = {
                topic: writer.add_connection(
                    topic, msgtype, typestore=ma.TYPESTORE, offered_qos_profiles=[RECORD_QOS]
                )
                for topic, msgtype in ma.HAND_TOPICS.items()
            }
            for traj in data:
                _write_episode(writer, connections, traj)
        bag.rename(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def _custom_data(data: TrajectorySet, metadata: Mapping[str, str] | None) -> dict[str, str]:
    user = dict(metadata or {})
    reserved = sorted(k for k in user if k.startswith("t42_transfer."))
    if reserved:
        raise ValueError(f"metadata keys {reserved} are reserved for t42_transfer itself")
    not_text = sorted(k for k, v in user.items() if not isinstance(k, str) or not isinstance(v, str))
    if not_text:
        raise ValueError(f"metadata keys and values must be strings; check {not_text}")
    episodes = [
        {"start_ns": t.start_ns, "transitions": len(t), "end_reason": t.end_reason, "hand": t.hand} for t in data
    ]
    custom = {**user, HAND_KEY: data.hand, EPISODES_KEY: json.dumps(episodes)}
    mangled = sorted(k for k, v in custom.items() if "\x85" in k + v)
    if mangled:  # rosbags' YAML emitter turns U+0085 into a space
        raise ValueError(f"metadata {mangled} contains U+0085 (NEL), which rosbag2 metadata cannot carry")
    return custom


def _check_timeline(trajectories: Iterable[Trajectory]) -> None:
    """Episodes must follow each other in time with room for the reader to tell them apart."""
    previous_end: int | None = None
    for i, traj in enumerate(trajectories):
        if traj.start_ns < 0:
            raise ValueError(f"episode {i} starts at a negative stamp, {traj.start_ns} ns")
        if previous_end is not None and traj.start_ns - previous_end < EPISODE_GAP_NS:
            raise ValueError(
                f"episode {i} starts at {traj.start_ns} ns, {(traj.start_ns - previous_end) / 1e9:g} s after "
                f"episode {i - 1}'s last state: episodes must be in time order and at least {EPISODE_GAP_S} s "
                "apart (assign_start_times lays them out)"
            )
        previous_end = traj.start_ns + len(traj) * CONTROL_PERIOD_NS


def _write_episode(writer: Writer, connections: dict[str, Any], traj: Trajectory) -> None:
    for k, state in enumerate(traj.states):
        stamp = traj.start_ns + k * CONTROL_PERIOD_NS
        angles = None if traj.actuator_angles is None else traj.actuator_angles[k]
        writer.write(connections[_POSE], stamp, _cdr(ma.object_pose_msg(state[:2], stamp)))
        writer.write(connections[_JOINTS], stamp, _cdr(ma.joint_state_msg(state[2:], angles, stamp)))
        if k < len(traj):
            writer.write(connections[_ACTION], stamp, _cdr(ma.applied_action_msg(traj.actions[k], stamp)))


def _cdr(msg: Any) -> bytes:
    return ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__)


# --------------------------------------------------------------------------- reading


@dataclasses.dataclass
class _Topic:
    msgtype: str
    count: int
    digest: str = ""


@dataclasses.dataclass
class _RawBag:
    """What storage gave: topic facts and the hand topics' CDR payloads in log-time order."""

    storage: str
    topics: dict[str, _Topic]
    messages: dict[str, list[tuple[int, bytes]]]
    """By bag topic: the hand topics found under :attr:`namespace`."""
    custom: dict[str, str]
    ros_distro: str | None
    start_ns: int
    end_ns: int
    truncated: bool = False
    """Only a readable prefix was recovered: a cut-off last step is not an error."""
    namespace: str = ""
    """Prefix of the hand topics in this bag ("" for ``/hand/...``, ``/left`` for ``/left/hand/...``)."""

    def hand_topic(self, topic: str) -> str:
        """The bag's name of hand topic ``topic`` (``/hand/object_pose`` -> ``/left/hand/object_pose``)."""
        return self.namespace + topic


def read_bag(path: str | Path, *, allow_gaps: bool = False) -> TrajectorySet:
    """Episodes recorded in a rosbag2 bag (MCAP or sqlite3, ours or a real ``ros2 bag record``'s).

    Every joint state is a state; the object pose with the nearest header stamp
    within half a control period gives its x, y; the applied action stamped
    within half a period gives its action.  Stamp gaps of ``EPISODE_GAP_S`` or more
    separate episodes; shorter gaps beyond 1.5 periods are missing messages and
    raise, or with ``allow_gaps`` split the episode with a warning.  An action on
    an episode's last state has no next state and is not a transition.  Episodes
    shorter than ``MIN_EPISODE_STEPS`` are dropped with a warning.
    """
    bag = Path(path)
    raw = _load(bag)
    return _assemble(bag, _decode(bag, raw), raw, allow_gaps)


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary for a CLI; episodes are counted as ``read_bag(path, allow_gaps=True)`` finds them."""
    bag = Path(path)
    raw = _load(bag)
    data = _assemble(bag, _decode(bag, raw), raw, allow_gaps=True)
    return {
        "path": str(bag),
        "storage": raw.storage,
        "ros_distro": raw.ros_distro,
        "start_ns": raw.start_ns,
        "duration_s": (raw.end_ns - raw.start_ns) / 1e9,
        "topics": {name: {"type": t.msgtype, "count": t.count} for name, t in sorted(raw.topics.items())},
        "namespace": raw.namespace or "/",
        "episodes": len(data),
        "transitions": data.num_transitions,
        "hand": data.hand,
        "metadata": {k: v for k, v in raw.custom.items() if k != EPISODES_KEY},
        "recovered_prefix": raw.truncated,
    }


# ----------------------------------------------------------------- reading: storage


def _load(path: Path) -> _RawBag:
    """Read through rosbags; fall back to scanning MCAP records when rosbags cannot."""
    if not path.exists():
        raise BagError(path, "does not exist")
    meta, problem = _metadata_yaml(path)
    storage, files = _storage_files(path, meta)
    if storage == "mcap" and path.is_dir() and meta is None:
        return _scan_mcap(path, files, None, problem)  # rosbags opens no bag directory without metadata.yaml
    try:
        raw = _read_with_rosbags([path] if meta is not None else files, storage, meta)
    except BagError:
        raise
    except Exception as err:  # rosbags, mcap and sqlite3 raise many types on damaged files
        problem = f"rosbags cannot read it ({type(err).__name__}: {err})"
        if storage != "mcap":
            raise BagError(path, problem) from None
        return _scan_mcap(path, files, meta, problem)
    if problem:
        warnings.warn(f"{path}: {problem}; read its storage files directly", stacklevel=3)
    raw.truncated = REPAIRED_KEY in raw.custom
    return raw


def _metadata_yaml(path: Path) -> tuple[dict[str, Any] | None, str]:
    """The bag's rosbag2_bagfile_information, or None and why not."""
    if not path.is_dir():
        return None, ""
    file = path / "metadata.yaml"
    if not file.exists():
        return None, "it has no metadata.yaml"
    try:
        info = yaml.safe_load(file.read_text())["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError(f"expected a mapping, got {type(info).__name__}")
    except Exception as err:  # any malformed YAML
        return None, f"its metadata.yaml is unreadable ({type(err).__name__}: {err})"
    return info, ""


def _storage_files(path: Path, meta: dict[str, Any] | None) -> tuple[str, list[Path]]:
    if not path.is_dir():
        if path.suffix not in _SUFFIXES:
            raise BagError(path, "is not a rosbag2 bag (expected a bag directory, an .mcap or a .db3 file)")
        return _SUFFIXES[path.suffix], [path]
    if meta is not None:
        storage = meta.get("storage_identifier")
        if storage not in _STORAGES:
            raise BagError(path, f"has storage {storage!r}; readable storages are {sorted(_STORAGES)}")
        return storage, [path / Path(str(p)).name for p in meta.get("relative_file_paths") or []]
    for suffix, storage in _SUFFIXES.items():
        files = sorted(path.glob(f"*{suffix}"))
        if files:
            return storage, files
    raise BagError(path, "is not a rosbag2 bag: no metadata.yaml and no .mcap or .db3 file")


def _add_topic(topics: dict[str, _Topic], topic: str, msgtype: str, count: int, digest: str) -> None:
    """Merge one connection into the topic table; a topic with several types keeps them all for the error."""
    known = topics.setdefault(topic, _Topic(msgtype, 0, digest))
    if msgtype not in known.msgtype.split(" and "):
        known.msgtype = f"{known.msgtype} and {msgtype}"
    known.count += count


def hand_namespace(path: str | Path, topics: Iterable[str]) -> str:
    """The one namespace the hand topics among ``topics`` lie under ("" for the root); BagError for several.

    A hand topic is found by suffix: ``/hand/object_pose`` or ``<ns>/hand/object_pose``.
    """
    found: dict[str, list[str]] = {}
    for name in topics:
        for hand in ma.HAND_TOPICS:
            if name.endswith(hand):
                found.setdefault(name[: -len(hand)], []).append(name)
    if len(found) > 1:
        listed = "; ".join(f"{ns or '/'} ({', '.join(sorted(names))})" for ns, names in sorted(found.items()))
        raise BagError(path, f"holds hand topics under {len(found)} namespaces: {listed}; "
                             "a bag must hold one hand's topics (filter it to one namespace)")
    return next(iter(found), "")


def _read_with_rosbags(sources: list[Path], storage: str, meta: dict[str, Any] | None) -> _RawBag:
    with AnyReader(sources, default_typestore=ma.TYPESTORE) as reader:
        topics: dict[str, _Topic] = {}
        for conn in reader.connections:
            _add_topic(topics, conn.topic, conn.msgtype, conn.msgcount, conn.digest)
        namespace = hand_namespace(sources[0], topics)
        messages: dict[str, list[tuple[int, bytes]]] = {namespace + topic: [] for topic in ma.HAND_TOPICS}
        wanted = [c for c in reader.connections if c.topic in messages]
        if wanted:  # an empty list would mean "every connection"
            for conn, log_ns, data in reader.messages(connections=wanted):
                messages[conn.topic].append((log_ns, bytes(data)))
        empty = reader.message_count == 0
        start, end = (0, 0) if empty else (reader.start_time, reader.end_time - 1)
    if meta is not None:
        custom, distro = _text_map(meta.get("custom_data")), meta.get("ros_distro")
    elif storage == "mcap":
        custom, distro = _mcap_metadata_record(sources[0])
    else:
        custom, distro = {}, None
    return _RawBag(storage, topics, messages, custom, distro, start, end, namespace=namespace)


def _text_map(value: Any) -> dict[str, str]:
    if not isinstance(value, dict):
        return {}
    return {str(k): str(v) for k, v in value.items()}


def _serialized_metadata(record: Metadata) -> tuple[dict[str, str], str | None]:
    """custom_data and ros_distro of rosbag2's own MCAP metadata record."""
    info = yaml.safe_load(record.metadata.get("serialized_metadata", "")) or {}
    info = info.get("rosbag2_bagfile_information", info)
    return _text_map(info.get("custom_data")), info.get("ros_distro")


def _mcap_metadata_record(file: Path) -> tuple[dict[str, str], str | None]:
    try:
        with file.open("rb") as stream:
            for record in make_reader(stream).iter_metadata():
                if record.name == "rosbag2":
                    return _serialized_metadata(record)
    except Exception:  # the record is a convenience copy; an unreadable one only loses custom_data
        pass
    return {}, None


class ExactReads:
    """A file view whose reads return all bytes asked for or raise, so a cut-off record is never half-parsed."""

    def __init__(self, stream: BinaryIO, size: int) -> None:
        self._stream, self._size = stream, size

    def read(self, n: int) -> bytes:
        at = self._stream.tell()
        if at + n > self._size:
            raise EOFError(f"a record needs {n} bytes at offset {at}, but the file ends at {self._size}")
        return self._stream.read(n)


def _scan_mcap(path: Path, files: list[Path], meta: dict[str, Any] | None, problem: str) -> _RawBag:
    """Read MCAP records in file order up to the first unreadable one."""
    schemas: dict[int, str] = {}
    channels: dict[int, str] = {}
    topics: dict[str, _Topic] = {}
    messages: dict[str, list[tuple[int, bytes]]] = {}
    """Every topic that may be a hand topic (the namespace is known once all channels are)."""
    custom, distro = (_text_map(meta.get("custom_data")), meta.get("ros_distro")) if meta else ({}, None)
    digests = _yaml_digests(meta)
    counts: Counter[str] = Counter()
    log_times: list[int] = []
    stopped = ""
    for file in files:
        try:
            with file.open("rb") as stream:
                size = file.stat().st_size
                for record in StreamReader(ExactReads(stream, size), record_size_limit=size).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel):
                        msgtype = schemas.get(record.schema_id, "(no schema)")
                        channels[record.id] = record.topic
                        digest = record.metadata.get("topic_type_hash", digests.get(record.topic, ""))
                        _add_topic(topics, record.topic, msgtype, 0, digest)
                    elif isinstance(record, Message):
                        topic = channels[record.channel_id]
                        counts[topic] += 1
                        log_times.append(record.log_time)
                        if topic.endswith(_HAND_SUFFIXES):
                            messages.setdefault(topic, []).append((record.log_time, record.data))
                    elif isinstance(record, Metadata) and record.name == "rosbag2" and meta is None:
                        custom, distro = _serialized_metadata(record)
        except Exception as err:  # whatever the damage, what was read before it stands
            stopped = f"{file.name} is unreadable from there on ({type(err).__name__}: {err})"
            break
    namespace = hand_namespace(path, topics)
    messages = {namespace + topic: messages.get(namespace + topic, []) for topic in ma.HAND_TOPICS}
    found = sum(len(m) for m in messages.values())
    if found == 0:
        detail = f"; {stopped}" if stopped else ""
        raise BagError(path, f"{problem}, and scanning its MCAP records recovered no hand messages{detail}")
    if stopped:
        warnings.warn(
            f"{path}: {problem}; recovered the readable prefix, {sum(counts.values())} messages up to log time "
            f"{max(log_times)} ns; {stopped}",
            stacklevel=4,
        )
    else:
        warnings.warn(f"{path}: {problem}; read it by scanning its MCAP records", stacklevel=4)
    for topic, info in topics.items():
        info.count = counts[topic]
    for received in messages.values():
        received.sort(key=lambda m: m[0])
    start, end = (min(log_times), max(log_times)) if log_times else (0, 0)
    return _RawBag("mcap", topics, messages, custom, distro, start, end, truncated=bool(stopped), namespace=namespace)


def _yaml_digests(meta: dict[str, Any] | None) -> dict[str, str]:
    if not meta:
        return {}
    digests = {}
    for entry in meta.get("topics_with_message_count") or []:
        topic = (entry or {}).get("topic_metadata") or {}
        if topic.get("type_description_hash"):
            digests[str(topic.get("name"))] = str(topic["type_description_hash"])
    return digests


# ----------------------------------------------------------------- reading: messages


@dataclasses.dataclass
class _Stream:
    stamps: np.ndarray
    """Header stamps (int64 ns), strictly increasing."""
    values: list[Any]


def _decode(path: Path, raw: _RawBag) -> dict[str, _Stream]:
    """Hand topics as header-stamped numpy values, checked for type, finiteness and order."""
    _check_topics(path, raw)
    streams = {}
    for topic, msgtype in ma.HAND_TOPICS.items():
        stamps: list[int] = []
        values = []
        name = raw.hand_topic(topic)
        for log_ns, data in raw.messages[name]:
            try:
                msg = ma.TYPESTORE.deserialize_cdr(data, msgtype)
            except Exception as err:  # corrupt CDR raises whatever the decoder trips over
                raise BagError(path, f"{name}: the message logged at {log_ns} ns cannot be decoded ({err})") from None
            stamp = ma.stamp_to_ns(msg.header.stamp)
            try:
                values.append(_CONVERTERS[topic](msg))
            except ValueError as err:
                raise BagError(path, f"{name} at stamp {stamp} ns: {err}") from None
            if stamps and stamp <= stamps[-1]:
                raise BagError(
                    path,
                    f"{name}: header stamps must increase, but {stamp} ns (logged at {log_ns} ns) "
                    f"follows {stamps[-1]} ns",
                )
            stamps.append(stamp)
        streams[topic] = _Stream(np.array(stamps, dtype=np.int64), values)
    return streams


def _check_topics(path: Path, raw: _RawBag) -> None:
    topics = raw.topics
    for hand, expected in ma.HAND_TOPICS.items():
        topic = raw.hand_topic(hand)
        info = topics.get(topic)
        if info is None:
            present = ", ".join(f"{name} ({t.msgtype})" for name, t in sorted(topics.items())) or "no topics"
            raise BagError(path, f"required topic {topic} ({expected}) is missing; the bag has {present}")
        if info.msgtype != expected:
            raise BagError(path, f"topic {topic} has type {info.msgtype}, expected {expected}")
        jazzy = ma.TYPESTORE.hash_rihs01(expected)
        if info.digest and info.digest != jazzy:
            raise BagError(
                path, f"topic {topic} declares {expected} with type hash {info.digest}, not ROS 2 Jazzy's {jazzy}"
            )


# ----------------------------------------------------------------- reading: episodes


def _nearest(stamps: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the stamp nearest each target, and whether it lies within half a control period."""
    if len(stamps) == 0:
        return np.zeros(len(targets), np.int64), np.zeros(len(targets), bool)
    right = np.searchsorted(stamps, targets).clip(0, len(stamps) - 1)
    left = (right - 1).clip(0, len(stamps) - 1)
    pick = np.where(np.abs(stamps[right] - targets) < np.abs(stamps[left] - targets), right, left)
    return pick, np.abs(stamps[pick] - targets) < _HALF_PERIOD_NS


def _drop_cut_tail(streams: dict[str, _Stream]) -> None:
    """In a recovered prefix the last step may have lost its pose; that step is cut, not wrong."""
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    last_pose = poses.stamps[-1] if len(poses.stamps) else -1
    keep = int(np.searchsorted(joints.stamps, last_pose + _HALF_PERIOD_NS))
    streams[_JOINTS] = _Stream(joints.stamps[:keep], joints.values[:keep])
    last_state = joints.stamps[keep - 1] if keep else -1
    keep = int(np.searchsorted(actions.stamps, last_state + _HALF_PERIOD_NS))
    streams[_ACTION] = _Stream(actions.stamps[:keep], actions.values[:keep])


def _episode_bounds(path: Path, stamps: np.ndarray, allow_gaps: bool) -> list[tuple[int, int]]:
    """``(first, last)`` state indices of each run of states one control period apart."""
    if len(stamps) == 0:
        return []
    cuts = []
    steps = np.diff(stamps)
    for i in np.flatnonzero((steps < _HALF_PERIOD_NS) | (steps > _MAX_STEP_NS)):
        step, before, after = int(steps[i]), int(stamps[i]), int(stamps[i + 1])
        if step >= EPISODE_GAP_NS:
            cuts.append(i + 1)
        elif step < _HALF_PERIOD_NS:
            raise BagError(
                path,
                f"{_JOINTS} stamps {before} and {after} ns are {step / 1e6:g} ms apart, "
                f"less than half the {CONTROL_PERIOD_NS / 1e6:g} ms control period",
            )
        elif allow_gaps:
            warnings.warn(
                f"{path}: {_JOINTS} skips {step / 1e6:g} ms from stamp {before} to {after} ns; "
                "split the episode there",
                stacklevel=4,
            )
            cuts.append(i + 1)
        else:
            raise BagError(
                path,
                f"{_JOINTS} skips {step / 1e6:g} ms from stamp {before} to {after} ns: messages are missing "
                f"(a gap under {EPISODE_GAP_S} s is not an episode border); pass allow_gaps=True to split there",
            )
    starts = [0, *cuts]
    ends = [c - 1 for c in cuts] + [len(stamps) - 1]
    return list(zip(starts, ends))


def _episode_records(path: Path, custom: dict[str, str]) -> dict[int, dict[str, Any]]:
    """The writer's per-episode facts by start stamp."""
    if EPISODES_KEY not in custom:
        return {}
    try:
        records = json.loads(custom[EPISODES_KEY])
        by_start = {}
        for r in records:
            if not (
                isinstance(r["start_ns"], int)
                and isinstance(r["transitions"], int)
                and r["end_reason"] in END_REASONS
                and isinstance(r["hand"], str)
            ):
                raise ValueError(f"bad entry {r!r}")
            by_start[r["start_ns"]] = r
    except (ValueError, TypeError, KeyError) as err:
        raise BagError(path, f"custom_data {EPISODES_KEY} is malformed ({type(err).__name__}: {err})") from None
    return by_start


def _assemble(path: Path, streams: dict[str, _Stream], raw: _RawBag, allow_gaps: bool) -> TrajectorySet:
    if raw.truncated:
        _drop_cut_tail(streams)
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    hand = raw.custom.get(HAND_KEY, "")
    pose_of, has_pose = _nearest(poses.stamps, joints.stamps)
    if not has_pose.all():
        stamp = joints.stamps[np.argmin(has_pose)]
        raise BagError(path, f"the state at stamp {stamp} ns on {_JOINTS} has no {_POSE} message {_WITHIN}")
    state_of, has_state = _nearest(joints.stamps, actions.stamps)
    if not has_state.all():
        stamp = actions.stamps[np.argmin(has_state)]
        raise BagError(path, f"the {_ACTION} at stamp {stamp} ns matches no {_JOINTS} message {_WITHIN}")
    taken, counts = np.unique(state_of, return_counts=True)
    if (counts > 1).any():
        stamp = joints.stamps[taken[np.argmax(counts > 1)]]
        raise BagError(path, f"several {_ACTION} messages match the state at stamp {stamp} ns")
    action_of = np.full(len(joints.stamps), -1)
    action_of[state_of] = np.arange(len(state_of))

    records = _episode_records(path, raw.custom)
    episodes = []
    for first, last in _episode_bounds(path, joints.stamps, allow_gaps):
        start = int(joints.stamps[first])
        lacking = np.flatnonzero(action_of[first:last] < 0)
        if len(lacking):
            stamp = joints.stamps[first + lacking[0]]
            raise BagError(
                path,
                f"the state at stamp {stamp} ns has no {_ACTION} {_WITHIN}; only an episode's last may lack one",
            )
        if last - first < MIN_EPISODE_STEPS:
            warnings.warn(
                f"{path}: dropped the episode starting at {start} ns: {last - first} transitions, "
                f"fewer than MIN_EPISODE_STEPS = {MIN_EPISODE_STEPS}",
                stacklevel=3,
            )
            continue
        record = records.get(start)
        complete = record is not None and record["transitions"] == last - first
        episodes.append(
            Trajectory(
                states=np.column_stack(
                    [
                        np.stack([poses.values[pose_of[k]] for k in range(first, last + 1)]),
                        np.stack([joints.values[k][0] for k in range(first, last + 1)]),
                    ]
                ),
                actions=np.stack([actions.values[action_of[k]] for k in range(first, last)]),
                actuator_angles=_angles(path, joints, first, last),
                start_ns=start,
                end_reason=record["end_reason"] if complete else "",
                hand=record["hand"] if record is not None else hand,
            )
        )
    if raw.truncated and not episodes:
        raise BagError(path, "its readable prefix holds no complete episode")
    return TrajectorySet(episodes, hand=hand)


def _angles(path: Path, joints: _Stream, first: int, last: int) -> np.ndarray | None:
    """Actuator angles of an episode: all there, or none (the real hands do not report them)."""
    angles = [joints.values[k][1] for k in range(first, last + 1)]
    if all(a is None for a in angles):
        return None
    if any(a is None for a in angles):
        missing = joints.stamps[first + next(i for i, a in enumerate(angles) if a is None)]
        raise BagError(path, f"{_JOINTS} at stamp {missing} ns has no positions while others in its episode do")
    return np.stack(angles)
