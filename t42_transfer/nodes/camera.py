"""Camera node: frames from an OpenCV capture as ``camera/image_raw`` + ``camera/camera_info``.

Wiring (relative names):

* ``camera/image_raw`` (sensor_msgs/Image, ``bgr8`` or ``mono8`` as the source gives): every frame, stamped
  with the node's clock when the frame was grabbed (before decoding);
* ``camera/camera_info`` (sensor_msgs/CameraInfo): with every frame, same stamp and frame id; the calibration
  from ``calibration_file`` (a ROS camera_info YAML, as ``t42 camera calibrate`` writes it), or K all zero (ROS's
  "uncalibrated") without one;
* ``diagnostics``: frames published, failed reads, the measured rate.

The source (``device``) is a device index (``0``), a device path (``/dev/video0``) or a video file.  Frames are
read on a thread of their own (a device's read blocks until its next frame), paced at ``fps`` (0: the source's
own rate, 30 for a file that gives none).  With a calibration file the source must give frames of its size.

A lifecycle node, as hardware is in ROS 2: configure opens the source (and reads the calibration), activate starts
publishing, deactivate stops it with the source kept open, cleanup releases the source.  With ``autostart`` (the
default) the node configures and activates itself at start; without it a lifecycle manager or ``ros2 lifecycle
set /camera configure`` drives it, and a configure that fails leaves it unconfigured with the reason on /rosout
and diagnostics, to be tried again (a camera plugged in later).

Failures: with ``autostart``, a missing device, a file that is not video, a bad calibration file or a size that
disagrees with it stop the node at start with one line (``t42 node camera`` exits 2).  A failed read while
running is an error line (at most one a second, with a count) and an ERROR on diagnostics; the node retries.  At
a video file's end the node starts the file again (``loop``) or is finished (its process exits 0).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.lifecycle import State, TransitionCallbackReturn
from sensor_msgs.msg import CameraInfo, Image

from msg_adapters import RCLPY, camera_info_msg, diagnostic_array, image_msg, names
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import DestroyableLifecycleNode, destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.qos import profile
from t42_transfer.tracking.capture import MAX_FPS, MAX_SIDE, Capture, CaptureError, Frame, load_camera_info
from t42_transfer.tracking.markers import Intrinsics

STATUS_NAME = "t42_transfer: camera"
FILE_FPS = 30.0
"""The pace of a video file that states no rate, when ``fps`` is 0."""
RETRY_S = 0.5
"""Pause after a failed read before the next try."""


@dataclass(frozen=True)
class CameraParams:
    """The camera node's ROS parameters."""

    device: str = param("0", "the source: a device index (0), a device path (/dev/video0) or a video file",
                        configure=True)
    width: int = param(0, "frame width the source must give (px; 0: as it gives, or the calibration's)",
                       configure=True, min=0, max=MAX_SIDE)
    height: int = param(0, "frame height the source must give (px; 0: as it gives, or the calibration's)",
                        configure=True, min=0, max=MAX_SIDE)
    fps: float = param(0.0, "frames per second asked of the source and published at most (0: the source's own)",
                       configure=True, min=0.0, max=MAX_FPS)
    frame_id: str = param("camera_optical", "frame id of the images and camera infos: the camera's optical frame "
                          "(z forward, x right, y down; REP 103's _optical suffix)")
    calibration_file: Path | None = param(None, "ROS camera_info YAML of the camera (unset: uncalibrated, K = 0)",
                                          configure=True)
    loop: bool = param(False, "at a video file's end, start it again (else the node is finished)", read_only=True)
    autostart: bool = param(True, "configure and activate at start, a source that fails ending the node (false: "
                            "drive the lifecycle yourself: ros2 lifecycle set /camera configure)", read_only=True)

    def __post_init__(self) -> None:
        if not self.frame_id.strip() or self.frame_id.startswith("/"):  # tf2 refuses both
            raise ValueError(f"frame_id must be a tf2 frame name (not empty, no leading '/'), got {self.frame_id!r}")
        if not (math.isfinite(self.fps) and 0.0 <= self.fps <= MAX_FPS):
            raise ValueError(f"fps must be in [0, {MAX_FPS}], got {self.fps}")
        if not (0 <= self.width <= MAX_SIDE and 0 <= self.height <= MAX_SIDE):
            raise ValueError(f"width and height must be in [0, {MAX_SIDE}], got {self.width}x{self.height}")


