"""Object tracker: the object's position in ``t42_base`` from camera images with ArUco markers.

Wiring (relative names):

* ``camera/image_raw`` (sensor_msgs/Image, ``mono8``, ``bgr8`` or ``rgb8``) and ``camera/camera_info``
  (sensor_msgs/CameraInfo): subscribed;
* ``tracker/object_pose`` (geometry_msgs/PoseStamped): published for each frame in which the object marker and
  the base frame are seen; metres in ``t42_base``, stamped with the image's stamp (REP 103);
* ``diagnostics`` (diagnostic_msgs/DiagnosticArray): counts and the last frame's quality, every
  ``diagnostics_period_s``;
* ``hand/status`` (std_msgs/String): subscribed, for the driver's grasps (below).

The work per frame (:class:`~t42_transfer.tracking.markers.ObjectTracker`: ArUco detection, solvePnP) runs on
one worker thread (:class:`~t42_transfer.tracking.worker.LatestOnly`), never on the executor: the image
callback only checks the frame and hands it over.  A frame that arrives while another still waits for the
worker replaces it; the replaced one is dropped and counted, so under a flood the backlog stays one frame and
the poses are about the newest images.

Tracking quality: a frame without the object marker (or before any base marker was seen) publishes no pose and
is counted; a jump above ``max_jump_m`` (the authors' 8 mm drop rule) is published, counted and warned about;
the reprojection errors (object and base markers, px) are reported.  The jump is measured from the last tracked
frame, also across frames without the object: an object seen again more than ``max_jump_m`` from where it was
hidden is flagged (a drop while out of sight and a move look the same here), and the warning says for how many
frames and seconds it was out of sight; one seen again where it was hidden is not.  A re-grasp moves the object
on purpose: from a driver's ``grasping`` to the first tracked frame that arrived after its ``reset`` (or
``reset_failed``), a jump is the object placed anew, counted as ``placed`` and said at info level, not warned
about as a drop.

Bad input (an image of another encoding or size than the camera's, a CameraInfo with zero or NaN intrinsics,
images before any CameraInfo) is a warning (at most one a second per kind, with a count) and a count on
diagnostics, never a crash.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from msg_adapters import (
    RCLPY,
    camera_info_calibration,
    diagnostic_array,
    image_array,
    names,
    object_pose_msg,
    stamp_to_ns,
    status_event,
)
from t42_transfer.conventions import DROP_JUMP_MM, MM_PER_M
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams, param
from t42_transfer.ros.qos import profile
from t42_transfer.tracking import markers
from t42_transfer.tracking.worker import LatestOnly

STATUS_NAME = "t42_transfer: object_tracker"
COUNTS = ("images", "tracked", "no_object", "no_base", "jumps", "placed", "bad_images", "bad_camera_info",
          "no_camera_info", "failed")
"""What diagnostics count beside the frames dropped while the worker was busy (the worker counts those): frames
received, poses published, frames without the object marker or without any base pose yet, jumps above the
limit, jumps of an object placed anew (a re-grasp), images refused, CameraInfos refused, images before a usable
CameraInfo, frames the tracker failed on."""


@dataclass(frozen=True)
class ObjectTrackerParams:
    """The tracker's ROS parameters: which markers, where the base markers sit, the jump limit."""

    dictionary: str = param(markers.DEFAULT_DICTIONARY, "ArUco dictionary of the markers (cv2.aruco's name)",
                            read_only=True)
    object_id: int = param(0, "id of the marker on the object's top", read_only=True, min=0)
    object_size_m: float = param(0.02, "side of the object's marker (m, the black square)", read_only=True,
                                 min=0.0)
    base_ids: tuple[int, ...] = param((1, 2), "ids of the markers on the hand's base (they define t42_base)",
                                      read_only=True)
    base_sizes_m: tuple[float, ...] = param((0.03, 0.03), "side of each base marker (m), as many as base_ids",
                                            read_only=True)
    base_poses: tuple[float, ...] = param(
        (-0.06, -0.035, 0.02, 0.0, 0.0, 0.0, 0.06, -0.035, 0.02, 0.0, 0.0, 0.0),
        "each base marker's centre and orientation in t42_base: x y z (m) roll pitch yaw (rad), 6 values per "
        "marker (zero angles: lying flat, facing up, its x along the palm's)", read_only=True)
    object_marker_height_m: float | None = param(
        None, "height of the object marker's face above t42_base's z = 0 (m): the object moves in the hand's "
              "plane, so its position is where the camera ray meets that plane; unset: the marker's own depth",
        read_only=True)
    max_jump_m: float = param(DROP_JUMP_MM / MM_PER_M, "a move between two tracked frames larger than this is "
                                                        "flagged (m)", min=0.0, renamed_from="max_jump_mm")
    diagnostics_period_s: float = param(1.0, "diagnostics are published this often (s)", read_only=True,
                                        min=0.01, max=60.0)

    def __post_init__(self) -> None:
        self.tracker_config()  # ValueError with the reason for a layout the tracker cannot use
        if not (math.isfinite(self.diagnostics_period_s) and self.diagnostics_period_s > 0):
            raise ValueError(f"diagnostics_period_s must be positive, got {self.diagnostics_period_s}")

    def tracker_config(self) -> markers.TrackerConfig:
        height = math.nan if self.object_marker_height_m is None else self.object_marker_height_m
        return markers.config_from_parameters(self.object_id, self.object_size_m, self.base_ids, self.base_sizes_m,
                                              self.base_poses, self.dictionary, self.max_jump_m * MM_PER_M,
                                              height)


