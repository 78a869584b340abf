"""Benchmark: wall time of one experiment cell (transfer + scoring) per method, on small simulated hands.

Writes bench/results/cell.json.  The experiment runner's own pieces are used:
an ``ExperimentConfig`` built in code (simulated source and target hands, one
amount, one seed), ``load_data`` and ``train_source`` once, then the runner's
private per-cell function ``evaluation.experiment._run_cell`` timed per method
(a benchmark may lean on that private function; it is what every runner worker
executes, including its ``torch.set_num_threads(1)`` and the model save).  A
warm-up cell (``direct``) loads the source model and target data into the
worker cache first, so no method pays for loading.

Reported per method: the median wall time of ``_run_cell`` and its own
``seconds`` column (transfer + scoring, without the save).  With ``--split``
(the default) each method is also run once as ``transfer()`` and the runner's
private ``_score()`` (on the split from its private ``_target_split()``)
separately, to show which half costs what.  The baseline is the ``direct`` cell
(no training: scoring only); ratios are method / direct.

    .venv/bin/python bench/bench_cell.py                  # source 60x300, target 60x300, amount 0.05, 1 seed
    .venv/bin/python bench/bench_cell.py --run-dir /tmp/cellrun --repeats 1   # keep and reuse data and source model
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from machine import machine_info  # bench/machine.py (scripts run from bench/)

from t42_transfer.evaluation import experiment
from t42_transfer.evaluation.experiment import (
    Cell,
    _run_cell,
    _score,
    load_data,
    target_split,
    train_source,
)
from t42_transfer.evaluation.experiment_config import DataSpec, ExperimentConfig
from t42_transfer.models.checkpoint import load_model
from t42_transfer.models.training import TrainConfig
from t42_transfer.planning.workspace import Workspace
from t42_transfer.transfer.methods import METHODS, transfer

RESULTS = Path(__file__).parent / "results" / "cell.json"



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source-episodes", type=int, default=60)
    parser.add_argument("--source-steps", type=int, default=300)
    parser.add_argument("--target-episodes", type=int, default=60)
    parser.add_argument("--target-steps", type=int, default=300)
    parser.add_argument("--amount", type=float, default=0.05, help="fraction of the target pool a cell trains on")
    parser.add_argument("--source-epochs", type=int, default=20, help="source-model epochs (patience 8)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--repeats", type=int, default=3, help="timed _run_cell calls per method")
    parser.add_argument("--no-split", dest="split", action="store_false", help="skip the transfer/scoring split")
    parser.add_argument("--threads", type=int, default=2, help="threads for data collection and source training")
    parser.add_argument("--run-dir", type=Path, default=None, help="keep (and reuse) data and source model here")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()

    cfg = ExperimentConfig(
        name="bench_cell",
        source=DataSpec(hand="source", episodes=args.source_episodes, steps=args.source_steps, seed=0),
        target=DataSpec(hand="target", episodes=args.target_episodes, steps=args.target_steps, seed=1),
        methods=tuple(args.methods),
        amounts=(args.amount,),
        seeds=1,
        source_training=TrainConfig(epochs=args.source_epochs, patience=8),
        workers=1,
    )
    tmp = None
    if args.run_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_cell_")
        run_dir = Path(tmp.name) / cfg.name
    else:
        run_dir = args.run_dir / cfg.name
    run_dir.mkdir(parents=True, exist_ok=True)

    setup: dict[str, float] = {}
    start = time.perf_counter()
    source_data = load_data(cfg.source, run_dir / "data")
    setup["source_data_s"] = time.perf_counter() - start
    start = time.perf_counter()
    target = load_data(cfg.target, run_dir / "data")
    setup["target_data_s"] = time.perf_counter() - start
    start = time.perf_counter()
    source_path = train_source(cfg, run_dir, progress=False)
    setup["source_training_s"] = time.perf_counter() - start

    # what run_experiment hands every cell: the planner's workspace of the source data
    workspace = Workspace.from_trajectories(source_data).to_dict()
    experiment._WORKER.clear()
    start = time.perf_counter()
    # fills the worker cache; sets 1 thread
    _run_cell((cfg, Cell("direct", args.amount, 0), run_dir, source_path, workspace))
    setup["warmup_cell_s"] = time.perf_counter() - start
    cell_threads = torch.get_num_threads()

    per_method: dict[str, dict] = {}
    for method in args.methods:
        walls, own = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            row = _run_cell((cfg, Cell(method, args.amount, 0), run_dir, source_path, workspace))
            walls.append(time.perf_counter() - start)
            own.append(row["seconds"])
        entry = {
            "run_cell_wall_s": statistics.median(walls),
            "cell_seconds_column": statistics.median(own),
            "train_transitions": row["train_transitions"],
            "train_episodes": row["train_episodes"],
            "test_rollouts": row["test_rollouts"],
            "divergence_mean": row["divergence_mean"],
            "repeats_s": walls,
        }
        if args.split:
            source = load_model(source_path)[0]
            train, test = target_split(cfg, target, Cell(method, args.amount, 0))
            start = time.perf_counter()
            model = transfer(method, source, train, cfg.transfer, seed=0)
            entry["transfer_s"] = time.perf_counter() - start
            start = time.perf_counter()
            _score(model, train, test, cfg)
            entry["scoring_s"] = time.perf_counter() - start
        per_method[method] = entry
    baseline = per_method.get("direct", {}).get("run_cell_wall_s")

    result = {
        "benchmark": "cell",
        "command": " ".join(["python", *map(shlex.quote, sys.argv)]),
        "machine": {
            **machine_info(), "threads_setup": args.threads, "threads_cells": cell_threads,
            "load_average_at_start": load_start, "load_average_at_end": os.getloadavg(),
            "oversubscribed": max(load_start[0], os.getloadavg()[0]) > (os.cpu_count() or 1),
        },
        "parameters": {
            "source": cfg.source.describe(), "target": cfg.target.describe(), "amount": args.amount, "seed": 0,
            "source_transitions": source_data.num_transitions, "target_transitions": target.num_transitions,
            "target_episodes": len(target), "test_fraction": cfg.test_fraction, "lyapunov_steps": cfg.lyapunov_steps,
            "source_training": {"epochs": args.source_epochs, "patience": 8}, "transfer": "TransferConfig() defaults",
            "repeats": args.repeats, "split": args.split, "run_dir": None if tmp else str(run_dir),
        },
        "setup": setup,
        "results": {m: v["run_cell_wall_s"] for m, v in per_method.items()},
        "baseline": {"description": "the direct cell: no training, scoring only", "run_cell_wall_s": baseline},
        "ratios": {m: v["run_cell_wall_s"] / baseline for m, v in per_method.items()} if baseline else None,
        "details": per_method,
    }
    if tmp is not None:
        tmp.cleanup()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
