"""What a round's executed-plan episodes do to the transferred model: training sets with and without them.

From one full demo run's bags (the explorer's random-action episodes, then the recorded goal episodes), L2
fine-tuning as the transfer server runs it (its hold-out split, 5 seeds) on: the exploration alone; exploration
and every goal episode; exploration and each goal episode's commanded stretch only (no settling, no hold); and
exploration and each goal episode from its first commanded step. Each model is scored on 30 random-action
target episodes collected apart (the demo's held-out kind, seed 99), and one-step position errors show which
regime each model fits.

    .venv/bin/python docs/experiments/online_loop/what_the_goals_do.py RUN_DIR SOURCE_MODEL [EXPLORATION_BAGS]
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.evaluation.metrics import evaluate_model
from t42_transfer.evaluation.online_loop import commanded, idle_share
from t42_transfer.hand.collect import collect
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import load_model
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.methods import transfer
from t42_transfer.transfer.online import hold_out, read_target


def one_step_mse(model, data: TrajectorySet) -> float:  # noqa: ANN001
    s, a, s2 = (torch.as_tensor(x) for x in data.transitions())
    predicted = model.rollout(s, a[:, None, :])[:, 1]
    return float(((predicted - s2)[:, :2] ** 2).sum(dim=1).mean())


def main() -> int:
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    run_dir, source_path = Path(sys.argv[1]), Path(sys.argv[2])
    explored = int(sys.argv[3]) if len(sys.argv) > 3 else 12
    bags = sorted((run_dir / "bags").glob("episode_*"))
    exploration, goals = read_target(bags[:explored]).data, read_target(bags[explored:]).data
    heldout, _ = collect("target", 30, 150, seed=99, workers=1)
    source = load_model(source_path)[0]
    print(f"idle steps: exploration {idle_share(exploration):.2f} of {exploration.num_transitions}, "
          f"goal episodes {idle_share(goals):.2f} of {goals.num_transitions}")
    print(f"30 held-out random-action episodes: source {evaluate_model(source, heldout)['divergence_mean']:.1f} "
          f"steps, hold still {evaluate_model(HoldStill(), heldout)['divergence_mean']:.1f}\n")
    plans = commanded(goals, to_last_command=True)
    both = lambda extra: TrajectorySet([*exploration, *extra], hand=exploration.hand)  # noqa: E731
    variants = {"exploration only": exploration, "exploration + goal episodes": both(goals),
                "exploration + commanded stretches": both(plans),
                "exploration + from the first command": both(commanded(goals))}
    print("| training set | episodes | transitions | idle share | held-out divergence per seed (steps) | mean |")
    print("|---|---:|---:|---:|---|---:|")
    models = {}
    for name, data in variants.items():
        scores = []
        for seed in range(5):
            train, _ = hold_out(data, 0.25, seed)
            model = transfer("l2_finetune", source, train, TransferConfig(), seed=seed)
            models.setdefault(name, model)
            scores.append(evaluate_model(model, heldout)["divergence_mean"])
        print(f"| {name} | {len(data)} | {data.num_transitions} | {idle_share(data):.2f} | "
              f"{', '.join(f'{v:.1f}' for v in scores)} | {np.mean(scores):.1f} |")
    print("\none-step position error (mm²): | exploration | goals' commanded stretches | held-out random |")
    for name, model in (("source", source), ("exploration only (seed 0)", models["exploration only"]),
                        ("hold still", HoldStill())):
        print(f"| {name} | {one_step_mse(model, exploration):.3f} | {one_step_mse(model, plans):.3f} | "
              f"{one_step_mse(model, heldout):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
