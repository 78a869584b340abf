"""``t42 sim``: simulated hands (collect episodes, compare with the real hands)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from t42_transfer.cli.args import SEED_MAX, existing_dir, float_arg, int_arg, new_output, output_dir


def _cmd_sim_collect(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag import assign_start_times, write_bag
    from t42_transfer.data.trajectory import TrajectorySet
    from t42_transfer.hand.collect import POLICIES, check_collection, collect

    if args.policy not in POLICIES:
        raise ValueError(f"--policy must be one of {', '.join(POLICIES)}, got {args.policy!r}")
    shortest = getattr(POLICIES[args.policy], "hold_min", 1)
    if args.hold_max is not None and args.hold_max < shortest:
        raise ValueError(f"--hold-max must be at least {shortest} with --policy {args.policy} (its shortest hold), "
                         f"got {args.hold_max}")
    hold = {} if args.hold_max is None else {"hold_max": args.hold_max}
    policy = POLICIES[args.policy](**hold)
    check_collection(args.hand, args.episodes, args.steps, args.workers, policy.hold_max)
    new_output(args.out)
    data, stats = collect(
        args.hand, args.episodes, args.steps, seed=args.seed, workers=args.workers, policy=policy,
        progress=not args.quiet,
    )
    placed = TrajectorySet(assign_start_times(data), hand=data.hand)
    meta = {"collector": "t42 sim collect", "seed": str(args.seed), "steps": str(args.steps),
            "policy": repr(policy)}
    bag = write_bag(args.out, placed, storage=args.storage, metadata=meta)
    print(
        f"{args.hand}: kept {stats.kept}/{stats.requested} episodes ({placed.num_transitions} transitions; "
        f"{stats.too_short} too short, {stats.grasp_failed} grasp failures; ends {stats.end_reasons}) -> {bag}"
    )
    return 0


def _cmd_sim_compare_real(args: argparse.Namespace) -> int:
    from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
    from t42_transfer.hand import realism
    from t42_transfer.hand.params import variant

    folder = existing_dir(args.real_dir or real_data_dir())
    for hand in args.hands:
        variant(hand)
    if args.out_dir:
        output_dir(args.out_dir)
    real = {hand: load_t42_testpaths(folder / name) for hand, name in REAL_FILES.items()}
    rows, replays = realism.compare(real, hands=args.hands, seed=args.seed)
    named = realism.labelled(real, replays)
    rates = [r for name, data in named.items() for r in realism.held_move_rates(name, data, args.window)]
    held = realism.held_moves_table(rates) if rates else f"No move is held {args.window} steps in any path.\n"
    onsets = [r for name, data in named.items()
              for r in realism.held_move_onsets(name, data, args.moving_threshold, args.moving_window)]
    waits = realism.held_onsets_table(onsets) if onsets else "No move is held 100 steps in any path.\n"
    table = realism.markdown_table(rows) + "\n" + held + "\n" + waits
    print(table)
    if args.out_dir:
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / "sim_vs_real.md").write_text(table)
        summary = {"paths": realism.rows_as_dicts(rows), "held_moves": realism.rows_as_dicts(rates),
                   "onsets": realism.rows_as_dicts(onsets)}
        (args.out_dir / "sim_vs_real.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
        figure = realism.plot_paths(real, replays, args.out_dir / "sim_vs_real_paths.png")
        written = [args.out_dir / "sim_vs_real.md", args.out_dir / "sim_vs_real.json", figure]
        if rates:
            written.append(realism.plot_held_moves(rates, args.out_dir / "sim_vs_real_held_moves.png"))
        if onsets:
            written.append(realism.plot_held_onsets(onsets, args.out_dir / "sim_vs_real_onsets.png"))
        print("wrote " + ", ".join(str(w) for w in written))
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    sim = commands.add_parser("sim", help="simulated hands").add_subparsers(dest="sim_command", metavar="ACTION")
    col = sim.add_parser("collect", help="collect episodes under a policy into a rosbag2 bag")
    col.add_argument("--hand", default="source", help="source, target, target_abrupt or family-<seed> (default source)")
    col.add_argument("--episodes", type=int_arg(1), default=300, help="episodes (paper: 300)")
    col.add_argument("--steps", type=int_arg(1), default=1000, help="max steps per episode at 10 Hz (paper: 1000)")
    col.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    col.add_argument("--workers", type=int_arg(1), default=None, help="worker processes (default: all cores)")
    col.add_argument("--policy", default="random",
                     help="random: uniform actions held 1..--hold-max steps (default 5), the training data of the "
                          "experiments; sustained: test paths like the real hands' (their eight moves held "
                          "120..--hold-max steps, default 700)")
    col.add_argument("--hold-max", type=int_arg(1), default=None, help="longest hold in steps (default: the policy's)")
    col.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    col.add_argument("--quiet", action="store_true", help="no progress bar")
    col.add_argument("--out", type=Path, required=True, help="bag directory to create")
    col.set_defaults(func=_cmd_sim_collect)

    cmp_ = sim.add_parser("compare-real", help="replay the real T42 test paths' actions on simulated hands")
    cmp_.add_argument(
        "--real-dir", type=Path, default=None,
        help="folder of the public T42 pickles (default: $T42_REAL_DATA or ../shared/data/t42_real)"
    )
    cmp_.add_argument("--hands", nargs="+", default=["source", "target"])
    cmp_.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    cmp_.add_argument(
        "--window", type=int_arg(1), default=30,
        help="steps of each held move over which its rates are measured (default 30)",
    )
    cmp_.add_argument(
        "--moving-threshold", type=float_arg(0.0, low_open=True), default=2.0,
        help="mm the object must move from a hold's start before it counts as moving (default 2; the real "
             "tracker's positions move in steps of about 0.4 mm)",
    )
    cmp_.add_argument(
        "--moving-window", type=int_arg(1, 99), default=20,
        help="steps, from that point, over which the moving speed is measured (default 20; under the 100 steps "
             "a move must be held)",
    )
    cmp_.add_argument("--out-dir", type=Path, default=None, help="write table (md, json) and figure here")
    cmp_.set_defaults(func=_cmd_sim_compare_real)
