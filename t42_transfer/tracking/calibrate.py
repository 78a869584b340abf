"""Camera calibration from checkerboard images, written as a ROS ``camera_info`` YAML.

:func:`calibrate` finds the board's inner corners (``cv2.findChessboardCornersSB``, sub-pixel) in every image
and runs ``cv2.calibrateCamera`` (plumb_bob: k1, k2, p1, p2; k3 held at 0, as ROS's camera_calibration
does by default).  :func:`camera_info_document` lays the result out as camera_calibration_parsers writes it
(``image_width``, ``camera_matrix``, ``distortion_coefficients``, ``rectification_matrix``,
``projection_matrix``), which :meth:`~t42_transfer.tracking.markers.Intrinsics.from_yaml_dict` reads back.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from t42_transfer.tracking.markers import Intrinsics

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
MIN_VIEWS = 3
MAX_IMAGES = 1000


@dataclass(frozen=True)
class Calibration:
    intrinsics: Intrinsics
    rms_px: float
    """RMS reprojection error over all corners of the images used (cv2.calibrateCamera's return value)."""
    per_image_px: tuple[float, ...]
    """RMS reprojection error of each image used, in the order of ``used``."""
    used: tuple[str, ...]
    skipped: tuple[str, ...]
    """Images where the whole board was not found."""


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): inner corners per row and per column."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"board pattern must be COLSxROWS of inner corners such as 9x6, got {text[:40]!r}") from None
    if cols < 2 or rows < 2 or cols * rows > 10_000:
        raise ValueError(f"board pattern {cols}x{rows}: need at least 2x2 inner corners")
    return cols, rows


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


def calibrate(images: Iterable[tuple[str, np.ndarray]], pattern: tuple[int, int], square_m: float) -> Calibration:
    """Calibrate from ``(name, grey or BGR image)`` pairs of one camera; ValueError if it cannot be done."""
    if not (np.isfinite(square_m) and square_m > 0):
        raise ValueError(f"square size must be positive metres, got {square_m}")
    object_points, image_points, used, skipped = [], [], [], []
    size: tuple[int, int] | None = None
    for name, image in images:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise ValueError(f"{name}: image is {this[0]}x{this[1]}, the first one {size[0]}x{size[1]}")
        corners = find_board(gray, pattern)
        if corners is None:
            skipped.append(name)
            continue
        object_points.append(board_points(pattern, square_m))
        image_points.append(corners)
        used.append(name)
    if size is None:
        raise ValueError("no images")
    if len(used) < MIN_VIEWS:
        raise ValueError(f"found the {pattern[0]}x{pattern[1]} board in {len(used)} of {len(used) + len(skipped)} "
                         f"images; need at least {MIN_VIEWS}")
    rms, k, d, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, size, None, None,
                                                  flags=cv2.CALIB_FIX_K3)
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
