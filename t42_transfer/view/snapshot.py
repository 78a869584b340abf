"""``t42 view --snapshot``: a :class:`~t42_transfer.view.scene.Scene` drawn with matplotlib (headless Agg) into a
PNG, in the markers' colours (:data:`msg_adapters.markers.COLORS`), for reports and for checking what the live
view shows without the Foxglove app.

The picture has a fixed scale, ``px_per_mm`` pixels a millimetre over the scene's ``extent_mm`` with no margins,
so a point's pixel is known (:func:`pixel_of`): tests look for the goal's circle and the path where they belong.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from msg_adapters.markers import COLORS, GOAL_DOT_MM, LINE_MM, circle_xy
from t42_transfer.plots import pyplot
from t42_transfer.view.scene import Scene

PX_PER_MM = 4.0
_DPI = 100


def image_size(scene: Scene, px_per_mm: float = PX_PER_MM) -> tuple[int, int]:
    """(width, height) in pixels of the scene's picture."""
    x0, x1, y0, y1 = scene.extent_mm
    return round((x1 - x0) * px_per_mm), round((y1 - y0) * px_per_mm)


def pixel_of(scene: Scene, xy_mm: Sequence[float], px_per_mm: float = PX_PER_MM) -> tuple[float, float]:
    """(column, row) of the pixel at ``xy_mm`` in the scene's picture (row 0 at the top)."""
    x0, _, _, y1 = scene.extent_mm
    return (float(xy_mm[0]) - x0) * px_per_mm, (y1 - float(xy_mm[1])) * px_per_mm


def render(scene: Scene, path: Path, px_per_mm: float = PX_PER_MM, title: str = "") -> Path:
    """Write the picture of ``scene`` to ``path`` (PNG, folders made); returns ``path``."""
    plt = pyplot()
    width, height = image_size(scene, px_per_mm)
    fig = plt.figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_axis_off()
    x0, x1, y0, y1 = scene.extent_mm
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)

    def points(mm: float) -> float:  # a width in mm -> line width in points
        return mm * px_per_mm * 72.0 / _DPI

    if scene.object_xy_mm is not None:
        ax.add_patch(plt.Circle(tuple(scene.object_xy_mm), scene.object_radius_mm, color=COLORS["object"], zorder=1))
    ax.plot(*scene.palm.T, color=COLORS["palm"], lw=points(LINE_MM["palm"]), zorder=2)
    for finger in scene.fingers:
        ax.plot(*finger.T, color=COLORS["hand"], lw=points(2.0 * scene.link_radius_mm), solid_capstyle="round",
                zorder=2)
    for candidate in scene.candidates:
        ax.plot(*np.asarray(candidate).T, color=COLORS["candidates"], lw=points(LINE_MM["candidates"]), zorder=3)
    if scene.path_xy_mm is not None and len(scene.path_xy_mm):
        ax.plot(*scene.path_xy_mm.T, color=COLORS["path"], lw=points(LINE_MM["path"]), zorder=4)
    if scene.goal_xy_mm is not None:
        color = COLORS["refused" if scene.goal_refused else "goal"]
        ax.plot(*circle_xy(scene.goal_xy_mm, scene.tolerance_mm).T, color=color, lw=points(LINE_MM["goal"]), zorder=5)
        ax.add_patch(plt.Circle(tuple(scene.goal_xy_mm), GOAL_DOT_MM / 2, color=color, zorder=5))
        if scene.goal_refused:
            ax.text(scene.goal_xy_mm[0], scene.goal_xy_mm[1] + scene.tolerance_mm + 2, f"refused: {scene.goal_refused}",
                    color=color, ha="center", va="bottom", fontsize=8, zorder=6)
    if title:
        ax.text(0.01, 0.99, title, transform=ax.transAxes, va="top", ha="left", fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path
