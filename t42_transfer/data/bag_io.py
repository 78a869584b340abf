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
topics of two namespaces is refused, as it mixes two hands.  A step that lost a
message (a recording begun or ended mid-step, a message dropped under load) is
left out with a warning naming it, and the other steps are kept.

Bags are untrusted input.  MCAP files are read by scanning their records (every
read bounded by the file's size, every chunk by its stated size), so a damaged
MCAP (cut off mid-write, writer killed) gives its readable prefix with a warning;
sqlite3 files are read through rosbags.  ``metadata.yaml`` is parsed and its
fields' types checked here, never by rosbags (which would unpack a compressed
bag into a temporary folder: compressed bags are refused).  Non-regular files
are refused before anything opens them.  Everything else that is wrong raises
:class:`BagError`, one line naming the bag and the problem.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import re
import shutil
import stat
import tempfile
import warnings
from pathlib import Path, PurePath
from typing import Any, BinaryIO, Callable, Iterable, Iterator, Mapping

import lz4.frame
import numpy as np
import yaml
import zstandard
from mcap.records import Channel, Chunk, McapRecord, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
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


@dataclasses.dataclass(frozen=True)
class BagMetadata:
    """What a bag's metadata.yaml says, each field's type checked (an absent field is None)."""

    storage: str | None
    files: tuple[str, ...]
    """Names of ``relative_file_paths`` (their directories are ignored: no path leads out of the bag)."""
    custom: dict[str, str]
    ros_distro: str | None
    counts: dict[str, int | None]
    """Message count by topic."""
    digests: dict[str, str]
    """Type hash by topic, where given."""
    message_count: int | None
    start_ns: int | None
    duration_ns: int | None


@dataclasses.dataclass
class RawBag:
    """What storage gave: every topic with its messages counted, and the CDR payloads of hand-like topics."""

    storage: str
    topics: dict[str, _Topic]
    messages: dict[str, list[tuple[int, bytes]]]
    """By bag topic, in log-time order: every topic named like a hand topic (the namespace is chosen later)."""
    custom: dict[str, str]
    ros_distro: str | None
    start_ns: int
    end_ns: int
    """First and last log time (0 and 0 without messages)."""
    stopped: str = ""
    """Where reading stopped in a damaged file ("" when every file was read to its end)."""
    unsummarized: tuple[str, ...] = ()
    """MCAP files read to their end that have no summary statistics."""
    meta: BagMetadata | None = None
    problem: str = ""
    """Why a bag directory's metadata.yaml was not used ("" when it was)."""

    @property
    def cut(self) -> bool:
        """Only a readable prefix is here (damaged, or repaired from damage): a cut-off last step is no error."""
        return bool(self.stopped) or REPAIRED_KEY in self.custom


def read_bag(path: str | Path, *, allow_gaps: bool = False) -> TrajectorySet:
    """Episodes recorded in a rosbag2 bag (MCAP or sqlite3, ours or a real ``ros2 bag record``'s).

    Every joint state is a state; the object pose with the nearest header stamp
    within half a control period gives its x, y; the applied action stamped
    within half a period gives its action.  A step that lost a message (a
    recording started or stopped mid-step, a message dropped under load) is left
    out and its episode split there, with one warning naming what was dropped.
    Stamp gaps of ``EPISODE_GAP_S`` or more separate episodes; a shorter gap with
    no message at all on the hand topics raises, or with ``allow_gaps`` splits
    the episode with a warning.  An action on an episode's last state has no
    next state and is not a transition.  Episodes shorter than
    ``MIN_EPISODE_STEPS`` are dropped with a warning.
    """
    bag = Path(path)
    with refusals(bag):
        raw = _load(bag)
        _warn_loaded(bag, raw)
        return _assemble(bag, _decode(bag, raw), raw, allow_gaps)


