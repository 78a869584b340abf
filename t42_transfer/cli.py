"""The ``t42`` command: one entry point whose subcommands reach every layer.

Each subcommand parses its arguments, calls one library function and prints a
summary; bad input ends with ``t42: error: <file>: <problem>`` and exit code 2,
never a traceback.  Numbers are checked by the parser (finite, in range, with bounds
where a number sizes an allocation) and paths before any work starts, so a typo is
refused in a second instead of after a long run or an 800 GB allocation.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import stat
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from t42_transfer import __version__

MAX_SAMPLES = 1_000_000
MAX_HORIZON = 10_000
MAX_SAMPLED_STEPS = 20_000_000
"""Planner samples x horizon at most: the sampled actions alone are 8 bytes per step (160 MB here)."""
MAX_REFINE = 1000
SEED_MAX = 2**32 - 1
ROS_NAMESPACE = re.compile(r"/?|/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*/?")

# ------------------------------------------------------------------ arguments


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one ``t42: error:`` line (exit 2), like every other error."""

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("t42").strip()
        self.exit(2, f"t42: error: {command + ': ' if command else ''}{message} (see {self.prog} --help)\n")


def int_arg(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in ``[low, high]``."""
    wanted = f"an integer from {low} to {high}" if high is not None else f"an integer >= {low}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}")
        return value

    return parse


def float_arg(low: float = -math.inf, high: float = math.inf, low_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number in ``[low, high]`` (``(low, high]`` with ``low_open``)."""
    bounds = [f"{'>' if low_open else '>='} {low:g}"] if low > -math.inf else []
    bounds += [f"<= {high:g}"] if high < math.inf else []
    wanted = " ".join(["a finite number", " and ".join(bounds)]).strip()

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value > low if low_open else value >= low) and value <= high):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text[:40]!r}")
        return value

    return parse


def check_plan_size(samples: int, horizon: int) -> None:
    """ValueError when samples x horizon would size an allocation beyond :data:`MAX_SAMPLED_STEPS`."""
    if samples * horizon > MAX_SAMPLED_STEPS:
        raise ValueError(f"--samples {samples} x --horizon {horizon} is over {MAX_SAMPLED_STEPS} sampled steps")


def _stat(path: Path) -> os.stat_result | None:
    """``path``'s status (following links); None when nothing is there; ValueError for any other failure."""
    try:
        return path.stat()
    except FileNotFoundError:
        return None
    except OSError as err:
        raise ValueError(f"{path}: {err.strerror or err}") from None


def _existing(path: Path, is_kind: Callable[[int], bool], kind: str) -> Path:
    """``path`` when it exists and ``is_kind(st_mode)``; ValueError naming it otherwise."""
    info = _stat(path)
    if info is None:
        raise ValueError(f"{path}: does not exist")
    if not is_kind(info.st_mode):
        raise ValueError(f"{path}: not {kind}")
    return path


def existing_file(path: Path) -> Path:
    """``path`` when it is a regular file (a FIFO would block the reader)."""
    return _existing(path, stat.S_ISREG, "a regular file")


def existing_dir(path: Path) -> Path:
    return _existing(path, stat.S_ISDIR, "a directory")


def output_dir(path: Path) -> Path:
    """``path`` when it is a directory, or can be made one (its nearest existing ancestor is a directory)."""
    for at in (path, *path.absolute().parents):
        info = _stat(at)
        if info is not None:
            if not stat.S_ISDIR(info.st_mode):
                raise ValueError(f"{path}: {'' if at == path else f'{at} '}is not a directory")
            break
    return path


def new_output(path: Path) -> Path:
    """``path`` when nothing is there yet and its directory can be made; outputs are never overwritten."""
    if os.path.lexists(path):
        raise ValueError(f"{path}: exists already; choose a new path")
    return output_dir(path)


def _os_error(err: OSError) -> str:
    """An OSError as ``<file>: <problem>``."""
    return f"{err.filename}: {err.strerror}" if err.filename is not None and err.strerror else str(err)


# ----------------------------------------------------------------------- commands


