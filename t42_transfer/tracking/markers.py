"""The object's position in ``t42_base`` from one camera image with ArUco markers.

One marker sits on the object's top; one or more sit on the hand's base at known poses in ``t42_base``
and define that frame.  Each marker's pose in the camera comes from ``cv2.solvePnP`` (``SOLVEPNP_IPPE_SQUARE``)
with the camera's intrinsics (a ``CameraInfo``'s K and D); the base markers' corners together then give the
camera's pose in ``t42_base`` (refined over all of them), and the object marker's centre is carried into that
frame.  Positions are reported in mm like the rest of the package (``x`` across the palm, ``y`` away from it);
on the wire they are metres (:func:`msg_adapters.hand.object_pose_msg`).

Quality measures per frame: the reprojection error (px, RMS over the corners used), the jump since the last
position (flagged above ``jump_mm``, the authors' 8 mm drop rule), and whether the object or base was seen.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from t42_transfer.conventions import DROP_JUMP_MM, MM_PER_M

DEFAULT_DICTIONARY = "DICT_4X4_50"
ENCODINGS = {"mono8": 1, "bgr8": 3, "rgb8": 3}
"""Image encodings the tracker reads (sensor_msgs/Image names) and their channel counts."""
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)
"""Distortion vectors OpenCV accepts (plumb_bob has 5, rational_polynomial 8)."""
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
"""The ROS distortion models OpenCV's pinhole model computes; ``equidistant`` (fisheye) is another model, whose
coefficients read as these would place every marker wrong."""
APRILTAG_CORNER_OFFSET_PX = 0.5
"""OpenCV's AprilTag corner refinement reports corners half a pixel right of and below where they are (pixel
centres on integer coordinates, OpenCV's convention): measured on images warped from known corners
(test_tracking checks it still holds); subtracted from every corner."""


# --------------------------------------------------------------------------- camera and image checks
@dataclass(frozen=True)
class Intrinsics:
    """A calibrated camera: image size, 3x3 camera matrix ``k`` and distortion ``d`` (OpenCV order)."""

    width: int
    height: int
    k: np.ndarray
    d: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        k = np.asarray(self.k, dtype=float)
        d = np.asarray(self.d, dtype=float).reshape(-1)
        if k.size != 9:
            raise ValueError(f"camera matrix K must have 9 values, got {k.size}")
        k = k.reshape(3, 3)
        if not (isinstance(self.width, (int, np.integer)) and isinstance(self.height, (int, np.integer))
                and self.width > 0 and self.height > 0):
            raise ValueError(f"camera image size must be positive integers, got {self.width!r} x {self.height!r}")
        if not np.all(np.isfinite(k)):
            raise ValueError(f"camera matrix K has non-finite values: {k.reshape(-1).tolist()}")
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        if fx <= 0 or fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={fx}, fy={fy} (an uncalibrated camera?)")
        if not (0 <= cx <= self.width and 0 <= cy <= self.height):
            raise ValueError(f"principal point ({cx}, {cy}) lies outside the {self.width}x{self.height} image")
        if k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            raise ValueError(f"camera matrix K is not upper triangular with K[2,2] = 1: {k.reshape(-1).tolist()}")
        if d.size not in DISTORTION_LENGTHS:
            raise ValueError(f"distortion must have one of {DISTORTION_LENGTHS} values, got {d.size}")
        if not np.all(np.isfinite(d)):
            raise ValueError(f"distortion has non-finite values: {d.tolist()}")
        if self.distortion_model not in DISTORTION_MODELS and (self.distortion_model or np.any(d)):
            raise ValueError(f"distortion model {self.distortion_model!r} is not one of {list(DISTORTION_MODELS)} "
                             "(OpenCV's pinhole model; a fisheye calibration needs another)")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "d", d)
        object.__setattr__(self, "distortion_model", self.distortion_model or "plumb_bob")  # ("": no distortion)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_camera_info(cls, msg: Any) -> Intrinsics:
        """From a ``sensor_msgs/CameraInfo`` (or anything with ``width, height, k, d``); ValueError if unusable."""
        try:
            width, height, k, d = msg.width, msg.height, msg.k, msg.d
        except AttributeError as err:
            raise ValueError(f"not a CameraInfo: {err}") from None
        try:
            return cls(int(width), int(height), np.asarray(k, dtype=float), np.asarray(d, dtype=float),
                       str(getattr(msg, "distortion_model", "plumb_bob")))
        except TypeError as err:
            raise ValueError(f"not a CameraInfo: {err}") from None

    @classmethod
    def from_yaml_dict(cls, data: Mapping[str, Any]) -> Intrinsics:
        """From a ROS ``camera_info`` YAML document (camera_calibration_parsers' layout)."""
        try:
            k = data["camera_matrix"]["data"]
            d = data.get("distortion_coefficients", {}).get("data", [])
            return cls(int(data["image_width"]), int(data["image_height"]), np.asarray(k, dtype=float),
                       np.asarray(d, dtype=float), str(data.get("distortion_model", "plumb_bob")))
        except (KeyError, TypeError, AttributeError) as err:
            raise ValueError(f"not a camera_info YAML document: missing or malformed {err}") from None


def gray_image(image: np.ndarray, encoding: str, intrinsics: Intrinsics | None = None) -> np.ndarray:
    """The 8-bit grey image of ``image`` (``encoding`` as sensor_msgs names it), checked against the camera."""
    if encoding not in ENCODINGS:
        raise ValueError(f"image encoding {encoding!r} is not one of {sorted(ENCODINGS)}")
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"image must be a uint8 array, got {type(image).__name__} "
                         f"{getattr(image, 'dtype', '')}".rstrip())
    channels = ENCODINGS[encoding]
    expected_ndim = 2 if channels == 1 else 3
    if image.ndim != expected_ndim or (channels > 1 and image.shape[2] != channels):
        raise ValueError(f"image of shape {image.shape} does not match encoding {encoding!r}")
    height, width = image.shape[:2]
    if intrinsics is not None and (width, height) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"image is {width}x{height} but the camera is calibrated for "
                         f"{intrinsics.width}x{intrinsics.height}")
    image = np.ascontiguousarray(image)  # a flipped or cropped view is fine too
    if channels == 1:
        return image
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if encoding == "bgr8" else cv2.COLOR_RGB2GRAY)