def bag_info(path: str | Path) -> dict[str, Any]:
    """Summary for a CLI; episodes are counted as ``read_bag(path, allow_gaps=True)`` finds them."""
    bag = Path(path)
    with refusals(bag):
        raw = _load(bag)
        _warn_loaded(bag, raw)
        data = _assemble(bag, _decode(bag, raw), raw, allow_gaps=True)
        namespace = hand_namespace(bag, raw.topics)
    return {
        "path": str(bag),
        "storage": raw.storage,
        "ros_distro": raw.ros_distro,
        "start_ns": raw.start_ns,
        "duration_s": (raw.end_ns - raw.start_ns) / 1e9,
        "topics": {name: {"type": t.msgtype, "count": t.count} for name, t in sorted(raw.topics.items())},
        "namespace": namespace or "/",
        "episodes": len(data),
        "transitions": data.num_transitions,
        "hand": data.hand,
        "metadata": {k: v for k, v in raw.custom.items() if k != EPISODES_KEY},
        "recovered_prefix": raw.cut,
    }


def verify_bag(path: str | Path) -> list[str]:
    """Where a bag directory's metadata.yaml disagrees with its data; empty when they agree.

    Checked: the storage files present against ``relative_file_paths``, each
    topic's message count, the total, the start time (first log time) and the
    duration (last minus first log time), all counted from the messages
    themselves; a damaged or missing file is reported too.  BagError for what is
    no bag directory or cannot be read at all.
    """
    bag = Path(path)
    with refusals(bag):
        raw = _load(bag)
        if raw.meta is None and not raw.problem:
            raise BagError(bag, "is a storage file, not a bag directory: it has no metadata.yaml to verify against")
        found = [raw.stopped] if raw.stopped else []
        if raw.meta is None:
            return [*found, f"{raw.problem}: nothing to verify the data against"]
        return [*found, *metadata_mismatches(bag, raw.meta, raw)]


@contextlib.contextmanager
def refusals(bag: Path) -> Iterator[None]:
    """Failures reading ``bag`` as one-line BagErrors.

    OS errors (permission denied, a directory where a file belongs...) become
    BagErrors naming the file; a problem quoting text with line breaks or other
    unprintable characters (a topic name from a damaged file) has them escaped.
    """
    try:
        yield
    except BagError as err:
        if err.problem.isprintable():
            raise
        raise BagError(err.path, _one_line(err.problem)) from None
    except FileExistsError:  # a refusal to overwrite, named as such
        raise
    except OSError as err:
        where = f": {err.filename}" if err.filename else ""
        raise BagError(bag, _one_line(f"{err.strerror or type(err).__name__}{where}")) from None


def _one_line(text: str) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


# ----------------------------------------------------------------- reading: files

_MAX_METADATA_BYTES = 1 << 24
"""A bag's metadata.yaml is kilobytes; a bigger one is refused before it is parsed."""
_MAX_CHUNK_BYTES = 1 << 28
"""An MCAP chunk may unpack to at most this (rosbag2 writes chunks of about 1 MiB); more is refused, not allocated."""
_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISCHR, "a device"), (stat.S_ISBLK, "a device"))


def path_mode(bag: Path) -> int:
    """``st_mode`` of the bag path; BagError when there is nothing."""
    try:
        return bag.stat().st_mode
    except FileNotFoundError:
        raise BagError(bag, "does not exist") from None


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "no regular file")


def regular_size(bag: Path, file: Path) -> int:
    """Size of ``file`` in ``bag``; BagError unless it is a regular file (checked before opening: a FIFO blocks)."""
    info = file.stat()
    if not stat.S_ISREG(info.st_mode):
        raise BagError(bag, f"{file.name} is {_kind(info.st_mode)}, not a regular file")
    return info.st_size


def _load(bag: Path) -> RawBag:
    """The bag's storage files (MCAP scanned record by record, sqlite3 through rosbags) and its metadata.yaml."""
    mode = path_mode(bag)
    meta, problem = None, ""
    if stat.S_ISDIR(mode):
        meta, problem = metadata_yaml(bag)
        storage, files = _storage_files(bag, meta)
    elif not stat.S_ISREG(mode):
        raise BagError(bag, f"is {_kind(mode)}, not a bag directory or storage file")
    elif bag.suffix in _SUFFIXES:
        storage, files = _SUFFIXES[bag.suffix], [bag]
    else:
        raise BagError(bag, "is not a rosbag2 bag (expected a bag directory, an .mcap or a .db3 file)")
    raw = scan_mcap(files, meta) if storage == "mcap" else _read_sqlite3(bag, files, meta)
    raw.meta, raw.problem = meta, problem
    return raw


