"""Pool bench_planner_quality.py results over goal seeds: hits per (optimiser, budget) at each tolerance.

    .venv/bin/python docs/experiments/planner_tuning/summarise.py docs/experiments/planner_tuning/seed*.json
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict

import numpy as np


def main(paths: list[str]) -> None:
    hits: dict[tuple[str, int], list[int]] = defaultdict(lambda: [0, 0, 0])
    millis: dict[tuple[str, int], list[float]] = defaultdict(list)
    for path in paths:
        result = json.loads(open(path).read())
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


if __name__ == "__main__":
    main(sys.argv[1:])