def image_from_buffer(data: bytes | Sequence[int] | np.ndarray, width: int, height: int, encoding: str,
                      step: int) -> np.ndarray:
    """The array view of a ``sensor_msgs/Image``'s fields; ValueError when they do not describe an image."""
    if encoding not in ENCODINGS:
        raise ValueError(f"image encoding {encoding!r} is not one of {sorted(ENCODINGS)}")
    channels = ENCODINGS[encoding]
    if width <= 0 or height <= 0:
        raise ValueError(f"image size {width}x{height} is empty")
    if step < width * channels:
        raise ValueError(f"image step {step} is shorter than a row ({width} px x {channels} bytes)")
    buffer = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    if buffer.size != step * height:
        raise ValueError(f"image data has {buffer.size} bytes, expected step {step} x height {height}")
    rows = buffer.reshape(height, step)[:, : width * channels]
    return rows.reshape(height, width) if channels == 1 else rows.reshape(height, width, channels)


# --------------------------------------------------------------------------- poses
def _rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return t


def _inverse(t: np.ndarray) -> np.ndarray:
    return _rigid(t[:3, :3].T, -t[:3, :3].T @ t[:3, 3])


def marker_corners(size: float) -> np.ndarray:
    """A square marker's corners in its own frame (x right, y up, z out of the face), in detection order."""
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class BaseMarker:
    """A marker fixed to the hand's base: its id, side (m) and pose in ``t42_base``."""

    marker_id: int
    size_m: float
    position_m: tuple[float, float, float]
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    """Marker axes in ``t42_base`` (columns); identity: lying flat, facing +z, its x along the palm's x."""

    def transform(self) -> np.ndarray:
        return _rigid(np.asarray(self.rotation, dtype=float), np.asarray(self.position_m, dtype=float))

    def corners_in_base(self) -> np.ndarray:
        t = self.transform()
        return marker_corners(self.size_m) @ t[:3, :3].T + t[:3, 3]

    @functools.cached_property
    def base_corners(self) -> np.ndarray:
        """:meth:`corners_in_base` computed once (read-only): the tracker needs them every frame."""
        corners = self.corners_in_base()
        corners.setflags(write=False)
        return corners


