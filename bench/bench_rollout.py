"""Benchmark: open-loop rollout throughput of every model kind through the one contract.

Writes bench/results/rollout.json.  Each model is built directly with random
weights (``TransitionModel``, the same with ``grasp_input``,
``CumulativeResidualModel`` and ``RecurrentResidualModel`` built from two
``TransitionModel``) and rolled out with ``model.rollout(x0[B, 4], actions[B, T, 2])``
(no grad, eval mode).  The baseline, measured in the same run and interleaved
with each model, is the plain eager loop ``s = s + net(cat(s, a))`` under
``no_grad`` with the same MLP, started from the z-normalised ``x0`` (the space
the network sees inside the models): fed raw millimetres and load units, SELU
inputs reach the exp-underflow range where SELU alone runs 4-5x slower here,
which would flatter the models.  Figures are sample-steps/s (B x T per second),
medians of repeats; ``ratio_to_baseline`` is model / baseline, and
``ratio_per_mlp_call`` divides out the number of MLP evaluations per step
(the residual models evaluate two).  Repeats alternate model and baseline;
a kind stops repeating (after 3) once ``--budget-s`` is spent on it.

Which transfer method yields which kind: new_model, direct, naive_finetune,
trajectory_finetune and l2_finetune give a ``transition`` model;
cumulative_residual and recurrent_residual give their own kinds.

    .venv/bin/python bench/bench_rollout.py                     # B=1000, T=100, 2 threads
    .venv/bin/python bench/bench_rollout.py --repeats 5         # quick look
    .venv/bin/python bench/bench_rollout.py --threads 1         # a shared machine: see below

``machine.oversubscribed`` is true when the 1-minute load average exceeded the
core count: then 2 intra-op threads wait on each other at every op (each op
can take a scheduler time slice) and the figures swing 10-30x between repeats;
use ``--threads 1`` for ratios that mean something.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from machine import machine_info  # bench/machine.py (scripts run from bench/)
from torch import nn

from t42_transfer.models import (
    CumulativeResidualModel,
    LatentDynamics,
    Normalisation,
    RecurrentResidualModel,
    TransitionModel,
)

RESULTS = Path(__file__).parent / "results" / "rollout.json"

METHOD_KIND = {
    "new_model": "transition",
    "direct": "transition",
    "naive_finetune": "transition",
    "trajectory_finetune": "transition",
    "l2_finetune": "transition",
    "cumulative_residual": "cumulative_residual",
    "recurrent_residual": "recurrent_residual",
}



def norm() -> Normalisation:
    """A plausible hand-data normalisation (mm and raw load units)."""
    return Normalisation(
        state_mean=np.array([0.0, 80.0, 120.0, 120.0], np.float32),
        state_std=np.array([15.0, 10.0, 30.0, 30.0], np.float32),
        delta_mean=np.zeros(4, np.float32),
        delta_std=np.array([0.4, 0.4, 2.0, 2.0], np.float32),
    )


def build_models(seed: int = 0) -> dict[str, tuple[LatentDynamics, int]]:
    """Model by kind name, with its MLP evaluations per step."""
    torch.manual_seed(seed)
    source, residual = TransitionModel(norm()), TransitionModel(norm())
    return {
        "transition": (TransitionModel(norm()).eval(), 1),
        "transition_grasp_input": (TransitionModel(norm(), grasp_input=True).eval(), 1),
        "cumulative_residual": (CumulativeResidualModel(source, residual, 0.3, 0.9997).eval(), 2),
        "recurrent_residual": (RecurrentResidualModel(source, residual, 0.3).eval(), 2),
    }


@torch.no_grad()
def baseline_rollout(net: nn.Module, x0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    s, out = x0, [x0]
    for t in range(actions.shape[1]):
        s = s + net(torch.cat([s, actions[:, t]], dim=-1))
        out.append(s)
    return torch.stack(out, dim=1)


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--budget-s", type=float, default=30.0,
                        help="per model kind: stop repeating (after 3) past this")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()

    gen = torch.Generator().manual_seed(0)
    x0 = (torch.randn(args.batch, 4, generator=gen) * torch.tensor([15.0, 10.0, 30.0, 30.0])
          + torch.tensor([0.0, 80.0, 120.0, 120.0]))
    actions = torch.rand(args.batch, args.horizon, 2, generator=gen) * 2 - 1
    models = build_models()
    reference = models["transition"][0]
    # the same MLP and weights; a copy, so rollout's train/eval toggling cannot reach it
    base_net = copy.deepcopy(reference.net).eval()
    base_x0 = (x0 - reference.state_mean) / reference.state_std
    sample_steps = args.batch * args.horizon

    for model, _ in models.values():  # warm-up: allocator, first-call dispatch
        model.rollout(x0[:10], actions[:10, :5])
    baseline_rollout(base_net, base_x0, actions)

    per_kind, baseline_all = {}, []
    for name, (model, calls) in models.items():
        ours, base, begun = [], [], time.perf_counter()
        for r in range(args.repeats):
            if r >= 3 and time.perf_counter() - begun > args.budget_s:
                break
            pair = [("ours", lambda model=model: model.rollout(x0, actions)),
                    ("base", lambda: baseline_rollout(base_net, base_x0, actions))]
            for who, fn in pair if r % 2 == 0 else pair[::-1]:
                (ours if who == "ours" else base).append(timed(fn))
        baseline_all += base
        m_ours, m_base = statistics.median(ours), statistics.median(base)
        pair_ratios = [b / o for o, b in zip(ours, base, strict=True)]
        per_kind[name] = {
            "sample_steps_per_s": sample_steps / m_ours,
            "ms_per_rollout": 1e3 * m_ours,
            "baseline_sample_steps_per_s": sample_steps / m_base,
            "baseline_ms_per_rollout": 1e3 * m_base,
            "ratio_to_baseline": m_base / m_ours,
            "median_paired_ratio": statistics.median(pair_ratios),
            "mlp_calls_per_step": calls,
            "ratio_per_mlp_call": calls * m_base / m_ours,
            "repeats_s": {"model": ours, "baseline": base},
        }

    result = {
        "benchmark": "rollout",
        "command": " ".join(["python", *map(shlex.quote, sys.argv)]),
        "machine": {**machine_info(), "load_average_at_start": load_start, "load_average_at_end": os.getloadavg(),
                    "oversubscribed": max(load_start[0], os.getloadavg()[0]) > (os.cpu_count() or 1)},
        "parameters": {"batch": args.batch, "horizon": args.horizon, "repeats": args.repeats, "budget_s": args.budget_s,
                       "dtype": "float32", "hidden": 128, "weights": "random (seeded)"},
        "results": {k: v["sample_steps_per_s"] for k, v in per_kind.items()},
        "baseline": {
            "description": "no_grad eager loop s = s + net(cat(s, a)), same MLP, s0 = normalised x0",
            "sample_steps_per_s": sample_steps / statistics.median(baseline_all),
        },
        "ratios": {k: v["ratio_to_baseline"] for k, v in per_kind.items()},
        "ratios_per_mlp_call": {k: v["ratio_per_mlp_call"] for k, v in per_kind.items()},
        "method_to_kind": METHOD_KIND,
        "details": per_kind,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
