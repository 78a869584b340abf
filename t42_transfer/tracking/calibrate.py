"""Camera calibration from checkerboard or ChArUco images, written as a ROS ``camera_info`` YAML.

:func:`calibrate` finds a board's corners in every image and runs ``cv2.calibrateCamera`` (plumb_bob: k1, k2,
p1, p2; k3 held at 0, as ROS's camera_calibration does by default).  Two kinds of board:

* :class:`Checkerboard`: the inner corners (``cv2.findChessboardCornersSB``, sub-pixel); an image counts only
  when the whole board is in it;
* :class:`Charuco`: a chessboard with ArUco markers in its white squares (``cv2.aruco.CharucoBoard``, found by
  ``cv2.aruco.CharucoDetector``); each corner is known by the markers next to it, so a view showing part of the
  board counts too (at least :data:`MIN_CHARUCO_CORNERS` corners, not all on one line).

:func:`camera_info_document` lays the result out as camera_calibration_parsers writes it (``image_width``,
``camera_matrix``, ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``), which
:meth:`~t42_transfer.tracking.markers.Intrinsics.from_yaml_dict` reads back.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from t42_transfer.tracking.markers import DEFAULT_DICTIONARY, Intrinsics, aruco_dictionary

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
MIN_TILT_DEG = 10.0
MIN_TILTED_VIEWS = 2
"""Views of a board parallel to the image plane fix no focal length (Zhang's method needs the plane to turn): a
fit of five square-on views gave fx 19 times the true one at 0.05 px of error.  ROS's camera_calibration asks for
skew the same way."""
MIN_VIEWS = 3
MAX_IMAGES = 1000
MIN_CHARUCO_CORNERS = 6
"""ChArUco corners a view needs to count (a view's homography needs 4; a few more keep a sliver out)."""


@dataclass(frozen=True)
class Calibration:
    intrinsics: Intrinsics
    rms_px: float
    """RMS reprojection error over all corners of the images used (cv2.calibrateCamera's return value)."""
    per_image_px: tuple[float, ...]
    """RMS reprojection error of each image used, in the order of ``used``."""
    used: tuple[str, ...]
    skipped: tuple[str, ...]
    """Images where the board was not found (a checkerboard not whole, a ChArUco board in too few corners)."""


def parse_grid(text: str, what: str = "board pattern", unit: str = "inner corners", example: str = "9x6",
               least: int = 2) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): so many per row and per column, each at least ``least``."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"{what} must be COLSxROWS of {unit} such as {example}, got {text[:40]!r}") from None
    if cols < least or rows < least:
        raise ValueError(f"{what} {cols}x{rows}: need at least {least}x{least} {unit}")
    if cols * rows > 10_000:
        raise ValueError(f"{what} {cols}x{rows}: at most 10000 {unit} in all")
    return cols, rows


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): a checkerboard's inner corners per row and per column."""
    return parse_grid(text)


def parse_squares(text: str) -> tuple[int, int]:
    """``"7x5"`` -> (7, 5): a ChArUco board's squares per row and per column."""
    return parse_grid(text, "ChArUco board", "squares", "7x5", least=3)


def _check_length(name: str, metres: float) -> None:
    if not (math.isfinite(metres) and metres > 0):
        raise ValueError(f"{name} must be positive metres, got {metres}")


