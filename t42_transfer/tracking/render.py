"""A simulated camera over the simulated hand: marker images, an offscreen renderer, the true answers.

:class:`HandCamera` builds the hand's scene with a :class:`~t42_transfer.hand.mjcf.MarkerScene` (ArUco marker
tiles made with ``cv2.aruco.generateImageMarker``, passed to MuJoCo as texture assets), copies a
:class:`~t42_transfer.hand.sim.SimulatedHand`'s configuration into it and renders the scene's camera offscreen.
It knows the truth a tracker is tested against: the intrinsics (from the camera's ``fovy`` and the image size),
the object's position and the camera's pose in ``t42_base`` (the hand's world frame).

The GL backend is ``MUJOCO_GL`` (``egl`` when unset; ``osmesa`` and ``glfw`` also work where installed), chosen
when the first camera is made, whatever MuJoCo was imported with.  Nothing here is imported unless a camera is
wanted, so rendering costs nothing when off.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import cv2
import mujoco
import numpy as np

from t42_transfer.conventions import MM_PER_M
from t42_transfer.hand.mjcf import (
    MARKER_MARGIN_FRACTION,
    MarkerScene,
    hand_mjcf,
    marker_texture_file,
    object_marker_height_mm,
)
from t42_transfer.hand.params import HandParams, variant
from t42_transfer.hand.sim import OBJECT_START_MM, SimulatedHand
from t42_transfer.tracking.markers import (
    DEFAULT_DICTIONARY,
    BaseMarker,
    Intrinsics,
    TrackerConfig,
    aruco_dictionary,
)

if TYPE_CHECKING:
    from t42_transfer.tracking.calibrate import Charuco

CAMERA_NAME = "tracker_camera"
MODULE_PX = 20
"""Texture pixels per marker module (cell)."""
MJ_TO_CV = np.diag([1.0, -1.0, -1.0])
"""MuJoCo camera axes (x right, y up, looking along -z) to OpenCV's (x right, y down, looking along +z)."""


