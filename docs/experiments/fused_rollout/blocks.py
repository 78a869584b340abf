"""Where the fused rollout's time goes beyond the matrix products, and whether cache blocking recovers any of it.

Two measurements at K = 1000 samples, T = 100 steps, one thread, the paper's MLP of ``bench/bench_planner.py``:

1. each kernel of one step alone (microseconds a call, median of 5 x 200 calls), the products and the
   activations' passes as ``planning/fused.py`` runs them;
2. the whole rollout over the batch at once against the same rollout run on row blocks of 500 ... 125
   samples one after another (each block's layers then fit the 1 MiB L2 of the AMD host), rounds interleaved.

If the activations' passes were bound by memory traffic, blocks that stay in L2 would run them faster.

    .venv/bin/python docs/experiments/fused_rollout/blocks.py
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
import bench_planner  # noqa: E402

from t42_transfer.planning.fused import NEGATIVE_BRANCH, FusedRollout  # noqa: E402

SAMPLES, HORIZON, HIDDEN = 1000, 100, 128


def per_call_us(fn: Callable[[], object], calls: int = 200, rounds: int = 5) -> float:
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - start) / calls * 1e6)
    return statistics.median(times)


def kernels(rollout: FusedRollout) -> dict[str, float]:
    w = rollout.weights
    x = torch.randn(SAMPLES, w.w1.shape[0])
    h1, pre = torch.randn(SAMPLES, HIDDEN), torch.randn(SAMPLES, HIDDEN) * 3
    e, h2, delta = torch.empty(SAMPLES, HIDDEN), torch.empty(SAMPLES, HIDDEN), torch.empty(4, SAMPLES)
    state, after = torch.randn(SAMPLES, 4), torch.empty(SAMPLES, 4)
    return {
        "first product": per_call_us(lambda: torch.addmm(w.b1, x, w.w1, out=h1)),
        "exp2": per_call_us(lambda: torch.exp2(pre, out=e)),
        "clamp_max_": per_call_us(lambda: e.clamp_max_(1.0)),
        "clamp_min_": per_call_us(lambda: h1.clamp_min_(0.0)),
        "add_ (negative branch)": per_call_us(lambda: h1.add_(e, alpha=NEGATIVE_BRANCH)),
        "second product": per_call_us(lambda: torch.addmm(w.b2, h1, w.w2, out=h2)),
        "sigmoid_": per_call_us(lambda: h2.sigmoid_()),
        "third product (transposed)": per_call_us(lambda: torch.addmm(w.b3, w.w3, h2.T, out=delta)),
        "add (state)": per_call_us(lambda: torch.add(state, delta.T, out=after)),
    }


def blocked(rollout: FusedRollout, x0: torch.Tensor, actions: torch.Tensor, rows: int) -> torch.Tensor:
    return torch.cat([rollout.time_major(x0[i:i + rows], actions[i:i + rows]) for i in range(0, SAMPLES, rows)], 1)


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rollout = FusedRollout(bench_planner.build_model())
    for name, us in kernels(rollout).items():
        print(f"{name:28s} {us:7.1f} us")
    x0 = bench_planner.START.expand(SAMPLES, 4).contiguous() + torch.randn(SAMPLES, 4)
    actions = torch.rand(SAMPLES, HORIZON, 2) * 2 - 1
    cases = {"whole batch": lambda: rollout.time_major(x0, actions)}
    cases |= {f"blocks of {rows}": (lambda rows=rows: blocked(rollout, x0, actions, rows))
              for rows in (500, 334, 250, 200, 125)}
    reference = cases["whole batch"]()
    for run in cases.values():
        torch.testing.assert_close(run(), reference)
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(7):
        for name, run in cases.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    for name, ts in times.items():
        print(f"{name:28s} {1e3 * statistics.median(ts):6.1f} ms (best {1e3 * min(ts):.1f})")


if __name__ == "__main__":
    main()