@dataclass(frozen=True)
class Checkerboard:
    """A checkerboard of ``pattern`` inner corners (per row, per column) and ``square_m`` squares."""

    pattern: tuple[int, int]
    square_m: float

    def __post_init__(self) -> None:
        _check_length("square size", self.square_m)

    def describe(self) -> str:
        return f"{self.pattern[0]}x{self.pattern[1]} board"

    def find(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(board points N x 3, image points N x 1 x 2; float32) of the whole board, or None."""
        corners = find_board(gray, self.pattern)
        return None if corners is None else (board_points(self.pattern, self.square_m), corners)


@dataclass(frozen=True)
class Charuco:
    """A ChArUco board: ``squares`` (per row, per column) of ``square_m``, markers of ``marker_m`` from
    ``dictionary`` in its white squares, laid out as ``cv2.aruco.CharucoBoard`` lays them out (OpenCV >= 4.6's
    layout: a board with an even number of rows printed by an older OpenCV differs and is not found)."""

    squares: tuple[int, int]
    square_m: float
    marker_m: float
    dictionary: str = DEFAULT_DICTIONARY

    def __post_init__(self) -> None:
        _check_length("square size", self.square_m)
        _check_length("marker size", self.marker_m)
        if self.marker_m >= self.square_m:
            raise ValueError(f"marker side {self.marker_m:g} m must be smaller than the square's {self.square_m:g} m")
        markers = self.squares[0] * self.squares[1] // 2
        available = aruco_dictionary(self.dictionary).bytesList.shape[0]
        if markers > available:
            raise ValueError(f"a {self.squares[0]}x{self.squares[1]} ChArUco board has {markers} markers; "
                             f"{self.dictionary} has only {available}")

    def describe(self) -> str:
        return f"{self.squares[0]}x{self.squares[1]} ChArUco board ({self.dictionary})"

    @functools.cached_property
    def board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` (what a renderer draws and the detector looks for)."""
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_m, aruco_dictionary(self.dictionary))

    @functools.cached_property
    def _detector(self) -> Any:
        return cv2.aruco.CharucoDetector(self.board)

    def find(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(board points N x 3, image points N x 1 x 2; float32) of the corners seen, or None when fewer than
        :data:`MIN_CHARUCO_CORNERS` are seen or they lie on one line."""
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS or self.board.checkCharucoCornersCollinear(ids):
            return None
        points, pixels = self.board.matchImagePoints(corners, ids)
        return points.reshape(-1, 3).astype(np.float32), pixels.reshape(-1, 1, 2).astype(np.float32)


Board = Checkerboard | Charuco


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """The inner corners in the board's plane (m), row by row, as the corner finder orders them."""
    cols, rows = pattern
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def find_board(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """The board's inner corners (N x 1 x 2 float32, px) in a grey image, or None if not all are found."""
    found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    return corners.astype(np.float32).reshape(-1, 1, 2) if found else None


def image_files(folder: Path) -> list[Path]:
    """The images in ``folder`` (by suffix), sorted; ValueError when there are none."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise ValueError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    if len(files) > MAX_IMAGES:
        raise ValueError(f"{folder}: {len(files)} images; at most {MAX_IMAGES}")
    return files


def calibrate(images: Iterable[tuple[str, np.ndarray]], board: Board) -> Calibration:
    """Calibrate from ``(name, grey or BGR image)`` pairs of one camera; ValueError if it cannot be done."""
    object_points, image_points, used, skipped = [], [], [], []
    size: tuple[int, int] | None = None
    for name, image in images:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise ValueError(f"{name}: image is {this[0]}x{this[1]}, the first one {size[0]}x{size[1]}")
        found = board.find(gray)
        if found is None:
            skipped.append(name)
            continue
        object_points.append(found[0])
        image_points.append(found[1])
        used.append(name)
    if size is None:
        raise ValueError("no images")
    if len(used) < MIN_VIEWS:
        charuco_unseen = isinstance(board, Charuco) and not used
        hint = " (is it the board's dictionary and number of squares?)" if charuco_unseen else ""
        raise ValueError(f"found the {board.describe()} in {len(used)} of {len(used) + len(skipped)} images; "
                         f"need at least {MIN_VIEWS}{hint}")
    rms, k, d, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, size, None, None,
                                                  flags=cv2.CALIB_FIX_K3)
    tilted = sum(np.degrees(np.arccos(min(1.0, abs(cv2.Rodrigues(r)[0][2, 2])))) >= MIN_TILT_DEG for r in rvecs)
    if tilted < MIN_TILTED_VIEWS:
        raise ValueError(f"the board faces the camera squarely (tilted under {MIN_TILT_DEG:g} deg) in "
                         f"{len(used) - tilted} of {len(used)} views: such views leave the focal length undetermined "
                         f"(a fit of them gave fx {k[0, 0]:.0f} px); take {MIN_TILTED_VIEWS} or more with the board "
                         "tilted 20-45 deg about different axes")
    per_image = []
    for obj, img, rvec, tvec in zip(object_points, image_points, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(obj, rvec, tvec, k, d)
        per_image.append(float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=2)))))
    intrinsics = Intrinsics(size[0], size[1], k, np.asarray(d, dtype=float).reshape(-1)[:5])
    return Calibration(intrinsics, float(rms), tuple(per_image), tuple(used), tuple(skipped))


def read_images(files: Sequence[Path]) -> Iterable[tuple[str, np.ndarray]]:
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{path}: not an image OpenCV can read")
        yield path.name, image


def _matrix(rows: int, cols: int, values: np.ndarray) -> dict:
    return {"rows": rows, "cols": cols, "data": [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]}


def camera_info_document(intrinsics: Intrinsics, camera_name: str = "camera") -> dict:
    """The ROS ``camera_info`` YAML document (camera_calibration_parsers' keys) of a monocular camera."""
    size = (intrinsics.width, intrinsics.height)
    projection, _ = cv2.getOptimalNewCameraMatrix(intrinsics.k, intrinsics.d, size, 0.0)
    return {
        "image_width": intrinsics.width,
        "image_height": intrinsics.height,
        "camera_name": camera_name,
        "camera_matrix": _matrix(3, 3, intrinsics.k),
        "distortion_model": "plumb_bob",
        "distortion_coefficients": _matrix(1, intrinsics.d.size, intrinsics.d),
        "rectification_matrix": _matrix(3, 3, np.eye(3)),
        "projection_matrix": _matrix(3, 4, np.hstack([projection, np.zeros((3, 1))])),
    }


def write_camera_info(path: Path, intrinsics: Intrinsics, camera_name: str = "camera") -> None:
    path.write_text(yaml.safe_dump(camera_info_document(intrinsics, camera_name), sort_keys=False))
