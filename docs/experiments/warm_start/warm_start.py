"""Warm-started replans against fresh ones, closed loop (replanning every 10 steps), on peg-in-hole goals.

Each setting plans every goal of ``PegInHoleConfig(seed=S)`` (30 goals at 20, 40 and 80 steps) with the given
models, replanning every 10 steps from the measured state on the true simulated hand; the baselines are left
out (they do not replan: ``t42 peg-in-hole`` gives them).  One JSON per seed, then the pooled table:

    .venv/bin/python docs/experiments/warm_start/warm_start.py --seed 2 \\
        --models runs/peg_in_hole_models/models/{naive_finetune,direct}-0.02-0-*.safetensors \\
        --out docs/experiments/warm_start/seed2.json
    .venv/bin/python docs/experiments/warm_start/warm_start.py --summarise docs/experiments/warm_start/seed*.json
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from dataclasses import asdict, replace
from pathlib import Path

import torch

from t42_transfer.evaluation.peg_in_hole import Contender, PegInHoleConfig, evaluate, load_models, make_goals
from t42_transfer.evaluation.stats import sign_test
from t42_transfer.planning import Workspace

REPLAN_EVERY = 10
SETTINGS = {"cold": {}, "warm": {"warm_start": True},
            "cold_refine4": {"refine_iterations": 4}, "warm_refine4": {"warm_start": True, "refine_iterations": 4}}
"""Name: PlannerConfig changes from the peg-in-hole default (300 rollouts a plan; refine 4: 150)."""
KEPT = ("model", "steps", "trial", "end_reason", "final_error_mm", "plans", "plan_seconds")
"""Each trial's fields in the JSON, beside its hits per tolerance."""


def run(seed: int, models: list[str], out: Path) -> None:
    torch.set_num_threads(1)
    loaded, meta = load_models(models)
    workspace = Workspace.for_planning(None, meta, models[0])
    cfg = PegInHoleConfig(seed=seed)
    goals = make_goals(cfg, workspace)
    contenders = [Contender(f"{name}+{setting}", (model,), planner=replace(cfg.planner, **changes),
                            replan_every=REPLAN_EVERY)
                  for name, model in loaded.items() for setting, changes in SETTINGS.items()]
    _, trials = evaluate(contenders, workspace, cfg, goals, progress=True, baselines=())
    kept = [{key: _rounded(asdict(t)[key]) for key in KEPT}
            | {"hits": {f"{tol:g}": t.success(tol) for tol in cfg.tolerances_mm}} for t in trials]
    out.write_text(json.dumps({"seed": seed, "models": models, "replan_every": REPLAN_EVERY, "settings": SETTINGS,
                               "trials": kept}) + "\n")


def _rounded(value: object) -> object:
    return round(value, 4) if isinstance(value, float) else value


def summarise(files: list[Path]) -> None:
    hits: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    seconds: dict[str, list[float]] = defaultdict(list)
    for file in files:
        for trial in json.loads(file.read_text())["trials"]:
            for tol, hit in trial["hits"].items():
                hits[trial["model"]][tol].append(hit)
            seconds[trial["model"]].append(trial["plan_seconds"] / max(1, trial["plans"]))
    print("| contender | goals | 10 mm | 4 mm | median ms a plan |\n|---|---:|---|---|---:|")
    for name, by_tol in hits.items():
        print(f"| {name} | {len(by_tol['10'])} | {sum(by_tol['10'])} | {sum(by_tol['4'])} | "
              f"{1000 * statistics.median(seconds[name]):.1f} |")
    print("\n| warm against cold, same goals | tolerance mm | warm only / cold only | sign p |\n|---|---|---|---|")
    for name in hits:
        if "+warm" not in name:
            continue
        cold = name.replace("+warm", "+cold")
        for tol in ("10", "4"):
            a, b = hits[name][tol], hits[cold][tol]
            only_a, only_b, _, p = sign_test([int(x) - int(y) for x, y in zip(a, b, strict=True)])
            print(f"| {name} vs {cold} | {tol} | {only_a} / {only_b} | {p:.2g} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int)
    parser.add_argument("--models", nargs="+", default=[])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--summarise", nargs="+", type=Path)
    args = parser.parse_args()
    if args.summarise:
        summarise(args.summarise)
    else:
        run(args.seed, args.models, args.out)


if __name__ == "__main__":
    main()
