"""``t42 experiment`` and ``t42 report``: run a transfer experiment, and report on a run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from t42_transfer.cli.args import existing_dir, existing_file, int_arg, output_dir


def _scheduler_arg(text: str) -> str:
    """argparse type for ``--scheduler`` (checked without importing Dask)."""
    from t42_transfer.evaluation.cluster import check_scheduler

    try:
        return check_scheduler(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _cmd_experiment(args: argparse.Namespace) -> int:
    """Run the experiment; cells that failed (the others kept) end in one error and exit code 1, Ctrl-C in one line
    and 130, each saying that the same command resumes the run."""
    import dataclasses

    from t42_transfer.evaluation.cluster import CellsFailed
    from t42_transfer.evaluation.experiment import run_experiment
    from t42_transfer.evaluation.experiment_config import load_config
    from t42_transfer.evaluation.report import write_report

    if args.workers is not None and args.scheduler is not None:
        args.parser.error("--workers or --scheduler, not both: on Dask the cluster's workers run the cells")
    cfg = load_config(args.config)
    if args.workers is not None:
        cfg = dataclasses.replace(cfg, workers=args.workers)
    output_dir(args.out)
    run_dir = args.out / cfg.name
    try:
        rows = run_experiment(cfg, args.out, progress=not args.quiet, scheduler=args.scheduler)
    except CellsFailed as err:
        print(f"t42: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"t42: interrupted: the cells that finished are kept in {run_dir / 'cells'}; the same command "
              "resumes the run", file=sys.stderr)
        return 130
    print(f"{len(rows)} rows (cells and the hold-still baseline) -> {run_dir / 'results.csv'}")
    if not args.no_report:
        print(f"report: {write_report(run_dir)}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from t42_transfer.evaluation.report import write_report

    existing_file(existing_dir(args.run_dir) / "results.json")
    print(f"report: {write_report(args.run_dir, args.out and output_dir(args.out))}")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    exp = commands.add_parser(
        "experiment", help="run (or resume) a transfer experiment from a YAML config, then write its report"
    )
    exp.add_argument("config", type=Path, help="experiment YAML (see configs/)")
    exp.add_argument("--out", type=Path, default=Path("runs"), help="runs directory (default runs/)")
    exp.add_argument("--workers", type=int_arg(1), default=None,
                     help="worker processes (default: the config's, else all cores)")
    exp.add_argument("--scheduler", type=_scheduler_arg, default=None, metavar="ADDRESS",
                     help="run the cells on Dask: local:N (N worker processes here) or a scheduler's address "
                          "(tcp://host:8786; the workers need this project and the run directory at the same path)")
    exp.add_argument("--no-report", action="store_true", help="skip the figures and report.md")
    exp.add_argument("--quiet", action="store_true", help="no progress bars")
    exp.set_defaults(func=_cmd_experiment, parser=exp)

    rep = commands.add_parser("report", help="figures and a Markdown report from an experiment run directory")
    rep.add_argument("run_dir", type=Path)
    rep.add_argument("--out", type=Path, default=None, help="output directory (default RUN_DIR/report)")
    rep.set_defaults(func=_cmd_report)
