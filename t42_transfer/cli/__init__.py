"""The ``t42`` command: one entry point whose subcommands reach every layer.

Each subcommand lives in the module of its group (``demo``, ``experiment``, ``evaluate``, ``plan``,
``sim``, ``bag``, ``model``, ``node``, ``topic``, ``graph``, ``hw``, ``camera``, ``view``), parses its arguments
with the shared checks of :mod:`t42_transfer.cli.args`, calls one library function and prints a summary; bad
input ends with ``t42: error: <file>: <problem>`` and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Sequence
from types import ModuleType

from t42_transfer import __version__
from t42_transfer.cli import (
    bag,
    camera,
    demo,
    evaluate,
    experiment,
    graph,
    hw,
    model,
    node,
    plan,
    reach,
    sim,
    topic,
    view,
)
from t42_transfer.cli.args import OneLineParser, os_error

GROUPS = (demo, experiment, evaluate, plan, sim, bag, model, node, topic, graph, reach, hw, camera, view)
"""Command modules, in the order ``t42 --help`` lists them."""


def build_parser(groups: Sequence[ModuleType] = GROUPS) -> argparse.ArgumentParser:
    """The ``t42`` parser with the commands of ``groups`` (default: all)."""
    parser = OneLineParser(
        prog="t42",
        description=(
            "t42: transfer learned dynamics models between Yale Model-T42 hands. "
            "Record a hand into rosbag2 bags, transfer a source model to it, plan open-loop reaches with the "
            "transferred model, on simulated, emulated or real hands; the experiments and evaluation of the paper."
        ),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for group in groups:
        group.add_commands(commands)
    return parser


def _groups_for(argv: Sequence[str]) -> Sequence[ModuleType]:
    """Only the node group for ``t42 node`` and ``t42 up``, which start every node process: the plan group's
    options take their defaults from modules that import torch and MuJoCo (~1.5 s of CPU a process)."""
    if argv[:1] and argv[0] in node.COMMANDS:
        return (node,)
    return (view,) if argv[:1] == ["view"] else GROUPS  # the view node runs in the `t42 view` process


def one_line_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                     line: str | None = None) -> str:
    """A warning as ``t42: warning: ...`` on one line, as errors are, without the source file and line a user
    has no use for (a salvaged bag's losses, a cell that failed)."""
    kind = "" if category is UserWarning else f"{category.__name__}: "
    return f"t42: warning: {kind}{' '.join(str(message).split())}\n"


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # the program itself (a caller passing argv keeps its own warning format)
        warnings.formatwarning = one_line_warning
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_groups_for(argv))
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        # `t42` or `t42 sim` alone: show the help of the level reached.
        chosen = [a for a in (args.command, getattr(args, "sim_command", None), getattr(args, "bag_command", None),
                              getattr(args, "hw_command", None), getattr(args, "model_command", None),
                              getattr(args, "camera_command", None)) if a]
        parser.parse_args([*chosen, "--help"]) if chosen else parser.print_help()
        return 0
    args.argv = argv
    try:
        code = func(args)
        sys.stdout.flush()  # here, not at exit: a reader gone by then would cost a traceback line
        return code
    except BrokenPipeError:  # the reader went away (`t42 bag info BAG --json | head`): as any Unix tool, say nothing
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (no second error when Python flushes)
        return 141
    except OSError as err:  # a path the user gave: missing, unreadable, a directory where a file belongs, ...
        message = os_error(err)
    except ValueError as err:  # DataFileError and CheckpointError included
        message = str(err)
    print(f"t42: error: {' '.join(message.split())}", file=sys.stderr)
    return 2
