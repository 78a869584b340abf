#!/usr/bin/env python3
"""The paper's Lyapunov bound term by term for every cell model of a stored run, beside the measured exponent.

Each cell's model is analysed on that cell's own training and test episodes (``evaluation/lyapunov_bound.py``): ``r``,
``epsilon``, ``c``, ``b``, the ``log(1 + b N ||J^-1||)`` term and ``lambda_f`` of the reference model (the stand-in
for the true map: give a model trained on dense data of the target hand), the bound, and the model's own exponent
after the burn-in, all in units of the reference's stored state std.  Cells whose model file is not kept, and
models with hidden state beyond the hand state (cumulative residual), are listed as skipped with the reason.

    .venv/bin/python scripts/lyapunov_bound.py docs/experiments/real_dense_b_to_a --reference A_own.safetensors \\
        --json docs/experiments/lyapunov/bound_real_dense_b_to_a.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from t42_transfer.evaluation.experiment import Cell, cell_model_file, data_cache, load_side, load_test, target_split
from t42_transfer.evaluation.experiment_config import load_config
from t42_transfer.evaluation.lyapunov import state_scales
from t42_transfer.evaluation.lyapunov_bound import bound_terms, measured_exponent
from t42_transfer.evaluation.stats import spearman
from t42_transfer.models.checkpoint import load_model

SHOWN = ("r", "epsilon", "c_model", "c_reference", "b", "inverse_norm", "log_term", "reference_exponent", "bound",
         "measured")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a stored experiment run (config.yaml, results.json, models/)")
    parser.add_argument("--reference", type=Path, required=True, help="the stand-in for the target hand's true map")
    parser.add_argument("--methods", help="comma-separated methods (default: every method of the run)")
    parser.add_argument("--steps", type=int, default=300, help="orbit length, burn-in included")
    parser.add_argument("--burn-in", type=int, default=50)
    parser.add_argument("--pairs", type=int, default=2000, help="state pairs that estimate c")
    parser.add_argument("--json", type=Path, help="write every cell's terms here")
    args = parser.parse_args(argv)
    if not 0 <= args.burn_in < args.steps:
        parser.error("need 0 <= --burn-in < --steps")
    for path in (args.run_dir / "config.yaml", args.run_dir / "results.json", args.reference):
        if not path.is_file():
            parser.error(f"{path} is not a file")

    torch.set_num_threads(1)
    cfg = load_config(args.run_dir / "config.yaml")
    source, target = (load_side(cfg, side, data_cache(args.run_dir)) for side in ("source", "target"))
    test_set = load_test(cfg, data_cache(args.run_dir))
    reference, reference_meta = load_model(args.reference)
    scales = state_scales(reference)
    wanted = None if args.methods is None else set(args.methods.split(","))
    rows = json.loads((args.run_dir / "results.json").read_text())["rows"]
    cells = [Cell(r["method"], next(a for a in cfg.amounts if float(a) == float(r["amount"])), r["seed"])
             for r in rows if r["method"] != "hold_still" and (wanted is None or r["method"] in wanted)]
    print(f"{len(cells)} cells of {args.run_dir.name}; reference {args.reference.name} "
          f"({reference_meta.get('method', '?')}); units: its state std {np.round(scales, 3).tolist()}; "
          f"orbits of up to {args.steps} steps, burn-in {args.burn_in}", flush=True)

    done, skipped, start = [], [], time.monotonic()
    for i, cell in enumerate(cells, 1):
        path = cell_model_file(cfg, args.run_dir, cell, source, target, test_set)
        if not path.exists():
            skipped.append({"cell": [cell.method, cell.amount, cell.seed], "why": "model file not kept"})
            continue
        train, test = target_split(cfg, target.data, cell, None if test_set is None else test_set.data)
        model = load_model(path)[0]
        try:
            terms = bound_terms(model, reference, train, test, scales, steps=args.steps, burn_in=args.burn_in,
                                pairs=args.pairs)
        except ValueError as err:  # no bound for it, but its exponent is measured alike
            measured, _ = measured_exponent(model, test, scales, steps=args.steps, burn_in=args.burn_in)
            skipped.append({"cell": [cell.method, cell.amount, cell.seed], "why": str(err), "measured": measured})
            continue
        done.append({"method": cell.method, "amount": cell.amount, "seed": cell.seed, **terms.as_dict()})
        print(f"  {i}/{len(cells)} {cell.method} {cell.amount} {cell.seed}: bound {terms.bound:.3f}, "
              f"measured {terms.measured:.4f} ({time.monotonic() - start:.0f} s)", file=sys.stderr, flush=True)

    why = defaultdict(int)
    for s in skipped:
        why[(s["cell"][0], s["why"].split(";")[0])] += 1
    for (method, reason), count in sorted(why.items()):
        print(f"skipped {count} cell(s) of {method}: {reason}")
    exponents = defaultdict(list)
    for row in done:
        exponents[row["method"]].append(row["measured"])
    for row in skipped:
        if "measured" in row:
            exponents[row["cell"][0]].append(row["measured"])
    print("\nmeasured exponent after the burn-in, every analysed cell (per 0.1 s step):\n")
    print("| method | cells | mean | median | min | max |\n|---|---:|---:|---:|---:|---:|")
    for method, values in exponents.items():
        print(f"| {method} | {len(values)} | {np.mean(values):.4f} | {np.median(values):.4f} | {np.min(values):.4f} "
              f"| {np.max(values):.4f} |")
    if not done:
        print("no cell analysed", file=sys.stderr)
        return 1
    print("\nmeans over seeds (normalised units; exponents per 0.1 s step):\n")
    print("| method | amount | cells | " + " | ".join(SHOWN) + " |")
    print("|---|---:|---:|" + "---:|" * len(SHOWN))
    groups = defaultdict(list)
    for row in done:
        groups[(row["method"], row["amount"])].append(row)
    for (method, amount), group in groups.items():
        means = [float(np.mean([g[k] for g in group])) for k in SHOWN]
        print(f"| {method} | {amount} | {len(group)} | " + " | ".join(f"{m:.4g}" for m in means) + " |")
    measured = np.array([r["measured"] for r in done])
    held = int(np.sum(measured <= np.array([r["bound"] for r in done])))
    print(f"\n{held} of {len(done)} cells have their measured exponent at or below the computed bound; "
          f"slack (bound - measured): median {np.median([r['bound'] - r['measured'] for r in done]):.3f}")
    for term in ("r", "epsilon", "b", "bound"):
        try:
            rho, p = spearman([r[term] for r in done], measured)
        except ValueError as err:  # too few cells, or all alike
            print(f"no rank correlation of {term} with the measured exponent: {err}")
            continue
        print(f"Spearman rank correlation of {term} with the measured exponent over the cells: {rho:.2f} (p = {p:.2g})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"run": args.run_dir.name, "reference": args.reference.name,
                                         "reference_sha256": reference_meta.get("authors_sha256"),
                                         "steps": args.steps, "burn_in": args.burn_in, "pairs": args.pairs,
                                         "scales": scales.tolist(), "cells": done, "skipped": skipped}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
