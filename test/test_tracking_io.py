"""What the camera and tracker nodes will wrap, without ROS: captures, calibration files, the latest-only
worker and the tracker's flat parameters (issue 21)."""

from __future__ import annotations

import itertools
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from videos import grey_video

from t42_transfer.tracking import markers as mk
from t42_transfer.tracking.calibrate import write_camera_info
from t42_transfer.tracking.capture import Capture, CaptureError, load_camera_info, parse_device
from t42_transfer.tracking.render import HandCamera
from t42_transfer.tracking.worker import LatestOnly


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return grey_video(tmp_path_factory.mktemp("video") / "five.avi", count=5, fps=10, step=40)


def test_a_video_file_gives_stamped_bgr_frames_then_a_clear_end(video: Path) -> None:
    clock = itertools.count(1_000, 100)
    with Capture(str(video), clock=lambda: next(clock)) as capture:
        frames = [capture.read() for _ in range(5)]
        with pytest.raises(CaptureError, match=r"no frame after 5 \(end of the video file\)"):
            capture.read()
    assert [f.stamp_ns for f in frames] == [1_000, 1_100, 1_200, 1_300, 1_400]
    assert all(f.encoding == "bgr8" and f.image.shape == (240, 320, 3) for f in frames)
    assert abs(int(frames[3].image.mean()) - 120) <= 3  # the frames come in order


def test_a_source_of_the_wrong_size_is_refused_on_the_first_read(video: Path) -> None:
    with Capture(str(video), width=640, height=480) as capture, pytest.raises(CaptureError,
                                                                               match="gives 320x240 frames"):
        capture.read()


@pytest.mark.parametrize("device, message", [
    ("63", "cannot open it"),
    ("/dev/video63", "cannot open it"),
    ("/no/such/clip.avi", "no such device or video file"),
    ("", "no camera device given"),
    (-1, "index must be >= 0"),
])
def test_a_missing_device_is_one_clear_line(device, message, capfd) -> None:
    with pytest.raises(CaptureError, match=message) as info:
        Capture(device)
    assert "\n" not in str(info.value)
    assert "WARN" not in capfd.readouterr().err  # OpenCV's own probing chatter is kept quiet


