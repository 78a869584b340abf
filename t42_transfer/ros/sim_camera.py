"""A simulated hand's camera on the camera topics: rendered frames, their true intrinsics, the true pose.

The mock driver and the emulated hardware (``t42 hw emulate``) hold a simulated hand; with
``camera_rate_hz`` above 0 they also render it, as a camera over the real hand would see it (ArUco markers
on the object's top and on the base, :class:`~t42_transfer.tracking.render.HandCamera`), and publish

* ``camera/image_raw`` (sensor_msgs/Image, ``rgb8``) and ``camera/camera_info`` (the camera's true
  intrinsics, no distortion), for an ``object_tracker``;
* ``sim/object_pose`` (PoseStamped, metres in ``t42_base``): the true position in the frame, with the frame's
  stamp, so a check pairs each tracked pose with the truth by stamp.

The camera is off by default, and off it costs nothing: neither MuJoCo's renderer nor OpenCV is imported.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from msg_adapters import RCLPY, camera_info_msg, image_msg, names, object_pose_msg
from t42_transfer.hand.params import HandParams
from t42_transfer.ros.params import param
from t42_transfer.ros.qos import profile

if TYPE_CHECKING:
    from t42_transfer.hand.sim import SimulatedHand

MAX_CAMERA_RATE_HZ = 10.0
"""A frame per control step at most: the simulated hand does not move between steps."""


@dataclass(frozen=True)
class SimCameraParams:
    """The simulated camera's ROS parameters, shared by the nodes that hold a simulated hand."""

    camera_rate_hz: float = param(0.0, "rendered camera frames per second of (sim) time, at most one per "
                                       "step (0: no camera)", read_only=True, min=0.0, max=MAX_CAMERA_RATE_HZ)
    camera_width: int = param(640, "width of the rendered frames (px)", read_only=True, min=16, max=4096)
    camera_height: int = param(480, "height of the rendered frames (px)", read_only=True, min=16, max=4096)
    camera_noise: float = param(0.0, "Gaussian pixel noise of the rendered frames (grey levels)", read_only=True,
                                min=0.0, max=100.0)
    camera_frame_id: str = param("camera_optical", "frame id of the rendered frames: the camera's optical frame "
                                 "(REP 103's _optical suffix)",
                                 read_only=True)

    def check_camera(self) -> None:
        """ValueError naming the setting the camera cannot use."""
        if not (math.isfinite(self.camera_rate_hz) and 0.0 <= self.camera_rate_hz <= MAX_CAMERA_RATE_HZ):
            raise ValueError(f"camera_rate_hz must be in [0, {MAX_CAMERA_RATE_HZ}], got {self.camera_rate_hz}")
        if not (math.isfinite(self.camera_noise) and self.camera_noise >= 0):
            raise ValueError(f"camera_noise must be a finite number >= 0, got {self.camera_noise}")
        if not (16 <= self.camera_width <= 4096 and 16 <= self.camera_height <= 4096):
            raise ValueError(f"the camera's size must be 16 to 4096 px a side, got "
                             f"{self.camera_width}x{self.camera_height}")
        if not self.camera_frame_id.strip():
            raise ValueError("camera_frame_id must not be empty")


class SimCamera:
    """Renders a simulated hand at ``camera_rate_hz`` of its stamps and publishes what a camera would."""

    def __init__(self, node: Node, hand: HandParams, params: SimCameraParams) -> None:
        """ValueError naming the node when the renderer cannot start (no GL): a node fails at start, in one line."""
        from t42_transfer.hand.mjcf import MarkerScene, SceneCamera  # noqa: PLC0415  (costs nothing when off)
        from t42_transfer.tracking.render import HandCamera  # noqa: PLC0415

        self.params = params
        try:
            self.camera = HandCamera(hand, MarkerScene(camera=SceneCamera(width=params.camera_width,
                                                                          height=params.camera_height)))
            self.camera.render()
        except Exception as err:
            raise ValueError(f"{node.get_fully_qualified_name()}: the simulated camera cannot render "
                             f"({type(err).__name__}: {err}); check MUJOCO_GL") from None
        intrinsics = self.camera.intrinsics()
        self._k, self._d = intrinsics.k, intrinsics.d
        self._period_ns = round(1e9 / params.camera_rate_hz)
        self._last_ns: int | None = None
        self.frames = 0
        self._lock = threading.Lock()
        """Held while rendering or closing: a node may close from another thread than its timer's."""
        self._closed = False
        self._image = node.create_publisher(Image, names.CAMERA_IMAGE, profile(names.IMAGES))
        self._info = node.create_publisher(CameraInfo, names.CAMERA_INFO, profile(names.IMAGES))
        self._truth = node.create_publisher(PoseStamped, names.SIM_POSE, 10)

    def restart(self) -> None:
        """The next :meth:`capture` takes a frame whatever the rate (the object was just placed anew)."""
        self._last_ns = None

    def capture(self, hand: SimulatedHand, stamp_ns: int) -> bool:
        """Render ``hand`` as it is now and publish the frame stamped ``stamp_ns``, if one is due by then."""
        with self._lock:
            if self._closed or (self._last_ns is not None
                                and stamp_ns - self._last_ns < self._period_ns - self._period_ns // 4):
                return False
            self._last_ns = stamp_ns
            self.camera.set_hand(hand)
            image = self.camera.render(self.params.camera_noise)
            xy = self.camera.object_xy_mm().copy()
        frame_id, height, width = self.params.camera_frame_id, image.shape[0], image.shape[1]
        self._image.publish(image_msg(image, "rgb8", stamp_ns, frame_id, RCLPY))
        self._info.publish(camera_info_msg(width, height, self._k, self._d, stamp_ns, frame_id, kit=RCLPY))
        self._truth.publish(object_pose_msg(xy, stamp_ns, RCLPY))
        self.frames += 1
        return True

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self.camera.close()

