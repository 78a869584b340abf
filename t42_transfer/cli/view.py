"""``t42 view``: the hand seen in Foxglove (a live graph or a recorded bag), or a picture of the scene (--snapshot)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from t42_transfer.cli.args import existing_file, float_arg, int_arg, namespace_arg, new_output
from t42_transfer.conventions import MM_PER_M


def _path_file(path: Path) -> np.ndarray:
    """Object positions ``[N, 2]`` (mm) of a text file, one ``x,y`` (or ``x y``) a line."""
    existing_file(path)
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (UTF-8) of x,y positions in mm, one a line") from None
    try:
        rows = [[float(v) for v in line.replace(",", " ").split()] for line in text.splitlines() if line.strip()]
        xy = np.array(rows, dtype=float)
    except ValueError:
        raise ValueError(f"{path}: not a list of x,y positions in mm, one a line") from None
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise ValueError(f"{path}: not a list of finite x,y positions in mm, one a line")
    return xy


def _snapshot(args: argparse.Namespace) -> int:
    from t42_transfer.view.bag_scene import SceneInputs, bag_scene_inputs
    from t42_transfer.view.scene import build_scene
    from t42_transfer.view.snapshot import render

    if args.snapshot.suffix.lower() != ".png":  # (matplotlib would add .png and write past the check below)
        raise ValueError(f"{args.snapshot}: --snapshot writes a PNG; give a path ending in .png")
    new_output(args.snapshot)
    inputs = bag_scene_inputs(args.bag, args.at) if args.bag is not None else SceneInputs()
    given = {"actuator_angles": args.angles, "object_xy_mm": args.object, "goal_xy_mm": args.goal,
             "path_xy_mm": None if args.path is None else _path_file(args.path)}
    for field, value in given.items():
        if value is not None:
            setattr(inputs, field, np.asarray(value, dtype=float))
    scene = build_scene(args.hand, actuator_angles=inputs.actuator_angles, object_xy_mm=inputs.object_xy_mm,
                        goal_xy_mm=inputs.goal_xy_mm, tolerance_mm=args.tolerance, path_xy_mm=inputs.path_xy_mm,
                        candidates=inputs.candidates or ())
    title = f"{args.bag.name} at {(inputs.log_ns - inputs.start_ns) / 1e9:.1f} s" if args.bag is not None else ""
    render(scene, args.snapshot, title=title)
    drawn = [name for name, value in (("object", scene.object_xy_mm), ("goal", scene.goal_xy_mm),
                                      ("path", scene.path_xy_mm)) if value is not None]
    print(f"wrote {args.snapshot}: the {args.hand} hand{''.join(', ' + d for d in drawn)}")
    return 0


def _serve_bag(args: argparse.Namespace) -> int:
    from t42_transfer.view.bag_server import serve_bag

    return serve_bag(args.bag, host=args.host, port=args.port, hand=args.hand, tolerance_mm=args.tolerance)


def _live(args: argparse.Namespace) -> int:
    from t42_transfer.ros.launcher import namespace_args
    from t42_transfer.ros.runner import keep_discovery_local, run_node

    keep_discovery_local()
    ros_args = ["--ros-args", *namespace_args(args.namespace), "-p", f"host:={args.host}", "-p", f"port:={args.port}",
                "-p", f"hand:={args.hand}", "-p", f"tolerance_m:={args.tolerance / MM_PER_M!r}", *args.ros_args]
    return run_node("view", ros_args)


SNAPSHOT_ONLY = {"at": "--at", "angles": "--angles", "object": "--object", "goal": "--goal", "path": "--path"}
"""Options that only a snapshot draws: given to a server, they would be dropped without a word."""


def _cmd_view(args: argparse.Namespace) -> int:
    if args.snapshot is not None:
        if args.at is not None and args.bag is None:
            args.parser.error("--at S picks a time in a bag: give --bag too")
        return _snapshot(args)
    given = [flag for name, flag in SNAPSHOT_ONLY.items() if getattr(args, name) is not None]
    if given:
        args.parser.error(f"{', '.join(given)}: for a --snapshot only (a server shows the graph or the bag as "
                          "they go)")
    if args.bag is not None:
        return _serve_bag(args)
    return _live(args)


def add_commands(commands: argparse._SubParsersAction) -> None:
    view = commands.add_parser(
        "view", help="a Foxglove WebSocket server of the live graph (default) or of a bag (--bag); "
                     "or a PNG of the scene (--snapshot)")
    view.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine "
                                                          "only; 0.0.0.0 opens it to the network)")
    view.add_argument("--port", type=int_arg(0, 65535), default=8765, help="port (default 8765; 0: any free one)")
    view.add_argument("--bag", type=Path, default=None, help="serve (or, with --snapshot, draw) this recorded bag")
    view.add_argument("--snapshot", type=Path, default=None, metavar="OUT.png",
                      help="draw the scene into this new PNG and exit (from --bag and/or the values below)")
    view.add_argument("--at", type=float_arg(0.0), default=None, metavar="S",
                      help="snapshot of a bag: seconds after its first message (default: its end)")
    view.add_argument("--hand", default="target", help="hand whose links are drawn (default target)")
    view.add_argument("--angles", type=float_arg(), nargs=2, default=None, metavar=("A1", "A2"),
                      help="snapshot: actuator angles (rad)")
    view.add_argument("--object", type=float_arg(), nargs=2, default=None, metavar=("X", "Y"),
                      help="snapshot: object position (mm)")
    view.add_argument("--goal", type=float_arg(), nargs=2, default=None, metavar=("X", "Y"),
                      help="snapshot: goal (mm)")
    view.add_argument("--tolerance", type=float_arg(0.0, low_open=True), default=2.0, metavar="MM",
                      help="radius of the goal's circle (mm, default 2: the planner's)")
    view.add_argument("--path", type=Path, default=None, help="snapshot: planned path file, x,y (mm) a line")
    view.add_argument("--namespace", type=namespace_arg, default="",
                      help="live view of a suite run with `t42 up --namespace` (e.g. /left): the view's names and "
                           "its /clock are that namespace's")
    view.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[], metavar="ARG",
                      help="live view: the rest are ROS arguments of the view node (-r __ns:=/left, -p name:=value)")
    view.set_defaults(func=_cmd_view, parser=view)
