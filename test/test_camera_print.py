"""``t42 camera markers`` and ``t42 camera board``: sheets that print at true size, checked by finding what they
hold with the tracker's own detector and the calibration's board finder on the sheet rendered at 300 dpi."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from t42_transfer.cli import main
from t42_transfer.tracking.calibrate import Charuco, Checkerboard
from t42_transfer.tracking.markers import detect, make_detector
from t42_transfer.tracking.printing import RASTER_DPI

REPO = Path(__file__).resolve().parents[1]
PX_PER_MM = RASTER_DPI / 25.4


def sheet(path: Path) -> np.ndarray:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert gray is not None, path
    return gray


def test_the_markers_of_the_real_hand_config_are_found_at_their_sizes(tmp_path: Path, capsys) -> None:
    """Every marker the tracker of configs/hardware_real.yaml looks for, and no other, at its side within 1 %."""
    config = tmp_path / "tracker.yaml"  # the shipped file with other sizes, so no default could pass for them
    config.write_text((REPO / "configs" / "hardware_real.yaml").read_text()
                      .replace("object_size_m: 0.02 ", "object_size_m: 0.025")
                      .replace("base_ids: [1, 2]", "base_ids: [7, 3]")
                      .replace("base_sizes_m: [0.03, 0.03]", "base_sizes_m: [0.04, 0.035]"))
    out = tmp_path / "markers.png"
    assert main(["camera", "markers", str(out), "--config", str(config)]) == 0
    assert "3 markers (DICT_4X4_50)" in capsys.readouterr().out
    found = detect(make_detector("DICT_4X4_50"), sheet(out))
    sides_mm = {i: np.linalg.norm(np.diff(c, axis=0, append=c[:1]), axis=1).mean() / PX_PER_MM
                for i, c in found.items()}
    assert sorted(sides_mm) == [0, 3, 7]
    for marker_id, side in ((0, 25.0), (7, 40.0), (3, 35.0)):
        assert sides_mm[marker_id] == pytest.approx(side, rel=0.01), sides_mm


def test_the_markers_of_one_hand_of_two_are_those_its_namespaced_node_would_take(tmp_path: Path) -> None:
    """A file for two hands, in rcl's nested form: each tracker's markers by its node's full name."""
    config = tmp_path / "two_hands.yaml"
    config.write_text("""
left:
  object_tracker:
    ros__parameters: {object_id: 4, base_ids: [5], base_sizes_m: [0.03], base_poses: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]}
right:
  object_tracker:
    ros__parameters: {object_id: 8, base_ids: [9], base_sizes_m: [0.03], base_poses: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]}
""")
    for node, ids in (("/left/object_tracker", [4, 5]), ("right/object_tracker", [8, 9])):
        out = tmp_path / node.strip("/").replace("/", "_") / "markers.png"  # a folder not there yet
        assert main(["camera", "markers", str(out), "--config", str(config), "--node", node]) == 0
        assert sorted(detect(make_detector("DICT_4X4_50"), sheet(out))) == ids
    assert main(["camera", "markers", str(tmp_path / "root.png"), "--config", str(config)]) == 2  # no root tracker


def test_a_pdf_sheet_is_one_page_of_the_papers_size(tmp_path: Path) -> None:
    for paper, points in (("a4", (595.28, 841.89)), ("letter", (612.0, 792.0))):
        out = tmp_path / f"{paper}.pdf"
        assert main(["camera", "markers", str(out), "--paper", paper]) == 0
        data = out.read_bytes()
        assert data.startswith(b"%PDF") and data.count(b"/Type /Page\n") + data.count(b"/Type /Page ") == 1
        box = [float(v) for v in re.search(rb"/MediaBox \[\s*([\d.\s]+)\]", data).group(1).split()]
        assert box[:2] == [0.0, 0.0] and box[2:] == pytest.approx(points, abs=0.5)


def test_a_charuco_board_is_found_whole_with_its_square_size(tmp_path: Path) -> None:
    out = tmp_path / "board.png"
    args = ["--board", "charuco", "--squares", "7x5", "--square", "0.024", "--marker", "0.017"]
    assert main(["camera", "board", str(out), *args]) == 0
    board = Charuco((7, 5), 0.024, 0.017)
    points, pixels = board.find(sheet(out))
    assert len(points) == 6 * 4  # every inner corner, each known by its markers
    spacing_mm = _spacing(points[:, :2], pixels.reshape(-1, 2))
    assert spacing_mm == pytest.approx(24.0, rel=0.01)


