"""Pool bench_planner_quality.py results over goal seeds: hits per (optimiser, budget) at each tolerance.

    .venv/bin/python docs/experiments/planner_tuning/summarise.py docs/experiments/planner_tuning/seed[1-5].json
    .venv/bin/python docs/experiments/planner_tuning/summarise.py FILES --pair default@300 mppi@1000

``--pair A@B C@D`` compares two (optimiser, budget) rows goal by goal (the same goals in every file): goals
only the first hits, only the second, and the exact two-sided sign-test (McNemar) p.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from t42_transfer.evaluation.stats import sign_test


def table(results: list[dict]) -> None:
    hits: dict[tuple[str, int], list[int]] = defaultdict(lambda: [0, 0, 0])
    millis: dict[tuple[str, int], list[float]] = defaultdict(list)
    for result in results:
        for row in result["rows"]:
            key = (row["optimiser"], row["budget"])
            tally = hits[key]
            tally[0] += row["success"][0]["successes"]
            tally[1] += row["success"][1]["successes"]
            tally[2] += row["trials"]
            millis[key].append(1e3 * row["median_plan_seconds"])
    print("| optimiser | budget | 10 mm | 4 mm | median of the seeds' median plan ms |\n|---|---:|---|---|---:|")
    for (name, budget), (ten, four, trials) in sorted(hits.items()):
        print(f"| {name} | {budget} | {ten}/{trials} | {four}/{trials} | {np.median(millis[name, budget]):.1f} |")


def _hits(results: list[dict], which: str) -> dict[tuple[int, int, str], bool]:
    name, _, budget = which.partition("@")
    return {(i, t["trial"], tol): verdict == "hit" for i, result in enumerate(results) for t in result["trials"]
            if t["optimiser"] == name and t["budget"] == int(budget) for tol, verdict in t["verdicts"].items()}


def pair(results: list[dict], first: str, second: str) -> None:
    a, b = _hits(results, first), _hits(results, second)
    if not a or a.keys() != b.keys():
        raise SystemExit(f"{first} and {second} must both be in every file, on the same goals")
    print(f"| tolerance mm | {first} | {second} | only {first} | only {second} | sign-test p |\n|---|---|---|---|---|---|")
    for tol in sorted({k[2] for k in a}, key=float, reverse=True):
        keys = [k for k in a if k[2] == tol]
        wins, losses, _, p = sign_test([int(a[k]) - int(b[k]) for k in keys])
        print(f"| {tol} | {sum(a[k] for k in keys)}/{len(keys)} | {sum(b[k] for k in keys)}/{len(keys)} "
              f"| {wins} | {losses} | {p:.2f} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("files", nargs="+", type=Path)
    parser.add_argument("--pair", nargs=2, metavar=("OPTIMISER@BUDGET", "OPTIMISER@BUDGET"))
    args = parser.parse_args()
    loaded = [json.loads(path.read_text()) for path in args.files]
    pair(loaded, *args.pair) if args.pair else table(loaded)