def metadata_yaml(bag: Path) -> tuple[BagMetadata | None, str]:
    """The bag directory's metadata.yaml, or None and why not (missing, or no YAML: a writer cut off closing).

    BagError when it is no regular file, too big, or not rosbag2 bag information
    (a field of the wrong type, a compressed bag).
    """
    file = bag / "metadata.yaml"
    if not file.exists() and not file.is_symlink():
        return None, "metadata.yaml is missing"
    size = regular_size(bag, file)
    if size > _MAX_METADATA_BYTES:
        raise BagError(bag, f"metadata.yaml is {size} bytes, more than the {_MAX_METADATA_BYTES} read of one")
    try:
        doc = yaml.safe_load(file.read_bytes().decode())
    except (ValueError, yaml.YAMLError, RecursionError) as err:  # not UTF-8, not YAML, nested beyond the stack
        first = next(iter(str(err).splitlines()), "")
        return None, f"metadata.yaml is unreadable ({type(err).__name__}: {first})"
    return _parse_metadata(bag, doc), ""


_EXPECTED = {str: "text", int: "an integer", list: "a list", dict: "a mapping"}


def _field(bag: Path, mapping: dict[Any, Any], key: str, kind: type, where: str = "") -> Any:
    """``mapping[key]`` if it is a ``kind`` (a bool is no integer) or absent (None); BagError otherwise."""
    value = mapping.get(key)
    if value is None or (isinstance(value, kind) and not (kind is int and isinstance(value, bool))):
        return value
    raise BagError(bag, f"metadata.yaml: {where}{key} must be {_EXPECTED[kind]}, not {type(value).__name__}")


def _parse_metadata(bag: Path, doc: Any) -> BagMetadata:
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagError(bag, "metadata.yaml holds no rosbag2_bagfile_information mapping")
    mode = _field(bag, info, "compression_mode", str) or ""
    if mode.lower() not in ("", "none"):
        compression = _field(bag, info, "compression_format", str)
        raise BagError(bag, f"is compressed (compression_mode {mode}, compression_format {compression}); only "
                            "uncompressed bags are read (ros2 bag convert decompresses one)")
    paths = _field(bag, info, "relative_file_paths", list) or []
    if not all(isinstance(p, str) for p in paths):
        raise BagError(bag, "metadata.yaml: relative_file_paths must list file names")
    custom = {}
    for key, value in (_field(bag, info, "custom_data", dict) or {}).items():
        if isinstance(value, (list, dict, set)):
            raise BagError(bag, f"metadata.yaml: custom_data {key} must be text, not {type(value).__name__}")
        custom[str(key)] = "" if value is None else str(value)
    counts: dict[str, int | None] = {}
    digests = {}
    for i, entry in enumerate(_field(bag, info, "topics_with_message_count", list) or []):
        where = f"topics_with_message_count[{i}]"
        if not isinstance(entry, dict):
            raise BagError(bag, f"metadata.yaml: {where} must be a mapping, not {type(entry).__name__}")
        topic = _field(bag, entry, "topic_metadata", dict, f"{where}.") or {}
        name = _field(bag, topic, "name", str, f"{where}.topic_metadata.")
        if name is None:
            raise BagError(bag, f"metadata.yaml: {where} names no topic")
        counts[name] = _field(bag, entry, "message_count", int, f"{where}.")
        digest = _field(bag, topic, "type_description_hash", str, f"{where}.topic_metadata.")
        if digest:
            digests[name] = digest
    return BagMetadata(
        storage=_field(bag, info, "storage_identifier", str),
        files=tuple(PurePath(p).name for p in paths),
        custom=custom,
        ros_distro=_field(bag, info, "ros_distro", str),
        counts=counts,
        digests=digests,
        message_count=_field(bag, info, "message_count", int),
        start_ns=_field(bag, _field(bag, info, "starting_time", dict) or {}, "nanoseconds_since_epoch", int,
                        "starting_time."),
        duration_ns=_field(bag, _field(bag, info, "duration", dict) or {}, "nanoseconds", int, "duration."),
    )


