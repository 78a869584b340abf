"""Printable sheets, at true size: the object tracker's ArUco markers and the camera calibration boards.

The tracker's positions rest on every marker being printed at the side it is told (``object_size_m``,
``base_sizes_m``), and a calibration on the board's squares being the size ``t42 camera calibrate`` is told.
A sheet here is drawn in millimetres on a page of the paper's size, the markers and squares as filled vector
shapes (no image to be resampled), so a print at 100 % ("actual size", not "fit to page") gives those sides.
Every sheet has a 50 mm scale bar to check the print with a ruler before the markers are measured in.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from t42_transfer.conventions import MM_PER_M
from t42_transfer.tracking.calibrate import Charuco, Checkerboard
from t42_transfer.tracking.markers import TrackerConfig, aruco_dictionary

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

PAPERS_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}
"""Page sizes (width, height in mm, portrait)."""
MARGIN_MM = 12.0
"""White border of the page (printers do not print to the edge)."""
GAP_MM = 10.0
"""Space between two markers: more than the one module of white quiet zone a marker needs, room to cut."""
LABEL_MM = 8.0
"""Height of the two lines of text under each marker."""
SCALE_BAR_MM = 50.0
TOP_MM = MARGIN_MM + 14.0
"""Where the markers or the board begin, below the title lines."""
RASTER_DPI = 300
"""Resolution of a sheet saved as an image (PNG...); PDF and SVG stay vector."""
VECTOR_SUFFIXES = (".pdf", ".svg", ".eps", ".ps")
SUFFIXES = (*VECTOR_SUFFIXES, ".png")


@dataclass(frozen=True)
class PrintedMarker:
    """One marker to print: its id, the side of its black square (m) and what it is for."""

    marker_id: int
    size_m: float
    role: str


def tracker_markers(config: TrackerConfig) -> list[PrintedMarker]:
    """The markers ``config`` looks for: the object's, then the base's in order."""
    return [PrintedMarker(config.object_id, config.object_size_m, "object"),
            *(PrintedMarker(m.marker_id, m.size_m, f"base {n + 1} of {len(config.base_markers)}")
              for n, m in enumerate(config.base_markers))]


def marker_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker's cells, True for black: (n + 2) x (n + 2) for an n x n dictionary (its black border
    included), row 0 at the top as the detector sees it; ValueError for an id the dictionary lacks."""
    found = aruco_dictionary(dictionary)
    count = found.bytesList.shape[0]
    if not 0 <= marker_id < count:
        raise ValueError(f"marker id {marker_id} is not in {dictionary} (ids 0 to {count - 1})")
    side = found.markerSize + 2
    return cv2.aruco.generateImageMarker(found, marker_id, side, borderBits=1) < 128


def _cells_path(bits: np.ndarray, x_mm: float, y_mm: float, cell_mm: float) -> list[tuple[float, float, float, float]]:
    """The black cells of ``bits`` as rectangles (x, y, width, height; mm, y down), one per run along a row."""
    boxes = []
    for row, line in enumerate(bits):
        padded = np.concatenate([[False], line, [False]])
        edges = np.flatnonzero(padded[1:] != padded[:-1])
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            boxes.append((x_mm + start * cell_mm, y_mm + row * cell_mm, (stop - start) * cell_mm, cell_mm))
    return boxes


def _fill(ax: Axes, boxes: Iterable[tuple[float, float, float, float]]) -> None:
    """Fill the rectangles black as one compound path (no seams between neighbours, no outline)."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    vertices, codes = [], []
    for x, y, w, h in boxes:
        vertices += [(x, y), (x + w, y), (x + w, y + h), (x, y + h), (x, y)]
        codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    if vertices:
        ax.add_patch(PathPatch(MplPath(vertices, codes), facecolor="black", edgecolor="none", linewidth=0))


def _paper(paper: str, landscape: bool = False) -> tuple[float, float]:
    """The page's (width, height) in mm."""
    if paper not in PAPERS_MM:
        raise ValueError(f"paper must be one of {', '.join(PAPERS_MM)}, got {paper!r}")
    width, height = PAPERS_MM[paper]
    return (height, width) if landscape else (width, height)


