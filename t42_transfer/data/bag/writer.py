"""TrajectorySet -> a new rosbag2 bag, in the hand wire format of :mod:`msg_adapters`, as Jazzy writes one.

Each step's three messages are stamped ``start_ns + k * CONTROL_PERIOD_NS`` in the header and as log
time (a trajectory's ``step_ns`` puts its late steps later, each with the driver's ``late`` status on
``/hand/status``); ``custom_data`` carries the hand and each episode's end reason.  A bag is built beside its path and
renamed into place once complete, so a failure never leaves a half bag that looks whole.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.names import LATE
from t42_transfer.conventions import ACTION_LIMIT, ACTION_UNIT_RAD, checked_action_unit
from t42_transfer.data.bag.episodes import EPISODE_GAP_NS, EPISODE_GAP_S
from t42_transfer.data.bag.metadata import EPISODES_KEY, HAND_KEY, UNIT_KEY
from t42_transfer.data.bag.storage import STORAGES
from t42_transfer.data.trajectory import Trajectory, TrajectorySet

DEFAULT_T0_NS = 1_000_000_000
"""First stamp :func:`assign_start_times` gives; non-zero because zero stamps read as "unset"."""
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
_DISTRO_LINE = re.compile(r"^( {0,2})ros_distro: rosbags$", re.MULTILINE)
"""rosbags' ros_distro line at the top level of the bag information (metadata.yaml nests it 2 deep)."""


def recorded_offer(qos: names.Qos) -> Qos:
    """The offer a bag records for a publisher of ``qos`` (reliable, KEEP_LAST; TRANSIENT_LOCAL when latched)."""
    durability = QosDurability.TRANSIENT_LOCAL if qos.latched else QosDurability.VOLATILE
    return RECORD_QOS._replace(depth=qos.depth, durability=durability)


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


class _StorageFile:
    """The storage file of a bag just opened, told apart from one put at its path later."""

    def __init__(self, bag: Path) -> None:
        files = sorted(p for p in bag.iterdir() if p.is_file()) if bag.is_dir() else []
        self.path = files[0] if files else bag / f"{bag.name}.mcap"
        try:
            st = os.stat(self.path)
            self._id: tuple[int, int] | None = (st.st_dev, st.st_ino)
        except OSError:
            self._id = None

    def lost(self) -> str | None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return f"{self.path} was removed while it was recorded"
        except OSError as err:
            return f"{self.path} cannot be reached ({err.strerror or err})"
        if (st.st_dev, st.st_ino) != self._id:
            return f"{self.path} was replaced by another file while it was recorded"
        return None


class BagWriter:
    """A new bag written message by message: one connection per topic, offered :data:`RECORD_QOS`, or for a topic
    of ``offered`` (resolved name -> its publishers' QoS) what they offer.

    What the recorder writes as messages arrive and :func:`write_bag` writes from trajectories, so both
    make the same bags.  ``flush`` closes the open MCAP chunk, so a writer killed later loses nothing
    flushed (``bag repair`` makes such a bag whole).
    """

    def __init__(self, path: Path, types: Mapping[str, str], storage: str = "mcap",
                 custom: Mapping[str, str] | None = None, offered: Mapping[str, names.Qos] | None = None) -> None:
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {storage!r}")
        self.path = path
        self.count = 0
        """Messages written."""
        self._offered = {topic: [recorded_offer(qos)] for topic, qos in (offered or {}).items()}
        self._writer = JazzyWriter(path, version=9, storage_plugin=STORAGES[storage])
        for key, value in (custom or {}).items():
            self._writer.set_custom_data(key, value)
        self._writer.open()
        self._file = _StorageFile(path)
        try:
            self._connections = {
                topic: self._writer.add_connection(topic, msgtype, typestore=ma.TYPESTORE,
                                                   offered_qos_profiles=self._offered.get(topic, [RECORD_QOS]))
                for topic, msgtype in types.items()
            }
        except Exception:
            self._writer.abort()
            raise

    def lost(self) -> str | None:
        """Why the storage file this writer writes to is no longer at its path (None while it is): a removed
        ``out_dir`` takes the file an open writer goes on writing to, unseen."""
        return self._file.lost()

    def write(self, topic: str, log_ns: int, cdr: bytes, msgtype: str | None = None) -> None:
        """One message; ``msgtype`` adds a topic not declared at the start (on its first message only, so a bag
        holds no empty connection for an optional topic such as ``hand/status``)."""
        if topic not in self._connections and msgtype is not None:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=ma.TYPESTORE, offered_qos_profiles=self._offered.get(topic, [RECORD_QOS]))
        self._writer.write(self._connections[topic], log_ns, cdr)
        self.count += 1

    def flush(self) -> None:
        """Write the open chunk and flush the file (no fsync: SIGKILL keeps the page cache).

        rosbags' MCAP writer (0.11.9) has no public flush; its storage closes a
        chunk only at 1 MiB, so this closes it through the storage object.
        """
        storage = self._writer.storage
        if storage is None or not hasattr(storage, "close_chunk"):
            return
        if storage.chunk.msgs:
            storage.close_chunk()
        storage.bio.flush()

    def close(self) -> None:
        """Finish the file and write ``metadata.yaml``."""
        self._writer.close()

    def abort(self) -> None:
        """Close the file without finishing it (what was written stays readable, as a killed writer's)."""
        self._writer.abort()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, kind: object, *_: object) -> None:
        self.close() if kind is None else self.abort()


