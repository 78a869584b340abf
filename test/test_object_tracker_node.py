"""The object_tracker and camera nodes (issue 21): rendered frames of the simulated hand, whose true pose is
known, go in as Image + CameraInfo; the tracked pose comes out on tracker/object_pose.  Bad input and a flood
are counted on diagnostics and the node keeps answering.  The camera node reads a video file written here."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from ros_rig import Rosout, Tester, assert_one_line_errors
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from videos import grey_video, write_video

from msg_adapters import (
    RCLPY,
    camera_info_calibration,
    camera_info_msg,
    image_array,
    image_msg,
    names,
    object_xy_mm,
    stamp_to_ns,
    status_message,
    status_report,
)
from t42_transfer.nodes.camera import Camera
from t42_transfer.nodes.object_tracker import STATUS_NAME, ObjectTracker
from t42_transfer.ros.qos import profile
from t42_transfer.tracking.calibrate import write_camera_info
from t42_transfer.tracking.render import HandCamera

PLACES_MM = ((0.0, 85.0), (3.0, 88.0), (1.0, 83.5))
"""Known object positions (mm), each within the 8 mm jump limit of the one before."""
MOVED_MM = (7.0, 92.0)
"""Where the object is seen again after it moved out of sight: 9.9 mm from the first place, over the 8 mm limit."""


@pytest.fixture(scope="module")
def scene() -> dict:
    """Rendered frames at known object positions, the camera's true intrinsics and the marker height."""
    with HandCamera("source") as cam:
        frames = []
        for xy in PLACES_MM:
            cam.set_object(xy)
            frames.append((cam.render(), cam.object_xy_mm().copy()))
        cam.set_object(MOVED_MM)
        moved = (cam.render(), cam.object_xy_mm().copy())
        cam.set_object((600.0, 85.0))  # out of view: the base markers are seen, the object's is not
        hidden = cam.render()
        return {"frames": frames, "moved": moved, "hidden": hidden, "intrinsics": cam.intrinsics(),
                "height_m": cam.object_marker_height_m()}


class Rig:
    """The tracker node beside a tester that publishes camera messages and listens to poses and diagnostics."""

    def __init__(self, ros, scene: dict) -> None:
        self.ros, self.scene = ros, scene
        self.node = ros.add(ObjectTracker, {"object_marker_height_m": scene["height_m"], "diagnostics_period_s": 0.1})
        self.tester = Tester(ros)
        node = self.tester.tester
        self.images = node.create_publisher(Image, names.CAMERA_IMAGE, profile(names.IMAGES))
        self.infos = node.create_publisher(CameraInfo, names.CAMERA_INFO, profile(names.IMAGES))
        self.poses = self.tester.listen(PoseStamped, names.TRACKER_POSE)
        self.diagnostics = self.tester.listen(DiagnosticArray, names.DIAGNOSTICS)
        assert self.tester.wait_graph(subscribers={names.CAMERA_IMAGE: 1, names.CAMERA_INFO: 1},
                                      publishers={names.TRACKER_POSE: 1})

    def info(self, k: np.ndarray | None = None, stamp_ns: int = 1) -> None:
        intr = self.scene["intrinsics"]
        self.infos.publish(camera_info_msg(intr.width, intr.height, intr.k if k is None else k, intr.d, stamp_ns,
                                           "camera", kit=RCLPY))
        self.ros.spin_for(0.05)

    def image(self, image: np.ndarray, stamp_ns: int, encoding: str = "rgb8") -> None:
        self.images.publish(image_msg(image, encoding, stamp_ns, "camera", RCLPY))

    def report(self, after: int = 0) -> dict[str, str]:
        """The tracker's newest diagnostics values, once one has come after the first ``after`` ones."""
        assert self.ros.spin_until(lambda: len(self.diagnostics) > after, 5.0)
        return status_report(self.diagnostics[-1], STATUS_NAME).values

    def report_when(self, condition, timeout_s: float = 5.0) -> dict[str, str]:
        """Spin until the newest diagnostics satisfy ``condition(values)``; those values."""
        def holds() -> bool:
            return bool(self.diagnostics) and condition(status_report(self.diagnostics[-1], STATUS_NAME).values)
        assert self.ros.spin_until(holds, timeout_s), status_report(self.diagnostics[-1], STATUS_NAME)
        return status_report(self.diagnostics[-1], STATUS_NAME).values

    def track(self, image: np.ndarray, stamp_ns: int, encoding: str = "rgb8") -> PoseStamped:
        before = len(self.poses)
        self.info(stamp_ns=stamp_ns)
        self.image(image, stamp_ns, encoding)

        def answered() -> list[PoseStamped]:  # a pose of an earlier frame may still be on its way
            return [p for p in self.poses[before:] if stamp_to_ns(p.header.stamp) == stamp_ns]

        assert self.ros.spin_until(lambda: bool(answered()), 10.0), "no pose for a frame with the object"
        return answered()[0]


