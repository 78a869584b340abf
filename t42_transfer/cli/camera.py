"""``t42 camera``: cameras for the object tracker (calibration)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from t42_transfer.cli.args import existing_dir, float_arg, new_output

if TYPE_CHECKING:
    from t42_transfer.tracking.calibrate import Board

BOARDS = ("checkerboard", "charuco")
CHARUCO_ONLY = ("squares", "marker", "dictionary")


def _board(args: argparse.Namespace) -> Board:
    """The board the options describe; ValueError when they do not fit together."""
    from t42_transfer.tracking.calibrate import Charuco, Checkerboard, parse_pattern, parse_squares
    from t42_transfer.tracking.markers import DEFAULT_DICTIONARY

    given = [f"--{name}" for name in CHARUCO_ONLY if getattr(args, name) is not None]
    if args.board == "checkerboard":
        if given:
            raise ValueError(f"{', '.join(given)}: for --board charuco; a checkerboard takes --pattern and --square")
        return Checkerboard(parse_pattern(args.pattern or "9x6"), args.square)
    if args.pattern is not None:
        raise ValueError("--pattern counts a checkerboard's inner corners; a ChArUco board takes --squares")
    if args.squares is None or args.marker is None:
        raise ValueError("--board charuco needs --squares (squares per row x per column, e.g. 7x5) and --marker "
                         "(marker side in metres)")
    return Charuco(parse_squares(args.squares), args.square, args.marker, args.dictionary or DEFAULT_DICTIONARY)


def _cmd_camera_calibrate(args: argparse.Namespace) -> int:
    from t42_transfer.tracking.calibrate import calibrate, image_files, read_images, write_camera_info

    board = _board(args)
    folder = existing_dir(args.folder)
    new_output(args.out)
    files = image_files(folder)
    result = calibrate(read_images(files), board)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_camera_info(args.out, result.intrinsics, args.camera_name)
    k = result.intrinsics.k
    worst = max(range(len(result.used)), key=result.per_image_px.__getitem__)
    skipped = f" (no board in: {', '.join(result.skipped[:10])}{' ...' if len(result.skipped) > 10 else ''})"
    print(f"calibrated from {len(result.used)} of {len(files)} images{skipped if result.skipped else ''}: "
          f"fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f} px, "
          f"distortion {' '.join(f'{v:.4f}' for v in result.intrinsics.d)}")
    print(f"reprojection error {result.rms_px:.3f} px RMS (worst image {result.used[worst]}: "
          f"{result.per_image_px[worst]:.3f} px) -> {args.out}")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    camera = commands.add_parser("camera", help="cameras for the object tracker").add_subparsers(
        dest="camera_command", metavar="ACTION")
    cal = camera.add_parser("calibrate", help="calibrate from checkerboard or ChArUco images; write a ROS "
                            "camera_info YAML")
    cal.add_argument("folder", type=Path, metavar="FOLDER", help="folder of images of one camera (png, jpg, ...)")
    cal.add_argument("out", type=Path, metavar="OUT.yaml", help="camera_info YAML to create")
    cal.add_argument("--board", choices=BOARDS, default="checkerboard",
                     help="checkerboard (the whole board in each image) or charuco (ArUco markers in the white "
                          "squares: part of the board is enough) (default checkerboard)")
    cal.add_argument("--pattern", help="checkerboard: inner corners per row x per column (default 9x6)")
    cal.add_argument("--squares", help="charuco: squares per row x per column, e.g. 7x5 (as cv2.aruco.CharucoBoard)")
    cal.add_argument("--square", type=float_arg(0.0, 10.0, low_open=True), default=0.025,
                     help="side of a board square in metres (default 0.025)")
    cal.add_argument("--marker", type=float_arg(0.0, 10.0, low_open=True),
                     help="charuco: side of a marker in metres (smaller than --square)")
    cal.add_argument("--dictionary", help="charuco: the markers' ArUco dictionary (default DICT_4X4_50)")
    cal.add_argument("--camera-name", default="camera", help="camera_name in the YAML (default camera)")
    cal.set_defaults(func=_cmd_camera_calibrate)
