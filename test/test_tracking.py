"""The object tracker on images rendered from the simulated hand, whose true pose is known (issue 21).

Images come from :class:`t42_transfer.tracking.render.HandCamera` (MuJoCo offscreen, EGL); the tracker is
:class:`t42_transfer.tracking.markers.ObjectTracker` (cv2.aruco + solvePnP).  Nothing is mocked.
"""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace

import cv2
import mujoco
import numpy as np
import pytest
import yaml

from t42_transfer.hand import SimulatedHand
from t42_transfer.hand.mjcf import MarkerScene, SceneCamera, hand_mjcf
from t42_transfer.hand.params import variant
from t42_transfer.hand.sim import OBJECT_START_MM
from t42_transfer.tracking import markers as mk
from t42_transfer.tracking.markers import Intrinsics, ObjectTracker
from t42_transfer.tracking.render import HandCamera

NOISE_STD = 2.0
"""Grey levels of Gaussian pixel noise on every rendered frame (a real sensor is not clean)."""


@pytest.fixture(scope="module")
def camera():
    cam = HandCamera("source")
    yield cam
    cam.close()


def _tracker(cam: HandCamera, **overrides) -> ObjectTracker:
    return ObjectTracker(cam.tracker_config(object_height_m=cam.object_marker_height_m(), **overrides))


def _tracking_errors(cam: HandCamera, frames: int, tracker: ObjectTracker) -> np.ndarray:
    """Distance (mm) between tracked and true object position over ``frames`` frames of random-policy motion."""
    hand = SimulatedHand("source")
    hand.reset(seed=3)
    rng = np.random.default_rng(7)
    intrinsics = cam.intrinsics()
    errors, truths = [], []
    for i in range(frames):
        hand.step(rng.uniform(-1.0, 1.0, size=2))
        if hand.done:
            hand.reset(seed=100 + i)
        cam.set_hand(hand)
        track = tracker.process(cam.render(NOISE_STD, rng), "rgb8", intrinsics)
        truth = cam.object_xy_mm()
        np.testing.assert_allclose(truth, hand.object_xy, atol=1e-6)
        truths.append(truth)
        errors.append(math.inf if track.xy_mm is None else float(np.linalg.norm(track.xy_mm - truth)))
    travel = np.ptp(np.array(truths), axis=0)
    assert np.linalg.norm(travel) > 5.0, f"the object hardly moved ({travel} mm): not a tracking test"
    return np.array(errors)


def test_tracked_pose_within_a_millimetre_40_frames(camera: HandCamera) -> None:
    errors = _tracking_errors(camera, 40, _tracker(camera))
    assert np.median(errors) < 1.0 and errors.max() < 3.0, errors


@pytest.mark.slow
def test_tracked_pose_within_a_millimetre_200_frames(camera: HandCamera) -> None:
    errors = _tracking_errors(camera, 200, _tracker(camera))
    assert np.median(errors) < 1.0 and errors.max() < 3.0, (np.median(errors), errors.max())


@pytest.mark.slow
def test_marker_pnp_alone_is_within_a_millimetre_median(camera: HandCamera) -> None:
    """Without the object's plane (the marker's own solvePnP depth) the median holds; single frames reach ~5 mm
    (measured: median 0.62, max 4.8 mm), still short of the 8 mm drop rule."""
    errors = _tracking_errors(camera, 200, ObjectTracker(camera.tracker_config()))
    assert np.median(errors) < 1.0 and errors.max() < 8.0, (np.median(errors), errors.max())


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