def assign_start_times(
    trajectories: Iterable[Trajectory], t0_ns: int = DEFAULT_T0_NS, gap_ns: int = 2 * EPISODE_GAP_NS
) -> list[Trajectory]:
    """Copies laid end to end from ``t0_ns``, ``gap_ns`` from one episode's last state to the next's first."""
    if gap_ns < EPISODE_GAP_NS:
        raise ValueError(f"gap_ns must be at least EPISODE_GAP_S ({EPISODE_GAP_NS} ns), got {gap_ns}")
    placed, start = [], int(t0_ns)
    for traj in trajectories:
        placed.append(dataclasses.replace(traj, start_ns=start))
        start += int(traj.durations_ns.sum()) + gap_ns
    return placed


def write_bag(
    path: str | Path,
    data: TrajectorySet,
    *,
    storage: str = "mcap",
    metadata: Mapping[str, str] | None = None,
    action_unit_rad: float = ACTION_UNIT_RAD,
) -> Path:
    """Write ``data`` (actions in ``action_unit_rad``) as a new rosbag2 bag at ``path``; returns ``path``.

    The bag is built in a hidden directory beside ``path`` and renamed into place
    only once complete, so a failure never leaves a half bag that looks whole.  FileExistsError when a bag is at
    ``path`` already, also one another writer put there while this one was built.
    ``metadata`` lands in rosbag2 ``custom_data`` next to the keys this module owns.
    """
    target = Path(path)
    if storage not in STORAGES:  # before anything is made on disk
        raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {storage!r}")
    unit = checked_action_unit(action_unit_rad)
    for i, traj in enumerate(data):
        if (largest := float(np.abs(traj.actions).max(initial=0.0))) > ACTION_LIMIT:
            raise ValueError(f"{target}: episode {i} has an action of {largest:g}, past the largest a hand takes "
                             f"({ACTION_LIMIT:g}): no bag holds it")
    if target.exists() or target.is_symlink():
        raise FileExistsError(f"{target} exists already; bags are never overwritten")
    custom = {**_custom_data(data, metadata), UNIT_KEY: repr(unit)}
    _check_timeline(data.trajectories)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    try:
        bag = staging / target.name
        with BagWriter(bag, ma.HAND_TOPICS, storage, custom) as writer:
            for traj in data:
                _write_episode(writer, traj, unit)
        try:
            bag.rename(target)
        except OSError:
            if target.exists() or target.is_symlink():  # another writer of the same path finished first
                raise FileExistsError(f"{target} exists already (written while this bag was built); bags are "
                                      "never overwritten") from None
            raise
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
        previous_end = traj.start_ns + int(traj.durations_ns.sum())


def _write_episode(writer: BagWriter, traj: Trajectory, unit_rad: float) -> None:
    """Each step's three messages at its stamp; a late step (``step_ns``) also gets the ``late`` status a driver
    publishes for it, which tells a reader that no step is missing before it."""
    stamps = traj.start_ns + np.concatenate([[0], np.cumsum(traj.durations_ns)])
    late = set((traj.late_steps + 1).tolist())
    for k, state in enumerate(traj.states):
        stamp = int(stamps[k])
        angles = None if traj.actuator_angles is None else traj.actuator_angles[k]
        writer.write(ma.OBJECT_POSE_TOPIC, stamp, _cdr(ma.object_pose_msg(state[:2], stamp)))
        writer.write(ma.JOINT_STATES_TOPIC, stamp, _cdr(ma.joint_state_msg(state[2:], angles, stamp)))
        if k < len(traj):
            action = ma.applied_action_msg(traj.actions[k], stamp, unit_rad=unit_rad)
            writer.write(ma.APPLIED_ACTION_TOPIC, stamp, _cdr(action))
        if k in late:
            text = ma.status_message(LATE, f"{(stamp - int(stamps[k - 1])) / 1e6:g} ms after the step before", stamp)
            writer.write(ma.HAND_STATUS_TOPIC, stamp, _cdr(ma.TYPESTORE.types[ma.STRING](data=text)), ma.STRING)


def _cdr(msg: Any) -> bytes:
    return ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__)