def test_rendered_frames_give_the_true_pose_with_the_images_stamp(ros, scene) -> None:
    rig = Rig(ros, scene)
    for i, (image, truth) in enumerate(scene["frames"]):
        stamp = 1_700_000_000_000_000_000 + i * 100_000_000
        pose = rig.track(image, stamp)
        assert pose.header.frame_id == "t42_base" and stamp_to_ns(pose.header.stamp) == stamp
        assert np.linalg.norm(object_xy_mm(pose) - truth) < 1.0, (object_xy_mm(pose), truth)
    values = rig.report_when(lambda v: int(v["tracked"]) == len(PLACES_MM))
    assert values["images"] == str(len(PLACES_MM)) and values["no_object"] == "0" and values["status"] == "ok"
    assert 0 < float(values["reprojection_error_px"]) < 1.0 and 0 < float(values["base_error_px"]) < 1.0
    assert math.isfinite(float(values["jump_mm"])) and values["jumps"] == "0"


def test_ros_qos_overrides_make_the_camera_readers_best_effort_and_nothing_else(ros, scene) -> None:
    """A camera driver publishing sensor data QoS (best effort) matches no reliable reader; ROS's QoS overrides
    make the tracker's readers best effort, which match it (and a reliable camera too).  The override stays
    with this node: rclpy writes it into the profile object it is given, which is therefore never shared."""
    overrides = {f"qos_overrides./{topic}.subscription.reliability": "best_effort"
                 for topic in (names.CAMERA_IMAGE, names.CAMERA_INFO)}
    tracker = ros.add(ObjectTracker, {"object_marker_height_m": scene["height_m"], **overrides})
    readers = {s.topic_name: s.qos_profile.reliability for s in tracker.subscriptions}
    assert readers["/" + names.CAMERA_IMAGE] == readers["/" + names.CAMERA_INFO] == ReliabilityPolicy.BEST_EFFORT
    assert profile(names.IMAGES).reliability == ReliabilityPolicy.RELIABLE  # what the camera publishes with


def test_bad_images_and_camera_infos_are_counted_and_the_node_goes_on(ros, scene) -> None:
    rig = Rig(ros, scene)
    image, truth = scene["frames"][0]
    rig.image(image, 10)  # before any CameraInfo
    rig.report_when(lambda v: v["no_camera_info"] == "1")
    rig.info(k=np.array([math.nan, 0, 320, 0, 500, 240, 0, 0, 1]))
    rig.image(image, 11)
    values = rig.report_when(lambda v: v["bad_camera_info"] == "1" and v["no_camera_info"] == "2")
    assert values["status"] == "no_camera_info"
    rig.info(k=np.zeros(9))  # ROS's "uncalibrated"
    rig.report_when(lambda v: v["bad_camera_info"] == "2")
    rig.info()
    bgra = np.dstack([image, np.full(image.shape[:2], 255, np.uint8)])
    log = Rosout(ros, "object_tracker")
    rig.image(bgra, 12, "bgra8")  # an encoding the tracker does not read
    ros.spin_for(0.05)  # camera topics keep 2 messages: one at a time
    yuv = image_msg(image, "rgb8", 12, "camera", RCLPY)
    yuv.encoding, yuv.step, yuv.data = "yuv422", 2 * yuv.width, bytes(2 * yuv.width * yuv.height)
    rig.images.publish(yuv)  # one no decoder here reads: the tracker's list is the one to name
    ros.spin_for(0.05)
    rig.image(image[:240, :320], 13)  # not the calibrated size
    ros.spin_for(0.05)
    bad = image_msg(image, "rgb8", 14, "camera", RCLPY)
    bad.step = 100  # fields that describe no image
    rig.images.publish(bad)
    values = rig.report_when(lambda v: v["bad_images"] == "4")
    said = [m.msg for m in log.lines if "encoding" in m.msg]
    assert said and all("is not one the tracker reads (['bgr8', 'mono8', 'rgb8'])" in m for m in said), said
    assert values["tracked"] == "0" and values["failed"] == "0" and values["status"] == "bad_image"
    pose = rig.track(image, 15)
    assert np.linalg.norm(object_xy_mm(pose) - truth) < 1.0
    assert rig.report_when(lambda v: v["tracked"] == "1")["status"] == "ok"


