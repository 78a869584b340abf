"""``t42 model``: model files (import the paper authors' own saved models)."""

from __future__ import annotations

import argparse
from pathlib import Path

from t42_transfer.cli.args import existing_file, float_arg, new_output


def _cmd_import_authors(args: argparse.Namespace) -> int:
    from t42_transfer.models.authors import save_authors_model

    source = existing_file(args.pkl)
    new_output(args.out)
    saved, converted = save_authors_model(source, args.out, negate_actions=args.negate_actions, gamma=args.gamma,
                                          alpha=args.alpha)
    weights = "" if converted.alpha is None else f", alpha {converted.alpha:g}"
    weights += "" if converted.gamma is None else f", gamma {converted.gamma:g}"
    print(f"{source.name}: the authors' {converted.family} ({converted.task}{weights}"
          f"{', actions negated' if args.negate_actions else ''}) -> {saved} ({converted.model.kind})")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    model = commands.add_parser("model", help="model files").add_subparsers(dest="model_command", metavar="ACTION")
    imp = model.add_parser(
        "import-authors", help="convert one of the paper authors' saved models (legacy torch pickle) to a model file",
        description="Read an authors' legacy torch file without running its code and write a project model file "
                    "whose metadata names the file's sha256 and the authors' family.",
    )
    imp.add_argument("pkl", type=Path, metavar="PKL", help="the authors' file (e.g. real_B_heldout0.1_1.pkl)")
    imp.add_argument("out", type=Path, metavar="OUT.safetensors", help="model file to create (never overwritten)")
    imp.add_argument("--negate-actions", action="store_true",
                     help="negate the actions inside the model, as the authors did for every model run on hand A")
    imp.add_argument("--alpha", type=float_arg(), default=None,
                     help="weight of the residual (residual families; default: the file's coeff, 1)")
    imp.add_argument("--gamma", type=float_arg(0.0, 1.0), default=None,
                     help="decay of the cumulative residual (default 0.993, the authors' last rollout code)")
    imp.set_defaults(func=_cmd_import_authors)
