"""Bags for tests of the bag package and its users: hand messages as the driver sends them,
copies of the fixture bag, a vendor's IDL-defined type as rosbag2 stores its definition."""

from __future__ import annotations

import contextlib
import dataclasses
import re
import shutil
import sqlite3
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

import msg_adapters as ma
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag import (
    JazzyWriter,
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


FOO = "my_msgs/msg/Foo"
"""A type Jazzy's store lacks (a lab's own message package)."""


# A type defined in .idl (a vendor's package): rosbag2 stores its definition as a ``ros2idl`` schema.
FINGER, TIME = "my_msgs/msg/Finger", "builtin_interfaces/msg/Time"
IDL = {
    FOO: """// generated from rosidl_adapter/resource/msg.idl.em
// with input from my_msgs/msg/Foo.msg
// generated code does not contain a copyright notice

#include "builtin_interfaces/msg/Time.idl"
#include "my_msgs/msg/Finger.idl"

module my_msgs {
  module msg {
    module Foo_Constants {
      const uint8 OPEN = 0;
      const uint8 CLOSED = 1;
    };
    @verbatim (language="comment", text=
      "A grasp, as the vendor's driver reports it.")
    struct Foo {
      builtin_interfaces::msg::Time stamp;

      @verbatim (language="comment", text=
        "OPEN or CLOSED.")
      uint8 state;

      my_msgs::msg::Finger thumb;

      sequence<my_msgs::msg::Finger, 4> fingers;

      double force[3];

      string<16> label;
    };
  };
};
""",
    FINGER: """#ifndef MY_MSGS__MSG__FINGER_IDL_
#define MY_MSGS__MSG__FINGER_IDL_

module my_msgs {
  module msg {
    struct Finger {
      string name;

      @default (value=0.5)
      float position;

      int32 a;
    };
  };
};

#endif  // MY_MSGS__MSG__FINGER_IDL_
""",
    TIME: """// generated from rosidl_adapter/resource/msg.idl.em
// with input from builtin_interfaces/msg/Time.msg
// generated code does not contain a copyright notice


module builtin_interfaces {
  module msg {
    @verbatim (language="comment", text=
      "This message communicates ROS Time defined here:" "\\n"
      "https://design.ros2.org/articles/clock_and_time.html")
    struct Time {
      @verbatim (language="comment", text=
        "The seconds component, valid over all int32 values.")
      int32 sec;

      @verbatim (language="comment", text=
        "The nanoseconds component, valid in the range [0, 10e9).")
      uint32 nanosec;
    };
  };
};
""",
}
"""Each type's .idl file: FOO's as rosidl_adapter generates it, FINGER's as a vendor writes one, TIME's as Jazzy
ships it."""


def rosbag2_idl(idl: dict[str, str], name: str = FOO) -> str:
    """The ``ros2idl`` schema rosbag2 (its LocalMessageDefinitionSource) writes for ``name``: each type's IDL after a
    line of 80 '=' and a line ``IDL: <type>``, the types it ``#include``s after it (depth first, sorted, each once)."""
    seen: set[str] = set()

    def delimiter(type_name: str) -> str:
        return "=" * 80 + f"\nIDL: {type_name}\n"

    def full(type_name: str) -> str:
        text = idl[type_name]
        for dep in sorted(set(re.findall(r'^#include\s+["<]([\w/]+)\.idl[">]', text, re.MULTILINE))):
            if dep not in seen:
                seen.add(dep)
                text += "\n" + delimiter(dep) + full(dep)
        return text

    return delimiter(name) + full(name)


def idl_store() -> Any:
    """A typestore of the IDL types, for writing them (rosbags' IDL parser takes no preprocessor lines)."""
    store = get_typestore(Stores.EMPTY)
    for text in IDL.values():
        store.register(get_types_from_idl(re.sub(r"^#.*$", "", text, flags=re.MULTILINE)))
    return store


def foo_message(store: Any, index: int) -> Any:
    """The FOO written for the fixture's ``index``-th message: every field, nested ones included, told by it."""
    finger = store.types[FINGER]
    return store.types[FOO](
        stamp=store.types[TIME](sec=index, nanosec=index * 1000),
        state=index // 10 % 2,
        thumb=finger(name=f"thumb {index}", position=index / 4, a=-index),
        fingers=[finger(name=f"f{j}", position=j + 0.5, a=index + j) for j in range(index // 10 % 4)],
        force=np.array([index, -index, 0.25]),
        label=f"grip {index}",
    )


def plain(value: Any) -> Any:
    """A decoded message as plain data (fields by name, arrays as lists), to compare across typestores."""
    if dataclasses.is_dataclass(value):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


IDL_TOPIC = "/vendor/grasp"


def idl_topic_bag(path: Path, data: TrajectorySet, storage=StoragePlugin.MCAP) -> tuple[Path, list[Any]]:
    """A sound bag as ``ros2 bag record -a`` records one where a vendor's package defines a message in IDL:
    ``data``'s hand messages and IDL_TOPIC of type FOO, its definition stored as rosbag2 stores one (``ros2idl``,
    :func:`rosbag2_idl`: ``#include`` lines, an include guard) with the type's hash, metadata.yaml written at close;
    and the FOOs written, in order (one after every 10th hand message, ``foo_message(store, index)``)."""
    store = idl_store()
    written = []
    with JazzyWriter(path, version=9, storage_plugin=storage) as writer:
        conns = {t: writer.add_connection(t, ma.HAND_TOPICS[t], typestore=ma.TYPESTORE) for t in ma.HAND_TOPICS}
        foo = writer.add_connection(IDL_TOPIC, FOO, msgdef=rosbag2_idl(IDL), rihs01=store.hash_rihs01(FOO))
        for index, (topic, stamp, msg) in enumerate(m for traj in data for m in step_messages(traj)):
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
            if index % 10 == 0:
                written.append(foo_message(store, index))
                writer.write(foo, stamp, store.serialize_cdr(written[-1], FOO))
    return path, written


BROKEN_TOPIC = "/vendor/broken"
BAR = "my_msgs/msg/Bar"
"""A type defined in .msg (a lab's package) that Jazzy's store lacks."""
BROKEN = {
    "ros2msg": (BAR, "int32 id\nfloat64 force\nmy_msgs/Fi"),
    "ros2idl": (FOO, rosbag2_idl(IDL)[:640]),
    "ros2idl, a part unheaded": (FOO, rosbag2_idl(IDL).replace(f"IDL: {FINGER}", f"// {FINGER}")),
    "ros2msg, a type it uses undefined": (BAR, "int32 id\nfloat64 force\nmy_msgs/Finger finger\n"),
    "ros2msg, another type hash": (BAR, "int32 id\nfloat64 force\n"),
}
"""Stored definitions rosbags cannot parse or check, by kind, with their type: a ``.msg`` definition cut off
mid-line, an IDL one cut off in its struct, an IDL one whose second type lost its ``IDL: <type>`` header line, a
``.msg`` one that parses but lacks a type it uses (its ``MSG:`` part), and one whose hash is not the stored one
(all are stored with a hash of zeros)."""
BROKEN_WHY = {"ros2msg, a type it uses undefined": "its stored definition uses a type no definition in the bag "
                                                   "gives (KeyError: 'my_msgs/msg/Finger')",
              "ros2msg, another type hash": "its stored definition hashes to RIHS01_9551c679..., not to its stored "
                                            "RIHS01_00000000..."}
"""How a warning says why a BROKEN kind is not decodable, where it is not that it does not parse."""
UNPARSED = "its stored definition cannot be parsed (TypesysError: Could not parse"


def broken_definition_bag(path: Path, data: TrajectorySet, storage=StoragePlugin.MCAP,
                          kind: str = "ros2msg") -> tuple[Path, int]:
    """A ``ros2 bag record -a`` bag of ``data``'s hand messages and BROKEN_TOPIC, whose stored definition (``kind``,
    one of :data:`BROKEN`) does not parse; and how many messages BROKEN_TOPIC holds (one after every 10th hand
    message, each bytes of no particular type: nothing reads them)."""
    msgtype, text = BROKEN[kind]
    assert text.startswith("=" * 80 + "\nIDL: ") == kind.startswith("ros2idl")  # how rosbags' writer tells encodings
    count = 0
    with JazzyWriter(path, version=9, storage_plugin=storage) as writer:
        conns = {t: writer.add_connection(t, ma.HAND_TOPICS[t], typestore=ma.TYPESTORE) for t in ma.HAND_TOPICS}
        broken = writer.add_connection(BROKEN_TOPIC, msgtype, msgdef=text, rihs01="RIHS01_" + "0" * 64)
        for index, (topic, stamp, msg) in enumerate(m for traj in data for m in step_messages(traj)):
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
            if index % 10 == 0:
                writer.write(broken, stamp, b"\x00\x01\x00\x00" + index.to_bytes(4, "little"))
                count += 1
    return path, count


CLASHING_TOPICS = {"/vendor/a": ("my_msgs/msg/A", "int32 x"), "/vendor/b": ("my_msgs/msg/B", "float64 y")}
"""Two topics whose types use one ``my_msgs/Sub``, each stored with a definition of its own (two installs of the
package: an ``int32`` field, a ``float64``) and its own hash."""


def clashing_definitions_bag(path: Path, data: TrajectorySet, storage=StoragePlugin.MCAP) -> Path:
    """A ``ros2 bag record -a`` bag of ``data``'s hand messages and the CLASHING_TOPICS, one message each: each
    definition is sound alone, but rosbags registers both in one store, where B's ``Sub`` replaces A's, and then
    refused the whole bag over A's hash."""
    separator = "=" * 80 + "\n"
    with JazzyWriter(path, version=9, storage_plugin=storage) as writer:
        conns = {t: writer.add_connection(t, ma.HAND_TOPICS[t], typestore=ma.TYPESTORE) for t in ma.HAND_TOPICS}
        vendor = []
        for topic, (msgtype, field) in CLASHING_TOPICS.items():
            text = f"my_msgs/Sub s\n{separator}MSG: my_msgs/Sub\n{field}\n"
            store = get_typestore(Stores.EMPTY)
            store.register(get_types_from_msg(text, msgtype))
            vendor.append(writer.add_connection(topic, msgtype, msgdef=text, rihs01=store.hash_rihs01(msgtype)))
        for index, (topic, stamp, msg) in enumerate(m for traj in data for m in step_messages(traj)):
            writer.write(conns[topic], stamp, ma.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))
            if index == 0:
                for conn in vendor:
                    writer.write(conn, stamp, b"\x00\x01\x00\x00" + bytes(8))
    return path
