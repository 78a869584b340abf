"""Each round's model of an updating online loop, scored on executed-plan episodes that no model trained on.

The loop's held-out episodes (random actions, collected apart) measure the regime of exploration. The loop's own
use is the executed plans: sustained actions from a settled grasp. This scores every round's model, the source
and holding still on the last round's executed-plan episodes (recorded after the last transfer, so no model saw
them): whole episodes, and from each episode's first commanded step on (the plan and the hold after it, without
the settling before it).

    .venv/bin/python docs/experiments/online_loop/plan_regime.py RUN_DIR SOURCE_MODEL
    .venv/bin/python docs/experiments/online_loop/plan_regime.py docs/experiments/online_loop/plan_regime.json  # stored
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

from t42_transfer.data.bag import read_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.online_loop import commanded, scores_on
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import load_model


def print_table(results: dict, episodes: int, transitions: int | None, last_round: int | None) -> None:
    sets = list(next(iter(results.values())))
    if last_round is not None:
        print(f"round {last_round}'s executed-plan episodes: {episodes} ({transitions} transitions)\n")
    print("| model | " + " | ".join(f"{name}: divergence (steps), position MSE (mm²)" for name in sets) + " |")
    print("|---|" + "---:|" * len(sets))
    for name, cells in results.items():
        print(f"| {name} | " + " | ".join(f"{c['divergence_steps']:.1f}, {c['position_mse_mm2']:.2f}"
                                          for c in cells.values()) + " |")


def main() -> int:
    if len(sys.argv) == 2:  # a stored record: its table again
        stored = json.loads(Path(sys.argv[1]).read_text())
        print(f"{stored['episodes']} executed-plan episodes of {stored['run']}\n")
        print_table(stored["results"], stored["episodes"], None, None)
        return 0
    run_dir, source = Path(sys.argv[1]), Path(sys.argv[2])
    summary = json.loads((run_dir / "demo.json").read_text())
    last = summary["rounds"][-1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (episodes too short to keep are named by the reader; counted below)
        episodes = [t for bag in last["bags_closed"] if bag["episodes"] for t in read_bag(bag["path"])]
    whole = TrajectorySet(episodes, hand="target")
    sets = {"whole episodes": whole, "from the first commanded step": commanded(whole)}
    models = {"source": load_model(source)[0], "hold still": HoldStill()}
    models.update({f"round {r['round']} model": load_model(r["model"])[0] for r in summary["rounds"]})
    by_set = {set_name: scores_on(models, data) for set_name, data in sets.items()}
    results = {name: {set_name: by_set[set_name][name] for set_name in sets} for name in models}
    print_table(results, len(whole), whole.num_transitions, last["round"])
    out = Path(__file__).parent / "plan_regime.json"
    out.write_text(json.dumps({"run": str(run_dir), "episodes": len(whole), "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