def _printable(page: tuple[float, float]) -> tuple[float, float]:
    """Width and height (mm) left for markers or a board under the title and above the scale bar."""
    return page[0] - 2 * MARGIN_MM, page[1] - TOP_MM - MARGIN_MM - 10.0


def _page(paper: str, landscape: bool = False) -> tuple[Figure, Axes, tuple[float, float]]:
    """A figure of the paper's size whose axes fill it in mm, origin top left, y down."""
    from matplotlib.figure import Figure

    width, height = _paper(paper, landscape)
    fig = Figure(figsize=(width / 25.4, height / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, width)
    ax.set_ylim(height, 0.0)
    ax.set_aspect("equal")
    ax.axis("off")
    return fig, ax, (width, height)


def _scale_bar(ax: Axes, x_mm: float, y_mm: float) -> None:
    """A 50 mm bar with a tick each 10 mm, and how to print."""
    ax.add_patch(_rect(x_mm, y_mm, SCALE_BAR_MM, 1.0))
    for tick in range(0, int(SCALE_BAR_MM) + 1, 10):
        ax.add_patch(_rect(x_mm + tick - 0.2 * (tick == SCALE_BAR_MM), y_mm - 2.0, 0.2, 2.0))
    ax.text(x_mm + SCALE_BAR_MM + 3.0, y_mm + 0.5, f"{SCALE_BAR_MM:g} mm: print at 100 % (actual size, not fit to "
            "page) and measure this bar", fontsize=7, va="center")


def _rect(x: float, y: float, w: float, h: float) -> Rectangle:
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, facecolor="black", edgecolor="none", linewidth=0)


LABEL_WIDTH_MM = 24.0
"""Room a marker's label takes across (its text at 7 pt): a slot is at least this wide."""


def _shelves(sizes_mm: Sequence[float], width_mm: float) -> list[tuple[float, float]]:
    """Top-left corners (mm, from the printable area's corner) of squares of ``sizes_mm`` placed left to right
    in rows, each in a slot as wide as the square or its label; each row as tall as its largest square plus its
    label."""
    corners, x, y, row = [], 0.0, 0.0, 0.0
    for size in sizes_mm:
        slot = max(size, LABEL_WIDTH_MM)
        if x > 0 and x + slot > width_mm:
            x, y, row = 0.0, y + row + LABEL_MM + GAP_MM, 0.0
        corners.append((x, y))
        x, row = x + slot + GAP_MM, max(row, size)
    return corners


def marker_sheet(markers: Sequence[PrintedMarker], dictionary: str, paper: str = "a4", title: str = "") -> Figure:
    """One page with every marker at its size, each labelled with its id, role and side; ValueError when an
    id is not in ``dictionary``, two markers share an id, or they do not fit on the page."""
    if not markers:
        raise ValueError("no markers to print")
    ids = [m.marker_id for m in markers]
    if len(set(ids)) != len(ids):
        raise ValueError(f"marker ids must differ, got {ids}")
    bits = [marker_bits(dictionary, m.marker_id) for m in markers]
    for m in markers:
        if not (math.isfinite(m.size_m) and m.size_m > 0):
            raise ValueError(f"marker {m.marker_id}: its side must be positive metres, got {m.size_m}")
    fig, ax, (width, height) = _page(paper)
    sizes = [m.size_m * MM_PER_M for m in markers]
    top = TOP_MM
    usable_w, usable_h = _printable((width, height))
    if max(sizes) > usable_w:
        raise ValueError(f"a {max(sizes):g} mm marker does not fit across {paper} paper ({usable_w:g} mm "
                         f"printable); choose a larger paper")
    corners = _shelves(sizes, usable_w)
    used = max(y + s + LABEL_MM for (_, y), s in zip(corners, sizes, strict=True))
    if used > usable_h:
        raise ValueError(f"{len(markers)} markers of {', '.join(f'{s:g}' for s in sizes)} mm need {used:.0f} mm "
                         f"of {paper} paper's {usable_h:.0f} mm; print them on two sheets or a larger paper")
    ax.text(MARGIN_MM, MARGIN_MM + 4.0, title or f"ArUco markers, {dictionary}", fontsize=10, va="center")
    ax.text(MARGIN_MM, MARGIN_MM + 9.0, "The side given is the black square's, border included: measure each "
            "printed marker and enter what you measure.", fontsize=7, va="center")
    for marker, cells, size, (x, y) in zip(markers, bits, sizes, corners, strict=True):
        x0, y0 = MARGIN_MM + x, top + y
        _fill(ax, _cells_path(cells, x0, y0, size / len(cells)))
        ax.text(x0, y0 + size + 1.0, f"id {marker.marker_id}, {size:g} mm\n{marker.role}", fontsize=7, va="top",
                linespacing=1.2)
    _scale_bar(ax, MARGIN_MM, height - MARGIN_MM - 2.0)
    return fig