def marker_tile_png(marker_id: int, dictionary: str = DEFAULT_DICTIONARY) -> bytes:
    """PNG bytes of marker ``marker_id`` with its white margin, as the scene's tiles show it."""
    d = aruco_dictionary(dictionary)
    side = (d.markerSize + 2) * MODULE_PX
    image = cv2.aruco.generateImageMarker(d, marker_id, side, borderBits=1)
    margin = int(round(side * MARKER_MARGIN_FRACTION))
    image = cv2.copyMakeBorder(image, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError(f"could not encode marker {marker_id}")
    return png.tobytes()


def _gl_context_class() -> type:
    backend = os.environ.get("MUJOCO_GL", "").strip().lower() or "egl"
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    elif backend in ("glfw", "glx"):
        from mujoco.glfw import GLContext
    else:
        raise ValueError(f"MUJOCO_GL={backend!r}: rendering needs egl, osmesa or glfw")
    return GLContext


def pinhole_intrinsics(width: int, height: int, fovy_deg: float) -> Intrinsics:
    """A MuJoCo camera's true intrinsics: square pixels, focal length from ``fovy``, centred, no distortion.

    OpenCV puts pixel centres on integer coordinates, so the image centre is ``((w - 1) / 2, (h - 1) / 2)``.
    """
    f = 0.5 * height / math.tan(math.radians(fovy_deg) / 2)
    k = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Intrinsics(width, height, k, np.zeros(5))


def add_noise(image: np.ndarray, noise_std: float, rng: np.random.Generator | None = None) -> np.ndarray:
    """``image`` with Gaussian pixel noise of ``noise_std`` grey levels (the image itself when 0)."""
    if noise_std <= 0:
        return image
    noisy = image + (rng or np.random.default_rng()).normal(0.0, noise_std, size=image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


class Offscreen:
    """Renders one named camera of a model into RGB arrays, in its own GL context."""

    def __init__(self, model: mujoco.MjModel, camera: str, width: int, height: int) -> None:
        self.width, self.height = width, height
        self._gl = _gl_context_class()(width, height)
        with self._gl.as_current():
            self._scene = mujoco.MjvScene(model, maxgeom=200)
            self._option = mujoco.MjvOption()
            self._camera = mujoco.MjvCamera()
            self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
            self._camera.fixedcamid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
            self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._model = model

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """The camera's view of ``data``.  The GL context is current only during the call, so any one thread at
        a time may render (a node's callbacks run on whichever executor thread is free)."""
        with self._gl.as_current():
            mujoco.mjv_updateScene(self._model, data, self._option, None, self._camera,
                                   mujoco.mjtCatBit.mjCAT_ALL, self._scene)
            mujoco.mjr_render(self._rect, self._scene, self._context)
            rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
            mujoco.mjr_readPixels(rgb, None, self._rect, self._context)
        return np.ascontiguousarray(rgb[::-1])  # OpenGL's rows run bottom-up

    def close(self) -> None:
        with self._gl.as_current():
            self._context.free()
        self._gl.free()


class HandCamera:
    """The scene camera of one hand's marker scene; one thread at a time may use it."""

    def __init__(self, params: HandParams | str = "source", scene: MarkerScene | None = None,
                 dictionary: str = DEFAULT_DICTIONARY) -> None:
        self.params = variant(params) if isinstance(params, str) else params
        self.scene = scene or MarkerScene()
        self.dictionary = dictionary
        cam = self.scene.camera
        if not (0 < cam.width <= 8192 and 0 < cam.height <= 8192):
            raise ValueError(f"camera resolution {cam.width}x{cam.height} is out of range")
        if not 1.0 <= cam.fovy_deg <= 170.0:
            raise ValueError(f"camera fovy {cam.fovy_deg} deg is out of range")
        markers = (self.scene.object_marker, *self.scene.base_markers)
        assets = {marker_texture_file(m.marker_id): marker_tile_png(m.marker_id, dictionary) for m in markers}
        self.model = mujoco.MjModel.from_xml_string(hand_mjcf(self.params, OBJECT_START_MM, self.scene), assets)
        self.data = mujoco.MjData(self.model)
        self._camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self._object_body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "object")
        self._screen: Offscreen | None = None
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ the truth
    @property
    def width(self) -> int:
        return self.scene.camera.width

    @property
    def height(self) -> int:
        return self.scene.camera.height

    def intrinsics(self) -> Intrinsics:
        """The camera's true intrinsics (:func:`pinhole_intrinsics`)."""
        return pinhole_intrinsics(self.width, self.height, self.scene.camera.fovy_deg)

    def base_from_camera(self) -> np.ndarray:
        """The camera's true pose in ``t42_base`` (4x4, OpenCV camera axes, metres)."""
        t = np.eye(4)
        t[:3, :3] = self.data.cam_xmat[self._camera_id].reshape(3, 3) @ MJ_TO_CV
        t[:3, 3] = self.data.cam_xpos[self._camera_id]
        return t

    def object_xy_mm(self) -> np.ndarray:
        """The object's true position in ``t42_base`` (mm) in the configuration last set."""
        return self.data.xpos[self._object_body][:2] * MM_PER_M

    def tracker_config(self, **overrides: Any) -> TrackerConfig:
        """The tracker configuration that matches this scene (marker ids, sizes and base marker poses)."""
        s = self.scene
        base = tuple(BaseMarker(m.marker_id, m.size_mm / MM_PER_M,
                                (m.x_mm / MM_PER_M, m.y_mm / MM_PER_M, m.z_mm / MM_PER_M))
                     for m in s.base_markers)
        settings: dict[str, Any] = dict(object_id=s.object_marker.marker_id,
                                        object_size_m=s.object_marker.size_mm / MM_PER_M,
                                        base_markers=base, dictionary=self.dictionary)
        settings.update(overrides)
        return TrackerConfig(**settings)

    def object_marker_height_m(self) -> float:
        return object_marker_height_mm(self.params) / MM_PER_M

    # ------------------------------------------------------------------ rendering
    def set_hand(self, hand: SimulatedHand) -> None:
        """Pose the scene as ``hand`` is now (joint positions; the scene's additions have no joints)."""
        snap = hand.snapshot()
        if snap.data.qpos.shape != self.data.qpos.shape:
            raise ValueError("the hand's model does not match this camera's scene")
        self.data.qpos[:] = snap.data.qpos
        mujoco.mj_forward(self.model, self.data)

    def set_object(self, xy_mm: np.ndarray | tuple[float, float], yaw: float = 0.0) -> None:
        """Place the object at ``xy_mm`` (``t42_base``), rotated by ``yaw``; the fingers stay where they are."""
        for joint, value in (("object_x", (xy_mm[0] - OBJECT_START_MM[0]) / MM_PER_M),
                             ("object_y", (xy_mm[1] - OBJECT_START_MM[1]) / MM_PER_M), ("object_yaw", yaw)):
            j = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, joint)
            self.data.qpos[self.model.jnt_qposadr[j]] = value
        mujoco.mj_forward(self.model, self.data)

    def render(self, noise_std: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """An RGB image (``rgb8``, height x width x 3) of the scene as last set; optional Gaussian pixel noise."""
        if self._screen is None:
            self._screen = Offscreen(self.model, CAMERA_NAME, self.width, self.height)
        return add_noise(self._screen.render(self.data), noise_std, rng)

    def close(self) -> None:
        """Free the GL resources (the camera can render again afterwards)."""
        if self._screen is not None:
            self._screen.close()
            self._screen = None

    def __enter__(self) -> HandCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- calibration boards
BOARD_SQUARE_PX = 40
"""Texture pixels per checkerboard square."""
CHARUCO_SQUARE_PX = 80
"""Texture pixels per ChArUco square (its markers' cells need more than a plain square)."""


def checkerboard_image(pattern: tuple[int, int]) -> np.ndarray:
    """A checkerboard with ``pattern`` inner corners (cols, rows) and a white margin of one square (grey)."""
    cols, rows = pattern
    squares = np.indices((rows + 1, cols + 1)).sum(axis=0) % 2
    board = np.where(squares == 0, 0, 255).astype(np.uint8)
    board = np.kron(board, np.ones((BOARD_SQUARE_PX, BOARD_SQUARE_PX), np.uint8))
    return cv2.copyMakeBorder(board, *(BOARD_SQUARE_PX,) * 4, cv2.BORDER_CONSTANT, value=255)


def charuco_image(board: Charuco) -> np.ndarray:
    """``board`` as ``cv2.aruco.CharucoBoard.generateImage`` draws it, with a white margin of one square (grey)."""
    cols, rows = board.squares
    size = ((cols + 2) * CHARUCO_SQUARE_PX, (rows + 2) * CHARUCO_SQUARE_PX)
    return board.board.generateImage(size, marginSize=CHARUCO_SQUARE_PX)


class BoardCamera:
    """A camera at the origin looking along -z at a printed calibration board it can place anywhere.

    The board is an image (grey, as printed: :func:`checkerboard_image`, :func:`charuco_image`) on a thin box,
    ``metres_per_px`` its scale; :meth:`checkerboard` and :meth:`charuco` make one for either kind.
    """

    def __init__(self, image: np.ndarray, metres_per_px: float, width: int = 640, height: int = 480,
                 fovy_deg: float = 50.0) -> None:
        if not (math.isfinite(metres_per_px) and metres_per_px > 0):
            raise ValueError(f"board scale must be positive metres per pixel, got {metres_per_px}")
        self.width, self.height, self.fovy_deg = width, height, fovy_deg
        half = (image.shape[1] * metres_per_px / 2, image.shape[0] * metres_per_px / 2)
        xml = f"""<mujoco model="board">
  <visual><global offwidth="{width}" offheight="{height}"/>
    <headlight ambient="0.6 0.6 0.6" diffuse="0.4 0.4 0.4" specular="0 0 0"/></visual>
  <asset><texture name="board" type="2d" file="board.png"/><material name="board" texture="board" specular="0"/>
  </asset>
  <worldbody>
    <camera name="camera" pos="0 0 0" fovy="{fovy_deg}"/>
    <body name="board" mocap="true">
      <geom type="box" size="{half[0]:.6f} {half[1]:.6f} 0.001" material="board" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>"""
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise ValueError("the board image could not be encoded")
        self.model = mujoco.MjModel.from_xml_string(xml, {"board.png": png.tobytes()})
        self.data = mujoco.MjData(self.model)
        self._screen = Offscreen(self.model, "camera", width, height)

    @classmethod
    def checkerboard(cls, pattern: tuple[int, int] = (9, 6), square_mm: float = 20.0, **camera: Any) -> BoardCamera:
        """A checkerboard of ``pattern`` inner corners, ``square_mm`` squares; ``camera``: width, height, fovy_deg."""
        return cls(checkerboard_image(pattern), square_mm / MM_PER_M / BOARD_SQUARE_PX, **camera)

    @classmethod
    def charuco(cls, board: Charuco, **camera: Any) -> BoardCamera:
        """The ChArUco ``board`` (its squares, sizes and dictionary); ``camera``: width, height, fovy_deg."""
        return cls(charuco_image(board), board.square_m / CHARUCO_SQUARE_PX, **camera)

    def intrinsics(self) -> Intrinsics:
        return pinhole_intrinsics(self.width, self.height, self.fovy_deg)

    def render_at(self, pos_m: Sequence[float], rotvec: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
        """RGB image of the board centred at ``pos_m`` (camera frame: it looks along -z), turned by ``rotvec``."""
        quat = np.zeros(4)
        mujoco.mju_axisAngle2Quat(quat, np.asarray(rotvec, float) / (np.linalg.norm(rotvec) or 1.0),
                                  float(np.linalg.norm(rotvec)))
        self.data.mocap_pos[0] = pos_m
        self.data.mocap_quat[0] = quat if np.linalg.norm(rotvec) else (1.0, 0.0, 0.0, 0.0)
        mujoco.mj_forward(self.model, self.data)
        return self._screen.render(self.data)

    def close(self) -> None:
        self._screen.close()

    def __enter__(self) -> BoardCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