def _file_period_s(path: str) -> float:
    """Seconds between a video file's frames, as the file states them (1 / :data:`FILE_FPS` if it does not)."""
    capture = cv2.VideoCapture(path)
    try:
        fps = float(capture.get(cv2.CAP_PROP_FPS))
    finally:
        capture.release()
    return 1.0 / (fps if math.isfinite(fps) and 0 < fps <= MAX_FPS else FILE_FPS)


def _size(p: CameraParams, calibration: Intrinsics | None) -> tuple[int, int]:
    """The frame size the source must give: the parameters', else the calibration's (0: any)."""
    if calibration is None:
        return p.width, p.height
    for asked, calibrated, what in ((p.width, calibration.width, "width"), (p.height, calibration.height, "height")):
        if asked and asked != calibrated:
            raise ValueError(f"{what} {asked} differs from the calibration's {calibrated} ({p.calibration_file})")
    return calibration.width, calibration.height


class Camera(DestroyableLifecycleNode):
    """An OpenCV capture on the camera topics, as a lifecycle node; see the module docstring."""

    params_class = CameraParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("camera", **node_kwargs)
        self._params = LiveParams(self, self.params_class)
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        self.calibration: Intrinsics | None = None
        self.width = self.height = 0
        self.capture: Capture | None = None
        self._first: Frame | None = None
        self.period_s = 0.0
        self.published = 0
        self.failed_reads = 0
        self.last_error = ""
        self._finished = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._image_pub = self.create_publisher(Image, names.CAMERA_IMAGE, profile(names.IMAGES))
        self._info_pub = self.create_publisher(CameraInfo, names.CAMERA_INFO, profile(names.IMAGES))
        self._diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self._timer = self.create_timer(1.0, self.publish_diagnostics)
        self._rate_from: tuple[float, int] = (time.monotonic(), 0)
        if self.params.autostart:  # a source that cannot be opened ends the process with one line (exit 2)
            if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                raise ValueError(f"{self.get_fully_qualified_name()}: {self.last_error}")
            self.trigger_activate()

    @property
    def params(self) -> CameraParams:
        return self._params.value

    @property
    def finished(self) -> bool:
        """True once a video file ended (without ``loop``): the runner then ends the process."""
        return self._finished.is_set()

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        """Open the source (and the calibration): a source that opens but gives no frame fails here."""
        p = self.params
        try:
            self.calibration = None if p.calibration_file is None else load_camera_info(p.calibration_file)
            self.width, self.height = _size(p, self.calibration)
            self.capture = self._open()
            self._first = self.capture.read()
        except ValueError as err:  # CaptureError included
            self.last_error = str(err)
            self.log.error(f"configure failed: {err}")
            self._release()
            return TransitionCallbackReturn.FAILURE
        self.period_s = 1.0 / p.fps if p.fps else _file_period_s(p.device) if self.capture.is_file else 0.0
        self.last_error, self._finished = "", threading.Event()
        rate = f"{1.0 / self.period_s:.1f} fps" if self.period_s else "the device's rate"
        height, width = self._first.image.shape[:2]
        self.log.info(f"opened {p.device!r}, {width}x{height} {self._first.encoding}, at {rate}"
                      + ("" if self.calibration else " (uncalibrated: no calibration_file)"))
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        """Frames go out from now on, read on a thread of their own."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)
        self._thread.start()
        self.log.info("active: publishing frames")
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        """No frame goes out; the source stays open (activate again resumes it)."""
        self._halt()
        self.log.info("inactive: no frames published; the source stays open")
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._release()
        self.log.info(f"unconfigured: {self.params.device!r} released")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self.close()
        self.log.info("finalized: the source released; the process runs until it is stopped (Ctrl-C)")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.close()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        """Stop reading and release the source, whatever the state (the owner destroys the node)."""
        self._halt()
        self._release()

    def _halt(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def _release(self) -> None:
        capture, self.capture, self._first = self.capture, None, None
        if capture is not None:
            capture.close()

    # ------------------------------------------------------------------ the capture thread
    def _open(self) -> Capture:
        p = self.params
        size_from = "asked for" if self.calibration is None else f"its calibration is for ({p.calibration_file})"
        return Capture(p.device, self.width, self.height, p.fps, clock=lambda: self.get_clock().now().nanoseconds,
                       size_from=size_from)

    def _run(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set():
            try:
                frame, self._first = self._first or self._source().read(), None
            except Exception as err:  # CaptureError, or OpenCV failing: reported, and the thread goes on
                if not self._after_failed_read(err):
                    return
                due = time.monotonic()
                continue
            try:
                self._publish(frame)
            except Exception as err:
                self.per_message.error(f"publishing a frame failed: {type(err).__name__}: {err}")
            due += self.period_s
            self._stop.wait(max(0.0, due - time.monotonic()))
            due = max(due, time.monotonic() - self.period_s)  # a slow source does not earn a burst later

    def _source(self) -> Capture:
        if self.capture is None:
            raise CaptureError("the source is closed")
        return self.capture

    def _after_failed_read(self, err: Exception) -> bool:
        """Handle a failed read; False when the thread should end (a video file's end without ``loop``)."""
        capture = self.capture
        if isinstance(err, CaptureError) and capture is not None and capture.is_file and capture.frames:
            if not self.params.loop:
                self.log.info(f"{err}; finished")
                self._finished.set()
                return False
            try:
                capture.close()
                self.capture = self._open()
                return True
            except CaptureError as reopen:
                err = reopen
        self.failed_reads += 1
        self.last_error = str(err)
        self.per_message.error(str(err))
        self._stop.wait(RETRY_S)
        return True

    def _publish(self, frame: Frame) -> None:
        p = self.params
        height, width = frame.image.shape[:2]
        self._image_pub.publish(image_msg(frame.image, frame.encoding, frame.stamp_ns, p.frame_id, RCLPY))
        if self.calibration is None:
            info = camera_info_msg(width, height, np.zeros(9), np.zeros(0), frame.stamp_ns, p.frame_id, kit=RCLPY)
        else:
            c = self.calibration
            info = camera_info_msg(c.width, c.height, c.k, c.d, frame.stamp_ns, p.frame_id, c.distortion_model,
                                   kit=RCLPY)
        self._info_pub.publish(info)
        self.published += 1

    # ------------------------------------------------------------------ reports
    def publish_diagnostics(self) -> None:
        now, published = time.monotonic(), self.published
        since, before = self._rate_from
        self._rate_from = (now, published)
        rate = (published - before) / (now - since) if now > since else 0.0
        failing = self.failed_reads and self.last_error
        level, message = ("ERROR", self.last_error) if failing and rate == 0 else ("OK", "capturing")
        if self.finished:
            level, message = "OK", "the video file ended"
        elif self.state != "active":  # (a configure that failed is an ERROR until one passes)
            level, message = ("ERROR", self.last_error) if self.last_error else ("OK", self.state)
        values = {"frames": published, "failed_reads": self.failed_reads, "fps": round(rate, 2),
                  "device": self.params.device, "calibrated": self.calibration is not None}
        self._diagnostics.publish(diagnostic_array(STATUS_NAME, level, message, values,
                                                   self.get_clock().now().nanoseconds, kit=RCLPY))
