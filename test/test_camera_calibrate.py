"""``t42 camera calibrate`` on checkerboard images rendered by MuJoCo with known intrinsics (issue 21)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from t42_transfer.cli import main
from t42_transfer.tracking.markers import Intrinsics
from t42_transfer.tracking.render import BoardCamera
from t42_transfer.yaml_files import read_yaml

PATTERN = (9, 6)


@pytest.fixture(scope="module")
def board_views(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Intrinsics]:
    """14 views of a 9x6 board (20 mm squares) at 30-45 cm, tilted up to ~30 deg, and one view without it."""
    folder = tmp_path_factory.mktemp("views")
    camera = BoardCamera(PATTERN, 20.0, 640, 480, fovy_deg=50.0)
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


@pytest.mark.parametrize("argv, message", [
    (["{missing}", "{out}"], "does not exist"),
    (["{empty}", "{out}"], "no images"),
    (["{few}", "{out}"], "found the 9x6 board in 1 of 2 images; need at least 3"),
    (["{views}", "{existing}"], "exists already"),
    (["{views}", "{out}", "--pattern", "9by6"], "board pattern must be COLSxROWS"),
    (["{views}", "{out}", "--pattern", "1x6"], "need at least 2x2"),
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