def _cmd_sim_collect(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag_io import assign_start_times, write_bag
    from t42_transfer.data.trajectory import TrajectorySet
    from t42_transfer.hand.collect import RandomPolicy, check_collection, collect

    check_collection(args.hand, args.episodes, args.steps, args.workers, args.hold_max)
    new_output(args.out)
    data, stats = collect(
        args.hand, args.episodes, args.steps, seed=args.seed, workers=args.workers,
        policy=RandomPolicy(hold_max=args.hold_max), progress=not args.quiet,
    )
    placed = TrajectorySet(assign_start_times(data), hand=data.hand)
    meta = {"collector": "t42 sim collect", "seed": str(args.seed), "steps": str(args.steps)}
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
    table = realism.markdown_table(rows)
    print(table)
    if args.out_dir:
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / "sim_vs_real.md").write_text(table)
        (args.out_dir / "sim_vs_real.json").write_text(json.dumps(realism.rows_as_dicts(rows), indent=2) + "\n")
        figure = realism.plot_paths(real, replays, args.out_dir / "sim_vs_real_paths.png")
        print(f"wrote {args.out_dir / 'sim_vs_real.md'}, .json and {figure}")
    return 0


def _cmd_bag_info(args: argparse.Namespace) -> int:
    import warnings

    from t42_transfer.data.bag_io import bag_info, read_bag, verify_bag
    from t42_transfer.data.quality import scan, summarise, summary_lines

    info = bag_info(args.bag)
    with warnings.catch_warnings():  # bag_info has already warned about whatever it salvaged
        warnings.simplefilter("ignore")
        data = read_bag(args.bag, allow_gaps=True)
    findings = scan(data)
    mismatches = verify_bag(args.bag) if args.verify else []
    if args.json:
        info["quality"] = summarise(data, findings)
        print(json.dumps({**info, "verify": mismatches} if args.verify else info, indent=2, default=str))
        return 1 if mismatches else 0
    for key, value in info.items():
        if isinstance(value, dict):
            print(f"{key}:")
            for k, v in value.items():
                print(f"  {k}: {v}")
        else:
            print(f"{key}: {value}")
    print(f"quality: {len(findings)} of {len(data)} episodes with frozen tracking or jumps")
    for line in summary_lines(findings) if findings else ():
        print(f"  {line}")
    if args.verify:
        print(f"verify: {len(mismatches)} mismatches between metadata.yaml and the data" if mismatches
              else "verify: metadata.yaml agrees with the data")
        for mismatch in mismatches:
            print(f"  {mismatch}")
    return 1 if mismatches else 0


