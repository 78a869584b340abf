"""Bags for tests of the bag package and its users: hand messages as the driver sends them,
copies of the fixture bag."""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import warnings
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from rosbags.rosbag2 import StoragePlugin, Writer

import msg_adapters as ma
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import (
    read_bag,
)
from t42_transfer.data.errors import BagError
from t42_transfer.data.trajectory import Trajectory, TrajectorySet

POSE, JOINTS, ACTION = ma.OBJECT_POSE_TOPIC, ma.JOINT_STATES_TOPIC, ma.APPLIED_ACTION_TOPIC


def assert_same(got: TrajectorySet, want: TrajectorySet) -> None:
    assert got.hand == want.hand
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a == b  # bit-exact arrays, start_ns, end_reason, hand


def read_quietly(path, **kwargs) -> TrajectorySet:
    """read_bag that fails the test on any warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_bag(path, **kwargs)


def step_messages(traj: Trajectory) -> list[tuple[str, int, object]]:
    """The hand's messages of one episode, as write_bag publishes them: (topic, stamp, message)."""
    out = []
    for k, state in enumerate(traj.states):
        stamp = traj.start_ns + k * CONTROL_PERIOD_NS
        angles = None if traj.actuator_angles is None else traj.actuator_angles[k]
        out.append((POSE, stamp, ma.object_pose_msg(state[:2], stamp)))
        out.append((JOINTS, stamp, ma.joint_state_msg(state[2:], angles, stamp)))
        if k < len(traj):
            out.append((ACTION, stamp, ma.applied_action_msg(traj.actions[k], stamp)))
    return out


def write_messages(path: Path, messages, types=ma.HAND_TOPICS, custom=None, storage=StoragePlugin.MCAP) -> Path:
    """A bag of arbitrary messages, written with rosbags directly (log time = the given stamp)."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for key, value in (custom or {}).items():
            writer.set_custom_data(key, value)
        conns = {t: writer.add_connection(t, types[t], typestore=ma.TYPESTORE) for t in types}
        for topic, stamp, msg in messages:
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
    return path


LOG = "rcl_interfaces/msg/Log"


def log_message(stamp: int) -> object:
    """A /rosout message, as every ROS node publishes."""
    time = ma.TYPESTORE.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
    return ma.TYPESTORE.types[LOG](stamp=time, level=20, name="node", msg="hi", file="f", function="g", line=1)


def sqlite3_without_a_definition(path: Path, data: TrajectorySet) -> Path:
    """A Jazzy sqlite3 bag of ``data``'s hand messages and /rosout, whose definition ``ros2 bag record`` did not
    find: stored as rosbag2 stores such a type (encoding "" and no text)."""
    messages = [m for traj in data for m in step_messages(traj)]
    messages.append(("/rosout", data[0].start_ns, log_message(data[0].start_ns)))
    write_messages(path, messages, {**ma.HAND_TOPICS, "/rosout": LOG}, storage=StoragePlugin.SQLITE3)
    with contextlib.closing(sqlite3.connect(path / f"{path.name}.db3")) as db, db:
        db.execute("UPDATE message_definitions SET encoding = '', encoded_message_definition = '' "
                    "WHERE topic_type = ?", (LOG,))
    return path


def damaged_copy(tmp_path: Path, bag: Path, size: int | None = None, drop_yaml: bool = False) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(bag, copy)
    mcap = copy / "bag.mcap"
    if size is not None:
        mcap.write_bytes(mcap.read_bytes()[:size])
    if drop_yaml:
        (copy / "metadata.yaml").unlink()
    return copy


REPO = Path(__file__).resolve().parents[1]
TARGET = REPO / "bags" / "target_small"


def fixture_message_count(bag: Path = TARGET) -> int:
    """The message count a fixture bag's shipped metadata.yaml gives (what a repair must find again)."""
    return int(yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["message_count"])


def mcap_ros_distro(mcap: Path) -> str:
    """ros_distro of rosbag2's own metadata record in the MCAP file."""
    with mcap.open("rb") as stream:
        record = next(r for r in make_reader(stream).iter_metadata() if r.name == "rosbag2")
    info = yaml.safe_load(record.metadata["serialized_metadata"])
    return info.get("rosbag2_bagfile_information", info)["ros_distro"]


def fixture_copy(tmp_path: Path, edit=None) -> Path:
    """The target fixture bag copied; ``edit(info)`` changes its rosbag2_bagfile_information in place."""
    bag = Path(shutil.copytree(TARGET, tmp_path / "target_small"))
    if edit is not None:
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())
        edit(meta["rosbag2_bagfile_information"])
        (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return bag


def refusal(bag: Path, function=read_bag) -> str:
    """The one-line BagError ``function`` raises for ``bag``."""
    with pytest.raises(BagError) as err:
        function(bag)
    text = str(err.value)
    assert text.startswith(f"{bag}: ") and "\n" not in text, text
    return text