def _storage_files(bag: Path, meta: BagMetadata | None) -> tuple[str, list[Path]]:
    """Storage plugin and files of a bag directory: those metadata.yaml lists, else those it holds; all regular."""
    if meta is None:
        for suffix, storage in _SUFFIXES.items():
            files = sorted(bag.glob(f"*{suffix}"))
            if files:
                break
        else:
            raise BagError(bag, "is not a rosbag2 bag: no metadata.yaml and no .mcap or .db3 file")
    else:
        if meta.storage not in _STORAGES:
            raise BagError(bag, f"has storage {meta.storage!r}; readable storages are {sorted(_STORAGES)}")
        if not meta.files:
            raise BagError(bag, "metadata.yaml lists no storage file (relative_file_paths is empty)")
        storage, files = meta.storage, []
        for name in meta.files:
            if name in ("", "..") or "\x00" in name:
                raise BagError(bag, f"metadata.yaml lists {name!r} in relative_file_paths, which names no file")
            if not (bag / name).exists() and not (bag / name).is_symlink():
                raise BagError(bag, f"metadata.yaml lists {name}, which is missing")
            files.append(bag / name)
    for file in files:
        regular_size(bag, file)
    return storage, files


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


def _read_sqlite3(bag: Path, files: list[Path], meta: BagMetadata | None) -> RawBag:
    """A sqlite3 bag through rosbags (its counts and times are SQL over the stored messages)."""
    digests = meta.digests if meta else {}
    try:
        with AnyReader(files, default_typestore=ma.TYPESTORE) as reader:
            topics: dict[str, _Topic] = {}
            for conn in reader.connections:
                _add_topic(topics, conn.topic, conn.msgtype, conn.msgcount, conn.digest or digests.get(conn.topic, ""))
            wanted = [c for c in reader.connections if c.topic.endswith(_HAND_SUFFIXES)]
            messages: dict[str, list[tuple[int, bytes]]] = {c.topic: [] for c in wanted}
            if wanted:  # an empty list would mean "every connection"
                for conn, log_ns, data in reader.messages(connections=wanted):
                    messages[conn.topic].append((log_ns, bytes(data)))
            start, end = (0, 0) if reader.message_count == 0 else (reader.start_time, reader.end_time - 1)
    except Exception as err:  # rosbags and sqlite3 raise many types on damaged files
        raise BagError(bag, f"rosbags cannot read it ({type(err).__name__}: {err})") from None
    custom, distro = (meta.custom, meta.ros_distro) if meta else ({}, None)
    return RawBag("sqlite3", topics, messages, custom, distro, start, end)


class _ExactReads:
    """A file view whose reads return all bytes asked for or raise, so a cut-off record is never half-parsed."""

    def __init__(self, stream: BinaryIO, size: int) -> None:
        self._stream, self._size = stream, size

    def read(self, n: int) -> bytes:
        at = self._stream.tell()
        if at + n > self._size:
            raise EOFError(f"a record needs {n} bytes at offset {at}, but the file ends at {self._size}")
        return self._stream.read(n)


def mcap_records(stream: BinaryIO, size: int) -> Iterator[McapRecord]:
    """The records of an MCAP file of ``size`` bytes in file order, chunks opened; raises where it is unreadable.

    No read goes past the file's size and no chunk unpacks beyond its stated size
    (at most :data:`_MAX_CHUNK_BYTES`), so a damaged length cannot allocate more than the file justifies.
    """
    for record in StreamReader(_ExactReads(stream, size), emit_chunks=True, record_size_limit=size).records:
        if isinstance(record, Chunk):
            yield from breakup_chunk(_unpacked(record))
        else:
            yield record