@dataclass(frozen=True)
class TrackerConfig:
    """Which markers to look for; sizes in metres."""

    object_id: int
    object_size_m: float
    base_markers: tuple[BaseMarker, ...]
    dictionary: str = DEFAULT_DICTIONARY
    jump_mm: float = DROP_JUMP_MM
    keep_base: bool = True
    """Keep the last base pose for frames where no base marker is seen (a fixed camera)."""
    object_height_m: float | None = None
    """Height of the object marker's face above ``t42_base``'s z = 0, when known: the object moves in the hand's
    plane, so its marker's centre is where the ray through the marker's image centre meets z = height (no
    depth from the marker's apparent size).  None: the marker's own solvePnP position."""

    def __post_init__(self) -> None:
        if not self.base_markers:
            raise ValueError("at least one base marker is needed to define t42_base")
        ids = [self.object_id, *(m.marker_id for m in self.base_markers)]
        if len(set(ids)) != len(ids):
            raise ValueError(f"marker ids must differ, got object {self.object_id} and base "
                             f"{[m.marker_id for m in self.base_markers]}")
        sizes = [self.object_size_m, *(m.size_m for m in self.base_markers)]
        if not all(math.isfinite(s) and s > 0 for s in sizes):
            raise ValueError(f"marker sizes must be positive metres, got {sizes}")
        if self.object_height_m is not None and not math.isfinite(self.object_height_m):
            raise ValueError(f"object_height_m must be finite, got {self.object_height_m}")
        if not (math.isfinite(self.jump_mm) and self.jump_mm > 0):
            raise ValueError(f"jump_mm must be positive, got {self.jump_mm}")
        for m in self.base_markers:
            r = np.asarray(m.rotation, dtype=float)
            if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
                raise ValueError(f"base marker {m.marker_id}: rotation is not a rotation matrix")
            if len(m.position_m) != 3 or not all(math.isfinite(v) for v in m.position_m):
                raise ValueError(f"base marker {m.marker_id}: position must be 3 finite numbers")
        count = aruco_dictionary(self.dictionary).bytesList.shape[0]
        outside = [i for i in ids if not 0 <= i < count]
        if outside:  # never detected: the tracker would wait for it for ever
            raise ValueError(f"marker id(s) {outside} are not in {self.dictionary} (ids 0 to {count - 1})")


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix of fixed-axis roll, pitch, yaw (REP 103: about x, then y, then z)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def config_from_parameters(object_id: int, object_size_m: float, base_ids: Sequence[int],
                           base_sizes_m: Sequence[float], base_poses: Sequence[float],
                           dictionary: str = DEFAULT_DICTIONARY, jump_mm: float = DROP_JUMP_MM,
                           object_height_m: float = math.nan) -> TrackerConfig:
    """A :class:`TrackerConfig` from flat values, as a node declares them: ``base_poses`` holds
    ``x y z roll pitch yaw`` (m, rad; in ``t42_base``) per base marker; a NaN ``object_height_m`` means unknown.
    """
    ids, sizes, poses = list(base_ids), [float(v) for v in base_sizes_m], [float(v) for v in base_poses]
    if len(sizes) != len(ids) or len(poses) != 6 * len(ids):
        raise ValueError(f"{len(ids)} base marker ids need as many sizes (got {len(sizes)}) and 6 pose values "
                         f"each, x y z roll pitch yaw (got {len(poses)})")
    if not all(math.isfinite(v) for v in poses):
        raise ValueError(f"base marker poses must be finite, got {poses}")
    markers = tuple(
        BaseMarker(int(i), s, tuple(poses[6 * n: 6 * n + 3]),
                   tuple(map(tuple, rotation_from_rpy(*poses[6 * n + 3: 6 * n + 6]))))
        for n, (i, s) in enumerate(zip(ids, sizes, strict=True)))
    height = None if math.isnan(object_height_m) else float(object_height_m)
    return TrackerConfig(int(object_id), float(object_size_m), markers, dictionary, float(jump_mm),
                         object_height_m=height)


