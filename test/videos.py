"""Video files for the camera tests: what an OpenCV capture reads as it would a recorded camera."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """``frames`` (BGR, all one size) as an MJPG file at ``fps``; ``path``."""
    frames = list(frames)
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
    assert writer.isOpened(), f"OpenCV cannot write {path}"
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def grey_video(path: Path, count: int, fps: float, step: int) -> Path:
    """``count`` uniform 320x240 frames, frame ``i`` grey level ``step * i`` (so their order can be read back)."""
    return write_video(path, (np.full((240, 320, 3), step * i, np.uint8) for i in range(count)), fps)