def _unpacked(chunk: Chunk) -> Chunk:
    size = chunk.uncompressed_size
    if chunk.compression in ("zstd", "lz4") and size > _MAX_CHUNK_BYTES:
        raise ValueError(f"a chunk claims {size} bytes unpacked, more than the {_MAX_CHUNK_BYTES} allowed")
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)).read(size + 1)
    elif chunk.compression == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"a chunk has unknown compression {chunk.compression!r}")
    if len(data) != size:
        raise ValueError(f"a chunk unpacks to {len(data)} bytes, not the {size} it states")
    return dataclasses.replace(chunk, compression="", data=data)


def scan_mcap(files: list[Path], meta: BagMetadata | None) -> RawBag:
    """Every record of the MCAP ``files`` in file order, up to the first unreadable one.

    Counts and log times are those of the messages read, whatever a summary says.
    Without ``meta``, custom_data comes from rosbag2's own metadata record in the MCAP.
    """
    topics: dict[str, _Topic] = {}
    messages: dict[str, list[tuple[int, bytes]]] = {}
    digests = meta.digests if meta else {}
    record_meta: tuple[dict[str, str], str | None] | None = None
    log_times: list[int] = []
    stopped, unsummarized = "", []
    for file in files:
        schemas: dict[int, str] = {}
        channels: dict[int, str] = {}
        summarized = False
        with file.open("rb") as stream:
            try:
                for record in mcap_records(stream, file.stat().st_size):
                    if isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel):
                        channels[record.id] = record.topic
                        digest = record.metadata.get("topic_type_hash", digests.get(record.topic, ""))
                        _add_topic(topics, record.topic, schemas.get(record.schema_id, "(no schema)"), 0, digest)
                    elif isinstance(record, Message):
                        topic = channels[record.channel_id]
                        topics[topic].count += 1
                        log_times.append(record.log_time)
                        if topic.endswith(_HAND_SUFFIXES):
                            messages.setdefault(topic, []).append((record.log_time, record.data))
                    elif isinstance(record, Metadata) and record.name == "rosbag2" and record_meta is None:
                        record_meta = record_metadata(record)
                    elif isinstance(record, Statistics):
                        summarized = True
            except Exception as err:  # whatever the damage, what was read before it stands
                stopped = f"{file.name} is unreadable from offset {stream.tell()} ({type(err).__name__}: {err})"
                break
        if not summarized:
            unsummarized.append(file.name)
    for received in messages.values():
        received.sort(key=lambda m: m[0])
    custom, distro = (meta.custom, meta.ros_distro) if meta else record_meta or ({}, None)
    start, end = (min(log_times), max(log_times)) if log_times else (0, 0)
    return RawBag("mcap", topics, messages, custom, distro, start, end, stopped, tuple(unsummarized))


def record_metadata(record: Metadata) -> tuple[dict[str, str], str | None]:
    """custom_data and ros_distro of rosbag2's metadata record in an MCAP: a convenience copy, a bad one is none."""
    try:
        doc = yaml.safe_load(record.metadata.get("serialized_metadata", ""))
        info = doc.get("rosbag2_bagfile_information", doc) if isinstance(doc, dict) else None
        meta = _parse_metadata(Path(record.name), {"rosbag2_bagfile_information": info})
    except (BagError, ValueError, yaml.YAMLError, RecursionError):
        return {}, None
    return meta.custom, meta.ros_distro


def metadata_mismatches(bag: Path, meta: BagMetadata, raw: RawBag) -> list[str]:
    """Where ``meta`` (the bag's metadata.yaml) disagrees with the data read from the bag directory's files."""
    found = []
    suffix = next(x for x, s in _SUFFIXES.items() if s == raw.storage)
    held = sorted(p.name for p in bag.glob(f"*{suffix}"))
    if sorted(meta.files) != held:
        found.append(f"metadata.yaml lists files {sorted(meta.files)}, the bag holds {held}")
    for name in sorted(set(meta.counts) | set(raw.topics)):
        count = raw.topics[name].count if name in raw.topics else 0
        if name not in meta.counts:
            if count:
                found.append(f"{name}: {count} messages in the data, not listed in metadata.yaml")
        elif meta.counts[name] != count:
            found.append(f"metadata.yaml counts {meta.counts[name]} messages on {name}, the data holds {count}")
    total = sum(t.count for t in raw.topics.values())
    if meta.message_count != total:
        found.append(f"metadata.yaml counts {meta.message_count} messages, the data holds {total}")
    if total and meta.start_ns != raw.start_ns:
        found.append(f"metadata.yaml says the bag starts at {meta.start_ns} ns, its first message is logged at "
                     f"{raw.start_ns} ns")
    if total and meta.duration_ns != raw.end_ns - raw.start_ns:
        found.append(f"metadata.yaml says the bag lasts {meta.duration_ns} ns, its messages span "
                     f"{raw.end_ns - raw.start_ns} ns")
    return found


