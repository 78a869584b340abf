"""The fused rollout against the same step compiled whole by torch.compile (inductor), and the matmul bound.

Could a compiler that fuses the activations' passes and drops eager dispatch reach issue 23's 0.8 of the matmul
bound?  The paper's MLP of ``bench/bench_planner.py`` (random weights, hand-like normalisation), K = 1000
samples, T = 100 steps, one thread; the compiled function unrolls the 100 steps (one compile per horizon).

    .venv/bin/python docs/experiments/fused_rollout/compile_loop.py
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch
from torch import Tensor
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
import bench_planner  # noqa: E402

from t42_transfer.planning.fused import NEGATIVE_BRANCH, FusedRollout  # noqa: E402

SAMPLES, HORIZON, REPEATS = 1000, 100, 11


def main() -> None:
    torch.set_num_threads(1)
    model = bench_planner.build_model()
    fused = FusedRollout(model)
    w = fused.weights
    if w.grasp_input:
        raise SystemExit("this comparison folds no grasp input")
    x0 = torch.tensor([0.0, 80.0, 100.0, -100.0]).expand(SAMPLES, 4).contiguous()
    actions = torch.rand(SAMPLES, HORIZON, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1

    def rollout(x0: Tensor, actions: Tensor) -> Tensor:
        """The fused rollout's arithmetic, written plainly for the compiler to fuse."""
        state, states = x0, [x0]
        for t in range(actions.shape[1]):
            h1 = torch.addmm(w.b1, torch.cat([state, actions[:, t]], 1), w.w1)
            h1 = h1.clamp_min(0) + NEGATIVE_BRANCH * torch.exp2(h1.clamp_max(0))
            state = state + F.linear(torch.sigmoid(torch.addmm(w.b2, h1, w.w2)), w.w3, w.b3[:, 0])
            states.append(state)
        return torch.stack(states)

    forms = bench_planner.fastest_forms(model, SAMPLES)
    fastest = tuple(forms[f"layer{i}"]["form"] for i in (1, 2, 3))
    print(f"the bound's forms, layers 1-3: {', '.join(fastest)}")
    with torch.inference_mode():
        start = time.perf_counter()
        compiled = torch.compile(rollout, dynamic=False)
        difference = (compiled(x0, actions) - fused.time_major(x0, actions)).abs().max().item()
        print(f"compile {time.perf_counter() - start:.1f} s; largest difference from the fused {difference:.2g}")
        cases = {"fused": lambda: fused.time_major(x0, actions), "compiled": lambda: compiled(x0, actions),
                 "matmul_bound": bench_planner.matmul_only(model, SAMPLES, HORIZON, fastest),
                 "matmul_bound_mkl": bench_planner.matmul_only(model, SAMPLES, HORIZON)}
        ms = {}
        for name, call in cases.items():
            for _ in range(3):
                call()
            times = []
            for _ in range(REPEATS):
                start = time.perf_counter()
                call()
                times.append(time.perf_counter() - start)
            ms[name] = 1e3 * statistics.median(times)
        for name in ("fused", "compiled"):
            print(f"{name}: {ms[name]:.1f} ms a call, {ms['matmul_bound'] / ms[name]:.2f} of the matmul bound "
                  f"({ms['matmul_bound']:.1f} ms), {ms['matmul_bound_mkl'] / ms[name]:.2f} of MKL's "
                  f"({ms['matmul_bound_mkl']:.1f} ms)")


if __name__ == "__main__":
    main()