def test_a_frame_without_the_object_counts_and_a_jump_is_flagged(ros, scene) -> None:
    rig = Rig(ros, scene)
    (first, _), (_, _), (third, _) = scene["frames"]
    rig.track(first, 1)
    blank = first.copy()
    blank[:] = 128  # nothing to see
    rig.info(stamp_ns=2)
    rig.image(blank, 2)
    rig.report_when(lambda v: v["no_object"] == "1" and v["status"] == "no_object")
    assert rig.node.set_parameters([Parameter("max_jump_m", value=0.001)])[0].successful
    rig.track(third, 3)  # 1.8 mm from the first place
    values = rig.report_when(lambda v: v["jumps"] == "1")
    assert values["status"] == "jump" and float(values["jump_mm"]) > 1.0
    assert not rig.node.set_parameters([Parameter("object_id", value=5)])[0].successful  # read-only
    for bad in (-1.0, 0.0, math.nan):  # out of range, or refused by the settings' own check, with a reason
        result = rig.node.set_parameters([Parameter("max_jump_m", value=bad)])[0]
        assert not result.successful and result.reason, bad
    assert rig.node.get_parameter("max_jump_m").value == 0.001 and rig.node.tracker.config.jump_mm == 1.0


def test_a_flood_is_dropped_and_counted_and_the_node_keeps_answering(ros, scene) -> None:
    rig = Rig(ros, scene)
    image, truth = scene["frames"][1]
    rig.track(image, 1)
    rig.info()
    for tick in range(50):  # 100 images in 1 s, two at a time
        rig.image(image, 10 + 2 * tick)
        rig.image(image, 11 + 2 * tick)
        assert rig.node.worker.backlog <= 1
        ros.spin_for(0.02)
    values = rig.report_when(lambda v: int(v["tracked"]) + int(v["dropped"]) + 1 >= int(v["images"]) > 20)
    assert int(values["dropped"]) > 0 and values["failed"] == "0", values
    pose = rig.track(scene["frames"][2][0], 1_000)
    assert stamp_to_ns(pose.header.stamp) == 1_000
    assert np.linalg.norm(object_xy_mm(pose) - scene["frames"][2][1]) < 1.0


# --------------------------------------------------------------------------- occlusion
RATE_HZ = 10.0
PERIOD_NS = 100_000_000
OCCLUDED = 20
"""Frames without the object marker: 2 s at 10 Hz."""


class Stream:
    """Frames published at 10 Hz (stamps 100 ms apart) in phases; each phase ends when the tracker has handled
    every frame of it (tracked, counted without the object, or dropped while the worker was busy), as its
    diagnostics say, so that what happened is known per phase."""

    def __init__(self, rig: Rig) -> None:
        self.rig, self.sent, self.truths, self.hidden = rig, 0, {}, []
        rig.info()
        self.values = rig.report()

    def frames(self, image: np.ndarray, count: int, truth: np.ndarray | None = None) -> tuple[list[int], dict]:
        """Publish ``image`` ``count`` times; the stamps, and the diagnostics' counts this phase added."""
        before, stamps = self.values, []
        for _ in range(count):
            stamp = 1_700_000_000_000_000_000 + self.sent * PERIOD_NS
            self.rig.image(image, stamp)
            self.sent += 1
            stamps.append(stamp)
            if truth is None:
                self.hidden.append(stamp)
            else:
                self.truths[stamp] = truth
            self.rig.ros.spin_for(1.0 / RATE_HZ)

        def handled(v: dict[str, str]) -> bool:
            done = sum(int(v[key]) for key in ("tracked", "no_object", "no_base", "failed", "dropped"))
            return int(v["images"]) == self.sent == done

        self.values = self.rig.report_when(handled, 10.0)
        return stamps, {key: int(self.values[key]) - int(before[key]) for key in ("tracked", "no_object", "dropped",
                                                                                  "jumps", "failed")}

    def check_poses(self) -> list[PoseStamped]:
        """Every pose is of a frame with the object, where it was, with that frame's stamp; the poses."""
        poses = self.rig.poses
        for pose in poses:
            stamp = stamp_to_ns(pose.header.stamp)
            assert stamp not in self.hidden, f"a pose for a frame without the object marker: {stamp}"
            assert pose.header.frame_id == "t42_base"
            assert np.linalg.norm(object_xy_mm(pose) - self.truths[stamp]) < 1.0, (object_xy_mm(pose),
                                                                                 self.truths[stamp])
        return poses


