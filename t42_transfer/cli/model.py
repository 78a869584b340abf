"""``t42 model``: model files (train a source model on recorded bags; import the paper authors' own saved models)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from t42_transfer.cli.args import bags_in, existing_file, float_arg, int_arg, new_output
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, MAX_ACTION_UNIT_RAD, same_action_unit


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


def _declared(bag: Path) -> float | None:
    """The action unit ``bag`` declares, or None for a bag that declares none or cannot be read (reading it says
    why)."""
    from t42_transfer.data.bag import declared_bag_unit
    from t42_transfer.data.errors import DataFileError

    try:
        return declared_bag_unit(bag)
    except DataFileError:
        return None


def _cmd_train(args: argparse.Namespace) -> int:
    import torch

    from t42_transfer.models.checkpoint import save_model
    from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
    from t42_transfer.planning.workspace import Workspace
    from t42_transfer.transfer.online import read_target

    bags = bags_in(args.bags)
    new_output(args.out)
    cfg = TrainConfig(seed=args.seed, **({} if args.epochs is None else {"epochs": args.epochs}))
    unit = args.action_unit_rad
    if unit is None:
        declared: list[float] = []
        for found in (u for bag in bags if (u := _declared(bag)) is not None):
            if not any(same_action_unit(found, u) for u in declared):
                declared.append(found)
        declared = sorted(declared) or [ACTION_UNIT_RAD]
        if len(declared) > 1:
            raise ValueError(f"the bags declare different action units ({', '.join(f'{u:.4g}' for u in declared)} "
                             "rad): a model learns one; name it with --action-unit-rad")
        unit = declared[0]
    target = read_target(bags, unit)
    for bag, why in target.skipped:
        print(f"t42: warning: skipped {bag}: {why}", file=sys.stderr)
    for note in target.notes:
        print(f"t42: warning: {note}", file=sys.stderr)
    data = target.data
    if not len(data):
        raise ValueError(f"no usable episode in {len(bags)} bag(s): nothing to train on")
    hands = sorted({t.hand for t in data if t.hand})
    if len(hands) > 1:
        raise ValueError(f"the bags hold episodes of {len(hands)} hands ({', '.join(hands)}): a source model is "
                         "one hand's; name that hand's bags only")
    torch.set_num_threads(1)  # the MLP and its batches are small: one thread is the fastest here
    model, report = train_transition_model(data, cfg, on_epoch=ProgressBar(), phase="source model")
    save_model(model, args.out, method="source", hyperparameters=dataclasses.asdict(cfg),
               data={"bags": [str(b.resolve()) for b in target.read], "source": data.fingerprint()},
               extra={"workspace": Workspace.from_trajectories(data).to_dict()}, action_unit_rad=unit)
    print(f"{len(data)} episodes ({data.num_transitions} transitions) of {len(target.read)} bag(s), hand "
          f"{data.hand or 'unnamed'}: {report.epochs_run} epochs (best {report.best_epoch + 1}; {report.validation}) "
          f"-> {args.out}")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    model = commands.add_parser("model", help="model files").add_subparsers(dest="model_command", metavar="ACTION")
    train = model.add_parser(
        "train", help="train a source model on a hand's recorded bags (the transfer server's source_model)",
        description="Fit the paper's transition model to the episodes of recorded bags (as the transfer server reads "
                    "them: each ended at its first drop, split at late steps) and write a model file that a transfer "
                    "server can start from: record the source hand, train on it here, then record the target hand "
                    "and transfer.",
    )
    train.add_argument("bags", type=Path, nargs="+", metavar="BAG",
                       help="a bag directory, or a directory of bags (a recorder's out_dir)")
    train.add_argument("--out", type=Path, required=True, metavar="OUT.safetensors",
                       help="model file to create (never overwritten)")
    train.add_argument("--epochs", type=int_arg(1), default=None,
                       help="most epochs (default: the training default, as experiments train); early stopping on "
                            "a held-out tenth of the episodes ends sooner")
    train.add_argument("--seed", type=int_arg(0), default=0, help="seed of the split and the initial weights")
    train.add_argument("--action-unit-rad", type=float_arg(0.0, MAX_ACTION_UNIT_RAD, low_open=True),
                       default=None, metavar="RAD",
                       help=f"the actuator step of an action of 1 that the model learns in, as the explorer's "
                            f"action_unit_rad (default: the unit the bags declare, else the suite's "
                            f"{ACTION_UNIT_RAD:g}; the paper authors' is {AUTHORS_ACTION_UNIT_RAD:.5f}); a bag "
                            "stepping further than 1.5 of it is skipped")
    train.set_defaults(func=_cmd_train)
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
