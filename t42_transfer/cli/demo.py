"""``t42 demo``: the README's main job."""

from __future__ import annotations

import argparse
from pathlib import Path

from t42_transfer.cli.args import int_arg, output_dir
from t42_transfer.demo.settings import HARDWARE


def _cmd_demo(args: argparse.Namespace) -> int:
    from t42_transfer.demo import run_demo

    return run_demo(output_dir(args.out), quick=args.quick, workers=args.workers, hardware=args.hardware,
                    rounds=args.rounds, goals=args.goals, update=not args.no_update)


def add_commands(commands: argparse._SubParsersAction) -> None:
    demo = commands.add_parser("demo", help="run the main job end to end on simulated hands")
    demo.add_argument("--quick", action="store_true", help="tiny sizes (about 30 s), as CI runs it")
    demo.add_argument("--out", type=Path, default=Path("runs/demo"), help="output directory (default runs/demo)")
    demo.add_argument("--hardware", choices=tuple(HARDWARE), default="sim",
                      help="the hand: sim (mock driver, default); emulated (the Dynamixel driver on an emulated "
                           "servo bus with an emulated tracker: the real hand's nodes without a hand); or camera "
                           "(the mock driver's hand rendered, its pose from the object tracker on the frames)")
    demo.add_argument("--workers", type=int_arg(1), default=None, help="worker processes (default: all cores)")
    demo.add_argument("--rounds", type=int_arg(1, 20), default=None,
                      help="transfer-then-goals rounds (default 2): a longer online loop")
    demo.add_argument("--goals", type=int_arg(1, 200), default=None,
                      help="goals per round (default 8, --quick 2), their lengths cycling through 30-60 steps "
                           "(--quick: 30 and 40)")
    demo.add_argument("--no-update", action="store_true",
                      help="transfer in round 1 only: the loop that never updates its model, to compare with")
    demo.set_defaults(func=_cmd_demo)
