"""``t42 evaluate``: score saved models on a data set's paths, beside hold-still (table and JSON)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from t42_transfer.cli.args import SEED_MAX, existing_file, int_arg, new_output, output_dir

PAPER_NOTE = ("The paper's numbers were taken with dropout on (the authors' scripts never call .eval(); one draw "
              "per model and path): compare them with dropout-on rows (--dropout-draws K).")


def paths_arg(text: str) -> tuple[int, ...]:
    """``0,1,2,3``: distinct path numbers."""
    try:
        numbers = tuple(int(part) for part in text.split(","))
    except ValueError:
        numbers = ()
    if not numbers or min(numbers) < 0 or len(set(numbers)) != len(numbers) or len(numbers) > 100_000:
        raise argparse.ArgumentTypeError(f"expected distinct path numbers such as 0,1,2,3, got {text[:40]!r}")
    return numbers


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from t42_transfer.evaluation.evaluate import evaluate_models, table
    from t42_transfer.evaluation.experiment import load_spec
    from t42_transfer.evaluation.experiment_config import parse_data_spec
    from t42_transfer.evaluation.model_files import check_action_unit, load_model_file

    spec = parse_data_spec(args.on, "--on")
    for model in args.models:
        existing_file(model)
    if args.json is not None:
        new_output(args.json)
    models = []
    for path in args.models:
        model, meta = load_model_file(path, args.negate_actions)
        check_action_unit(path, meta, spec.unit_rad(), args.on)
        models.append((str(path), model))
    data = load_spec(spec, output_dir(args.cache), progress=not args.quiet).data
    chosen = args.paths if args.paths is not None else tuple(range(len(data)))
    missing = [i for i in chosen if i >= len(data)]
    if missing:
        raise ValueError(f"--paths: {args.on} has {len(data)} paths (0 to {len(data) - 1}), not {missing[0]}")
    episodes = data.subset(chosen)
    result = evaluate_models(models, episodes, indices=chosen, dropout_draws=args.dropout_draws, seed=args.seed,
                             definition=args.definition, progress=not args.quiet)
    print(f"on {args.on}: paths {','.join(map(str, chosen))} ({result.steps} steps), {args.definition} definition")
    short = [path.name for path in args.models]  # the file's name, its path where two names are alike
    print(table(result, [str(path) if short.count(path.name) > 1 else path.name for path in args.models]))
    print(PAPER_NOTE)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.as_json(), indent=1) + "\n")
        print(f"-> {args.json}")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    ev = commands.add_parser(
        "evaluate", help="score saved models on a data set's paths beside hold-still (divergence at 4 and 10 mm, MSE)",
        description="Roll each model out open loop on each path from its first true state with its recorded actions; "
                    "report the steps before the x,y error first exceeds 4 and 10 mm and the position MSE, per path "
                    "and overall, beside holding still. " + PAPER_NOTE,
    )
    ev.add_argument("models", type=Path, nargs="+", metavar="MODEL",
                    help="a model file (.safetensors) or a paper authors' file (.pkl, imported on the fly)")
    ev.add_argument("--on", required=True, metavar="SPEC",
                    help="the data, as an experiment config's data spec: e.g. '{real: A, negate_actions: true}'")
    ev.add_argument("--paths", type=paths_arg, default=None, metavar="I,J,...",
                    help="path numbers in the data set (default: all)")
    ev.add_argument("--dropout-draws", type=int_arg(1, 1000), default=None, metavar="K",
                    help="also roll out with dropout on, K draws per path, and report their mean (as the paper's "
                         "numbers were taken); the JSON's models then hold the dropout-on numbers and its "
                         "dropout_off the others")
    ev.add_argument("--seed", type=int_arg(0, SEED_MAX), default=0, help="seed of the dropout draws (default 0)")
    ev.add_argument("--definition", choices=("paper", "authors"), default="paper",
                    help="paper: steps before the first crossing, MSE of dx^2+dy^2; authors: the crossing step counts "
                         "(one more), MSE halved (their scripts)")
    ev.add_argument("--negate-actions", action="store_true",
                    help="negate the actions inside authors' models (as they did for models run on hand A)")
    ev.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the numbers as JSON (new file)")
    ev.add_argument("--cache", type=Path, default=Path("runs") / "data",
                    help="where simulated data sets are kept (default runs/data, as t42 experiment's)")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_cmd_evaluate)
