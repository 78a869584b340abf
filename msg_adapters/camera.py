"""Camera messages <-> numpy: ``sensor_msgs/Image`` and ``sensor_msgs/CameraInfo``.

An image is a ``height x width`` (one channel) or ``height x width x channels`` array of the encoding's depth
(sensor_msgs' encoding names: ``mono8``, ``bgr8``, ``rgb8``, ...).  :func:`image_array` reads a message into
such an array without copying its pixels (a view of the message's buffer, rows cut to ``width`` when ``step``
pads them) and refuses one whose fields do not describe an image.  A calibration is the image size, the 3x3
camera matrix K and the distortion vector D (OpenCV's order); :func:`camera_info_msg` fills P and R as a
monocular camera has them.  Builders make rosbags objects by default and rclpy's with ``kit=RCLPY``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from msg_adapters.hand import ns_to_stamp
from msg_adapters.kit import ROSBAGS, MessageKit, RosbagsKit

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

IMAGE_ENCODINGS: dict[str, tuple[int, type]] = {
    "mono8": (1, np.uint8),
    "bgr8": (3, np.uint8),
    "rgb8": (3, np.uint8),
    "bgra8": (4, np.uint8),
    "rgba8": (4, np.uint8),
    "mono16": (1, np.uint16),
}
"""The encodings read and written here: channels and the dtype of one channel."""
MAX_SIDE = 16384
"""Larger images are refused unread (no camera here gives them; a bad message could claim anything)."""
PLUMB_BOB, RATIONAL_POLYNOMIAL = "plumb_bob", "rational_polynomial"


def image_msg(image: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, kit: MessageKit = ROSBAGS) -> Any:
    """``sensor_msgs/Image`` of ``image`` (rows packed, ``step`` = width x pixel bytes, native byte order)."""
    channels, dtype = _encoding(encoding)
    array = np.asarray(image)
    expected = 2 if channels == 1 else 3
    if array.dtype != dtype or array.ndim != expected or (channels > 1 and array.shape[2] != channels):
        raise ValueError(f"an image of shape {array.shape} {array.dtype} is not {encoding!r}")
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array)
    return kit.make(IMAGE, header=_header(stamp_ns, frame_id, kit), height=height, width=width, encoding=encoding,
                    is_bigendian=int(sys.byteorder == "big"), step=width * channels * data.itemsize,
                    data=_bytes(data, kit))


def image_array(msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as an array view; ValueError when the fields describe no image."""
    channels, dtype = _encoding(msg.encoding)
    width, height, step = int(msg.width), int(msg.height), int(msg.step)
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise ValueError(f"image size {width}x{height} is empty or over {MAX_SIDE} px a side")
    pixel = channels * np.dtype(dtype).itemsize
    if step < width * pixel:
        raise ValueError(f"image step {step} is shorter than a row ({width} px x {pixel} bytes)")
    if np.dtype(dtype).itemsize > 1 and bool(msg.is_bigendian) != (sys.byteorder == "big"):
        raise ValueError(f"{msg.encoding} image of the other byte order (is_bigendian={msg.is_bigendian})")
    data = msg.data
    buffer = data.reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if buffer.size != step * height:
        raise ValueError(f"image data has {buffer.size} bytes, expected step {step} x height {height}")
    rows = buffer.reshape(height, step)[:, : width * pixel]
    if np.dtype(dtype).itemsize > 1:
        rows = np.ascontiguousarray(rows).view(dtype)
    return rows.reshape(height, width) if channels == 1 else rows.reshape(height, width, channels)


class Calibration(NamedTuple):
    """A camera's calibration as ``CameraInfo`` carries it (nothing checked: see the tracker's Intrinsics)."""

    width: int
    height: int
    k: np.ndarray
    """3x3 camera matrix."""
    d: np.ndarray
    """Distortion coefficients, OpenCV's order."""
    distortion_model: str


def camera_info_msg(width: int, height: int, k: np.ndarray | Sequence[float], d: np.ndarray | Sequence[float],
                    stamp_ns: int, frame_id: str, distortion_model: str | None = None,
                    kit: MessageKit = ROSBAGS) -> Any:
    """``sensor_msgs/CameraInfo`` of a monocular camera (R identity, P = [K | 0]).

    ``distortion_model`` None: ``rational_polynomial`` for 8 or more coefficients, else ``plumb_bob``.  An
    uncalibrated camera is K all zero, as ROS has it.
    """
    k = np.asarray(k, dtype=np.float64).reshape(-1)
    d = np.asarray(d, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise ValueError(f"camera matrix K must have 9 values, got {k.size}")
    if distortion_model is None:
        distortion_model = RATIONAL_POLYNOMIAL if d.size >= 8 else PLUMB_BOB
    p = np.zeros((3, 4))
    p[:, :3] = k.reshape(3, 3)
    return kit.make(
        CAMERA_INFO, header=_header(stamp_ns, frame_id, kit), height=int(height), width=int(width),
        distortion_model=distortion_model, d=kit.floats(d), k=k.copy(), r=np.eye(3).reshape(-1),
        p=p.reshape(-1), binning_x=0, binning_y=0,
        roi=kit.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                     do_rectify=False))


def camera_info_calibration(msg: Any) -> Calibration:
    """The calibration a ``CameraInfo`` carries; ValueError when its fields are not numbers of the right count."""
    try:
        k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
        d = np.asarray(msg.d, dtype=np.float64).reshape(-1)
        width, height = int(msg.width), int(msg.height)
    except (AttributeError, TypeError, ValueError) as err:
        raise ValueError(f"not a CameraInfo: {err}") from None
    if k.size != 9:
        raise ValueError(f"camera matrix K must have 9 values, got {k.size}")
    return Calibration(width, height, k.reshape(3, 3), d, str(msg.distortion_model))


def _encoding(encoding: str) -> tuple[int, type]:
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"image encoding {encoding!r} is not one of {sorted(IMAGE_ENCODINGS)}")
    return IMAGE_ENCODINGS[encoding]


def _header(stamp_ns: int, frame_id: str, kit: MessageKit) -> Any:
    return kit.make("std_msgs/msg/Header", stamp=ns_to_stamp(stamp_ns, kit), frame_id=frame_id)


def _bytes(data: np.ndarray, kit: MessageKit) -> Any:
    """A ``uint8[]`` field's value: a numpy array for rosbags, bytes for rclpy (copied once into its array)."""
    flat = data.reshape(-1).view(np.uint8)
    return flat.copy() if isinstance(kit, RosbagsKit) else flat.tobytes()
