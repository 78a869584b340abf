"""The camera and object tracker nodes as processes (``t42 node camera``, ``t42 node object_tracker``), used by a
plain rclpy script (test/tracker_user.py, importing nothing of the project): parameters listed, bad values refused
with a reason, good ones accepted, and the object's pose received from a looping video of rendered frames."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from ros_rig import REPO, start_node, stop, unbuffered_env
from videos import write_video

from t42_transfer.tracking.calibrate import write_camera_info
from t42_transfer.tracking.render import HandCamera

USER = Path(__file__).with_name("tracker_user.py")
PLACES_MM = ((0.0, 85.0), (3.0, 88.0), (1.0, 83.5))
POSES = 5


@pytest.fixture(scope="module")
def hand_video(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """An MJPG video (10 fps) of rendered frames at known object positions, the camera's true intrinsics as a
    calibration YAML, the object marker's height and the true positions (mm)."""
    root = tmp_path_factory.mktemp("hand_video")
    with HandCamera("source") as cam:
        frames, truths = [], []
        for xy in PLACES_MM:
            cam.set_object(xy)
            frames.append(cv2.cvtColor(cam.render(), cv2.COLOR_RGB2BGR))
            truths.append(cam.object_xy_mm().copy())
        write_camera_info(root / "camera.yaml", cam.intrinsics())
        height_m = cam.object_marker_height_m()
    return {"video": write_video(root / "hand.avi", frames, 10), "calibration": root / "camera.yaml",
            "height_m": height_m, "truths": truths}


def test_a_plain_rclpy_script_sets_parameters_and_receives_poses(ros_domain: int, hand_video: dict,
                                                                  tmp_path: Path) -> None:
    logs = {name: tmp_path / f"{name}.log" for name in ("camera", "object_tracker")}
    nodes = [
        start_node("camera", "-p", f"device:={hand_video['video']}", "-p", "loop:=true",
                   "-p", f"calibration_file:={hand_video['calibration']}", log=logs["camera"]),
        start_node("object_tracker", "-p", f"object_marker_height_m:={hand_video['height_m']!r}",
                   log=logs["object_tracker"]),
    ]
    try:
        user = subprocess.run([sys.executable, str(USER), str(POSES)], cwd=REPO, env=unbuffered_env(),
                              capture_output=True, text=True, timeout=120)
    finally:
        codes = stop(nodes)
    said = "\n".join(f"{name} said:\n{log.read_text()[-3000:]}" for name, log in logs.items())
    assert all(node.poll() is not None for node in nodes)  # no orphans
    if user.returncode != 0:  # pytest.fail prints all of it (an assertion's message is cut short)
        pytest.fail(f"the user script failed:\n{user.stdout}\n{user.stderr}\n{said}")
    seen = json.loads(user.stdout.strip().splitlines()[-1])

    camera, tracker = seen["parameters"]["/camera"], seen["parameters"]["/object_tracker"]
    assert {"device", "fps", "loop", "frame_id", "calibration_file", "width", "height"} <= set(camera), camera
    assert {"object_id", "max_jump_m", "object_marker_height_m", "base_ids", "dictionary"} <= set(tracker), tracker
    # the camera's topics, and the driver's events (a re-grasp's jump is no drop)
    assert {"/camera/image_raw", "/camera/camera_info", "/hand/status"} <= set(seen["tracker_subscribes"]), seen
    assert seen["camera_values"]["device"] == str(hand_video["video"]) and seen["camera_values"]["loop"] is True
    assert seen["camera_values"]["frame_id"] == "camera_optical"
    assert seen["tracker_values"] == {"object_id": 0, "max_jump_m": 0.008,
                                      "object_marker_height_m": hand_video["height_m"]}

    (jump_ok, jump_reason), (id_ok, id_reason) = seen["tracker_bad"]
    assert not jump_ok and "max_jump_m" in jump_reason, seen["tracker_bad"]
    assert not id_ok and "read-only" in id_reason, seen["tracker_bad"]
    assert seen["tracker_after_bad"] == {"max_jump_m": 0.008, "object_id": 0}
    assert seen["tracker_good"] == [True, ""] and seen["tracker_after_good"] == {"max_jump_m": 0.012}

    empty, slash, fps = seen["camera_bad"]
    assert not empty[0] and "frame_id" in empty[1] and not slash[0] and "frame_id" in slash[1], seen["camera_bad"]
    assert not fps[0] and "read at configure" in fps[1] and "it is active" in fps[1], seen["camera_bad"]
    assert seen["camera_after_bad"] == {"frame_id": "camera_optical", "fps": 0.0}
    assert seen["camera_good"] == [True, ""] and seen["camera_after_good"] == {"frame_id": "hand_camera_optical"}

    poses = seen["poses"]
    assert len(poses) >= POSES
    for pose in poses:  # metres in t42_base, where the object is in one of the video's frames (MJPG: within 1 mm)
        assert pose["frame_id"] == "t42_base" and pose["xyz_m"][2] == 0.0, pose
        xy_mm = np.array(pose["xyz_m"][:2]) * 1000.0
        assert min(np.linalg.norm(xy_mm - truth) for truth in hand_video["truths"]) < 1.0, pose
        assert pose["stamp_ns"] in seen["camera_info_stamps_ns"], pose  # the stamp of the image it came from
    assert codes == [0, 0], said
