"""Per-round table of two `t42 demo` runs of the online loop: one that updates its model each round, one that never
does (``--no-update``).  Reads each run's demo.json; writes the reduced records beside this file and prints markdown.
Given two reduced records instead (the stored ``updating.json`` and ``frozen.json``), prints the same tables from them.

    .venv/bin/python docs/experiments/online_loop/summarise.py UPDATING_RUN_DIR FROZEN_RUN_DIR
    .venv/bin/python docs/experiments/online_loop/summarise.py docs/experiments/online_loop/{updating,frozen}.json
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from t42_transfer.evaluation.stats import wilson_interval

HERE = Path(__file__).parent


def reduced(run_dir: Path) -> dict:
    """What the tables need from a run: per round the held-out divergence and the goals' verdicts."""
    summary = json.loads((run_dir / "demo.json").read_text())
    goals = summary["goals"]
    rounds = []
    for record in summary["rounds"]:
        mine = [g for g in goals if g["round"] == record["round"]]
        rounds.append({"round": record["round"], "model": Path(record["model"]).name,
                       "updated": record["transfer"].get("updated", True),
                       "transfer_message": record["transfer"]["message"], "heldout": record["heldout"],
                       "goals": [{"steps": g["steps"], "goal_mm": g["goal_mm"], "grasp_seed": g["grasp_seed"],
                                  "verdict": g["verdict"], "error_mm": g["error_mm"],
                                  "doing_nothing_verdict": g["still_verdict"]} for g in mine]})
    return {"run": str(run_dir), "update": summary.get("update", True), "size": summary["size"],
            "seconds": summary.get("seconds"), "rounds": rounds}


def table(runs: dict[str, dict]) -> str:
    lines = ["| loop | round | goals hit (95 % Wilson) | doing nothing hits | held-out divergence, model (steps) "
             "| source alone | hold still |",
             "|---|---:|---|---|---:|---:|---:|"]
    for name, run in runs.items():
        for r in run["rounds"]:
            hits, n = sum(g["verdict"] == "hit" for g in r["goals"]), len(r["goals"])
            low, high = wilson_interval(hits, n)
            still = sum(g["doing_nothing_verdict"] == "hit" for g in r["goals"])
            h = r["heldout"]
            lines.append(f"| {name} | {r['round']} | {hits}/{n} ({low:.2f}-{high:.2f}) | {still}/{n} | "
                         f"{h['model']:.1f} | {h['source']:.1f} | {h['hold_still']:.1f} |")
    return "\n".join(lines)


def main() -> int:
    paths = [Path(p) for p in sys.argv[1:3]]
    stored = all(p.suffix == ".json" for p in paths)
    updating, frozen = (json.loads(p.read_text()) if stored else reduced(p) for p in paths)
    runs = {"updates each round": updating, "never updates": frozen}
    for name, run in (("updating", updating), ("frozen", frozen)):
        if not stored:
            (HERE / f"{name}.json").write_text(json.dumps(run, indent=1) + "\n")
    same = [[(g["grasp_seed"], g["goal_mm"]) for g in r["goals"]] for r in updating["rounds"]] == \
           [[(g["grasp_seed"], g["goal_mm"]) for g in r["goals"]] for r in frozen["rounds"]]
    print(table(runs))
    print(f"\nthe two loops' goals are the same goals, in order: {same}")
    if same:  # paired over the goals of rounds 2 on, where the loops differ: exact McNemar (two-sided binomial)
        pairs = [(a["verdict"] == "hit", b["verdict"] == "hit") for ra, rb in
                 zip(updating["rounds"][1:], frozen["rounds"][1:], strict=True)
                 for a, b in zip(ra["goals"], rb["goals"], strict=True)]
        only_updating, only_frozen = sum(a and not b for a, b in pairs), sum(b and not a for a, b in pairs)
        n = only_updating + only_frozen
        tail = sum(math.comb(n, k) for k in range(min(only_updating, only_frozen) + 1)) / 2 ** n if n else 1.0
        print(f"rounds 2 on, {len(pairs)} paired goals: hit by the updating loop only {only_updating}, by the "
              f"frozen loop only {only_frozen}; exact McNemar p = {min(1.0, 2 * tail):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
