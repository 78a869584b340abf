"""Planner messages <-> numpy: goals (``PointStamped``) and predicted paths (``nav_msgs/Path``).

Same rules as :mod:`msg_adapters.hand`: metres in ``FRAME_ID`` on the wire, float32
mm inside the package, one multiplication or division per direction, so positions
survive a round trip bit for bit.  Readers refuse other frames and non-finite
values with a ``ValueError`` that says why.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msg_adapters.hand import (
    _MM_PER_M,
    _header,
    _pair,
    _to_f32,
    object_pose_msg,
    object_xy_mm,
)
from msg_adapters.kit import ROSBAGS, MessageKit
from msg_adapters.wire import CONTROL_PERIOD_NS, FRAME_ID

POINT_STAMPED = "geometry_msgs/msg/PointStamped"
PATH = "nav_msgs/msg/Path"


def goal_msg(xy_mm: np.ndarray | Sequence[float], stamp_ns: int, kit: MessageKit = ROSBAGS) -> Any:
    """``PointStamped`` of a goal for the object centre (metres in FRAME_ID, z = 0)."""
    x, y = _pair("goal", xy_mm) / _MM_PER_M
    return kit.make(
        POINT_STAMPED,
        header=_header(stamp_ns, FRAME_ID, kit),
        point=kit.make("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0),
    )


def goal_xy_mm(msg: Any) -> np.ndarray:
    """Goal ``(x, y)`` in mm (float32) of a ``PointStamped``; z is ignored but must be finite.

    Raises ``ValueError`` for another frame (the planner cannot transform), a
    non-finite coordinate, or one float32 mm cannot hold.
    """
    if msg.header.frame_id != FRAME_ID:
        raise ValueError(f"goal is in frame {msg.header.frame_id!r}, expected {FRAME_ID!r}")
    point = np.array([msg.point.x, msg.point.y, msg.point.z], np.float64)
    if not np.all(np.isfinite(point)):
        raise ValueError(f"goal has a non-finite coordinate: {point.tolist()}")
    return _to_f32("goal position", point[:2] * _MM_PER_M)


def path_msg(
    xy_mm: np.ndarray, start_ns: int, period_ns: int = CONTROL_PERIOD_NS, kit: MessageKit = ROSBAGS
) -> Any:
    """``Path`` of object positions ``xy_mm[N, 2]``, pose ``k`` stamped ``start_ns + k * period_ns``."""
    xy = np.asarray(xy_mm, dtype=np.float32)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"path positions must have shape [N, 2], got {xy.shape}")
    if period_ns <= 0:
        raise ValueError(f"path period must be positive, got {period_ns} ns")
    poses = [object_pose_msg(p, start_ns + k * period_ns, kit) for k, p in enumerate(xy)]
    return kit.make(PATH, header=_header(start_ns, FRAME_ID, kit), poses=poses)


def path_xy_mm(msg: Any) -> np.ndarray:
    """Object positions ``[N, 2]`` in mm (float32) of a ``Path``; refuses other frames."""
    if msg.header.frame_id != FRAME_ID:
        raise ValueError(f"path is in frame {msg.header.frame_id!r}, expected {FRAME_ID!r}")
    if not msg.poses:
        return np.zeros((0, 2), np.float32)
    return np.stack([object_xy_mm(pose) for pose in msg.poses])


PLAN_CANDIDATES = "t42_interfaces/msg/PlanCandidates"


def candidates_msg(paths_mm: Sequence[np.ndarray], stamp_ns: int, kit: MessageKit = ROSBAGS) -> Any:
    """``PlanCandidates`` of predicted object paths (each ``[N, 2]`` mm, lowest cost first), stamped ``stamp_ns``."""
    return kit.make(PLAN_CANDIDATES, header=_header(stamp_ns, FRAME_ID, kit),
                    paths=[path_msg(p, stamp_ns, kit=kit) for p in paths_mm])


def candidates_xy_mm(msg: Any) -> list[np.ndarray]:
    """The paths of a ``PlanCandidates`` (``[N, 2]`` mm each, as sent); refuses other frames."""
    if msg.header.frame_id != FRAME_ID:
        raise ValueError(f"plan candidates are in frame {msg.header.frame_id!r}, expected {FRAME_ID!r}")
    return [path_xy_mm(p) for p in msg.paths]
