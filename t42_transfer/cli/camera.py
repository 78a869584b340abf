"""``t42 camera``: cameras for the object tracker (calibration)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from t42_transfer.cli.args import existing_dir, existing_file, float_arg, new_output

if TYPE_CHECKING:
    from t42_transfer.nodes.object_tracker import ObjectTrackerParams
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


def _board_arguments(parser: argparse.ArgumentParser) -> None:
    """The board options ``calibrate`` and ``board`` share (checked together by :func:`_board`)."""
    parser.add_argument("--board", choices=BOARDS, default="checkerboard",
                        help="checkerboard (the whole board in each image) or charuco (ArUco markers in the white "
                             "squares: part of the board is enough) (default checkerboard)")
    parser.add_argument("--pattern", help="checkerboard: inner corners per row x per column (default 9x6)")
    parser.add_argument("--squares",
                        help="charuco: squares per row x per column, e.g. 7x5 (as cv2.aruco.CharucoBoard)")
    parser.add_argument("--square", type=float_arg(0.0, 10.0, low_open=True), default=0.02,
                        help="side of a board square in metres (default 0.02: the default board fits on a4)")
    parser.add_argument("--marker", type=float_arg(0.0, 10.0, low_open=True),
                        help="charuco: side of a marker in metres (smaller than --square)")
    parser.add_argument("--dictionary", help="charuco: the markers' ArUco dictionary (default DICT_4X4_50)")


def _cmd_camera_markers(args: argparse.Namespace) -> int:
    from t42_transfer.tracking.printing import marker_sheet, save_sheet, tracker_markers

    params = _tracker_params(args.config, args.node)
    new_output(args.out)
    config = params.tracker_config()
    markers = tracker_markers(config)
    source = f"{args.node} in {args.config}" if args.config else f"the {args.node} node's defaults"
    fig = marker_sheet(markers, config.dictionary, args.paper,
                       title=f"ArUco markers ({config.dictionary}) for the object tracker: {source}")
    save_sheet(fig, args.out)
    print(f"{len(markers)} markers ({config.dictionary}): "
          + ", ".join(f"id {m.marker_id} {m.role} {m.size_m * 1000:g} mm" for m in markers)
          + f" -> {args.out}; print at 100 % (actual size) and check the 50 mm bar")
    return 0


def _tracker_params(config: Path | None, node: str) -> ObjectTrackerParams:
    """The tracker's parameters as the node named ``node`` would take them from ``config``, or its defaults."""
    from t42_transfer.nodes.object_tracker import ObjectTrackerParams
    from t42_transfer.ros.launcher import params_from_file

    if config is None:
        return ObjectTrackerParams()
    params, unknown = params_from_file(ObjectTrackerParams, existing_file(config), node)
    unknown = [n for n in unknown if not n.startswith("qos_overrides.")]  # (declared with the node's readers)
    if unknown:  # a misspelt size would print a marker of the default size: refused, not warned about
        raise ValueError(f"{config}: {node}: {', '.join(unknown)}: not a parameter of the object tracker (it has "
                         f"{', '.join(f.name for f in dataclasses.fields(ObjectTrackerParams))})")
    return params


def _cmd_camera_board(args: argparse.Namespace) -> int:
    from t42_transfer.tracking.printing import board_sheet, save_sheet

    board = _board(args)
    new_output(args.out)
    save_sheet(board_sheet(board, args.paper), args.out)
    print(f"{board.describe()}, {board.square_m * 1000:g} mm squares -> {args.out}; print at 100 % (actual size), "
          "check the 50 mm bar, then measure a square and give t42 camera calibrate what you measure")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    camera = commands.add_parser("camera", help="cameras for the object tracker").add_subparsers(
        dest="camera_command", metavar="ACTION")
    cal = camera.add_parser("calibrate", help="calibrate from checkerboard or ChArUco images; write a ROS "
                            "camera_info YAML")
    cal.add_argument("folder", type=Path, metavar="FOLDER", help="folder of images of one camera (png, jpg, ...)")
    cal.add_argument("out", type=Path, metavar="OUT.yaml", help="camera_info YAML to create")
    _board_arguments(cal)
    cal.add_argument("--camera-name", default="camera", help="camera_name in the YAML (default camera)")
    cal.set_defaults(func=_cmd_camera_calibrate)

    outputs = "(.pdf, .svg, .eps, .ps: vector, or .png at 300 dpi)"
    paper = "page size: a4, a3 or letter (default a4)"
    markers = camera.add_parser("markers", help="print the object tracker's ArUco markers at their sizes")
    markers.add_argument("out", type=Path, metavar="OUT", help=f"sheet to create {outputs}")
    markers.add_argument("--config", type=Path, metavar="PARAMS.yaml",
                         help="a params file (configs/hardware_real.yaml): the markers its tracker section names "
                              "(default: the tracker's defaults)")
    markers.add_argument("--node", default="object_tracker",
                         help="the tracker's node name, with its namespace if it runs in one (/left/object_tracker; "
                              "default object_tracker): the parameters the file gives that node")
    markers.add_argument("--paper", default="a4", help=paper)
    markers.set_defaults(func=_cmd_camera_markers)

    board = camera.add_parser("board", help="print a calibration board at its size, as calibrate takes it")
    board.add_argument("out", type=Path, metavar="OUT", help=f"sheet to create {outputs}")
    _board_arguments(board)
    board.add_argument("--paper", default="a4", help=paper)
    board.set_defaults(func=_cmd_camera_board)