def _occlusion(rig: Rig, stream: Stream, scene: dict, seen: np.ndarray) -> list[int]:
    """2 s without the object marker after 5 frames with it; the hidden frames' stamps."""
    stamps, added = stream.frames(seen, 5, scene["frames"][0][1])
    assert added["tracked"] + added["dropped"] == 5 and added["tracked"] >= 1, added
    hidden, added = stream.frames(scene["hidden"], OCCLUDED)
    # every hidden frame is counted on diagnostics, or was dropped unseen while the worker was busy
    assert added["no_object"] + added["dropped"] == OCCLUDED and added["no_object"] >= OCCLUDED // 2, added
    assert added["tracked"] == 0 and added["failed"] == 0, added
    report = status_report(rig.diagnostics[-1], STATUS_NAME)
    assert (report.level, report.values["status"]) == ("WARN", "no_object"), report
    assert math.isnan(float(report.values["reprojection_error_px"]))
    assert not [p for p in rig.poses if stamp_to_ns(p.header.stamp) > stamps[-1]], "poses while hidden"
    return hidden


def _resumed(rig: Rig, hidden: list[int], stamps: list[int]) -> PoseStamped:
    """The first pose after the occlusion, which is of the first or second frame after it."""
    after = [p for p in rig.poses if stamp_to_ns(p.header.stamp) > hidden[-1]]
    assert after and stamp_to_ns(after[0].header.stamp) in stamps[:2], ([stamp_to_ns(p.header.stamp) for p in after],
                                                                        stamps)
    return after[0]


def test_an_occluded_object_gives_no_pose_and_tracking_resumes_without_a_jump(ros, scene) -> None:
    """The object marker hidden for 2 s while the object stays put: no poses, the frames counted, then poses
    again from the first frame after, accurate, and no jump (nothing moved)."""
    rig = Rig(ros, scene)
    rosout = Rosout(ros, "object_tracker")
    stream = Stream(rig)
    image, truth = scene["frames"][0]
    hidden = _occlusion(rig, stream, scene, image)
    stamps, added = stream.frames(image, 5, truth)
    assert added["tracked"] + added["dropped"] == 5 and added["jumps"] == 0, added
    first = _resumed(rig, hidden, stamps)
    assert np.linalg.norm(object_xy_mm(first) - truth) < 1.0
    poses = stream.check_poses()
    assert len(poses) == int(stream.values["tracked"]) == stream.sent - OCCLUDED - int(stream.values["dropped"])
    values = stream.values
    assert values["status"] == "ok" and values["jumps"] == "0" and values["failed"] == "0", values
    assert float(values["jump_mm"]) < 1.0, values  # measured from the last position before the occlusion
    assert int(values["no_object"]) + int(values["dropped"]) >= OCCLUDED
    assert rosout.wait_warnings(1, 1.0) == []  # no jump warning, nor any other