def _warn_loaded(bag: Path, raw: RawBag) -> None:
    """Warn of what was read in place of a sound bag; BagError when damage left no hand message."""
    if raw.problem:
        warnings.warn(f"{bag}: {raw.problem}; read its storage files directly", stacklevel=3)
    if raw.stopped:
        if not any(raw.messages.values()):
            raise BagError(bag, f"{raw.stopped}; scanning its MCAP records recovered no hand messages")
        warnings.warn(
            f"{bag}: recovered the readable prefix, {sum(t.count for t in raw.topics.values())} messages up to "
            f"log time {raw.end_ns} ns; {raw.stopped}",
            stacklevel=3,
        )


# ----------------------------------------------------------------- reading: messages


@dataclasses.dataclass
class _Stream:
    stamps: np.ndarray
    """Header stamps (int64 ns), strictly increasing."""
    values: list[Any]


def _decode(bag: Path, raw: RawBag) -> dict[str, _Stream]:
    """Hand topics as header-stamped numpy values, checked for type, finiteness and order."""
    namespace = hand_namespace(bag, raw.topics)
    _check_topics(bag, raw, namespace)
    streams = {}
    for topic, msgtype in ma.HAND_TOPICS.items():
        stamps: list[int] = []
        values = []
        name = namespace + topic
        for log_ns, data in raw.messages.get(name, []):
            try:
                msg = ma.TYPESTORE.deserialize_cdr(data, msgtype)
            except Exception as err:  # corrupt CDR raises whatever the decoder trips over
                raise BagError(bag, f"{name}: the message logged at {log_ns} ns cannot be decoded ({err})") from None
            stamp = ma.stamp_to_ns(msg.header.stamp)
            try:
                values.append(_CONVERTERS[topic](msg))
            except ValueError as err:
                raise BagError(bag, f"{name} at stamp {stamp} ns: {err}") from None
            if stamps and stamp <= stamps[-1]:
                raise BagError(
                    bag,
                    f"{name}: header stamps must increase, but {stamp} ns (logged at {log_ns} ns) "
                    f"follows {stamps[-1]} ns",
                )
            stamps.append(stamp)
        streams[topic] = _Stream(np.array(stamps, dtype=np.int64), values)
    return streams


