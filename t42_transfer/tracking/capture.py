"""Frames from an OpenCV capture (a device index, a device path or a video file), stamped at capture.

What the ``camera`` node wraps, without ROS: :class:`Capture` opens the source and checks what it delivers,
:func:`load_camera_info` reads the calibration (a ROS ``camera_info`` YAML, as ``t42 camera calibrate``
writes it).  Every problem is a :class:`CaptureError` (a ValueError) of one line naming the source.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from t42_transfer.tracking.markers import Intrinsics
from t42_transfer.yaml_files import read_yaml

MAX_SIDE = 8192
MAX_FPS = 1000.0


class CaptureError(ValueError):
    """The camera cannot be opened or read, or gives frames other than asked for."""


@dataclass(frozen=True)
class Frame:
    image: np.ndarray
    """``bgr8`` (height x width x 3 uint8) or ``mono8`` (height x width)."""
    stamp_ns: int
    """The clock's time when the frame was grabbed (before it was decoded)."""
    encoding: str


def parse_device(text: str | int) -> int | str:
    """A device index (``0``, ``"2"``) or a path (``/dev/video0``, a video file)."""
    if isinstance(text, int):
        if text < 0:
            raise CaptureError(f"camera index must be >= 0, got {text}")
        return text
    text = str(text).strip()
    if not text:
        raise CaptureError("no camera device given (an index such as 0, a /dev/video path or a video file)")
    return int(text) if text.isdigit() else text


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV's own warnings while probing a source (our error says it in one line)."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


class Capture:
    """One opened source; ``width``/``height``/``fps`` of 0 take what it gives, otherwise it must give that.

    ``size_from`` ends the error of a frame of another size: where the size came from (a calibration file's, say)."""

    def __init__(self, device: str | int, width: int = 0, height: int = 0, fps: float = 0.0,
                 clock: Callable[[], int] = time.time_ns, size_from: str = "asked for") -> None:
        self.device = parse_device(device)
        if not (0 <= width <= MAX_SIDE and 0 <= height <= MAX_SIDE):
            raise CaptureError(f"camera size {width}x{height} is out of range (0 = as the camera gives)")
        if not (np.isfinite(fps) and 0.0 <= fps <= MAX_FPS):
            raise CaptureError(f"camera fps {fps} is out of range (0 = as the camera gives)")
        if isinstance(self.device, str) and not self.device.startswith("/dev/") and not Path(self.device).is_file():
            raise CaptureError(f"camera {self.device!r}: no such device or video file")
        self.width, self.height, self.fps = width, height, fps
        self._clock, self._size_from = clock, size_from
        with _quiet_opencv():
            self._cap = cv2.VideoCapture(self.device)
            if not self._cap.isOpened():
                self._cap.release()
                raise CaptureError(f"camera {self.device!r}: cannot open it (no such device, busy, or not video)")
            if width:
                self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            if height:
                self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            if fps:
                self._cap.set(cv2.CAP_PROP_FPS, fps)
        self.frames = 0

    @property
    def is_file(self) -> bool:
        return isinstance(self.device, str) and not self.device.startswith("/dev/")

    def read(self) -> Frame:
        """The next frame; CaptureError when none comes (a file's end included) or it is not what was asked."""
        with _quiet_opencv():
            grabbed = self._cap.grab()
            stamp = self._clock()
            ok, image = self._cap.retrieve() if grabbed else (False, None)
        if not ok or image is None:
            end = "end of the video file" if self.is_file and self.frames else "the read failed"
            raise CaptureError(f"camera {self.device!r}: no frame after {self.frames} ({end})")
        encoding = "mono8" if image.ndim == 2 else "bgr8"
        if image.dtype != np.uint8 or (image.ndim == 3 and image.shape[2] != 3) or image.ndim not in (2, 3):
            raise CaptureError(f"camera {self.device!r}: frames of shape {image.shape} {image.dtype}; "
                               "expected 8-bit BGR or grey")
        h, w = image.shape[:2]
        if (self.width and w != self.width) or (self.height and h != self.height):
            raise CaptureError(f"camera {self.device!r} gives {w}x{h} frames, not the {self.width or w}x"
                               f"{self.height or h} {self._size_from}")
        self.frames += 1
        return Frame(image, int(stamp), encoding)

    def close(self) -> None:
        self._cap.release()

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def load_camera_info(path: str | Path) -> Intrinsics:
    """The intrinsics in a ROS ``camera_info`` YAML; ValueError naming the file when it is not one."""
    document = read_yaml(path, "camera_info")
    if not isinstance(document, dict):
        raise ValueError(f"{path}: not a camera_info YAML document (a mapping)")
    try:
        return Intrinsics.from_yaml_dict(document)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
