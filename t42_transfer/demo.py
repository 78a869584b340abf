"""The README's main job, on embedded defaults: simulated source and target hands.

So far the story covers data: collect random-policy episodes on both hands,
record them as rosbag2 MCAP bags, read the bags back and check every number
survived, and summarise.  Transfer, planning and the ROS nodes join it as they
land.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t42_transfer.data.bag_io import assign_start_times, read_bag, write_bag
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import collect


@dataclass(frozen=True)
class DemoSize:
    source_episodes: int
    target_episodes: int
    steps: int


FULL = DemoSize(source_episodes=60, target_episodes=15, steps=400)
QUICK = DemoSize(source_episodes=8, target_episodes=4, steps=120)


def _summary_row(name: str, data: TrajectorySet, seconds: float) -> dict:
    states = np.concatenate([t.states for t in data])
    ends: dict[str, int] = {}
    for t in data:
        ends[t.end_reason] = ends.get(t.end_reason, 0) + 1
    return {
        "hand": name,
        "episodes": len(data),
        "transitions": data.num_transitions,
        "mean_length": data.num_transitions / max(1, len(data)),
        "x_range_mm": [float(states[:, 0].min()), float(states[:, 0].max())],
        "y_range_mm": [float(states[:, 1].min()), float(states[:, 1].max())],
        "end_reasons": ends,
        "collect_s": seconds,
    }


def run_demo(out: Path, quick: bool = False, workers: int | None = None) -> int:
    """Collect on both hands, round-trip through bags, print and save a summary; 0 on success."""
    size = QUICK if quick else FULL
    out = Path(out)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dir = out / stamp
    run_dir.mkdir(parents=True, exist_ok=False)
    print(f"t42 demo{' --quick' if quick else ''}: simulated source and target hands -> {run_dir}")
    rows = []
    for hand, episodes, seed in (("source", size.source_episodes, 0), ("target", size.target_episodes, 1)):
        start = time.perf_counter()
        data, _ = collect(hand, episodes, size.steps, seed=seed, workers=workers)
        data = TrajectorySet(assign_start_times(data), hand=data.hand)
        seconds = time.perf_counter() - start
        bag = write_bag(run_dir / f"{hand}_bag", data, metadata={"collector": "t42 demo", "seed": str(seed)})
        back = read_bag(bag)
        if len(back) != len(data) or not all(a == b for a, b in zip(data, back)):
            print(f"FAILED: {bag} did not read back to the trajectories that were written")
            return 1
        rows.append({**_summary_row(hand, data, seconds), "bag": str(bag)})
    print(f"\n{'hand':8} {'episodes':>8} {'transitions':>11} {'mean len':>8} {'x range mm':>16} {'y range mm':>16}  ends")
    for r in rows:
        xr, yr = r["x_range_mm"], r["y_range_mm"]
        print(
            f"{r['hand']:8} {r['episodes']:8d} {r['transitions']:11d} {r['mean_length']:8.1f} "
            f"{xr[0]:7.1f} ..{xr[1]:6.1f} {yr[0]:7.1f} ..{yr[1]:6.1f}  {r['end_reasons']}"
        )
    print("\nbags read back exactly (same numbers) for both hands:")
    for r in rows:
        print(f"  {r['bag']}")
    (run_dir / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"summary: {run_dir / 'summary.json'}")
    return 0
