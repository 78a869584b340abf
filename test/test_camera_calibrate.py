"""``t42 camera calibrate`` on checkerboard and ChArUco images rendered by MuJoCo with known intrinsics (issue 21)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from t42_transfer.cli import main
from t42_transfer.tracking.calibrate import Charuco
from t42_transfer.tracking.markers import Intrinsics
from t42_transfer.tracking.render import BoardCamera
from t42_transfer.yaml_files import read_yaml

PATTERN = (9, 6)
CHARUCO = Charuco((7, 5), 0.03, 0.022, "DICT_4X4_50")
CHARUCO_ARGS = ["--board", "charuco", "--squares", "7x5", "--square", "0.03", "--marker", "0.022"]


@pytest.fixture(scope="module")
def board_views(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Intrinsics]:
    """14 views of a 9x6 board (20 mm squares) at 30-45 cm, tilted up to ~30 deg, and one view without it."""
    folder = tmp_path_factory.mktemp("views")
    camera = BoardCamera.checkerboard(PATTERN, 20.0, width=640, height=480, fovy_deg=50.0)
    rng = np.random.default_rng(0)
    try:
        for i in range(14):
            position = (rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), -rng.uniform(0.30, 0.45))
            rotation = np.append(rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3))
            cv2.imwrite(str(folder / f"view_{i:02d}.png"), camera.render_at(position, rotation)[:, :, ::-1])
        cv2.imwrite(str(folder / "view_99.png"), camera.render_at((0.0, 0.0, 5.0)))  # behind the camera
        (folder / "notes.txt").write_text("not an image")
        return folder, camera.intrinsics()
    finally:
        camera.close()


def test_calibrated_focal_lengths_and_principal_point_within_one_percent(board_views, tmp_path, capsys) -> None:
    folder, truth = board_views
    out = tmp_path / "camera_info.yaml"
    assert main(["camera", "calibrate", str(folder), str(out), "--pattern", "9x6", "--square", "0.02"]) == 0
    printed = capsys.readouterr().out
    assert "calibrated from 14 of 15 images (no board in: view_99.png)" in printed
    error = float(printed.split("reprojection error ")[1].split()[0])
    assert 0.0 < error < 0.5
    document = read_yaml(out, "camera_info")
    assert document["distortion_model"] == "plumb_bob" and document["camera_name"] == "camera"
    assert len(document["projection_matrix"]["data"]) == 12 and document["rectification_matrix"]["rows"] == 3
    found = Intrinsics.from_yaml_dict(document)
    assert (found.width, found.height) == (640, 480)
    for (row, col) in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert found.k[row, col] == pytest.approx(truth.k[row, col], rel=0.01), (row, col, found.k, truth.k)
    assert np.abs(found.d).max() < 0.05  # a pinhole renderer: next to no distortion


def test_views_that_all_face_the_camera_squarely_are_refused_not_fitted(tmp_path, capsys) -> None:
    """Such views fit a focal length many times the true one at a tiny error, and nothing looked wrong."""
    camera = BoardCamera.checkerboard(PATTERN, 20.0, width=640, height=480, fovy_deg=50.0)
    try:
        for i, (x, y) in enumerate([(-0.04, -0.03), (0.04, -0.03), (0.0, 0.0), (-0.04, 0.03), (0.04, 0.03)]):
            square_on = camera.render_at((x, y, -0.4), (0.0, 0.0, 0.1 * i))
            cv2.imwrite(str(tmp_path / f"flat_{i}.png"), square_on[:, :, ::-1])
    finally:
        camera.close()
    out = tmp_path / "camera_info.yaml"
    assert main(["camera", "calibrate", str(tmp_path), str(out), "--pattern", "9x6", "--square", "0.02"]) == 2
    assert "the board faces the camera squarely (tilted under 10 deg) in 5 of 5 views" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["{missing}", "{out}"], "does not exist"),
    (["{empty}", "{out}"], "no images"),
    (["{few}", "{out}"], "found the 9x6 board in 1 of 2 images; need at least 3"),
    (["{views}", "{existing}"], "exists already"),
    (["{views}", "{out}", "--pattern", "9by6"], "board pattern must be COLSxROWS"),
    (["{views}", "{out}", "--pattern", "1x6"], "need at least 2x2"),
    (["{views}", "{out}", "--pattern", "1000x1000"], "at most 10000 inner corners"),
    (["{bad}", "{out}"], "not an image OpenCV can read"),
    (["{mixed}", "{out}"], "is 320x240, the first one 640x480"),
])
def test_bad_calibration_input_is_one_line(board_views, tmp_path, capsys, argv, message) -> None:
    views = board_views[0]
    paths = {name: tmp_path / name for name in ("missing", "empty", "few", "bad", "mixed")}
    for name in ("empty", "few", "bad", "mixed"):
        paths[name].mkdir()
    for name in ("few", "mixed"):
        (paths[name] / "a.png").write_bytes((views / "view_00.png").read_bytes())
    (paths["few"] / "b.png").write_bytes((views / "view_99.png").read_bytes())
    cv2.imwrite(str(paths["mixed"] / "b.png"), np.zeros((240, 320), np.uint8))
    (paths["bad"] / "a.png").write_bytes(b"not a png")
    (tmp_path / "existing.yaml").write_text("x: 1\n")
    fill = {**{k: str(v) for k, v in paths.items()}, "views": str(views), "out": str(tmp_path / "out.yaml"),
            "existing": str(tmp_path / "existing.yaml")}
    assert main(["camera", "calibrate", *(a.format(**fill) for a in argv)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("t42: error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out.yaml").exists()


# --------------------------------------------------------------------------- ChArUco boards
@pytest.fixture(scope="module")
def charuco_views(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Intrinsics]:
    """12 views of a 7x5 ChArUco board (30 mm squares, 22 mm DICT_4X4_50 markers) at 30-45 cm, tilted up to
    ~30 deg; one with part of the board out of the frame; one without it."""
    folder = tmp_path_factory.mktemp("charuco")
    rng = np.random.default_rng(0)
    with BoardCamera.charuco(CHARUCO, width=640, height=480, fovy_deg=50.0) as camera:
        for i in range(12):
            position = (rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), -rng.uniform(0.30, 0.45))
            rotation = np.append(rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3))
            cv2.imwrite(str(folder / f"view_{i:02d}.png"), camera.render_at(position, rotation)[:, :, ::-1])
        cv2.imwrite(str(folder / "view_50.png"), camera.render_at((0.12, 0.05, -0.3), (0.2, -0.3, 0.1))[:, :, ::-1])
        cv2.imwrite(str(folder / "view_99.png"), camera.render_at((0.0, 0.0, 5.0)))  # behind the camera
        return folder, camera.intrinsics()


def test_charuco_calibration_within_one_percent_partial_views_included(charuco_views, tmp_path, capsys) -> None:
    folder, truth = charuco_views
    partial = CHARUCO.find(cv2.imread(str(folder / "view_50.png"), cv2.IMREAD_GRAYSCALE))
    assert partial is not None and 6 <= len(partial[0]) < 24, "view_50 should show part of the board"
    out = tmp_path / "camera_info.yaml"
    assert main(["camera", "calibrate", str(folder), str(out), *CHARUCO_ARGS, "--dictionary", "DICT_4X4_50"]) == 0
    printed = capsys.readouterr().out
    assert "calibrated from 13 of 14 images (no board in: view_99.png)" in printed
    assert 0.0 < float(printed.split("reprojection error ")[1].split()[0]) < 0.5
    found = Intrinsics.from_yaml_dict(read_yaml(out, "camera_info"))
    assert (found.width, found.height) == (640, 480)
    for (row, col) in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert found.k[row, col] == pytest.approx(truth.k[row, col], rel=0.01), (row, col, found.k, truth.k)
    assert np.abs(found.d).max() < 0.05


@pytest.mark.parametrize("argv, message", [
    (["{blank}", "{out}", *CHARUCO_ARGS], "found the 7x5 ChArUco board (DICT_4X4_50) in 0 of 3 images; need at "
                                          "least 3 (is it the board's dictionary and number of squares?)"),
    (["{views}", "{out}", *CHARUCO_ARGS, "--dictionary", "DICT_5X5_50"],
     "found the 7x5 ChArUco board (DICT_5X5_50) in 0 of 14 images"),
    (["{few}", "{out}", *CHARUCO_ARGS], "found the 7x5 ChArUco board (DICT_4X4_50) in 2 of 3 images; need at least 3"),
    (["{views}", "{out}", *CHARUCO_ARGS, "--dictionary", "DICT_NOPE"], "unknown ArUco dictionary 'DICT_NOPE'"),
    (["{views}", "{out}", *CHARUCO_ARGS[:2], "--squares", "20x20", "--square", "0.03", "--marker", "0.022"],
     "a 20x20 ChArUco board has 200 markers; DICT_4X4_50 has only 50"),
    (["{views}", "{out}", *CHARUCO_ARGS[:2], "--squares", "2x5", "--marker", "0.01"], "need at least 3x3 squares"),
    (["{views}", "{out}", *CHARUCO_ARGS[:4], "--square", "0.03", "--marker", "0.03"],
     "marker side 0.03 m must be smaller than the square's 0.03 m"),
    (["{views}", "{out}", "--board", "charuco", "--squares", "7x5"], "--board charuco needs --squares"),
    (["{views}", "{out}", *CHARUCO_ARGS, "--pattern", "6x4"], "a ChArUco board takes --squares"),
    (["{views}", "{out}", "--squares", "7x5"], "--squares: for --board charuco"),
    (["{views}", "{out}", "--board", "aruco"], "argument --board: invalid choice: 'aruco'"),
])
def test_bad_charuco_input_is_one_line(charuco_views, tmp_path, capsys, argv, message) -> None:
    views = charuco_views[0]
    paths = {name: tmp_path / name for name in ("blank", "few")}
    for name in paths.values():
        name.mkdir()
    for i in range(3):
        cv2.imwrite(str(paths["blank"] / f"{i}.png"), np.full((480, 640), 200, np.uint8))
    for name in ("view_00.png", "view_50.png", "view_99.png"):
        (paths["few"] / name).write_bytes((views / name).read_bytes())
    fill = {**{k: str(v) for k, v in paths.items()}, "views": str(views), "out": str(tmp_path / "out.yaml")}
    try:
        code = main(["camera", "calibrate", *(a.format(**fill) for a in argv)])
    except SystemExit as stop:  # the parser's own checks (a choice) exit from argparse, on one line too
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("t42: error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out.yaml").exists()
