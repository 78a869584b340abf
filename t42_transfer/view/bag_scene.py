"""The scene's inputs at one moment of a recorded bag: the newest actuator angles, object position, goal and
planned path at or before that time (topics matched by their relative names under any namespace, or the hand topics
under the names a recorder wrote down)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.planning import candidates_xy_mm
from t42_transfer.data.bag.hand_topics import HAND_TOPICS_KEY, hand_topic_names
from t42_transfer.data.bag.metadata import metadata_yaml
from t42_transfer.data.bag.playback import open_bag
from t42_transfer.data.errors import BagError


@dataclass
class SceneInputs:
    """What a scene is built from (mm, rad); None: not in the bag before that time."""

    actuator_angles: np.ndarray | None = None
    object_xy_mm: np.ndarray | None = None
    goal_xy_mm: np.ndarray | None = None
    path_xy_mm: np.ndarray | None = None
    candidates: list[np.ndarray] | None = None
    log_ns: int = 0
    """Log time of the newest message used."""
    start_ns: int = 0
    """Log time of the bag's first message."""


_READERS = {
    names.JOINT_STATES: ("actuator_angles", lambda msg: ma.joint_state_arrays(msg)[1]),
    names.OBJECT_POSE: ("object_xy_mm", ma.object_xy_mm),
    names.GOAL: ("goal_xy_mm", ma.goal_xy_mm),
    names.PLANNED_PATH: ("path_xy_mm", ma.path_xy_mm),
    names.PLAN_CANDIDATES: ("candidates", candidates_xy_mm),
}


def input_reader(topic: str, renamed: dict[str, str] | None = None) -> tuple[str, Callable[[Any], Any]] | None:
    """(the :class:`SceneInputs` field, its message reader) of a bag topic that feeds the scene, else None;
    ``renamed``: recorded topic -> the relative name it stands for (a recorder's record of its hand topics,
    which then are read under those names only, as ``read_bag`` reads them)."""
    renamed = renamed or {}
    if topic in renamed:
        return _READERS[renamed[topic]]
    hand = set(renamed.values())
    for name, reading in _READERS.items():
        if name not in hand and (topic == "/" + name or topic.endswith("/" + name)):
            return reading
    return None


def _renamed(path: Path, reader: Any) -> dict[str, str]:
    """The recorded topic of each remapped hand topic the scene draws, as the bag's recorder wrote it down in
    its metadata.yaml."""
    meta, _ = metadata_yaml(path if path.is_dir() else path.parent)
    custom = meta.custom if meta else {}
    if HAND_TOPICS_KEY not in custom:
        return {}
    recorded = hand_topic_names(path, custom, [c.topic for c in reader.connections])
    return {recorded["/" + name]: name for name in (names.JOINT_STATES, names.OBJECT_POSE)}


def bag_scene_inputs(bag: str | Path, at_s: float | None = None) -> SceneInputs:
    """The inputs at ``at_s`` seconds after the bag's first message (None: its end); BagError for what cannot be
    read (a missing path, no bag, a FIFO where a bag file belongs, a message that is not what its topic carries)
    and for a time after the bag's end."""
    path = Path(bag)
    reader = open_bag(path, "read for a snapshot")
    inputs = SceneInputs()
    try:
        renamed = _renamed(path, reader)
        wanted = [c for c in reader.connections if input_reader(c.topic, renamed)]
        inputs.start_ns = reader.start_time
        until = None if at_s is None else reader.start_time + round(at_s * 1e9)
        if until is not None and until > reader.end_time:
            raise BagError(path, f"ends {(reader.end_time - reader.start_time) / 1e9:.1f} s after its first "
                                 f"message: no scene at {at_s:g} s")
        for conn, log_ns, raw in reader.messages(connections=wanted) if wanted else ():  # []: every connection
            if until is not None and log_ns > until:
                break
            field, read = input_reader(conn.topic, renamed)
            value = read(reader.deserialize(raw, conn.msgtype))
            if value is not None:
                setattr(inputs, field, value)
                inputs.log_ns = log_ns
    except BagError:
        raise
    except Exception as err:  # rosbags and the readers raise many types for what is not a sound bag
        raise BagError(path, f"cannot be read for a snapshot ({type(err).__name__}: {err})") from None
    finally:
        reader.close()
    return inputs