class _Frame(NamedTuple):
    image: np.ndarray
    encoding: str
    stamp_ns: int
    intrinsics: markers.Intrinsics
    grasps: int
    """Grasp events heard when the frame arrived."""
    grasping: bool
    """Whether it arrived during a grasp (between ``grasping`` and the grasp's end)."""


class ObjectTracker(Node):
    """Images in, the object's pose out; see the module docstring."""

    params_class = ObjectTrackerParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("object_tracker", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        p = self.params
        self.log = self.get_logger()
        self.per_message = ThrottledLog(self.log)
        self.tracker = markers.ObjectTracker(p.tracker_config())
        self._lock = threading.Lock()
        self.counts = dict.fromkeys(COUNTS, 0)
        self._last: dict[str, object] = {"status": "waiting", "reprojection_error_px": math.nan,
                                         "base_error_px": math.nan, "jump_mm": math.nan}
        self._intrinsics: markers.Intrinsics | None = None
        self._seen: tuple[int, int] | None = None
        """The stamp of the last tracked frame and the frames without the object since (the worker's)."""
        self._grasps, self._grasping = 0, False
        """Grasp events heard, and whether a grasp is under way (the executor's)."""
        self._tracked_grasps = 0
        """Grasp events heard when the last tracked frame arrived (the worker's)."""
        self._pose_pub = self.create_publisher(PoseStamped, names.TRACKER_POSE, 10)
        self._diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self.worker = LatestOnly(self._track, self._publish, self._failed, name="object_tracker")
        # A camera driver that publishes best effort (sensor data QoS) matches no reliable reader:
        # ``-p qos_overrides./camera/image_raw.subscription.reliability:=best_effort`` (and camera_info alike).
        overridable = QoSOverridingOptions.with_default_policies()
        # Created first: an executor takes ready subscriptions in the order they were made, so a grasp's status
        # that came with its first frame is heard before that frame is handed to the worker.
        self.create_subscription(String, names.HAND_STATUS, self._on_status, profile(names.EVENT_READER))
        self.create_subscription(CameraInfo, names.CAMERA_INFO, self._on_camera_info, profile(names.IMAGES),
                                 qos_overriding_options=overridable)
        self.create_subscription(Image, names.CAMERA_IMAGE, self._on_image, profile(names.IMAGES),
                                 qos_overriding_options=overridable)
        self._timer = self.create_timer(p.diagnostics_period_s, self.publish_diagnostics)

    @property
    def params(self) -> ObjectTrackerParams:
        return self._params.value

    def close(self) -> None:
        """Stop the worker after the frame in hand (the owner destroys the node)."""
        self.worker.close()

    # ------------------------------------------------------------------ callbacks (executor)
    def _on_params(self, old: ObjectTrackerParams, new: ObjectTrackerParams) -> None:
        if new.max_jump_m != old.max_jump_m:
            # the config is read once per frame by the worker; swapping the reference is atomic
            self.tracker.config = dataclasses.replace(self.tracker.config, jump_mm=new.max_jump_m * MM_PER_M)

    def _count(self, key: str) -> None:
        with self._lock:
            self.counts[key] += 1

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            calibration = camera_info_calibration(msg)
            intrinsics = markers.Intrinsics(calibration.width, calibration.height, calibration.k, calibration.d,
                                            calibration.distortion_model)
        except ValueError as err:
            self._intrinsics = None  # a camera that now says this is not calibrated any more
            self._count("bad_camera_info")
            self._set_last(status="bad_camera_info")
            self.per_message.warning(f"{names.CAMERA_INFO} refused: {err}")
            return
        self._intrinsics = intrinsics

    def _on_status(self, msg: String) -> None:
        event = status_event(msg.data)
        if event in names.GRASP_EVENTS:
            self._grasps += 1
            self._grasping = event == names.GRASPING

    def _on_image(self, msg: Image) -> None:
        self._count("images")
        intrinsics = self._intrinsics
        if intrinsics is None:
            self._count("no_camera_info")
            self._set_last(status="no_camera_info")
            self.per_message.warning(f"{names.CAMERA_IMAGE}: no usable {names.CAMERA_INFO} yet; frame not tracked")
            return
        try:
            if msg.encoding not in markers.ENCODINGS:  # before decoding: the decoder's own list is no answer here
                raise ValueError(f"image encoding {msg.encoding!r} is not one the tracker reads "
                                 f"({sorted(markers.ENCODINGS)})")
            image = image_array(msg)
            _check_image(image, intrinsics)
        except ValueError as err:
            self._count("bad_images")
            self._set_last(status="bad_image")
            self.per_message.warning(f"{names.CAMERA_IMAGE} refused: {err}")
            return
        self.worker.submit(_Frame(image, msg.encoding, stamp_to_ns(msg.header.stamp), intrinsics, self._grasps,
                                  self._grasping))

    # ------------------------------------------------------------------ the worker thread
    def _track(self, frame: _Frame) -> tuple[_Frame, markers.Track]:
        return frame, self.tracker.process(frame.image, frame.encoding, frame.intrinsics)

    def _publish(self, result: tuple[_Frame, markers.Track]) -> None:
        frame, track = result
        # a grasp began or ended since the last tracked frame, or while this one was tracked (its status may
        # have been heard after the frame: topics are not ordered against each other)
        placed = track.jumped and (frame.grasping or self._grasps != self._tracked_grasps)
        with self._lock:
            self.counts["tracked"] += track.xy_mm is not None
            self.counts["placed" if placed else "jumps"] += track.jumped
            if track.status in ("no_object", "no_base"):
                self.counts[track.status] += 1
            self._last.update(status="placed" if placed else track.status, base_error_px=track.base_error_px,
                              reprojection_error_px=track.reprojection_error_px, jump_mm=track.jump_mm)
        seen = self._seen
        if track.xy_mm is None:
            if seen is not None and track.status == "no_object":
                self._seen = (seen[0], seen[1] + 1)
            return
        self._seen, self._tracked_grasps = (frame.stamp_ns, 0), frame.grasps
        self._pose_pub.publish(object_pose_msg(track.xy_mm, frame.stamp_ns, RCLPY))
        if placed:
            self.per_message.info(f"the object was placed anew (a grasp): {track.jump_mm:.1f} mm from where it "
                                  "was last seen")
            return
        if not track.jumped:
            return
        limit = f"over {self.tracker.config.jump_mm} mm"
        if seen is not None and seen[1]:
            self.per_message.warning(
                f"the object moved {track.jump_mm:.1f} mm while out of sight ({seen[1]} frames without it, "
                f"{(frame.stamp_ns - seen[0]) / 1e9:.1f} s since it was last seen; {limit}: dropped while hidden?)")
        else:
            self.per_message.warning(f"the object moved {track.jump_mm:.1f} mm in one frame ({limit}: a drop or a "
                                     "misdetection?)")

    def _failed(self, frame: _Frame, err: BaseException) -> None:
        self._count("failed")
        self._set_last(status="failed")
        self.per_message.warning(f"tracking a frame failed: {type(err).__name__}: {err}")

    # ------------------------------------------------------------------ reports
    def _set_last(self, **values: object) -> None:
        with self._lock:
            self._last.update(values)

    def publish_diagnostics(self) -> None:
        with self._lock:
            values: dict[str, object] = {**self.counts, **self._last}
        values.update(dropped=self.worker.counts["dropped"])
        status = str(values["status"])
        level = "OK" if status in ("ok", "jump", "placed") else "WARN"
        message = {"ok": "tracking", "jump": "tracking (the last frame jumped)",
                   "placed": "tracking (the object was placed anew)"}.get(status, status.replace("_", " "))
        self._diagnostics.publish(diagnostic_array(STATUS_NAME, level, message, values,
                                                   self.get_clock().now().nanoseconds, kit=RCLPY))


def _check_image(image: np.ndarray, intrinsics: markers.Intrinsics) -> None:
    """ValueError for an image the calibrated camera cannot have taken."""
    height, width = image.shape[:2]
    if (width, height) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"image is {width}x{height} but the camera is calibrated for "
                         f"{intrinsics.width}x{intrinsics.height}")