def test_an_object_that_moved_while_out_of_sight_is_flagged_when_seen_again(ros, scene) -> None:
    """Seen again 9.9 mm from where it was hidden (over max_jump_m): a drop and a move while hidden look the
    same to the tracker, so the pose is published and flagged as a jump, once, the warning saying that the
    object was out of sight; the next frames at the new place are not jumps."""
    rig = Rig(ros, scene)
    rosout = Rosout(ros, "object_tracker")
    stream = Stream(rig)
    image, truth = scene["frames"][0]
    hidden = _occlusion(rig, stream, scene, image)
    moved, moved_truth = scene["moved"]
    assert np.linalg.norm(moved_truth - truth) > 8.0
    stamps, added = stream.frames(moved, 5, moved_truth)
    assert added["jumps"] == 1 and added["tracked"] + added["dropped"] == 5, added
    first = _resumed(rig, hidden, stamps)
    assert np.linalg.norm(object_xy_mm(first) - moved_truth) < 1.0
    stream.check_poses()
    assert stream.values["status"] == "ok" and float(stream.values["jump_mm"]) < 1.0, stream.values
    warnings = rosout.wait_warnings(1)
    gap_s = (stamp_to_ns(first.header.stamp) - (hidden[0] - PERIOD_NS)) / 1e9  # since the object was last seen
    assert len(warnings) == 1 and "out of sight" in warnings[0], warnings
    moved_mm = float(re.search(r"moved ([0-9.]+) mm", warnings[0]).group(1))
    assert abs(moved_mm - np.linalg.norm(moved_truth - truth)) < 1.0, warnings
    assert f"{stream.values['no_object']} frames without it, {gap_s:.1f} s since" in warnings[0], (gap_s, warnings)


def test_a_jump_across_a_grasp_is_the_object_placed_anew_and_not_warned_about(ros, scene) -> None:
    """From the driver's ``grasping`` to the first frame tracked after its ``reset``, a jump is a new placement:
    counted as ``placed``, said at info level; the next jump is a drop again, warned about."""
    rig = Rig(ros, scene)
    rosout = Rosout(ros, "object_tracker")
    statuses = rig.tester.tester.create_publisher(String, names.HAND_STATUS, profile(names.EVENTS))
    assert rig.tester.wait_graph(subscribers={names.HAND_STATUS: 1})
    (first, truth), moved = scene["frames"][0], scene["moved"][0]
    assert np.linalg.norm(scene["moved"][1] - truth) > 8.0

    def said(event: str) -> None:
        statuses.publish(String(data=status_message(event, "test")))
        ros.spin_for(0.2)

    rig.track(first, 1)
    said(names.GRASPING)
    rig.track(moved, 2)  # placed while the hand opens
    said(names.RESET)
    rig.track(first, 3)  # the first frame after the grasp closed: still the placement
    values = rig.report_when(lambda v: v["tracked"] == "3")
    assert (values["placed"], values["jumps"], values["status"]) == ("2", "0", "placed"), values
    assert rosout.wait_warnings(1, 1.0) == []
    assert [m.msg for m in rosout.lines if "placed anew" in m.msg]  # said, at info level
    rig.track(moved, 4)  # in the episode: a drop
    values = rig.report_when(lambda v: v["tracked"] == "4")
    assert (values["placed"], values["jumps"], values["status"]) == ("2", "1", "jump"), values
    warnings = rosout.wait_warnings(1)
    assert len(warnings) == 1 and "in one frame" in warnings[0], warnings
    # a simulated hand's re-grasp: its statuses and the new grasp's frame come at once, in any order; a grasp
    # that failed ends the placement as one that closed does
    rig.info(stamp_ns=5)
    statuses.publish(String(data=status_message(names.GRASPING, "test")))
    rig.image(first, 5)
    statuses.publish(String(data=status_message(names.RESET_FAILED, "test")))
    values = rig.report_when(lambda v: v["tracked"] == "5")
    assert (values["placed"], values["jumps"]) == ("3", "1"), values
    assert len(rosout.wait_warnings(2, 1.0)) == 1
    rig.track(moved, 6)  # the first frame after the grasp ended: still the placement
    rig.track(first, 7)  # in the episode: a jump
    values = rig.report_when(lambda v: v["tracked"] == "7")
    assert (values["placed"], values["jumps"]) == ("4", "2"), values


# --------------------------------------------------------------------------- the camera node
@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return grey_video(tmp_path_factory.mktemp("video") / "eight.avi", count=8, fps=20, step=30)


