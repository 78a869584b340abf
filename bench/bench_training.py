"""Benchmark: training throughput of our loops against plain PyTorch loops run in the same process.

Writes bench/results/training.json.  Two measurements, each with a same-run baseline:

* single-step training (``fit_single_step``, Adam, dropout on, clipping) in
  samples/s at batch 64 and 1024 on synthetic random-walk episodes shaped like
  the hand data (4-D states, 2-D actions, ~100k transitions); the baseline is the
  plain loop ``perm = randperm(n); for i in range(0, n, bs): idx = perm[i:i+bs];
  loss = mse(net(X[idx]), Y[idx]); zero_grad; backward; clip_grad_norm_; step``
  with the same MLP (``network.mlp``) and tensors built beforehand.  "ours" is
  timed by the loop itself (``TrainReport.samples_per_s``, tensors already built,
  like the baseline) and end to end (the whole ``fit_single_step`` call, which
  also builds the training tensors from the episodes).  A third contender, the
  baseline with ``Adam(fused=True)`` and ``clip_grad_norm_(foreach=True)``,
  measures what that change to ``fit`` would buy (``proposal_fused_adam``).
* trajectory fine-tuning (the ``trajectory_finetune`` method: backprop through
  open-loop rollouts of whole episodes) in model-steps/s = episodes x steps x epochs
  / seconds; the baseline is a plain loop ``s = s + net(cat(norm(s), a)) * std + mean``
  over the same episodes with the same 1/i-weighted loss, Adam and clipping.

Repeats alternate ours and the baseline (fewer once ``--budget-s`` is spent on
one measurement); the figures are medians.  The machine's load average is
recorded: with more runnable processes than cores, 2 intra-op threads wait on
each other every op and every figure drops many-fold (compare ``--threads 1``).

    .venv/bin/python bench/bench_training.py                         # default: 100 x 1000 transitions, 2 threads
    .venv/bin/python bench/bench_training.py --episodes 20 --repeats 1  # quick look
    .venv/bin/python bench/bench_training.py --threads 1                # a shared, oversubscribed machine
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from machine import machine_info  # bench/machine.py (scripts run from bench/)
from torch import nn

from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.models.network import Normalisation, TransitionModel, mlp
from t42_transfer.models.training import TrainConfig, fit_single_step, step_batch, trajectory_weights
from t42_transfer.transfer.config import TrajectoryFineTuneConfig, TransferConfig
from t42_transfer.transfer.methods import METHODS

RESULTS = Path(__file__).parent / "results" / "training.json"



def alternate(fns: list, repeats: int, budget_s: float) -> list[list]:  # type: ignore[type-arg]
    """Run every ``fns[k]()`` ``repeats`` times in rotating order (fewer once ``budget_s`` is spent); results per fn."""
    out: list[list] = [[] for _ in fns]
    start = time.perf_counter()
    for r in range(repeats):
        for j in range(len(fns)):
            k = (j + r) % len(fns)
            out[k].append(fns[k]())
        if time.perf_counter() - start > budget_s:
            break
    return out


def random_walk_set(episodes: int, steps: int, seed: int = 0) -> TrajectorySet:
    """Episodes shaped like the hand data: held random actions in [-1, 1]^2 move (x, y) mm; loads follow."""
    rng = np.random.default_rng(seed)
    trajs = []
    for _ in range(episodes):
        hold = np.repeat(rng.uniform(-1, 1, size=(steps // 3 + 1, 2)), 3, axis=0)[:steps]
        xy = np.cumsum(0.4 * hold + 0.05 * rng.standard_normal((steps, 2)), axis=0)
        xy = np.concatenate([rng.normal(0, 5, size=(1, 2)), xy + rng.normal(0, 5, size=(1, 2))])
        loads = 120 + 20 * np.tanh(xy / 20) + rng.normal(0, 2, size=xy.shape)
        trajs.append(Trajectory(np.concatenate([xy, loads], axis=1), hold))
    return TrajectorySet(trajs, hand="synthetic")


def fresh_model(data: TrajectorySet, seed: int = 0) -> TransitionModel:
    x, _, x_next = data.transitions()
    torch.manual_seed(seed)
    return TransitionModel(Normalisation.from_transitions(x, x_next))


# --------------------------------------------------------------------------- single step


def ours_single_step(data: TrajectorySet, batch_size: int, epochs: int) -> tuple[float, float]:
    """(loop samples/s from the report, end-to-end samples/s of the fit_single_step call)."""
    model = fresh_model(data)
    cfg = TrainConfig(epochs=epochs, batch_size=batch_size, patience=None)
    start = time.perf_counter()
    report = fit_single_step(model, data, None, cfg)
    wall = time.perf_counter() - start
    n = data.num_transitions
    return report.samples_per_s, epochs * n / wall


def reference_single_step(X: torch.Tensor, Y: torch.Tensor, batch_size: int, epochs: int, fused: bool = False) -> float:
    """The plain loop of the docstring; samples/s.  ``fused``: Adam(fused=True) and foreach clipping (the proposal)."""
    torch.manual_seed(0)
    net = mlp(X.shape[1], Y.shape[1])
    net.train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-3, **({"fused": True} if fused else {}))
    mse = nn.functional.mse_loss
    n = len(X)
    start = time.perf_counter()
    for _ in range(epochs):
        perm = torch.randperm(n)
        for i in range(0, n, batch_size):
            idx = perm[i : i + batch_size]
            loss = mse(net(X[idx]), Y[idx])
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(net.parameters(), 10.0, **({"foreach": True} if fused else {}))
            opt.step()
    return epochs * n / (time.perf_counter() - start)


# ------------------------------------------------------------------------- trajectory


def ours_trajectory(source: TransitionModel, target: TrajectorySet, tcfg: TrajectoryFineTuneConfig) -> float:
    """Seconds of one trajectory_finetune call."""
    cfg = TransferConfig(trajectory_finetune=tcfg)
    start = time.perf_counter()
    METHODS["trajectory_finetune"](source, target, cfg, 0, None)
    return time.perf_counter() - start


def reference_trajectory(
    source: TransitionModel, x: torch.Tensor, a: torch.Tensor, tcfg: TrajectoryFineTuneConfig
) -> float:
    """Seconds of the plain rollout-backprop loop over the same episodes (the paper's loss, no cutoff)."""
    net = mlp(6, 4)
    net.load_state_dict(source.net.state_dict())
    net.train()
    mean, std, dmean, dstd = source.state_mean, source.state_std, source.delta_mean, source.delta_std
    weights = trajectory_weights(a.shape[1])
    opt = torch.optim.Adam(net.parameters(), lr=tcfg.train.lr, weight_decay=tcfg.train.weight_decay)
    n, bs = len(x), tcfg.train.batch_size
    start = time.perf_counter()
    for _ in range(tcfg.train.epochs):
        perm = torch.randperm(n)
        for i in range(0, n, bs):
            idx = perm[i : i + bs]
            true, acts = x[idx], a[idx]
            s, preds = true[:, 0], []
            for t in range(acts.shape[1]):
                s = s + net(torch.cat([(s - mean) / std, acts[:, t]], dim=-1)) * dstd + dmean
                preds.append(s)
            err = ((torch.stack(preds, 1) - true[:, 1:]) / std) ** 2
            loss = (err.mean(dim=(0, 2)) * weights).sum()
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(net.parameters(), tcfg.train.grad_clip)
            opt.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100, help="synthetic episodes for single-step training")
    parser.add_argument("--steps", type=int, default=1000, help="steps per synthetic episode")
    parser.add_argument("--batches", type=int, nargs="+", default=[64, 1024])
    parser.add_argument("--epochs", type=int, default=1, help="epochs per timed single-step run")
    parser.add_argument("--repeats", type=int, default=5,
                        help="alternating ours/baseline pairs (fewer past --budget-s)")
    parser.add_argument("--budget-s", type=float, default=60.0, help="stop repeating a measurement after this long")
    parser.add_argument("--traj-episodes", type=int, default=8)
    parser.add_argument("--traj-steps", type=int, default=200)
    parser.add_argument("--traj-epochs", type=int, default=2)
    parser.add_argument("--traj-repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()

    data = random_walk_set(args.episodes, args.steps)
    sb = step_batch(fresh_model(data), data)
    X, Y = sb.features.contiguous(), sb.target.contiguous()
    single: dict[str, dict] = {}
    for bs in args.batches:
        runs, ref, fused = alternate(
            [
                lambda bs=bs: ours_single_step(data, bs, args.epochs),
                lambda bs=bs: reference_single_step(X, Y, bs, args.epochs),
                lambda bs=bs: reference_single_step(X, Y, bs, args.epochs, fused=True),
            ],
            args.repeats, args.budget_s,
        )
        loop, e2e = [r[0] for r in runs], [r[1] for r in runs]
        m_fused = statistics.median(fused)
        m_loop, m_e2e, m_ref = (statistics.median(v) for v in (loop, e2e, ref))
        single[str(bs)] = {
            "ours_loop_samples_per_s": m_loop,
            "ours_end_to_end_samples_per_s": m_e2e,
            "baseline_samples_per_s": m_ref,
            "ratio_loop": m_loop / m_ref,
            "ratio_end_to_end": m_e2e / m_ref,
            "median_paired_ratio_loop": statistics.median(o / r for o, r in zip(loop, ref, strict=True)),
            "seconds_per_epoch_ours_loop": len(X) / m_loop,
            "seconds_per_epoch_baseline": len(X) / m_ref,
            "baseline_fused_adam_samples_per_s": m_fused,
            "fused_adam_over_baseline": m_fused / m_ref,
            "repeats": {"ours_loop": loop, "ours_end_to_end": e2e, "baseline": ref, "baseline_fused_adam": fused},
        }

    # Trajectory fine-tuning: a small target set, the method's defaults but fewer epochs.
    target = random_walk_set(args.traj_episodes, args.traj_steps, seed=1)
    source = fresh_model(data)
    tcfg = dataclasses.replace(
        TrajectoryFineTuneConfig(), train=dataclasses.replace(TrajectoryFineTuneConfig().train, epochs=args.traj_epochs)
    )
    x = torch.from_numpy(np.stack([t.states for t in target]))  # random_walk_set's episodes are equally long
    a = torch.from_numpy(np.stack([t.actions for t in target]))
    model_steps = args.traj_epochs * a.shape[0] * a.shape[1]
    ours_t, ref_t = alternate(
        [lambda: ours_trajectory(source, target, tcfg), lambda: reference_trajectory(source, x, a, tcfg)],
        args.traj_repeats, args.budget_s,
    )
    ours_rate, ref_rate = model_steps / statistics.median(ours_t), model_steps / statistics.median(ref_t)

    result = {
        "benchmark": "training",
        "command": " ".join(["python", *map(shlex.quote, sys.argv)]),
        "machine": {**machine_info(), "load_average_at_start": load_start, "load_average_at_end": os.getloadavg(),
                    "oversubscribed": max(load_start[0], os.getloadavg()[0]) > (os.cpu_count() or 1)},
        "parameters": {
            "single_step": {
                "data": "synthetic random-walk episodes",
                "episodes": args.episodes, "steps": args.steps, "transitions": len(X),
                "batch_sizes": args.batches, "epochs_per_run": args.epochs, "repeats": args.repeats,
                "budget_s": args.budget_s,
                "optimiser": "Adam lr 1e-3 wd 1e-3, clip 10, dropout on",
            },
            "trajectory_finetune": {
                "episodes": args.traj_episodes, "steps": args.traj_steps, "whole_episodes": True,
                "batch_size": tcfg.train.batch_size, "epochs": args.traj_epochs,
                "repeats": args.traj_repeats, "budget_s": args.budget_s, "model_steps_per_run": model_steps,
            },
        },
        "results": {
            "single_step_samples_per_s": {bs: v["ours_loop_samples_per_s"] for bs, v in single.items()},
            "single_step_end_to_end_samples_per_s": {
                bs: v["ours_end_to_end_samples_per_s"] for bs, v in single.items()
            },
            "trajectory_finetune_model_steps_per_s": ours_rate,
        },
        "baseline": {
            "single_step_samples_per_s": {bs: v["baseline_samples_per_s"] for bs, v in single.items()},
            "trajectory_model_steps_per_s": ref_rate,
        },
        "ratios": {
            "single_step_loop_ours_over_baseline": {bs: v["ratio_loop"] for bs, v in single.items()},
            "single_step_end_to_end_ours_over_baseline": {bs: v["ratio_end_to_end"] for bs, v in single.items()},
            "single_step_loop_median_paired_ratio": {bs: v["median_paired_ratio_loop"] for bs, v in single.items()},
            "trajectory_finetune_ours_over_baseline": ours_rate / ref_rate,
        },
        "proposal_fused_adam": {
            "description": "the baseline loop with torch.optim.Adam(..., fused=True) and "
                           "clip_grad_norm_(..., foreach=True)",
            "samples_per_s": {bs: v["baseline_fused_adam_samples_per_s"] for bs, v in single.items()},
            "over_baseline": {bs: v["fused_adam_over_baseline"] for bs, v in single.items()},
        },
        "details": {
            "single_step": single,
            "trajectory_seconds": {"ours": ours_t, "baseline": ref_t},
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
