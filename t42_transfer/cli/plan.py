"""``t42 plan`` and ``t42 peg-in-hole``: open-loop plans from a model file, and their evaluation on a simulated hand."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from t42_transfer.cli.args import (
    SEED_MAX,
    existing_dir,
    existing_file,
    float_arg,
    int_arg,
    output_dir,
)
from t42_transfer.conventions import (
    MAX_PLAN_HORIZON,
    MAX_PLAN_SAMPLES,
    MAX_REFINE,
    MAX_THREADS,
    MAX_TRIALS,
    PLAN_LENGTHS,
)


def _cmd_plan(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from t42_transfer.models.checkpoint import UNIT_KEY, load_model
    from t42_transfer.planning import Planner, PlannerConfig, Workspace
    from t42_transfer.planning.export import write_plan

    cfg = PlannerConfig(  # first: its checks (samples x horizon among them) come before anything is loaded
        samples=PlannerConfig.samples if args.samples is None else args.samples, horizon=args.horizon,
        sampler=args.sampler or PlannerConfig.sampler, tolerance_mm=args.tolerance, horizon_search=args.horizon_search,
        refine_iterations=PlannerConfig.refine_iterations if args.refine is None else args.refine, seed=args.seed,
    )
    for path in (args.workspace or []):
        existing_dir(path)
    output_dir(args.out)
    model, meta = load_model(existing_file(args.model))
    workspace = Workspace.for_planning(args.workspace, meta, args.model)
    plan = Planner(model, workspace, cfg).plan(args.start, args.goal)
    info = {"model": str(args.model), "method": meta.get("method"), "action_unit_rad": meta[UNIT_KEY],
            "config": asdict(cfg)}
    files = write_plan(plan, args.out, workspace, info)
    if plan.ok:
        print(f"plan: {len(plan.actions)} steps, predicted final error {plan.error_mm:.2f} mm "
              f"-> {files[0]}, .csv, .png")
        return 0
    print(f"t42: plan not ok ({plan.status}): {plan.reason} -> {files[0]}", file=sys.stderr)
    return 1


def _cmd_peg_in_hole(args: argparse.Namespace) -> int:
    from t42_transfer.evaluation.peg_in_hole_report import report_from_json

    if args.from_json is not None:
        if args.models:
            args.parser.error("--from-json takes no model files")
        return report_from_json(existing_file(args.from_json))
    if not args.models or args.out is None:
        args.parser.error("the model files and --out are required (or --from-json JSON)")
    return _run_peg_in_hole(args)


def _run_peg_in_hole(args: argparse.Namespace) -> int:
    """Every argument is checked before a model is loaded or a goal made; then the evaluation runs."""
    import json
    import shlex
    from dataclasses import asdict, replace

    import torch

    from t42_transfer.evaluation.peg_in_hole import (
        BASELINES,
        PegInHoleConfig,
        contenders_for,
        evaluate,
        load_models,
        model_spec,
    )
    from t42_transfer.evaluation.peg_in_hole_report import write_report
    from t42_transfer.hand.params import variant
    from t42_transfer.planning import PlannerConfig, Workspace

    # The defaults are the configs' own, filled in here: the parser is built without importing torch or MuJoCo.
    for name, default in (("distances", list(PegInHoleConfig.distances)), ("trials", PegInHoleConfig.trials),
                          ("tolerances", list(PegInHoleConfig.tolerances_mm)),
                          ("plan_length", PegInHoleConfig.plan_length), ("samples", PlannerConfig.samples),
                          ("refine", PlannerConfig.refine_iterations), ("horizon", PlannerConfig.horizon)):
        if getattr(args, name) is None:
            setattr(args, name, default)
    # Everything the user gave is checked before a model is loaded or a goal made; the longest plan a goal
    # distance asks for is sized as the planner will size it.
    PlannerConfig(samples=args.samples, horizon=max(args.horizon, *args.distances))
    variant(args.hand)
    names = [model_spec(spec)[0] for spec in args.models]
    if twice := sorted({n for n in [*names, *BASELINES] if [*names, *BASELINES].count(n) > 1}):
        args.parser.error(f"model name(s) {twice} given twice or a baseline's (the baselines are {list(BASELINES)});"
                          " name each model file NAME=PATH")
    for spec in args.models:
        existing_file(model_spec(spec)[1])
    for name in [*args.ensemble, *(args.variants_of or [])]:
        if name not in names:
            args.parser.error(f"{name!r} names no model; the models are {names}")
    if args.ensemble and len(args.ensemble) < 2:
        args.parser.error("--ensemble needs at least two models")
    for bag in args.workspace or []:
        existing_dir(bag)
    output_dir(args.out)
    planner = replace(PegInHoleConfig().planner, samples=args.samples, refine_iterations=args.refine,
                      horizon=args.horizon, warm_start=args.warm_start)
    try:
        cfg = PegInHoleConfig(tuple(args.distances), args.trials, tuple(args.tolerances), hand=args.hand,
                              plan_length=args.plan_length, replan_every=args.replan_every, planner=planner,
                              seed=args.seed)
    except ValueError as err:
        args.parser.error(str(err))
    if args.mpc and cfg.plan_length != "fixed":
        args.parser.error("--mpc needs --plan-length fixed")
    torch.set_num_threads(args.threads)

    models, first_meta = load_models(args.models)
    try:
        workspace = Workspace.for_planning(args.workspace, first_meta, args.models[0])
    except ValueError as err:
        args.parser.error(str(err))
    contenders = contenders_for(models, planner, args.mpc, args.dropout, args.ensemble, args.variants_of, args.risk)
    rows, trials = evaluate(contenders, workspace, cfg, progress=not args.quiet)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {
        "command": shlex.join(["t42", *args.argv]),
        "config": asdict(cfg),
        "contenders": [{"name": c.name, "baseline": c.baseline, "models": len(c.models),
                        "planner": asdict(c.planner) if c.planner else None, "replan_every": c.replan_every}
                       for c in contenders],
        "workspace": workspace.to_dict(),
        "rows": [asdict(r) for r in rows],
        "trials": [asdict(t) for t in trials],
    }
    (args.out / "peg_in_hole.json").write_text(json.dumps(report, indent=2) + "\n")
    return write_report(args.out, rows, trials, cfg.tolerances_mm)


def add_commands(commands: argparse._SubParsersAction) -> None:
    plan = commands.add_parser(
        "plan", help="plan an open-loop action sequence to a goal with a model file (exit 1 when not ok)"
    )
    plan.add_argument("model", type=Path, help="model file (.safetensors)")
    plan.add_argument(
        "--start", type=float_arg(), nargs=4, required=True, metavar=("X", "Y", "LOAD1", "LOAD2"),
                                  help="start state (mm, raw loads)"
    )
    plan.add_argument("--goal", type=float_arg(), nargs=2, required=True, metavar=("X", "Y"),
                      help="goal object position (mm)")
    plan.add_argument("--horizon", type=int_arg(1, MAX_PLAN_HORIZON), default=100, help="steps of 0.1 s (default 100)")
    plan.add_argument("--samples", type=int_arg(1, MAX_PLAN_SAMPLES), default=None,
                      help="sequences sampled per round (default: PlannerConfig's)")
    plan.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    plan.add_argument("--sampler", choices=("gaussian", "piecewise", "uniform", "discrete"), default=None,
                      help="first draw's sampler (default: PlannerConfig's)")
    plan.add_argument("--tolerance", type=float_arg(0, low_open=True), default=2.0,
                      help="predicted error that reaches the goal (mm, default 2)")
    plan.add_argument("--horizon-search", action="store_true", help="return the shortest sequence reaching the goal")
    plan.add_argument("--refine", type=int_arg(0, MAX_REFINE), default=None,
                      help="cross-entropy refinement rounds after the first draw (default: PlannerConfig's)")
    plan.add_argument(
        "--workspace", type=Path, nargs="+", default=None,
        help="bags of the training data (default: stored in the model file)"
    )
    plan.add_argument("--out", type=Path, required=True, help="directory for plan.json, plan.csv, plan.png")
    plan.set_defaults(func=_cmd_plan)

    peg = commands.add_parser(
        "peg-in-hole",
        help="plan with saved models, execute open loop on the simulated target hand, success vs distance",
        description="Peg-in-hole: plan with a model, execute on the true (simulated) target hand, and judge honestly.",
        epilog="t42 peg-in-hole --from-json DIR/peg_in_hole.json rebuilds its tables and figure",
    )
    peg.add_argument("models", nargs="*", help="model files, PATH or NAME=PATH")
    peg.add_argument("--from-json", type=Path, default=None, metavar="JSON",
                     help="rebuild the .md and .png of one stored peg_in_hole.json (no models)")
    peg.add_argument(
        "--workspace", nargs="+", type=Path, default=None,
        help="bags whose states define the trained workspace (default: the one the first model file stores)"
    )
    peg.add_argument("--out", type=Path, default=None, help="directory for peg_in_hole.{json,md,png}")
    # (defaults None: the configs' own, filled in by _run_peg_in_hole, so building the parser loads no torch)
    peg.add_argument("--distances", nargs="+", type=int_arg(1, MAX_PLAN_HORIZON), default=None,
                     help="goal distances in steps (default: PegInHoleConfig's)")
    peg.add_argument("--trials", type=int_arg(1, MAX_TRIALS), default=None,
                     help="trials per distance (default: PegInHoleConfig's)")
    peg.add_argument("--tolerances", nargs="+", type=float_arg(0, low_open=True), default=None,
                     help="success tolerances (mm); the first is the paper's (default: PegInHoleConfig's)")
    peg.add_argument("--plan-length", choices=PLAN_LENGTHS, default=None,
                        help="fixed: plans of exactly n steps (default); "
                             "search: the shortest predicted to reach the goal")
    peg.add_argument("--replan-every", type=int_arg(0, MAX_PLAN_HORIZON), default=0,
                        help="0: open loop (default); k: every model replans from the measured state every k steps")
    peg.add_argument("--mpc", type=int_arg(0, MAX_PLAN_HORIZON), default=0,
                        help="also evaluate each model replanning every K steps, beside open loop")
    peg.add_argument("--warm-start", action="store_true",
                     help="each replan's search starts from the rest of the plan it replaces")
    peg.add_argument("--dropout", type=int_arg(0, 1000), default=0,
                        help="also evaluate each model with M dropout samples per sequence, "
                             "risk-averse (same rollouts)")
    peg.add_argument("--ensemble", nargs="+", default=(), metavar="NAME",
                        help="also evaluate an ensemble of these models (their names), risk-averse (same rollouts)")
    peg.add_argument("--risk", type=float_arg(0), default=1.0, help="weight of the spread: mean + risk * std")
    peg.add_argument("--variants-of", nargs="+", default=None, metavar="NAME",
                        help="models that get the --mpc and --dropout variants (default: all)")
    peg.add_argument("--samples", type=int_arg(1, MAX_PLAN_SAMPLES), default=None,
                        help="sequences sampled per round (default: PlannerConfig's)")
    peg.add_argument("--refine", type=int_arg(0, 100), default=None,
                        help="cross-entropy rounds after the first draw (default: PlannerConfig's)")
    peg.add_argument("--horizon", type=int_arg(1, MAX_PLAN_HORIZON), default=None,
                        help="longest plan with --plan-length search (default: PlannerConfig's)")
    peg.add_argument("--hand", default="target")
    peg.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0)
    peg.add_argument("--threads", type=int_arg(1, MAX_THREADS), default=1,
                        help="torch threads (default 1: robust on a busy machine)")
    peg.add_argument("--quiet", action="store_true")
    peg.set_defaults(func=_cmd_peg_in_hole, parser=peg)