def test_the_camera_node_publishes_a_video_files_frames_with_stamps_and_calibration(ros, video, scene,
                                                                                   tmp_path) -> None:
    from t42_transfer.tracking.markers import Intrinsics

    calibration = Intrinsics(320, 240, np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]]),
                             np.array([0.1, -0.05, 0, 0, 0]))
    write_camera_info(tmp_path / "camera.yaml", calibration)
    tester = Tester(ros)
    images = tester.listen(Image, names.CAMERA_IMAGE)
    infos = tester.listen(CameraInfo, names.CAMERA_INFO)
    node = ros.add(Camera, {"device": str(video), "calibration_file": str(tmp_path / "camera.yaml"),
                            "frame_id": "cam_optical"})
    assert ros.spin_until(lambda: node.finished and len(images) == 8 and len(infos) == 8, 10.0), (
        len(images), len(infos))
    stamps = [stamp_to_ns(m.header.stamp) for m in images]
    assert stamps == sorted(stamps) and len(set(stamps)) == 8 and stamps[0] > 0
    assert stamps == [stamp_to_ns(m.header.stamp) for m in infos]
    assert all(m.header.frame_id == "cam_optical" and m.encoding == "bgr8" for m in images)
    assert abs(int(image_array(images[3]).mean()) - 90) <= 3
    # 20 fps as the file says: the 8 frames span about 0.35 s
    assert 0.25 < (stamps[-1] - stamps[0]) / 1e9 < 2.0, stamps
    got = camera_info_calibration(infos[0])
    assert (got.width, got.height, got.distortion_model) == (320, 240, "plumb_bob")
    np.testing.assert_allclose(got.k, calibration.k)
    np.testing.assert_allclose(got.d, calibration.d)


def test_bad_camera_and_tracker_settings_are_one_line_errors(ros_domain, video, tmp_path) -> None:
    from t42_transfer.tracking.markers import Intrinsics

    (tmp_path / "bad.yaml").write_text("image_width: 320\n")
    wider = tmp_path / "wider.yaml"  # a sound calibration of another camera size than the video's 320x240
    write_camera_info(wider, Intrinsics(640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5)))
    cases = (
        (["camera", "--ros-args", "-p", "device:=/nonexistent"], "no such device or video file"),
        (["camera", "--ros-args", "-p", f"device:={video}", "-p", "width:=640"], "gives 320x240 frames, not the "
                                                                                 "640x240 asked for"),
        (["camera", "--ros-args", "-p", f"device:={video}", "-p", f"calibration_file:={wider}"],
         f"gives 320x240 frames, not the 640x480 its calibration is for ({wider})"),
        (["camera", "--ros-args", "-p", f"device:={video}", "-p", f"calibration_file:={tmp_path / 'bad.yaml'}"],
         "bad.yaml"),
        (["camera", "--ros-args", "-p", f"device:={video}", "-p", "frame_id:=/cam"], "tf2 frame name"),
        (["object_tracker", "--ros-args", "-p", "base_ids:=[1]"], "as many sizes"),
        (["object_tracker", "--ros-args", "-p", "max_jump_mm:=8.0"], "'max_jump_mm' is now 'max_jump_m'"),
    )
    assert_one_line_errors(cases)


def test_the_camera_node_loops_a_video_file_when_asked(ros, video) -> None:
    tester = Tester(ros)
    images, infos = tester.listen(Image, names.CAMERA_IMAGE), tester.listen(CameraInfo, names.CAMERA_INFO)
    node = ros.add(Camera, {"device": str(video), "loop": True, "fps": 100.0})
    assert ros.spin_until(lambda: len(images) > 12 and infos, 10.0), len(images)
    assert not node.finished and node.failed_reads == 0
    calibration = camera_info_calibration(infos[0])
    assert (calibration.width, calibration.height) == (320, 240)
    assert not calibration.k.any()  # without a calibration file K is zero: ROS's "uncalibrated"


