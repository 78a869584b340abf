"""Benchmark: simulated-hand control steps per second, and the paper-size data set's wall time.

Writes bench/results/collect.json.  The baseline, measured in the same run, is
bare MuJoCo stepping of the same model with no control logic: the ratio says what
the hand interface and sensing cost on top of the physics.

    .venv/bin/python bench/bench_collect.py            # paper size: 300 x 1000 per hand
    .venv/bin/python bench/bench_collect.py --episodes 20 --steps 200   # quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

from t42_transfer.hand.collect import RandomPolicy, collect
from t42_transfer.hand.sim import SimulatedHand

RESULTS = Path(__file__).parent / "results" / "collect.json"


def control_steps_per_s(hand_name: str, steps: int = 3000) -> float:
    hand = SimulatedHand(hand_name)
    actions = RandomPolicy().sample(np.random.default_rng(0), steps)
    done, episode, start = 0, 0, time.perf_counter()
    while done < steps:
        hand.reset(seed=episode)
        episode += 1
        while not hand.done and done < steps:
            hand.step(actions[done])
            done += 1
    return done / (time.perf_counter() - start)


def bare_physics_control_steps_per_s(hand_name: str, steps: int = 3000) -> float:
    """The same model stepped 0.1 s at a time with constant servo targets and no sensing."""
    hand = SimulatedHand(hand_name)
    hand.reset(seed=0)
    model, data, substeps = hand._model, hand._data, hand._substeps  # the benchmark's baseline needs the raw model
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data, nstep=substeps)
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=os.cpu_count())
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    per_core = {h: control_steps_per_s(h) for h in ("source", "target")}
    bare = {h: bare_physics_control_steps_per_s(h) for h in ("source", "target")}
    runs = {}
    total_start = time.perf_counter()
    for hand in ("source", "target"):
        start = time.perf_counter()
        data, stats = collect(hand, args.episodes, args.steps, seed=0, workers=args.workers)
        runs[hand] = {
            "wall_s": time.perf_counter() - start,
            "episodes_kept": stats.kept,
            "transitions": data.num_transitions,
            "end_reasons": stats.end_reasons,
            "too_short": stats.too_short,
            "grasp_failed": stats.grasp_failed,
        }
    total = time.perf_counter() - total_start
    transitions = sum(r["transitions"] for r in runs.values())
    result = {
        "benchmark": "collect",
        "command": shlex.join(["python", *sys.argv]),
        "load_average_at_end": os.getloadavg(),
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor(), "mujoco": mujoco.__version__},
        "control_steps_per_s_per_core": per_core,
        "baseline_bare_physics_steps_per_s": bare,
        "ratio_to_bare_physics": {h: per_core[h] / bare[h] for h in per_core},
        "dataset": {"episodes": args.episodes, "steps": args.steps, "workers": args.workers, "per_hand": runs},
        "dataset_wall_s_both_hands": total,
        "dataset_control_steps_per_s": transitions / total,
        "target_wall_s": 600.0,
        "meets_target": total < 600.0,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