def _cmd_bag_import_t42(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag_io import read_bag
    from t42_transfer.data.t42_real import import_t42_to_bag, quality_lines

    bag = import_t42_to_bag(existing_file(args.pickle), new_output(args.out))
    data = read_bag(bag)
    print(f"{args.pickle} -> {bag}: {len(data)} paths, {data.num_transitions} transitions, hand {data.hand!r}")
    print("flagged stretches: " + "; ".join(quality_lines(data)))
    return 0


def _cmd_bag_repair(args: argparse.Namespace) -> int:
    from t42_transfer.data.bag_repair import repair_bag

    report = repair_bag(existing_dir(args.bag))
    if not report.repaired:
        print(f"{report.path}: sound, left as it is ({report.message_count} messages)")
        return 0
    print(f"{report.path}: repaired ({'; '.join(report.problems)})")
    if report.stopped:
        print(f"  salvaged up to where {report.stopped}")
    for topic, count in sorted(report.counts.items()):
        print(f"  {topic}: {count} messages")
    print(f"  originals kept as {', '.join(str(p) for p in report.originals)}")
    return 0


def _cmd_bag_play(args: argparse.Namespace) -> int:
    from t42_transfer.nodes.player import PlayerParams
    from t42_transfer.ros.runner import keep_discovery_local

    topics = tuple(args.topics) if args.topics else None
    # bad input: exit 2, before rclpy starts
    PlayerParams(existing_dir(args.bag), rate=args.rate, loop=args.loop, topics=topics, clock_hz=args.clock)
    keep_discovery_local()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from t42_transfer.nodes.player import BagPlayer

    overrides = [Parameter("bag", value=str(args.bag)), Parameter("rate", value=float(args.rate)),
                 Parameter("loop", value=args.loop), Parameter("clock_hz", value=float(args.clock)),
                 Parameter("start_paused", value=True)]
    if topics:
        overrides.append(Parameter("topics", value=list(topics)))
    context = rclpy.Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        player = BagPlayer(context=context, parameter_overrides=overrides)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(player)
        try:
            if not player.wait_for_subscribers(args.wait_subscribers, settle_s=0.5):
                print(f"not every topic had a subscriber within {args.wait_subscribers} s; playing anyway",
                      file=sys.stderr)
            player.resume()
            while not player.finished:
                executor.spin_once(timeout_sec=0.1)
            player.wait_for_acks(5.0)
        except KeyboardInterrupt:
            pass
        finally:
            player.close()
            executor.shutdown(timeout_sec=2.0)
            player.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    print(f"{args.bag}: published {player.published} messages on {len(player.topic_publishers)} topics")
    return 0


def _cmd_experiment(args: argparse.Namespace) -> int:
    import dataclasses

    from t42_transfer.evaluation.experiment import load_config, run_experiment
    from t42_transfer.evaluation.report import write_report

    cfg = load_config(args.config)
    if args.workers is not None:
        cfg = dataclasses.replace(cfg, workers=args.workers)
    output_dir(args.out)
    rows = run_experiment(cfg, args.out, progress=not args.quiet)
    run_dir = args.out / cfg.name
    print(f"{len(rows)} rows (cells and the hold-still baseline) -> {run_dir / 'results.csv'}")
    if not args.no_report:
        print(f"report: {write_report(run_dir)}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from t42_transfer.evaluation.report import write_report

    existing_file(existing_dir(args.run_dir) / "results.json")
    print(f"report: {write_report(args.run_dir, args.out and output_dir(args.out))}")
    return 0


def _cmd_plan(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from t42_transfer.models.checkpoint import load_model
    from t42_transfer.planning import Planner, PlannerConfig, Workspace
    from t42_transfer.planning.export import write_plan

    check_plan_size(PlannerConfig.samples if args.samples is None else args.samples, args.horizon)
    for path in (args.workspace or []):
        existing_dir(path)
    output_dir(args.out)
    model, meta = load_model(existing_file(args.model))
    workspace = Workspace.for_planning(args.workspace, meta, args.model)
    cfg = PlannerConfig(
        samples=PlannerConfig.samples if args.samples is None else args.samples, horizon=args.horizon,
        sampler=args.sampler, tolerance_mm=args.tolerance, horizon_search=args.horizon_search,
        refine_iterations=PlannerConfig.refine_iterations if args.refine is None else args.refine, seed=args.seed,
    )
    plan = Planner(model, workspace, cfg).plan(args.start, args.goal)
    info = {"model": str(args.model), "method": meta.get("method"), "config": asdict(cfg)}
    files = write_plan(plan, args.out, workspace, info)
    if plan.ok:
        print(f"plan: {len(plan.actions)} steps, predicted final error {plan.error_mm:.2f} mm -> {files[0]}, .csv, .png")
        return 0
    print(f"t42: plan not ok ({plan.status}): {plan.reason} -> {files[0]}", file=sys.stderr)
    return 1


def _cmd_peg_in_hole(args: argparse.Namespace) -> int:
    from t42_transfer.planning import peg_in_hole

    return peg_in_hole.main([a for a in args.rest if a != "--"] or ["--help"])


def _cmd_demo(args: argparse.Namespace) -> int:
    from t42_transfer.demo import run_demo

    return run_demo(output_dir(args.out), quick=args.quick, workers=args.workers)


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
    return up(args.config, only=only, stop_timeout_s=args.stop_timeout, namespace=args.namespace)


# ------------------------------------------------------------------------ parser


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="t42",
        description=(
            "t42: transfer learned dynamics models between Yale Model-T42 hands. "
            "Simulate hands, collect random-policy data, and move trajectories in and out of rosbag2 bags."
        ),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = commands.add_parser("demo", help="run the main job end to end on simulated hands")
    demo.add_argument("--quick", action="store_true", help="tiny sizes (about a minute), as CI runs it")
    demo.add_argument("--out", type=Path, default=Path("runs/demo"), help="output directory (default runs/demo)")
    demo.add_argument("--workers", type=int_arg(1), default=None, help="worker processes (default: all cores)")
    demo.set_defaults(func=_cmd_demo)

    exp = commands.add_parser(
        "experiment", help="run (or resume) a transfer experiment from a YAML config, then write its report"
    )
    exp.add_argument("config", type=Path, help="experiment YAML (see configs/)")
    exp.add_argument("--out", type=Path, default=Path("runs"), help="runs directory (default runs/)")
    exp.add_argument("--workers", type=int_arg(1), default=None,
                     help="worker processes (default: the config's, else all cores)")
    exp.add_argument("--no-report", action="store_true", help="skip the figures and report.md")
    exp.add_argument("--quiet", action="store_true", help="no progress bars")
    exp.set_defaults(func=_cmd_experiment)

    rep = commands.add_parser("report", help="figures and a Markdown report from an experiment run directory")
    rep.add_argument("run_dir", type=Path)
    rep.add_argument("--out", type=Path, default=None, help="output directory (default RUN_DIR/report)")
    rep.set_defaults(func=_cmd_report)

    plan = commands.add_parser(
        "plan", help="plan an open-loop action sequence to a goal with a model file (exit 1 when not ok)"
    )
    plan.add_argument("model", type=Path, help="model file (.safetensors)")
    plan.add_argument(
        "--start", type=float_arg(), nargs=4, required=True, metavar=("X", "Y", "LOAD1", "LOAD2"), help="start state (mm, raw loads)"
    )
    plan.add_argument("--goal", type=float_arg(), nargs=2, required=True, metavar=("X", "Y"), help="goal object position (mm)")
    plan.add_argument("--horizon", type=int_arg(1, MAX_HORIZON), default=100, help="steps of 0.1 s (default 100)")
    plan.add_argument("--samples", type=int_arg(1, MAX_SAMPLES), default=None,
                      help="sequences sampled per round (default: PlannerConfig's)")
    plan.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    plan.add_argument("--sampler", choices=("piecewise", "uniform", "discrete"), default="piecewise")
    plan.add_argument("--tolerance", type=float_arg(0, low_open=True), default=2.0, help="predicted error that reaches the goal (mm, default 2)")
    plan.add_argument("--horizon-search", action="store_true", help="return the shortest sequence reaching the goal")
    plan.add_argument("--refine", type=int_arg(0, MAX_REFINE), default=None,
                      help="cross-entropy refinement rounds after the first draw (default: PlannerConfig's)")
    plan.add_argument(
        "--workspace", type=Path, nargs="+", default=None, help="bags of the training data (default: stored in the model file)"
    )
    plan.add_argument("--out", type=Path, required=True, help="directory for plan.json, plan.csv, plan.png")
    plan.set_defaults(func=_cmd_plan)

    peg = commands.add_parser(
        "peg-in-hole", help="plan with saved models, execute open loop on the simulated target hand, success vs distance",
        add_help=False,
    )
    peg.add_argument("rest", nargs=argparse.REMAINDER, help="arguments of the evaluation (see `t42 peg-in-hole --help`)")
    peg.set_defaults(func=_cmd_peg_in_hole)

    sim = commands.add_parser("sim", help="simulated hands").add_subparsers(dest="sim_command", metavar="ACTION")
    col = sim.add_parser("collect", help="collect random-policy episodes into a rosbag2 bag")
    col.add_argument("--hand", default="source", help="source, target or family-<seed> (default source)")
    col.add_argument("--episodes", type=int_arg(1), default=300, help="episodes (paper: 300)")
    col.add_argument("--steps", type=int_arg(1), default=1000, help="max steps per episode at 10 Hz (paper: 1000)")
    col.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    col.add_argument("--workers", type=int_arg(1), default=None, help="worker processes (default: all cores)")
    col.add_argument("--hold-max", type=int_arg(1), default=5, help="random actions are held 1..N steps (default 5)")
    col.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    col.add_argument("--quiet", action="store_true", help="no progress bar")
    col.add_argument("--out", type=Path, required=True, help="bag directory to create")
    col.set_defaults(func=_cmd_sim_collect)

    cmp_ = sim.add_parser("compare-real", help="replay the real T42 test paths' actions on simulated hands")
    cmp_.add_argument(
        "--real-dir", type=Path, default=None, help="folder of the public T42 pickles (default: $T42_REAL_DATA or ../shared/data/t42_real)"
    )
    cmp_.add_argument("--hands", nargs="+", default=["source", "target"])
    cmp_.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    cmp_.add_argument("--out-dir", type=Path, default=None, help="write table (md, json) and figure here")
    cmp_.set_defaults(func=_cmd_sim_compare_real)

    bag = commands.add_parser("bag", help="rosbag2 bags").add_subparsers(dest="bag_command", metavar="ACTION")
    info = bag.add_parser("info", help="summarise a bag: topics, counts, episodes, metadata")
    info.add_argument("bag", type=Path)
    info.add_argument("--json", action="store_true")
    info.add_argument("--verify", action="store_true",
                      help="check metadata.yaml's message counts, start time and duration against the data; "
                           "exit 1 on a mismatch")
    info.set_defaults(func=_cmd_bag_info)
    imp = bag.add_parser("import-t42", help="convert a public T42 test-path pickle into a bag")
    imp.add_argument("pickle", type=Path)
    imp.add_argument("out", type=Path, help="bag directory to create")
    imp.set_defaults(func=_cmd_bag_import_t42)
    rep = bag.add_parser("repair", help="rewrite a bag left by a killed recorder (originals kept as *.orig)")
    rep.add_argument("bag", type=Path, help="bag directory")
    rep.set_defaults(func=_cmd_bag_repair)
    play = bag.add_parser("play", help="publish a bag's messages on their topics over ROS 2 (rclpy), as ros2 bag play")
    play.add_argument("bag", type=Path, help="bag directory")
    play.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1.0)")
    play.add_argument("--topics", nargs="+", default=None, help="play only these topics (as named in the bag)")
    play.add_argument("--loop", action="store_true", help="play again from the start, until Ctrl-C")
    play.add_argument("--clock", type=float, nargs="?", const=40.0, default=0.0, metavar="HZ",
                      help="publish /clock from the bag's time at HZ (40 when HZ is not given), as ros2 bag play --clock")
    play.add_argument("--wait-subscribers", type=float_arg(0, 3600), default=2.0, metavar="S",
                      help="wait up to S seconds for every topic's subscriber to match before starting (default 2)")
    play.set_defaults(func=_cmd_bag_play)

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
    up.add_argument("--stop-timeout", type=float_arg(0, 3600, low_open=True), default=5.0, help="seconds per stop signal (default 5)")
    up.add_argument("--namespace", type=_namespace, default="", help="run every node under this ROS namespace (e.g. /left)")
    up.set_defaults(func=_cmd_up)
    return parser


def _namespace(text: str) -> str:
    if not ROS_NAMESPACE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected a ROS namespace such as /left (letters, digits, _ and /; "
                                         f"no token starting with a digit), got {text[:40]!r}")
    return text


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["peg-in-hole"]:
        # Its own parser (shared with the module entry point) takes every argument, --help included.
        argv = ["peg-in-hole", "--", *argv[1:]] if argv[1:] else argv
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        # `t42` or `t42 sim` alone: show the help of the level reached.
        chosen = [a for a in (args.command, getattr(args, "sim_command", None), getattr(args, "bag_command", None)) if a]
        parser.parse_args([*chosen, "--help"]) if chosen else parser.print_help()
        return 0
    try:
        return func(args)
    except OSError as err:  # a path the user gave: missing, unreadable, a directory where a file belongs, ...
        message = _os_error(err)
    except ValueError as err:  # DataFileError and CheckpointError included
        message = str(err)
    print(f"t42: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
