"""The scene's inputs at one moment of a recorded bag: the newest actuator angles, object position, goal and
planned path at or before that time (topics matched by their relative names under any namespace)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import msg_adapters as ma
from msg_adapters import names
from msg_adapters.planning import candidates_xy_mm
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


def input_reader(topic: str) -> tuple[str, Callable[[Any], Any]] | None:
    """(the :class:`SceneInputs` field, its message reader) of a bag topic that feeds the scene, else None."""
    for name, reading in _READERS.items():
        if topic == "/" + name or topic.endswith("/" + name):
            return reading
    return None


def bag_scene_inputs(bag: str | Path, at_s: float | None = None) -> SceneInputs:
    """The inputs at ``at_s`` seconds after the bag's first message (None: its end); BagError for what cannot be
    read (a missing path, no bag, a FIFO where a bag file belongs, a message that is not what its topic carries)
    and for a time after the bag's end."""
    path = Path(bag)
    reader = open_bag(path, "read for a snapshot")
    inputs = SceneInputs()
    try:
        wanted = [c for c in reader.connections if input_reader(c.topic)]
        inputs.start_ns = reader.start_time
        until = None if at_s is None else reader.start_time + round(at_s * 1e9)
        if until is not None and until > reader.end_time:
            raise BagError(path, f"ends {(reader.end_time - reader.start_time) / 1e9:.1f} s after its first "
                                 f"message: no scene at {at_s:g} s")
        for conn, log_ns, raw in reader.messages(connections=wanted):
            if until is not None and log_ns > until:
                break
            field, read = input_reader(conn.topic)
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