def board_sheet(board: Checkerboard | Charuco, paper: str = "a4") -> Figure:
    """One page with the calibration board ``t42 camera calibrate`` looks for, turned landscape when only so it
    fits; ValueError when it does not fit."""
    if isinstance(board, Checkerboard):
        cols, rows = board.pattern[0] + 1, board.pattern[1] + 1  # inner corners -> squares
    else:
        cols, rows = board.squares
    square = board.square_m * MM_PER_M
    fits = [landscape for landscape in (False, True)
            if all(need <= room for need, room in zip((cols * square, rows * square),
                                                       _printable(_paper(paper, landscape)), strict=True))]
    if not fits:
        room = " or ".join(f"{w:g} x {h:g}" for w, h in (_printable(_paper(paper, turn)) for turn in (False, True)))
        raise ValueError(f"a {cols}x{rows} board of {square:g} mm squares ({cols * square:g} x {rows * square:g} "
                         f"mm) does not fit {paper} paper ({room} mm printable); use smaller squares or a larger "
                         "paper")
    fig, ax, (width, height) = _page(paper, landscape=fits[0])
    usable_w, top = _printable((width, height))[0], TOP_MM
    x0, y0 = MARGIN_MM + (usable_w - cols * square) / 2, top
    if isinstance(board, Checkerboard):
        black = [(c, r) for r in range(rows) for c in range(cols) if (r + c) % 2 == 0]
        what = (f"checkerboard: {board.pattern[0]}x{board.pattern[1]} inner corners, {square:g} mm squares "
                f"(t42 camera calibrate --pattern {board.pattern[0]}x{board.pattern[1]} --square {board.square_m:g})")
        markers = []
    else:
        cv_board = board.board
        corners_mm = np.asarray(cv_board.getObjPoints(), dtype=float)[:, :, :2] * MM_PER_M  # y down, as drawn
        ids = cv_board.getIds().ravel()
        held = {(int(c.mean(axis=0)[0] // square), int(c.mean(axis=0)[1] // square)) for c in corners_mm}
        black = [(c, r) for r in range(rows) for c in range(cols) if (c, r) not in held]
        markers = list(zip(ids, corners_mm, strict=True))
        what = (f"ChArUco board: {cols}x{rows} squares of {square:g} mm, {board.marker_m * MM_PER_M:g} mm markers, "
                f"{board.dictionary} (t42 camera calibrate --board charuco --squares {cols}x{rows} "
                f"--square {board.square_m:g} --marker {board.marker_m:g} --dictionary {board.dictionary})")
    _fill(ax, [(x0 + c * square, y0 + r * square, square, square) for c, r in black])
    for marker_id, corners in markers:
        cells = marker_bits(board.dictionary, int(marker_id))
        left, upper = corners[0]
        _fill(ax, _cells_path(cells, x0 + left, y0 + upper, (corners[1][0] - left) / len(cells)))
    ax.text(MARGIN_MM, MARGIN_MM + 4.0, "Camera calibration board", fontsize=10, va="center")
    ax.text(MARGIN_MM, MARGIN_MM + 9.0, what, fontsize=6, va="center")
    _scale_bar(ax, MARGIN_MM, height - MARGIN_MM - 2.0)
    return fig


def save_sheet(fig: Figure, path: Path) -> None:
    """Write the sheet as PDF, SVG, EPS or PS (vector, the page's size) or PNG (:data:`RASTER_DPI`), its folder
    made if need be; whole or not at all (written beside it, then renamed)."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"{path}: write a sheet as {', '.join(SUFFIXES)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    try:
        fig.savefig(partial, format=suffix[1:], facecolor="white", **({"dpi": RASTER_DPI} if suffix == ".png" else {}))
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