def test_not_a_video_and_bad_settings(tmp_path: Path, video: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(CaptureError, match="cannot open it"):
        Capture(str(text))
    with pytest.raises(CaptureError, match="size"):
        Capture(str(video), width=-1)
    with pytest.raises(CaptureError, match="fps"):
        Capture(str(video), fps=math.nan)
    assert parse_device("2") == 2 and parse_device("/dev/video0") == "/dev/video0"


def test_calibration_files_round_trip_and_bad_ones_name_the_file(tmp_path: Path) -> None:
    truth = mk.Intrinsics(640, 480, np.array([[600.0, 0, 321.0], [0, 602.0, 238.0], [0, 0, 1]]),
                          np.array([0.1, -0.05, 0.001, 0.002, 0.0]))
    path = tmp_path / "camera_info.yaml"
    write_camera_info(path, truth, "wrist")
    back = load_camera_info(path)
    np.testing.assert_allclose(back.k, truth.k)
    np.testing.assert_allclose(back.d, truth.d)
    for text, message in (("[1, 2]", "a mapping"), ("image_width: 640\n", "missing or malformed"),
                          ("a: [", "not valid YAML")):
        path.write_text(text)
        with pytest.raises(ValueError, match=message) as info:
            load_camera_info(path)
        assert str(path) in str(info.value)
    uncalibrated = "image_width: 640\nimage_height: 480\ncamera_matrix: {data: [0, 0, 0, 0, 0, 0, 0, 0, 0]}\n"
    path.write_text(uncalibrated)
    with pytest.raises(ValueError, match="must be positive"):
        load_camera_info(path)
    with pytest.raises(ValueError, match="cannot read"):
        load_camera_info(tmp_path / "missing.yaml")


# --------------------------------------------------------------------------- the latest-only worker
def test_a_flood_keeps_one_frame_waiting_and_counts_the_dropped() -> None:
    seen: list[int] = []
    worker = LatestOnly(lambda i: (time.sleep(0.03), i)[1], done=seen.append)
    largest_backlog = 0
    try:
        for i in range(100):  # 100 frames at 100 per second against 30 ms of work each
            worker.submit(i)
            largest_backlog = max(largest_backlog, worker.backlog)
            time.sleep(0.01)
        assert worker.wait_idle(5.0)
    finally:
        worker.close()
    counts = worker.counts
    assert largest_backlog == 1 and seen[-1] == 99 and seen == sorted(seen)
    assert counts["submitted"] == 100 and counts["processed"] + counts["dropped"] == 100
    assert 10 <= counts["processed"] <= 60 and counts["dropped"] >= 40 and counts["failed"] == 0


def test_a_failing_item_or_callback_does_not_stop_the_worker() -> None:
    failures: list[str] = []

    def work(item: int) -> int:
        if item == 1:
            raise ValueError("bad frame")
        return item

    def done(result: int) -> None:
        if result == 2:
            raise RuntimeError("publisher gone")

    worker = LatestOnly(work, done=done, failed=lambda item, err: failures.append(f"{item}: {err}"))
    try:
        for i in range(4):
            worker.submit(i)
            assert worker.wait_idle(5.0)
    finally:
        worker.close()
    assert failures == ["1: bad frame", "2: publisher gone"]
    assert worker.counts == {"submitted": 4, "processed": 3, "dropped": 0, "failed": 2}
    with pytest.raises(RuntimeError, match="closed"):
        worker.submit(5)


def test_the_tracker_behind_a_latest_only_worker_under_a_flood() -> None:
    with HandCamera("source") as camera:
        camera.set_object((2.0, 86.0))
        image, intrinsics = camera.render(), camera.intrinsics()
        tracker = mk.ObjectTracker(camera.tracker_config(object_height_m=camera.object_marker_height_m()))
    tracks: list[mk.Track] = []
    worker = LatestOnly(lambda img: tracker.process(img, "rgb8", intrinsics), done=tracks.append)
    threads_before = threading.active_count()
    try:
        for _ in range(100):
            worker.submit(image)
            assert worker.backlog <= 1
        assert worker.wait_idle(30.0)
    finally:
        worker.close()
    assert worker.counts["processed"] == tracker.counts["frames"] == len(tracks)
    assert worker.counts["processed"] + worker.counts["dropped"] == 100 and worker.counts["dropped"] > 0
    assert all(np.linalg.norm(t.xy_mm - (2.0, 86.0)) < 1.0 for t in tracks)
    assert threading.active_count() <= threads_before - 1


# --------------------------------------------------------------------------- parameters
def test_flat_parameters_make_the_scene_config() -> None:
    with HandCamera("source") as camera:
        scene = camera.tracker_config(object_height_m=camera.object_marker_height_m())
    flat = mk.config_from_parameters(
        0, 0.02, [1, 2], [0.03, 0.03], [-0.06, -0.035, 0.02, 0, 0, 0, 0.06, -0.035, 0.02, 0, 0, 0],
        object_height_m=scene.object_height_m)
    assert flat == scene
    assert mk.config_from_parameters(0, 0.02, [1], [0.03], [0.0] * 6).object_height_m is None
    turned = mk.config_from_parameters(0, 0.02, [1], [0.03], [0, 0, 0, 0, 0, math.pi / 2]).base_markers[0]
    np.testing.assert_allclose(np.asarray(turned.rotation) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(mk.rotation_from_rpy(0.3, -0.2, 1.1) @ mk.rotation_from_rpy(0.3, -0.2, 1.1).T,
                               np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="6 pose values each"):
        mk.config_from_parameters(0, 0.02, [1, 2], [0.03, 0.03], [0.0] * 6)
    with pytest.raises(ValueError, match="as many sizes"):
        mk.config_from_parameters(0, 0.02, [1, 2], [0.03], [0.0] * 12)
    with pytest.raises(ValueError, match="finite"):
        mk.config_from_parameters(0, 0.02, [1], [0.03], [0, 0, math.inf, 0, 0, 0])
    with pytest.raises(ValueError, match="at least one base marker"):
        mk.config_from_parameters(0, 0.02, [], [], [])
