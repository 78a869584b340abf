"""A drawn scene -> ``visualization_msgs/MarkerArray``, and the colours every picture of it uses.

The scene is plain data (:class:`SceneLike`: :class:`t42_transfer.view.scene.Scene` is one), millimetres in
``FRAME_ID``; the markers are in metres (REP 103) on the plane z = 0.  The array starts with a ``DELETEALL``, so a
viewer forgets what the previous array drew (a goal reached and gone, a shorter path).  Namespaces: ``hand``
(fingers and palm), ``object``, ``goal`` (a dot and the tolerance circle; red, with the planner's status word,
when it refused the goal), ``path`` (the planned path),
``candidates`` (the planner's other rollouts).  Built with rclpy's classes by default: rosbags' need every
field of the Marker's textures and meshes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from msg_adapters.hand import _header
from msg_adapters.kit import RCLPY, MessageKit
from msg_adapters.wire import FRAME_ID

MARKER = "visualization_msgs/msg/Marker"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

COLORS: dict[str, tuple[float, float, float, float]] = {
    "hand": (0.55, 0.57, 0.62, 1.0),
    "palm": (0.35, 0.37, 0.42, 1.0),
    "object": (0.85, 0.55, 0.2, 0.9),
    "goal": (0.1, 0.75, 0.2, 1.0),
    "refused": (0.85, 0.1, 0.1, 1.0),
    "path": (0.15, 0.35, 0.95, 1.0),
    "candidates": (0.6, 0.3, 0.8, 0.35),
}
"""RGBA (0-1) of each part, shared by the markers and ``t42 view --snapshot``'s picture."""
CIRCLE_POINTS = 64
"""Points of the tolerance circle's closed line strip (and of the picture's circle)."""
GOAL_DOT_MM = 3.0
"""Diameter of the goal's dot."""
LINE_MM = {"path": 1.5, "goal": 0.8, "candidates": 0.8, "palm": 1.5}
"""Line widths (mm) of the thin parts; a finger is drawn as wide as its links."""
_M_PER_MM = 0.001
DELETEALL, LINE_STRIP, CYLINDER, SPHERE, TEXT_VIEW_FACING = 3, 4, 3, 2, 9
TEXT_MM = 6.0
"""Height of the refusal's text."""
ADD = 0


class SceneLike(Protocol):
    """What :func:`scene_markers` reads (mm in ``FRAME_ID``; None or empty: not drawn)."""

    fingers: Sequence[np.ndarray]
    palm: np.ndarray
    link_radius_mm: float
    object_radius_mm: float
    object_xy_mm: np.ndarray | None
    goal_xy_mm: np.ndarray | None
    tolerance_mm: float
    path_xy_mm: np.ndarray | None
    candidates: Sequence[np.ndarray]
    goal_refused: str


def circle_xy(centre_mm: Sequence[float], radius_mm: float, n: int = CIRCLE_POINTS) -> np.ndarray:
    """A closed circle's points ``[n + 1, 2]`` (mm), the first repeated last."""
    angles = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.column_stack([centre_mm[0] + radius_mm * np.cos(angles), centre_mm[1] + radius_mm * np.sin(angles)])


def _color(kit: MessageKit, part: str) -> Any:
    r, g, b, a = COLORS[part]
    return kit.make("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)


def _point(kit: MessageKit, xy_mm: Sequence[float]) -> Any:
    return kit.make("geometry_msgs/msg/Point", x=float(xy_mm[0]) * _M_PER_MM, y=float(xy_mm[1]) * _M_PER_MM, z=0.0)


def _marker(kit: MessageKit, header: Any, ns: str, marker_id: int, kind: int, part: str, **fields: Any) -> Any:
    pose = kit.make("geometry_msgs/msg/Pose", position=fields.pop("position", _point(kit, (0.0, 0.0))),
                    orientation=kit.make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
    size = fields.pop("size_mm", (1.0, 1.0, 1.0))
    scale = kit.make("geometry_msgs/msg/Vector3", x=size[0] * _M_PER_MM, y=size[1] * _M_PER_MM, z=size[2] * _M_PER_MM)
    return kit.make(MARKER, header=header, ns=ns, id=marker_id, type=kind, action=ADD, pose=pose, scale=scale,
                    color=_color(kit, part), **fields)


def _strip(kit: MessageKit, header: Any, ns: str, marker_id: int, part: str, xy_mm: np.ndarray,
           width_mm: float) -> Any:
    return _marker(kit, header, ns, marker_id, LINE_STRIP, part, size_mm=(width_mm, 0.0, 0.0),
                   points=[_point(kit, p) for p in np.asarray(xy_mm, dtype=float)])


def scene_markers(scene: SceneLike, stamp_ns: int, kit: MessageKit = RCLPY) -> Any:
    """The ``MarkerArray`` of ``scene`` stamped ``stamp_ns``: a DELETEALL, then every part drawn."""
    header = _header(stamp_ns, FRAME_ID, kit)
    markers = [kit.make(MARKER, header=header, action=DELETEALL)]
    for i, finger in enumerate(scene.fingers):
        markers.append(_strip(kit, header, "hand", i, "hand", finger, 2.0 * scene.link_radius_mm))
    markers.append(_strip(kit, header, "hand", len(scene.fingers), "palm", scene.palm, LINE_MM["palm"]))
    if scene.object_xy_mm is not None:
        diameter = 2.0 * scene.object_radius_mm
        markers.append(_marker(kit, header, "object", 0, CYLINDER, "object", position=_point(kit, scene.object_xy_mm),
                               size_mm=(diameter, diameter, 10.0)))
    if scene.goal_xy_mm is not None:
        part = "refused" if scene.goal_refused else "goal"
        markers.append(_marker(kit, header, "goal", 0, SPHERE, part, position=_point(kit, scene.goal_xy_mm),
                               size_mm=(GOAL_DOT_MM,) * 3))
        markers.append(_strip(kit, header, "goal", 1, part, circle_xy(scene.goal_xy_mm, scene.tolerance_mm),
                              LINE_MM["goal"]))
        if scene.goal_refused:
            above = (scene.goal_xy_mm[0], scene.goal_xy_mm[1] + scene.tolerance_mm + TEXT_MM)
            markers.append(_marker(kit, header, "goal", 2, TEXT_VIEW_FACING, part, position=_point(kit, above),
                                   size_mm=(TEXT_MM,) * 3, text=f"refused: {scene.goal_refused}"))
    if scene.path_xy_mm is not None and len(scene.path_xy_mm) >= 2:
        markers.append(_strip(kit, header, "path", 0, "path", scene.path_xy_mm, LINE_MM["path"]))
    for i, candidate in enumerate(c for c in scene.candidates if len(c) >= 2):
        markers.append(_strip(kit, header, "candidates", i, "candidates", candidate, LINE_MM["candidates"]))
    return kit.make(MARKER_ARRAY, markers=markers)
