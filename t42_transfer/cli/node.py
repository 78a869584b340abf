"""``t42 node`` and ``t42 up``: one node as a process (as ``ros2 run``), or the suite of a params file."""

from __future__ import annotations

import argparse
from pathlib import Path

from t42_transfer.cli.args import float_arg, namespace_arg

COMMANDS = ("node", "up")
"""The commands :func:`add_commands` defines."""


def _cmd_node(args: argparse.Namespace) -> int:
    from t42_transfer.nodes.registry import NODES

    if args.list or not args.name:
        for name, spec in NODES.items():
            print(f"{name:16s} {spec.description}")
        return 0
    from t42_transfer.ros.runner import keep_discovery_local, run_node

    keep_discovery_local()
    return run_node(args.name, args.ros_args)


def _cmd_up(args: argparse.Namespace) -> int:
    from t42_transfer.ros.launcher import up

    only = [n for n in args.only.split(",") if n] if args.only else None
    return up(args.config, only=only, stop_timeout_s=args.stop_timeout, namespace=args.namespace,
              respawn=not args.no_respawn)


# ------------------------------------------------------------------------ parser


def add_commands(commands: argparse._SubParsersAction) -> None:
    node = commands.add_parser("node", help="run one ROS node until Ctrl-C (as `ros2 run t42_transfer NAME`)")
    node.add_argument("--list", action="store_true", help="list the runnable nodes")
    node.add_argument("name", nargs="?", help="node to run (see --list)")
    node.add_argument("ros_args", nargs=argparse.REMAINDER,
                      help="ROS arguments, e.g. --ros-args --params-file F.yaml -p name:=value -r __ns:=/left "
                           "-r hand/object_pose:=pose --log-level debug")
    node.set_defaults(func=_cmd_node)

    up = commands.add_parser("up", help="run every node of a ROS params file as its own process until Ctrl-C")
    up.add_argument("config", type=Path, help="ROS params file (e.g. configs/suite.yaml); one process per node section")
    up.add_argument("--only", default=None, help="comma-separated node names to run (default: all)")
    up.add_argument("--stop-timeout", type=float_arg(0, 3600, low_open=True), default=5.0,
                    help="seconds per stop signal (default 5)")
    up.add_argument("--namespace", type=namespace_arg, default="",
                    help="run every node under this ROS namespace (e.g. /left)")
    up.add_argument("--no-respawn", action="store_true",
                    help="a node that exits stops the whole suite (default: it is restarted alone, with backoff, "
                         "up to 5 times, unless it failed within 5 s of its start)")
    up.set_defaults(func=_cmd_up)
