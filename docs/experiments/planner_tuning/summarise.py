"""Pool bench_planner_quality.py results over goal seeds: hits per (optimiser, budget) at each tolerance.

    .venv/bin/python docs/experiments/planner_tuning/summarise.py docs/experiments/planner_tuning/seed[1-5].json
    .venv/bin/python docs/experiments/planner_tuning/summarise.py FILES --pair default@300 mppi@1000

``--pair A@B C@D`` compares two (optimiser, budget) rows goal by goal (the same goals in every file): goals
only the first hits, only the second, and the exact two-sided sign-test (McNemar) p.  ``--by-predicted A@B C@D``
groups the goals by the first row's predicted error and gives both rows' hits and median true errors per group:
whether more search helps the goals the first left far from the goal in prediction.
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


def _trials(results: list[dict], which: str) -> dict[tuple[int, int], dict]:
    name, _, budget = which.partition("@")
    return {(i, t["trial"]): t for i, result in enumerate(results) for t in result["trials"]
            if t["optimiser"] == name and t["budget"] == int(budget)}


def _paired(results: list[dict], first: str, second: str) -> tuple[dict, dict]:
    """Both rows' trials by (file, goal); exits unless both cover the same goals."""
    a, b = _trials(results, first), _trials(results, second)
    if not a or a.keys() != b.keys():
        raise SystemExit(f"{first} and {second} must both be in every file, on the same goals")
    return a, b


PREDICTED_MM = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, float("inf"))


def by_predicted(results: list[dict], first: str, second: str) -> None:
    a, b = _paired(results, first, second)
    print(f"| {first} predicted mm | goals | {first} hits 10 / 4 mm | {second} hits 10 / 4 mm "
          f"| median true mm, {first} / {second} |\n|---|---|---|---|---|")
    for low, high in zip(PREDICTED_MM, PREDICTED_MM[1:], strict=False):
        keys = [k for k, t in a.items()
                if t["predicted_error_mm"] is not None and low <= t["predicted_error_mm"] < high]
        if not keys:
            continue
        hits = [" / ".join(str(sum(t[k]["verdicts"][tol] == "hit" for k in keys)) for tol in ("10", "4"))
                for t in (a, b)]
        true = [np.median([t[k]["final_error_mm"] for k in keys if t[k]["final_error_mm"] is not None])
                for t in (a, b)]
        print(f"| {low:g}-{high:g} | {len(keys)} | {hits[0]} | {hits[1]} | {true[0]:.1f} / {true[1]:.1f} |")


def pair(results: list[dict], first: str, second: str) -> None:
    a, b = _paired(results, first, second)
    print(f"| tolerance mm | {first} | {second} | only {first} | only {second} | sign-test p |\n"
          "|---|---|---|---|---|---|")
    for tol in sorted(next(iter(a.values()))["verdicts"], key=float, reverse=True):
        hits = [[t[k]["verdicts"][tol] == "hit" for k in a] for t in (a, b)]
        wins, losses, _, p = sign_test([int(x) - int(y) for x, y in zip(*hits, strict=True)])
        print(f"| {tol} | {sum(hits[0])}/{len(a)} | {sum(hits[1])}/{len(a)} | {wins} | {losses} | {p:.2f} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("files", nargs="+", type=Path)
    parser.add_argument("--pair", nargs=2, metavar=("OPTIMISER@BUDGET", "OPTIMISER@BUDGET"))
    parser.add_argument("--by-predicted", nargs=2, metavar=("OPTIMISER@BUDGET", "OPTIMISER@BUDGET"))
    args = parser.parse_args()
    loaded = [json.loads(path.read_text()) for path in args.files]
    if args.pair:
        pair(loaded, *args.pair)
    elif args.by_predicted:
        by_predicted(loaded, *args.by_predicted)
    else:
        table(loaded)