def aruco_dictionary(name: str = DEFAULT_DICTIONARY) -> Any:
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def make_detector(dictionary: str = DEFAULT_DICTIONARY) -> Any:
    """An ``ArucoDetector`` with AprilTag corner refinement (what the pose accuracy rests on).

    On rendered and warped test images its corners scatter about 0.1 px (once :data:`APRILTAG_CORNER_OFFSET_PX`
    is taken off), against 0.3-0.6 px for ``CORNER_REFINE_SUBPIX`` and ``CORNER_REFINE_CONTOUR``.
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    return cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)


def detect(detector: Any, gray: np.ndarray) -> dict[int, np.ndarray]:
    """Marker id -> its 4 image corners (px, float64) of every marker found; a repeated id is dropped."""
    corners, ids, _ = detector.detectMarkers(gray)
    if detector.getDetectorParameters().cornerRefinementMethod == cv2.aruco.CORNER_REFINE_APRILTAG:
        corners = [np.asarray(c, dtype=float) - APRILTAG_CORNER_OFFSET_PX for c in corners]
    found: dict[int, np.ndarray] = {}
    repeated: set[int] = set()
    for c, i in zip(corners, [] if ids is None else ids.reshape(-1), strict=True):
        key = int(i)
        if key in found:
            repeated.add(key)
        found[key] = np.asarray(c, dtype=float).reshape(4, 2)
    for key in repeated:
        del found[key]
    return found


def reprojection_error(points: np.ndarray, image_points: np.ndarray, camera_from: np.ndarray,
                       intrinsics: Intrinsics) -> float:
    """RMS distance (px) between ``image_points`` and ``points`` projected through pose ``camera_from``."""
    rvec, _ = cv2.Rodrigues(camera_from[:3, :3])
    projected, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, camera_from[:3, 3], intrinsics.k, intrinsics.d)
    return float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points.reshape(-1, 2)) ** 2, axis=1))))


def _ippe_pose(corners: np.ndarray, size: float, intrinsics: Intrinsics) -> np.ndarray:
    ok, rvec, tvec = cv2.solvePnP(marker_corners(size), corners.reshape(4, 1, 2), intrinsics.k, intrinsics.d,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        raise ValueError("solvePnP found no pose for the marker")
    return _rigid(cv2.Rodrigues(rvec)[0], tvec)


def marker_pose(corners: np.ndarray, size: float, intrinsics: Intrinsics) -> tuple[np.ndarray, float]:
    """(4x4 pose of the marker in the camera frame, reprojection error px) by IPPE for squares."""
    pose = _ippe_pose(corners, size, intrinsics)
    return pose, reprojection_error(marker_corners(size), corners, pose, intrinsics)


def base_pose(found: Mapping[int, np.ndarray], markers: Sequence[BaseMarker],
              intrinsics: Intrinsics) -> tuple[np.ndarray, float, tuple[int, ...]] | None:
    """(pose of ``t42_base`` in the camera frame, reprojection error px, ids used), or None if none is seen.

    Started from the IPPE pose of the largest base marker in view, refined (Levenberg-Marquardt) over the
    corners of all base markers in view.
    """
    seen = [m for m in markers if m.marker_id in found]
    if not seen:
        return None
    points = np.concatenate([m.base_corners for m in seen])
    pixels = np.concatenate([found[m.marker_id] for m in seen])

    def area(m: BaseMarker) -> float:
        return float(cv2.contourArea(found[m.marker_id].astype(np.float32)))

    first = max(seen, key=area)
    camera_from_marker = _ippe_pose(found[first.marker_id], first.size_m, intrinsics)  # its own error: not used
    camera_from_base = camera_from_marker @ _inverse(first.transform())
    if len(seen) > 1:
        rvec, _ = cv2.Rodrigues(camera_from_base[:3, :3])
        tvec = camera_from_base[:3, 3].reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(points.reshape(-1, 1, 3), pixels.reshape(-1, 1, 2), intrinsics.k,
                                          intrinsics.d, rvec, tvec)
        camera_from_base = _rigid(cv2.Rodrigues(rvec)[0], tvec)
    error = reprojection_error(points, pixels, camera_from_base, intrinsics)
    return camera_from_base, error, tuple(m.marker_id for m in seen)


def square_centre(corners: np.ndarray) -> np.ndarray:
    """Image of a square's centre: where its diagonals cross (a projection keeps that, not the corners' mean)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=float).reshape(4, 2).tolist()
    # homogeneous lines through corners 0-2 and 1-3 (p x q with z = 1), then their crossing, as np.cross would
    a = (y0 - y2, x2 - x0, x0 * y2 - y0 * x2)
    b = (y1 - y3, x3 - x1, x1 * y3 - y1 * x3)
    point = np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
    if abs(point[2]) < 1e-12:
        raise ValueError("degenerate marker corners")
    return point[:2] / point[2]


def ray_on_plane(pixel: np.ndarray, base_from_camera: np.ndarray, height: float, intrinsics: Intrinsics) -> np.ndarray:
    """The point of ``t42_base``'s plane z = ``height`` seen at ``pixel``; ValueError if the ray misses it."""
    normalized = cv2.undistortPoints(pixel.reshape(1, 1, 2), intrinsics.k, intrinsics.d).reshape(2)
    direction = base_from_camera[:3, :3] @ np.array([normalized[0], normalized[1], 1.0])
    origin = base_from_camera[:3, 3]
    if abs(direction[2]) < 1e-9:
        raise ValueError("the camera looks along the object's plane")
    s = (height - origin[2]) / direction[2]
    if s <= 0:
        raise ValueError("the object's plane is behind the camera")
    return origin + s * direction


