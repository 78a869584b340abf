"""The README's main job, on embedded defaults: simulated source and target hands.

The story so far: collect random-policy episodes on both hands and record them
as rosbag2 MCAP bags (checking every number survives the trip); train the
source model on the source bag; transfer it to the target hand with a little
data from the target bag by each method; score every model on held-out target
episodes (time before 4 mm divergence, position MSE) and save the transferred
models.  Planning and the ROS nodes join it as they land.
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
    source_epochs: int
    transfer_episodes: int
    """Target episodes given to the transfer; the rest are the held-out test set."""


FULL = DemoSize(source_episodes=80, target_episodes=20, steps=400, source_epochs=40, transfer_episodes=3)
QUICK = DemoSize(source_episodes=10, target_episodes=6, steps=150, source_epochs=5, transfer_episodes=2)
DEMO_METHODS = ("direct", "new_model", "naive_finetune", "cumulative_residual", "l2_finetune")


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
    print("bags read back exactly (same numbers) for both hands:")
    for r in rows:
        print(f"  {r['bag']}")
    scores = _transfer_story(run_dir, size)
    (run_dir / "summary.json").write_text(json.dumps({"data": rows, "transfer": scores}, indent=2) + "\n")
    print(f"summary: {run_dir / 'summary.json'}")
    return 0


def _transfer_story(run_dir: Path, size: DemoSize) -> list[dict]:
    """Source model from the source bag, each method from a few target episodes, scores on the rest."""
    import torch

    from t42_transfer.evaluation.metrics import evaluate_model
    from t42_transfer.models.checkpoint import save_model
    from t42_transfer.models.training import ProgressBar, TrainConfig, train_transition_model
    from t42_transfer.transfer import transfer

    torch.set_num_threads(1)
    source_data = read_bag(run_dir / "source_bag")
    target_data = read_bag(run_dir / "target_bag")
    source, report = train_transition_model(
        source_data, TrainConfig(epochs=size.source_epochs), on_epoch=ProgressBar(), phase="source model"
    )
    from t42_transfer.planning.workspace import Workspace

    extra = {"workspace": Workspace.from_trajectories(source_data).to_dict()}
    save_model(
        source, run_dir / "models" / "source.safetensors", method="source", data={"source": source_data.fingerprint()},
        extra=extra,
    )
    given = target_data.subset(range(size.transfer_episodes))
    test = target_data.subset(range(size.transfer_episodes, len(target_data)))
    print(
        f"\nsource model: {report.epochs_run} epochs on {source_data.num_transitions} transitions; transfer with "
        f"{given.num_transitions} target transitions ({len(given)} episodes), test on {len(test)} held-out episodes"
    )
    scores = []
    for method in DEMO_METHODS:
        start = time.perf_counter()
        model = transfer(method, source, given, seed=0)
        seconds = time.perf_counter() - start
        result = evaluate_model(model, test)
        path = save_model(
            model, run_dir / "models" / f"{method}.safetensors", method=method, data={"target": given.fingerprint()},
            extra=extra,
        )
        scores.append({
            "method": method, "divergence_steps": result["divergence_mean"], "position_mse_mm2": result["position_mse_mean"],
            "seconds": seconds, "model": str(path),
        })
    print(f"\n{'method':22} {'steps before 4 mm':>17} {'position MSE mm^2':>17} {'transfer s':>10}")
    for r in scores:
        print(f"{r['method']:22} {r['divergence_steps']:17.1f} {r['position_mse_mm2']:17.1f} {r['seconds']:10.1f}")
    print(f"models: {run_dir / 'models'}")
    return scores