def _check_topics(bag: Path, raw: RawBag, namespace: str) -> None:
    topics = raw.topics
    for hand, expected in ma.HAND_TOPICS.items():
        topic = namespace + hand
        info = topics.get(topic)
        if info is None:
            present = ", ".join(f"{name} ({t.msgtype})" for name, t in sorted(topics.items())) or "no topics"
            raise BagError(bag, f"required topic {topic} ({expected}) is missing; the bag has {present}")
        if info.msgtype != expected:
            raise BagError(bag, f"topic {topic} has type {info.msgtype}, expected {expected}")
        jazzy = ma.TYPESTORE.hash_rihs01(expected)
        if info.digest and info.digest != jazzy:
            raise BagError(
                bag, f"topic {topic} declares {expected} with type hash {info.digest}, not ROS 2 Jazzy's {jazzy}"
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
    """In a recovered prefix the last step may be cut after any of its messages; that step is cut, not lost."""
    poses, joints = streams[_POSE], streams[_JOINTS]
    last_pose = poses.stamps[-1] if len(poses.stamps) else -1
    keep = int(np.searchsorted(joints.stamps, last_pose + _HALF_PERIOD_NS))
    streams[_JOINTS] = _Stream(joints.stamps[:keep], joints.values[:keep])
    last_state = joints.stamps[keep - 1] if keep else -1
    for topic in (_POSE, _ACTION):
        cut = streams[topic]
        keep = int(np.searchsorted(cut.stamps, last_state + _HALF_PERIOD_NS))
        streams[topic] = _Stream(cut.stamps[:keep], cut.values[:keep])


def _any_between(stamps: np.ndarray, after: int, before: int) -> bool:
    """Whether a stamp lies strictly between ``after`` and ``before``."""
    return bool(np.searchsorted(stamps, after, "right") < np.searchsorted(stamps, before, "left"))


def _episode_bounds(
    bag: Path, streams: dict[str, _Stream], allow_gaps: bool
) -> list[tuple[int, int]]:
    """``(first, last)`` state indices of each run of states one control period apart.

    A longer step whose missing states left a pose or an action behind lost
    those states (the salvage drops them); one with no hand message at all is a
    hole in the recording.
    """
    stamps = streams[_JOINTS].stamps
    if len(stamps) == 0:
        return []
    cuts = []
    steps = np.diff(stamps)
    for i in np.flatnonzero((steps < _HALF_PERIOD_NS) | (steps > _MAX_STEP_NS)):
        step, before, after = int(steps[i]), int(stamps[i]), int(stamps[i + 1])
        lost = any(
            _any_between(streams[t].stamps, before + _HALF_PERIOD_NS, after - _HALF_PERIOD_NS) for t in (_POSE, _ACTION)
        )
        if step >= EPISODE_GAP_NS or lost:
            cuts.append(i + 1)
        elif step < _HALF_PERIOD_NS:
            raise BagError(
                bag,
                f"{_JOINTS} stamps {before} and {after} ns are {step / 1e6:g} ms apart, "
                f"less than half the {CONTROL_PERIOD_NS / 1e6:g} ms control period",
            )
        elif allow_gaps:
            warnings.warn(
                f"{bag}: {_JOINTS} skips {step / 1e6:g} ms from stamp {before} to {after} ns; "
                "split the episode there",
                stacklevel=4,
            )
            cuts.append(i + 1)
        else:
            raise BagError(
                bag,
                f"{_JOINTS} skips {step / 1e6:g} ms from stamp {before} to {after} ns with no hand message between: "
                f"messages are missing (a gap under {EPISODE_GAP_S} s is not an episode border); "
                "pass allow_gaps=True to split there",
            )
    starts = [0, *cuts]
    ends = [c - 1 for c in cuts] + [len(stamps) - 1]
    return list(zip(starts, ends))


def _complete_runs(posed: np.ndarray, acted: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` runs of states with a pose in which every state but the last has an action."""
    runs, start = [], None
    for k in range(len(posed)):
        if not posed[k]:
            if start is not None:
                runs.append((start, k - 1))
            start = None
            continue
        start = k if start is None else start
        if not acted[k] and k < len(posed) - 1:
            runs.append((start, k))
            start = None
    if start is not None:
        runs.append((start, len(posed) - 1))
    return runs


def _dropped(what: str, stamps: np.ndarray) -> list[str]:
    """``[what was dropped, with its first stamps]``, or ``[]`` when nothing was."""
    if not len(stamps):
        return []
    shown = ", ".join(str(s) for s in stamps[:3].tolist()) + (", ..." if len(stamps) > 3 else "")
    return [f"{what}: {len(stamps)} (stamp{'s' if len(stamps) > 1 else ''} {shown} ns)"]


def _episode_records(bag: Path, custom: dict[str, str]) -> dict[int, dict[str, Any]]:
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
    except (ValueError, TypeError, KeyError, RecursionError) as err:
        raise BagError(bag, f"custom_data {EPISODES_KEY} is malformed ({type(err).__name__}: {err})") from None
    return by_start


def _assemble(bag: Path, streams: dict[str, _Stream], raw: RawBag, allow_gaps: bool) -> TrajectorySet:
    """Episodes of whole steps; a step missing a message is dropped (and named in one warning)."""
    if raw.cut:
        _drop_cut_tail(streams)
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    hand = raw.custom.get(HAND_KEY, "")
    pose_of, has_pose = _nearest(poses.stamps, joints.stamps)
    state_of, has_state = _nearest(joints.stamps, actions.stamps)
    acting = np.flatnonzero(has_state)
    taken, counts = np.unique(state_of[acting], return_counts=True)
    if (counts > 1).any():
        stamp = joints.stamps[taken[np.argmax(counts > 1)]]
        raise BagError(bag, f"several {_ACTION} messages match the state at stamp {stamp} ns")
    action_of = np.full(len(joints.stamps), -1)
    action_of[state_of[acting]] = acting
    posed = np.zeros(len(poses.stamps), bool)
    posed[pose_of[has_pose]] = True
    dropped = [
        *_dropped(f"{_ACTION} messages with no {_JOINTS} {_WITHIN}", actions.stamps[~has_state]),
        *_dropped(f"{_POSE} messages with no {_JOINTS} {_WITHIN}", poses.stamps[~posed]),
        *_dropped(f"{_JOINTS} messages with no {_POSE} {_WITHIN}, with their actions", joints.stamps[~has_pose]),
    ]
    records = _episode_records(bag, raw.custom)
    episodes = []
    for first, last in _episode_bounds(bag, streams, allow_gaps):
        inner = first + np.flatnonzero(has_pose[first:last] & (action_of[first:last] < 0))
        lacking = f"the transitions from {_JOINTS} messages with no {_ACTION} {_WITHIN}"
        dropped += _dropped(lacking, joints.stamps[inner])
        for a, b in _complete_runs(has_pose[first : last + 1], action_of[first : last + 1] >= 0):
            start, steps = int(joints.stamps[first + a]), b - a
            if steps < MIN_EPISODE_STEPS:
                warnings.warn(
                    f"{bag}: dropped the episode starting at {start} ns: {steps} transitions, "
                    f"fewer than MIN_EPISODE_STEPS = {MIN_EPISODE_STEPS}",
                    stacklevel=3,
                )
                continue
            episodes.append(_episode(bag, streams, first + a, first + b, pose_of, action_of, records.get(start), hand))
    if dropped:
        warnings.warn(f"{bag}: kept the whole steps only; dropped {'; '.join(dropped)}", stacklevel=3)
    if raw.cut and not episodes:
        raise BagError(bag, "its readable prefix holds no complete episode")
    return TrajectorySet(episodes, hand=hand)


def _episode(
    bag: Path, streams: dict[str, _Stream], first: int, last: int, pose_of: np.ndarray, action_of: np.ndarray,
    record: dict[str, Any] | None, hand: str,
) -> Trajectory:
    """States ``first..last`` of the joint states with their poses and actions; the writer's record if it has one."""
    poses, joints, actions = streams[_POSE], streams[_JOINTS], streams[_ACTION]
    complete = record is not None and record["transitions"] == last - first
    return Trajectory(
        states=np.column_stack(
            [
                np.stack([poses.values[pose_of[k]] for k in range(first, last + 1)]),
                np.stack([joints.values[k][0] for k in range(first, last + 1)]),
            ]
        ),
        actions=np.stack([actions.values[action_of[k]] for k in range(first, last)]),
        actuator_angles=_angles(bag, joints, first, last),
        start_ns=int(joints.stamps[first]),
        end_reason=record["end_reason"] if complete else "",
        hand=record["hand"] if record is not None else hand,
    )


def _angles(bag: Path, joints: _Stream, first: int, last: int) -> np.ndarray | None:
    """Actuator angles of an episode: all there, or none (the real hands do not report them)."""
    angles = [joints.values[k][1] for k in range(first, last + 1)]
    if all(a is None for a in angles):
        return None
    if any(a is None for a in angles):
        missing = joints.stamps[first + next(i for i, a in enumerate(angles) if a is None)]
        raise BagError(bag, f"{_JOINTS} at stamp {missing} ns has no positions while others in its episode do")
    return np.stack(angles)