# --------------------------------------------------------------------------- the tracker
@dataclass(frozen=True)
class Track:
    """What one frame said about the object."""

    xy_mm: np.ndarray | None
    """Object (x, y) in ``t42_base`` (mm), or None when the object marker or the base frame is missing."""
    position_m: np.ndarray | None
    """The object marker's centre in ``t42_base`` (m), z included."""
    reprojection_error_px: float
    """RMS reprojection error (px) of the object marker's corners (nan when not seen)."""
    base_error_px: float
    """RMS reprojection error (px) of the base markers' corners (nan when no base marker was seen this frame)."""
    jump_mm: float
    """Distance from the previous position (nan for the first one)."""
    jumped: bool
    """The jump is larger than the configured limit (the authors' drop rule)."""
    status: str
    """'ok', 'jump', 'no_object' or 'no_base'."""
    markers: tuple[int, ...]
    """Ids of all markers found in the frame."""
    base_from_camera: np.ndarray | None = None
    """The camera's pose in ``t42_base`` (4x4) used for this frame."""


class ObjectTracker:
    """Frame-by-frame object tracking; keeps the last position (jump check) and base pose (fixed camera)."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._detector = make_detector(config.dictionary)
        self._camera_from_base: np.ndarray | None = None
        self._last_xy: np.ndarray | None = None
        self.counts = {"frames": 0, "tracked": 0, "no_object": 0, "no_base": 0, "jumps": 0}

    def reset(self) -> None:
        """Forget the last position and base pose (the counts stay)."""
        self._camera_from_base = None
        self._last_xy = None

    def process(self, image: np.ndarray, encoding: str, intrinsics: Intrinsics) -> Track:
        """Track the object in one image; ValueError for an image the camera could not have produced."""
        gray = gray_image(image, encoding, intrinsics)
        self.counts["frames"] += 1
        found = detect(self._detector, gray)
        ids = tuple(sorted(found))
        try:
            base = base_pose(found, self.config.base_markers, intrinsics)
        except (cv2.error, ValueError):  # degenerate base markers (seen edge-on): as if not seen
            base = None
        base_error = math.nan
        if base is not None:
            camera_from_base, base_error, _ = base
            if self.config.keep_base:
                self._camera_from_base = camera_from_base
        elif self.config.keep_base and self._camera_from_base is not None:
            camera_from_base = self._camera_from_base
        else:
            camera_from_base = None
        try:
            return self._track(found, ids, camera_from_base, base_error, intrinsics)
        except (cv2.error, ValueError):  # a degenerate view of the object's marker (edge-on): not a pose
            self.counts["no_object"] += 1
            return Track(None, None, math.nan, base_error, math.nan, False, "no_object", ids)

    def _track(self, found: dict[int, np.ndarray], ids: tuple[int, ...], camera_from_base: np.ndarray | None,
               base_error: float, intrinsics: Intrinsics) -> Track:
        if self.config.object_id not in found:
            self.counts["no_object"] += 1
            return Track(None, None, math.nan, base_error, math.nan, False, "no_object", ids,
                         None if camera_from_base is None else _inverse(camera_from_base))
        camera_from_object, error = marker_pose(found[self.config.object_id], self.config.object_size_m, intrinsics)
        if camera_from_base is None:
            self.counts["no_base"] += 1
            return Track(None, None, error, base_error, math.nan, False, "no_base", ids)
        base_from_camera = _inverse(camera_from_base)
        if self.config.object_height_m is None:
            position = base_from_camera[:3, :3] @ camera_from_object[:3, 3] + base_from_camera[:3, 3]
        else:
            centre = square_centre(found[self.config.object_id])
            position = ray_on_plane(centre, base_from_camera, self.config.object_height_m, intrinsics)
        xy = position[:2] * MM_PER_M
        jump = math.nan if self._last_xy is None else float(np.linalg.norm(xy - self._last_xy))
        jumped = bool(jump > self.config.jump_mm)
        self._last_xy = xy
        self.counts["tracked"] += 1
        self.counts["jumps"] += jumped
        return Track(xy, position, error, base_error, jump, jumped, "jump" if jumped else "ok", ids, base_from_camera)
