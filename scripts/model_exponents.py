#!/usr/bin/env python3
"""Finite-time Lyapunov exponents of saved models, after a burn-in and in normalised coordinates.

Every model runs open loop along the same test episodes (collected on a simulated
hand under a chosen policy, or read from a bag); the maximal exponent of each orbit
is averaged over the steps after ``--burn-in``, with lengths measured in units of the
FIRST model's stored state std (give the source model first, so that all models are
measured alike).  The raw-unit estimate without burn-in (what experiments report as
``lyapunov_mean``) is printed beside it.

    .venv/bin/python scripts/model_exponents.py --hand target_abrupt --policy sustained \\
        runs/sources/source-*.safetensors runs/<experiment>/models/naive-*.safetensors
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from t42_transfer.data.bag import read_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.lyapunov import model_lyapunov, state_scales
from t42_transfer.hand.collect import POLICIES, collect
from t42_transfer.models.checkpoint import load_model


def _label(path: Path) -> str:
    """``run/file`` for a cell model of an experiment run (``run/models/file``), else the file name."""
    return f"{path.parent.parent.name}/{path.name}" if path.parent.name == "models" else path.name


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="model files; the first one's state std sets the units")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--hand", default="target_abrupt", help="simulated hand of the test episodes")
    source.add_argument("--bag", type=Path, help="read the test episodes from this bag instead")
    parser.add_argument("--policy", choices=sorted(POLICIES), default="sustained")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--steps", type=int, default=300, help="orbit length, burn-in included")
    parser.add_argument("--burn-in", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1000, help="collection seed (keep it apart from training data)")
    args = parser.parse_args(argv)
    if not 0 <= args.burn_in < args.steps:
        parser.error("need 0 <= --burn-in < --steps")

    torch.set_num_threads(1)
    if args.bag:
        data = read_bag(args.bag)
    else:
        data, _ = collect(args.hand, args.episodes, args.steps, seed=args.seed, policy=POLICIES[args.policy](),
                          workers=1, progress=False)
    kept = TrajectorySet([t for t in data if len(t) > args.burn_in], hand=data.hand)
    if not len(kept):
        print(f"no test episode is longer than the burn-in ({args.burn_in} steps)", file=sys.stderr)
        return 1
    models = [load_model(path) for path in args.models]
    scales = state_scales(models[0][0])
    print(f"{len(kept)} of {len(data)} test episodes longer than the burn-in; orbits of up to {args.steps} steps, "
          f"burn-in {args.burn_in}; units: state std {np.round(scales, 3).tolist()} of {args.models[0].name}")
    print("| model | method | normalised, burn-in: mean | median | p10 | p90 | raw units, no burn-in: mean |")
    print("|---|---|---|---|---|---|---|")
    for path, (model, meta) in zip(args.models, models, strict=True):
        exponents = model_lyapunov(model, kept, steps=args.steps, burn_in=args.burn_in, scales=scales).numpy()
        raw = model_lyapunov(model, kept, steps=args.steps).numpy()
        p10, median, p90 = np.percentile(exponents, [10, 50, 90])
        print(f"| {_label(path)} | {meta.get('method', '?')} | {exponents.mean():.4f} | {median:.4f} | {p10:.4f} "
              f"| {p90:.4f} | {raw.mean():.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
