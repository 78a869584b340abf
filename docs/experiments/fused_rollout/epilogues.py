"""Can the activations ride on the products?  oneDNN's linear with the sigmoid (or tanh) inside, and SELU as one ELU.

Per batch size K (the planner's refinement batches are small, its first draw K = 1000), one thread, the
paper's MLP shapes (6 -> 128 -> 128 -> 4), median microseconds a call over interleaved rounds:

* the second layer and its activation: MKL's ``addmm`` then an in-place ``sigmoid_`` (what
  ``planning/fused.py`` does), against oneDNN's ``_linear_pointwise`` with the sigmoid or the tanh fused
  into the product, with the weight as it is and prepacked (``_reorder_linear_weight``);
* the first layer and SELU: ``addmm`` then the four passes of ``fused.py`` (exp2, two clamps, an add) against
  ``addmm`` then one in-place ``elu_`` (SELU's scale folds into the next layer).

If the fused forms were much cheaper at K = 1000, choosing them by batch size would move the fused rollout
towards the issue's 0.8 of the matmul bound.

    .venv/bin/python docs/experiments/fused_rollout/epilogues.py
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable

import torch

from t42_transfer.planning.fused import NEGATIVE_BRANCH, SELU_ALPHA

HIDDEN, INPUTS = 128, 6
BATCHES = (30, 100, 300, 1000)


def per_call_us(fn: Callable[[], object], calls: int) -> float:
    fn()
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls * 1e6


def cases(batch: int) -> dict[str, Callable[[], object]]:
    gen = torch.Generator().manual_seed(batch)
    h1_in, x = torch.randn(batch, INPUTS, generator=gen), torch.randn(batch, HIDDEN, generator=gen)
    w1, w2 = torch.randn(HIDDEN, INPUTS, generator=gen), torch.randn(HIDDEN, HIDDEN, generator=gen) / HIDDEN**0.5
    b1, b2 = torch.randn(HIDDEN, generator=gen), torch.randn(HIDDEN, generator=gen)
    w1t, w2t = w1.T.contiguous(), w2.T.contiguous()
    h1, exponential, h2 = (torch.empty(batch, HIDDEN) for _ in range(3))
    linear = torch.ops.mkldnn._linear_pointwise
    packed = torch.ops.mkldnn._reorder_linear_weight(w2, batch)

    def selu_passes() -> None:
        torch.addmm(b1, h1_in, w1t, out=h1)
        torch.exp2(h1, out=exponential).clamp_max_(1.0)
        h1.clamp_min_(0.0).add_(exponential, alpha=NEGATIVE_BRANCH)

    return {
        "layer2: addmm + sigmoid_": lambda: torch.addmm(b2, x, w2t, out=h2).sigmoid_(),
        "layer2: oneDNN with sigmoid": lambda: linear(x, w2, b2, "sigmoid", [], ""),
        "layer2: oneDNN with tanh": lambda: linear(x, w2, b2, "tanh", [], ""),
        "layer2: oneDNN prepacked with sigmoid": lambda: linear(x, packed, b2, "sigmoid", [], ""),
        "layer1: addmm + SELU in four passes": selu_passes,
        "layer1: addmm + elu_": lambda: torch.nn.functional.elu_(torch.addmm(b1, h1_in, w1t, out=h1), SELU_ALPHA),
    }


def main() -> None:
    torch.set_num_threads(1)
    load = os.getloadavg()
    results = {}
    for batch in BATCHES:
        runs = cases(batch)
        times: dict[str, list[float]] = {name: [] for name in runs}
        calls = max(50, 40_000 // batch)
        for _ in range(7):
            for name, run in runs.items():
                times[name].append(per_call_us(run, calls))
        results[batch] = {name: round(statistics.median(t), 1) for name, t in times.items()}
        print(batch, json.dumps(results[batch]), flush=True)
    print(json.dumps({"load_average_at_start": load, "load_average_at_end": os.getloadavg(),
                      "torch": torch.__version__}))


if __name__ == "__main__":
    main()