def test_the_default_board_as_the_readme_prints_it_fits_a4(tmp_path: Path, capsys) -> None:
    assert main(["camera", "board", str(tmp_path / "board.pdf")]) == 0
    assert capsys.readouterr().out.startswith("9x6 board, 20 mm squares") and (tmp_path / "board.pdf").stat().st_size


def test_a_checkerboard_too_wide_for_a_portrait_page_is_turned_landscape(tmp_path: Path) -> None:
    out = tmp_path / "board.png"
    assert main(["camera", "board", str(out), "--pattern", "9x6", "--square", "0.02"]) == 0
    gray = sheet(out)
    assert gray.shape[1] > gray.shape[0]  # 10 squares of 20 mm: wider than A4's printable 186 mm
    points, pixels = Checkerboard((9, 6), 0.02).find(gray)
    assert len(points) == 54 and _spacing(points[:, :2], pixels.reshape(-1, 2)) == pytest.approx(20.0, rel=0.01)


def _spacing(board_m: np.ndarray, image_px: np.ndarray) -> float:
    """The sheet's millimetres per board millimetre times the board's square: a least-squares scale of the
    corners' image positions against their board positions, in mm on paper per square."""
    a, b = board_m - board_m.mean(axis=0), image_px - image_px.mean(axis=0)
    scale_px_per_m = float(np.sqrt((b ** 2).sum() / (a ** 2).sum()))
    steps = np.diff(np.unique(board_m[:, 0]))
    return scale_px_per_m * float(steps.min()) / PX_PER_MM


@pytest.mark.parametrize("args, message", [
    (["markers", "{out}", "--paper", "a5"], "paper must be one of a4, letter, a3, got 'a5'"),
    (["markers", "{out}", "--config", "{missing}"], "missing.yaml"),
    (["markers", "{out}", "--config", "{config}", "--node", "recorder"],
     "recorder: mode, out_dir: not a parameter of the object tracker"),
    (["markers", "{out}", "--config", "{typo}"], "object_size: not a parameter of the object tracker"),
    (["markers", "{out}", "--config", "{text_id}"], r"text_id.yaml: /object_tracker: parameter 'object_id'"),
    (["markers", "{out}", "--config", "{not_yaml}"], "not_yaml.yaml"),
    (["markers", "{out}", "--config", "{bad_id}"], r"marker id\(s\) \[60\] are not in DICT_4X4_50"),
    (["markers", "{out}", "--config", "{no_tracker}"], "no parameters for /object_tracker"),
    (["markers", "{out}", "--config", "{huge}"], "does not fit across a4 paper"),
    (["markers", "{exists}"], "exists already"),
    (["markers", "{tmp}/sheet.jpg"], "write a sheet as .pdf, .svg, .eps, .ps, .png"),
    (["board", "{out}", "--pattern", "9x6", "--square", "0.025"], "does not fit a4 paper"),
    (["board", "{out}", "--board", "charuco", "--squares", "7x5", "--marker", "0.03"], "smaller than the square"),
])
def test_bad_requests_are_one_line_errors_and_write_nothing(tmp_path: Path, capsys, args: list[str],
                                                            message: str) -> None:
    shipped = (REPO / "configs" / "hardware_real.yaml").read_text()
    files = {"config": REPO / "configs" / "hardware_real.yaml", "missing": tmp_path / "missing.yaml",
             "bad_id": tmp_path / "bad_id.yaml", "no_tracker": tmp_path / "no_tracker.yaml",
             "huge": tmp_path / "huge.yaml", "exists": tmp_path / "exists.pdf", "out": tmp_path / "out.pdf",
             "tmp": tmp_path}
    files.update({k: tmp_path / f"{k}.yaml" for k in ("typo", "text_id", "not_yaml")})
    files["typo"].write_text(shipped.replace("object_size_m: 0.02 ", "object_size: 0.025"))  # the default: 20 mm
    files["text_id"].write_text(shipped.replace("object_id: 0", "object_id: '3'"))
    files["not_yaml"].write_text("/**/object_tracker: {ros__parameters: [")
    files["bad_id"].write_text(shipped.replace("object_id: 0", "object_id: 60"))
    files["no_tracker"].write_text(shipped.replace("/**/object_tracker:", "/**/tracker_elsewhere:"))
    files["huge"].write_text(shipped.replace("base_sizes_m: [0.03, 0.03]", "base_sizes_m: [0.03, 0.3]"))
    files["exists"].write_bytes(b"mine")
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(["camera", *(a.format(**files) for a in args)])
    err = capsys.readouterr().err
    assert code == 2 and re.search(message, err) and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before and files["exists"].read_bytes() == b"mine"