def test_the_camera_is_a_lifecycle_node_driven_through_its_services(ros, video, tmp_path) -> None:
    """``autostart: false``: nothing opens or goes out until configure and activate (as ``ros2 lifecycle set``
    asks them); deactivate stops the frames, activate resumes them, cleanup releases the source; a configure
    that fails leaves the node unconfigured, saying why, and may be tried again."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    from t42_transfer.nodes.camera import STATUS_NAME as CAMERA_STATUS

    tester = Tester(ros)
    log = Rosout(ros, "camera")
    images = tester.listen(Image, names.CAMERA_IMAGE)
    diagnostics = tester.listen(DiagnosticArray, names.DIAGNOSTICS)
    change = tester.tester.create_client(ChangeState, "camera/change_state")
    get = tester.tester.create_client(GetState, "camera/get_state")
    missing = tmp_path / "later.avi"
    node = ros.add(Camera, {"device": str(missing), "loop": True, "fps": 50.0, "autostart": False})

    def go(transition: int) -> bool:
        return ros.call(change, ChangeState.Request(transition=Transition(id=transition))).success

    def state() -> str:
        return ros.call(get, GetState.Request()).current_state.label

    def reports(level: str) -> list:
        found = []
        for array in diagnostics:
            try:
                found.append(status_report(array, CAMERA_STATUS))
            except KeyError:
                continue
        return [r for r in found if r.level == level]

    assert state() == "unconfigured" and node.capture is None
    assert not go(Transition.TRANSITION_CONFIGURE) and state() == "unconfigured"  # no such file yet
    assert ros.spin_until(lambda: any("no such device" in r.message for r in reports("ERROR")), 3.0)
    missing.write_bytes(video.read_bytes())  # the camera is plugged in
    assert go(Transition.TRANSITION_CONFIGURE) and state() == "inactive"
    ros.spin_for(0.3)
    assert images == []  # configured, not publishing
    assert go(Transition.TRANSITION_ACTIVATE)
    assert ros.spin_until(lambda: len(images) >= 5, 5.0)
    assert go(Transition.TRANSITION_DEACTIVATE) and state() == "inactive"
    ros.spin_for(0.2)  # what was in flight arrives
    stopped = len(images)
    ros.spin_for(0.5)
    assert len(images) == stopped and node.capture is not None  # no frames, the source kept open
    assert go(Transition.TRANSITION_ACTIVATE) and ros.spin_until(lambda: len(images) >= stopped + 5, 5.0)
    assert go(Transition.TRANSITION_DEACTIVATE) and go(Transition.TRANSITION_CLEANUP)
    assert state() == "unconfigured" and node.capture is None
    said = ("opened", "active: publishing", "inactive: no frames", "unconfigured: ")  # each transition on /rosout
    assert ros.spin_until(lambda: all(any(m.msg.startswith(w) for m in log.lines) for w in said), 5.0), \
        [m.msg for m in log.lines]


def test_camera_and_tracker_nodes_together_track_a_video_of_rendered_frames(ros, scene, tmp_path) -> None:
    """The whole path: a video file (MJPG) of rendered frames -> camera node -> object_tracker -> the true pose."""
    frames = scene["frames"] * 2
    path = write_video(tmp_path / "hand.avi", (cv2.cvtColor(image, cv2.COLOR_RGB2BGR) for image, _ in frames), 10)
    truths = [truth for _, truth in frames]
    write_camera_info(tmp_path / "camera.yaml", scene["intrinsics"])
    tester = Tester(ros)
    images = tester.listen(Image, names.CAMERA_IMAGE)
    poses = tester.listen(PoseStamped, names.TRACKER_POSE)
    tracker = ros.add(ObjectTracker, {"object_marker_height_m": scene["height_m"]})
    assert tester.wait_graph(subscribers={names.CAMERA_IMAGE: 2})
    camera = ros.add(Camera, {"device": str(path), "calibration_file": str(tmp_path / "camera.yaml")})
    assert ros.spin_until(lambda: camera.finished and len(images) == len(truths), 10.0)
    # Every frame is tracked, or counted where it was not: the first may beat its CameraInfo, and on a busy
    # machine (one executor thread for all three nodes here) a frame may wait while the tracker is busy.
    def accounted() -> bool:
        return len(poses) + tracker.worker.counts["dropped"] + tracker.counts["no_camera_info"] >= len(truths)

    assert ros.spin_until(accounted, 5.0), (len(poses), tracker.worker.counts, tracker.counts)
    assert len(poses) >= len(truths) // 2, len(poses)
    truth_at = {stamp_to_ns(m.header.stamp): t for m, t in zip(images, truths, strict=True)}
    for pose in poses:
        assert np.linalg.norm(object_xy_mm(pose) - truth_at[stamp_to_ns(pose.header.stamp)]) < 1.0