@pytest.mark.parametrize("placement", [
    SceneCamera(),
    SceneCamera(pos_mm=(-150.0, 10.0, 260.0), target_mm=(10.0, 60.0, 0.0), fovy_deg=50.0),
])
def test_base_frame_recovered_with_an_off_axis_tilted_camera(placement: SceneCamera) -> None:
    with HandCamera("source", MarkerScene(camera=placement)) as cam:
        truth = cam.base_from_camera()
        optical_axis = truth[:3, 2]
        tilt = math.degrees(math.acos(-optical_axis[2]))
        assert tilt > 25.0, f"camera tilt {tilt:.1f} deg: not a tilted view"
        assert np.linalg.norm(truth[:2, 3]) > 0.1, "camera above the base origin: not off-axis"
        image = cam.render(NOISE_STD, np.random.default_rng(0))
        intrinsics = cam.intrinsics()
        # The renderer's intrinsics are true: the base markers' corners land where they project.
        found = mk.detect(mk.make_detector(), cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
        camera_from_base = np.linalg.inv(truth)
        for marker in cam.tracker_config().base_markers:
            rvec, _ = cv2.Rodrigues(camera_from_base[:3, :3])
            projected, _ = cv2.projectPoints(marker.corners_in_base(), rvec, camera_from_base[:3, 3],
                                             intrinsics.k, intrinsics.d)
            assert np.abs(projected.reshape(4, 2) - found[marker.marker_id]).max() < 0.5
        track = _tracker(cam).process(image, "rgb8", intrinsics)
        assert track.status == "ok" and track.base_error_px < 0.5
        assert np.linalg.norm(track.base_from_camera[:3, 3] - truth[:3, 3]) < 2e-3
        assert _rotation_deg(track.base_from_camera, truth) < 0.3
        # One base marker is enough for the frame, less precisely.
        first = cam.tracker_config().base_markers[:1]
        single = _tracker(cam, base_markers=first).process(image, "rgb8", intrinsics)
        assert np.linalg.norm(single.base_from_camera[:3, 3] - truth[:3, 3]) < 15e-3
        assert _rotation_deg(single.base_from_camera, truth) < 3.0


def test_a_frame_without_the_object_marker_gives_no_pose_and_tracking_resumes(camera: HandCamera) -> None:
    tracker = _tracker(camera)
    intrinsics = camera.intrinsics()
    camera.set_object((0.0, 85.0))
    seen = tracker.process(camera.render(), "rgb8", intrinsics)
    assert seen.status == "ok" and np.linalg.norm(seen.xy_mm - (0.0, 85.0)) < 1.0
    camera.set_object((600.0, 85.0))  # out of view
    for _ in range(3):
        missing = tracker.process(camera.render(), "rgb8", intrinsics)
        assert missing.xy_mm is None and missing.position_m is None and missing.status == "no_object"
        assert math.isnan(missing.reprojection_error_px)
    assert 0 not in missing.markers and {1, 2} <= set(missing.markers)
    blank = tracker.process(np.full((480, 640), 128, np.uint8), "mono8", intrinsics)
    assert blank.xy_mm is None and blank.markers == ()
    camera.set_object((3.0, 88.0))
    again = tracker.process(camera.render(), "rgb8", intrinsics)
    assert again.status == "ok" and np.linalg.norm(again.xy_mm - (3.0, 88.0)) < 1.0
    assert abs(again.jump_mm - math.hypot(3.0, 3.0)) < 1.0 and not again.jumped
    assert tracker.counts == {"frames": 6, "tracked": 2, "no_object": 4, "no_base": 0, "jumps": 0}


def test_a_jump_beyond_the_drop_rule_is_flagged(camera: HandCamera) -> None:
    tracker = _tracker(camera)
    assert tracker.config.jump_mm == 8.0
    intrinsics = camera.intrinsics()
    statuses = []
    for xy in ((0.0, 80.0), (5.0, 84.0), (5.0, 94.0), (4.0, 95.0)):  # steps of 6.4, 10 and 1.4 mm
        camera.set_object(xy, yaw=0.3 * xy[0])
        statuses.append(tracker.process(camera.render(), "rgb8", intrinsics))
    assert [t.status for t in statuses] == ["ok", "ok", "jump", "ok"]
    assert math.isnan(statuses[0].jump_mm) and abs(statuses[2].jump_mm - 10.0) < 1.0
    assert statuses[2].xy_mm is not None and tracker.counts["jumps"] == 1
    assert all(t.reprojection_error_px < 0.5 for t in statuses)


def test_the_base_pose_is_kept_while_the_base_markers_are_hidden(camera: HandCamera) -> None:
    tracker = _tracker(camera)
    intrinsics = camera.intrinsics()
    camera.set_object((0.0, 85.0))
    image = camera.render()
    tracker.process(image, "rgb8", intrinsics)
    hidden = image.copy()
    hidden[300:, :] = 90  # the base tiles are in the lower part of the default view
    track = tracker.process(hidden, "rgb8", intrinsics)
    assert {1, 2}.isdisjoint(track.markers) and track.status == "ok" and math.isnan(track.base_error_px)
    fresh = _tracker(camera, keep_base=False)
    assert fresh.process(hidden, "rgb8", intrinsics).status == "no_base"


def test_a_configurable_resolution_has_its_own_true_intrinsics() -> None:
    scene = MarkerScene(camera=SceneCamera(width=1280, height=720, fovy_deg=40.0))
    with HandCamera("source", scene) as cam:
        intrinsics = cam.intrinsics()
        assert (intrinsics.width, intrinsics.height) == (1280, 720)
        assert intrinsics.k[0, 0] == pytest.approx(360 / math.tan(math.radians(20.0)))
        assert tuple(intrinsics.k[:2, 2]) == (639.5, 359.5)
        cam.set_object((-4.0, 92.0))
        image = cam.render()
        assert image.shape == (720, 1280, 3) and image.dtype == np.uint8
        track = _tracker(cam).process(image[:, :, ::-1], "bgr8", intrinsics)  # a view, not a copy
        assert np.linalg.norm(track.xy_mm - (-4.0, 92.0)) < 0.5


# --------------------------------------------------------------------------- bad input
@pytest.fixture(scope="module")
def intrinsics(camera: HandCamera) -> Intrinsics:
    return camera.intrinsics()


@pytest.mark.parametrize("image, encoding, message", [
    (np.zeros((480, 640, 3), np.uint8), "bgra8", "encoding 'bgra8' is not one of"),
    (np.zeros((480, 640, 3), np.uint8), "16UC1", "encoding '16UC1'"),
    (np.zeros((480, 640), np.uint8), "rgb8", "does not match encoding 'rgb8'"),
    (np.zeros((480, 640, 4), np.uint8), "bgr8", "does not match encoding 'bgr8'"),
    (np.zeros((480, 640, 3), np.uint8), "mono8", "does not match encoding 'mono8'"),
    (np.zeros((480, 640), np.uint16), "mono8", "uint8 array"),
    (np.zeros((240, 320, 3), np.uint8), "rgb8", "image is 320x240 but the camera is calibrated for 640x480"),
    (np.zeros((640, 480), np.uint8), "mono8", "image is 480x640"),
    ([[0, 1], [2, 3]], "mono8", "uint8 array"),
])
def test_images_of_the_wrong_encoding_or_size_are_refused(camera, intrinsics, image, encoding, message) -> None:
    tracker = _tracker(camera)
    with pytest.raises(ValueError, match=message):
        tracker.process(image, encoding, intrinsics)
    assert tracker.counts["frames"] == 0


def _k(fx=500.0, fy=500.0, cx=319.5, cy=239.5) -> list[float]:
    return [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("k, d, message", [
    ([0.0] * 9, [0.0] * 5, "must be positive"),  # an uncalibrated CameraInfo is all zeros
    (_k(fx=0.0), [0.0] * 5, "focal lengths must be positive"),
    (_k(fy=-3.0), [0.0] * 5, "focal lengths must be positive"),
    (_k(fx=math.nan), [0.0] * 5, "non-finite"),
    (_k(cx=math.inf), [0.0] * 5, "non-finite"),
    (_k(cx=900.0), [0.0] * 5, "outside the 640x480 image"),
    (_k(), [0.0, math.nan, 0.0, 0.0, 0.0], "distortion has non-finite"),
    (_k(), [0.0] * 3, "distortion must have one of"),
    (_k()[:6], [0.0] * 5, "9 values"),
    ([500.0, 0, 319.5, 0, 500.0, 239.5, 0, 0, 2.0], [0.0] * 5, "upper triangular"),
])
def test_camera_infos_with_zero_or_nan_intrinsics_are_refused(k, d, message) -> None:
    class CameraInfo:  # the fields of sensor_msgs/CameraInfo the tracker reads
        width, height = 640, 480

    info = CameraInfo()
    info.k, info.d = k, d
    with pytest.raises(ValueError, match=message):
        Intrinsics.from_camera_info(info)


def test_intrinsics_from_messages_and_yaml(intrinsics: Intrinsics) -> None:
    with pytest.raises(ValueError, match="not a CameraInfo"):
        Intrinsics.from_camera_info(object())
    with pytest.raises(ValueError, match="not a CameraInfo"):
        Intrinsics.from_camera_info(type("Info", (), {"width": None, "height": 480, "k": _k(), "d": []})())
    with pytest.raises(ValueError, match="image size"):
        Intrinsics(0, 480, np.array(_k()))
    with pytest.raises(ValueError, match="not a camera_info YAML"):
        Intrinsics.from_yaml_dict({"image_width": 640})
    doc = {"image_width": 640, "image_height": 480, "camera_matrix": {"rows": 3, "cols": 3, "data": _k()},
           "distortion_model": "plumb_bob", "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.1] * 5}}
    parsed = Intrinsics.from_yaml_dict(doc)
    assert parsed.k[0, 0] == 500.0 and parsed.d.tolist() == [0.1] * 5


@pytest.mark.parametrize("model, d, refused", [
    ("equidistant", [0.1, 0.05, 0.01, 0.0], True),  # fisheye: its 4 numbers are no k1 k2 p1 p2
    ("", [0.1, 0.05, 0.01, 0.0], True),
    ("", [], False),  # what a camera without distortion may say
    ("rational_polynomial", [0.1] * 8, False),
    ("plumb_bob", [0.1] * 5, False),
])
def test_a_distortion_model_opencvs_pinhole_model_does_not_compute_is_refused(model: str, d: list, refused: bool,
                                                                              tmp_path) -> None:
    """Read as plumb_bob, a fisheye calibration moved a tracked pose by 2 mm without a word."""
    from t42_transfer.tracking.capture import load_camera_info

    info = type("Info", (), {"width": 640, "height": 480, "k": _k(), "d": d, "distortion_model": model})()
    doc = {"image_width": 640, "image_height": 480, "camera_matrix": {"rows": 3, "cols": 3, "data": _k()},
           "distortion_model": model, "distortion_coefficients": {"rows": 1, "cols": len(d), "data": d}}
    (tmp_path / "cam.yaml").write_text(yaml.safe_dump(doc))
    for read in (lambda: Intrinsics.from_camera_info(info), lambda: load_camera_info(tmp_path / "cam.yaml")):
        if refused:
            with pytest.raises(ValueError, match=f"distortion model {model!r} is not one of"):
                read()
        else:
            assert read().distortion_model == (model or "plumb_bob")


def test_image_buffers_are_checked() -> None:
    rows = np.arange(2 * 8, dtype=np.uint8).reshape(2, 8)  # 2 rows of 6 bytes plus 2 bytes of padding
    image = mk.image_from_buffer(rows.tobytes(), 2, 2, "rgb8", 8)
    assert image.shape == (2, 2, 3) and image[1, 1].tolist() == [11, 12, 13]
    for args, message in (((2, 2, "rgb8", 5), "shorter than a row"), ((2, 3, "rgb8", 8), "expected step 8"),
                          ((0, 2, "mono8", 8), "empty"), ((2, 2, "yuv422", 8), "encoding")):
        with pytest.raises(ValueError, match=message):
            mk.image_from_buffer(rows.tobytes(), *args)


@pytest.mark.parametrize("change, message", [
    (dict(object_id=1), "marker ids must differ"),
    (dict(object_size_m=0.0), "marker sizes must be positive"),
    (dict(object_size_m=math.nan), "marker sizes must be positive"),
    (dict(base_markers=()), "at least one base marker"),
    (dict(jump_mm=-1.0), "jump_mm must be positive"),
    (dict(dictionary="DICT_NOPE"), "unknown ArUco dictionary"),
    (dict(object_id=50), r"marker id\(s\) \[50\] are not in DICT_4X4_50 \(ids 0 to 49\)"),
    (dict(object_height_m=math.inf), "object_height_m must be finite"),
])
def test_bad_tracker_settings_are_refused(camera: HandCamera, change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        camera.tracker_config(**change)
    tilted = replace(camera.tracker_config().base_markers[0], rotation=((1, 0, 0), (0, 1, 0), (0, 0, -1)))
    with pytest.raises(ValueError, match="not a rotation"):
        camera.tracker_config(base_markers=(tilted,))


# --------------------------------------------------------------------------- OpenCV and the scene, checked
def test_apriltag_corner_offset_still_holds() -> None:
    """The half-pixel the detector takes off AprilTag-refined corners, measured on images warped from known
    corners (no MuJoCo): a different OpenCV that changed its convention fails here."""
    dictionary = mk.aruco_dictionary()
    side = 600
    marker = cv2.aruco.generateImageMarker(dictionary, 5, side, borderBits=1)
    edges = np.float32([[-0.5, -0.5], [side - 0.5, -0.5], [side - 0.5, side - 0.5], [-0.5, side - 0.5]])
    rng = np.random.default_rng(0)
    detector = mk.make_detector()
    offsets = []
    for _ in range(12):
        centre = np.array([320.0, 240.0]) + rng.uniform(-120, 120, 2)
        angle = rng.uniform(0, 2 * math.pi)
        rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * rng.uniform(15, 30)
        corners = (centre + square @ rotation.T + rng.normal(0, 1.5, (4, 2))).astype(np.float32)
        image = cv2.warpPerspective(marker, cv2.getPerspectiveTransform(edges, corners), (640, 480),
                                    flags=cv2.INTER_LINEAR, borderValue=255)
        found = mk.detect(detector, image)
        offsets.append(found[5] - corners)
    offsets = np.concatenate(offsets)
    assert np.abs(offsets.mean(axis=0)).max() < 0.1 and offsets.std(axis=0).max() < 0.2, offsets.mean(axis=0)


def test_the_marker_scene_leaves_the_physics_alone() -> None:
    params = variant("source")
    plain = mujoco.MjModel.from_xml_string(hand_mjcf(params, OBJECT_START_MM))
    with HandCamera(params) as cam:
        seen = cam.model
    assert seen.ncam == 1 and plain.ncam == 0 and seen.ngeom > plain.ngeom
    assert (seen.nq, seen.nv, seen.nu, seen.nbody) == (plain.nq, plain.nv, plain.nu, plain.nbody)
    np.testing.assert_array_equal(seen.body_mass, plain.body_mass)
    np.testing.assert_array_equal(seen.body_inertia, plain.body_inertia)
    datas = [mujoco.MjData(m) for m in (plain, seen)]
    for m, d in zip((plain, seen), datas, strict=True):
        d.ctrl[:] = -0.01
        d.qpos[0] = 0.002
        mujoco.mj_step(m, d, nstep=200)
    np.testing.assert_array_equal(datas[0].qpos, datas[1].qpos)


def test_rendering_off_costs_nothing() -> None:
    """The simulator alone imports neither OpenCV nor the renderer, and its model has no camera."""
    code = ("import sys; from t42_transfer.hand import SimulatedHand; SimulatedHand('source').reset(seed=0); "
            "print(sorted(m for m in sys.modules if m == 'cv2' or m.startswith('t42_transfer.tracking')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"
    text = hand_mjcf(variant("source"), OBJECT_START_MM)
    assert "<camera" not in text and "<texture" not in text and "marker" not in text
