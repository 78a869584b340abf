"""Benchmark: Monte Carlo planning throughput (sample-steps/s) at K=1000 samples, horizon T=100.

Writes bench/results/planner.json.  All in one run, float32, no torch.compile
anywhere.  Each round runs every case once (order rotated); rates are medians
(and bests) over rounds, ratios the median over rounds of the two cases' ratio
in that round, which a shared machine's changing load disturbs least:

- ``planner_default``: ``Planner.plan`` end to end (sampling, fused rollout, safety and
  goal scoring, selection) in the planner's default mode, ``samples = K`` with its
  refinement rounds (``1 + refine_iterations`` draws, the elites kept), on the paper's MLP
  (a ``TransitionModel`` with random weights and a hand-like normalisation);
- ``planner_one_round``: the same with ``refine_iterations = 0``: one draw of K;
- ``fused_rollout``: the planner's rollout alone (planning/fused.py);
- ``eager_loop``: the plain eager loop ``s = s + net(cat(s, a))`` under no_grad
  with the same MLP (baseline a);
- ``mppi``: pytorch_mppi 0.9.1 ``MPPI.command`` with the same MLP as dynamics
  (``s + net(cat(s, a))``) and a squared goal distance as running cost
  (baseline b): one command rolls out K samples once; skipped with a note when
  pytorch_mppi is not installed (``pip install pytorch_mppi==0.9.1``);
- ``matmul_bound``: only the three products of one step at batch K, each in the
  form torch computes it fastest on the CPU (MKL's ``addmm`` with the weight
  stored transposed, as a transposed view, or the output transposed, or oneDNN's
  linear; timed per layer at the start: ``matmul_forms``): the matrix work of one
  step, the reference ceiling.  ``matmul_bound_mkl``: ``addmm`` with the weight
  stored transposed for all three, the bound as this benchmark defined it until
  2026-12-05 (on the AMD host other forms are faster at two of the three
  shapes, so that bound was no ceiling);
- ``transcendental_floor``: ``matmul_bound`` plus the two transcendental passes
  every step of this MLP needs, one ``exp2`` over the first hidden layer (SELU's
  negative branch) and one ``sigmoid`` over the second (tanh), as eager torch
  kernels at batch K (the sigmoid inside oneDNN's product when the second layer's
  form is oneDNN).  ``transcendental_floor_vs_matmul_bound`` is the most an
  eager rollout evaluating those two functions over whole layers with torch's
  kernels can reach against the bound; ``fused_rollout_vs_transcendental_floor``
  is what the fused rollout's other work (clamps, adds, copies, dispatch) leaves
  of that.

Every rate counts the rollouts a call actually made (``rollouts_per_call`` x horizon
sample-steps): a planner call in the default mode rolls out about four times K, so
equal call counts would compare unequal work.  Every ratio is of those rates (work per
second), named ``A_vs_B`` and described in ``ratios_described``.  How fast a plan is at
equal success (not at equal work) is the quality benchmark's ``time_to_rate``
(``bench/bench_planner_quality.py``), copied under ``latency_at_equal_success``
from ``bench/results/planner_quality.json`` when that file is there.

Peak RSS: a fresh subprocess per setting plans once with K=100k (default
chunking, then one unchunked batch) and reports its peak resident memory.

    .venv/bin/python bench/bench_planner.py                 # 1 thread (robust on a busy machine)
    .venv/bin/python bench/bench_planner.py --threads 2 --repeats 11
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from machine import machine_info  # bench/machine.py (scripts run from bench/)
from torch import Tensor, nn

from t42_transfer.models import Normalisation, TransitionModel
from t42_transfer.planning import Planner, PlannerConfig, Workspace
from t42_transfer.planning.fused import FusedRollout
from t42_transfer.planning.planner import CHUNK

RESULTS = Path(__file__).parent / "results" / "planner.json"
START = torch.tensor([0.0, 80.0, 120.0, -120.0])
GOAL = torch.tensor([10.0, 70.0])
WORKSPACE = Workspace.box(-200.0, 200.0, -100.0, 300.0, load_limit=1e6)
"""Wide: random weights drift, and a rejected sample must not change the work measured."""


def build_model(seed: int = 0) -> TransitionModel:
    torch.manual_seed(seed)
    norm = Normalisation(
        state_mean=np.array([0.0, 80.0, 120.0, -120.0], np.float32),
        state_std=np.array([15.0, 10.0, 30.0, 30.0], np.float32),
        delta_mean=np.zeros(4, np.float32),
        delta_std=np.array([0.4, 0.4, 2.0, 2.0], np.float32),
    )
    return TransitionModel(norm).eval()


@torch.no_grad()
def eager_loop(net: nn.Module, x0: Tensor, actions: Tensor) -> Tensor:
    s, out = x0, [x0]
    for t in range(actions.shape[1]):
        s = s + net(torch.cat([s, actions[:, t]], dim=-1))
        out.append(s)
    return torch.stack(out, dim=1)


def _find_onednn_linear() -> Callable[..., Tensor] | None:
    """oneDNN's fused linear (what inductor emits for CPU linears), when this torch has it."""
    if not torch.backends.mkldnn.is_available():
        return None
    try:
        return torch.ops.mkldnn._linear_pointwise
    except (AttributeError, RuntimeError):
        return None


ONEDNN_LINEAR = _find_onednn_linear()
FORMS = ("mkl", "mkl_weight_view", "mkl_transposed_output", *(("onednn",) if ONEDNN_LINEAR else ()))
"""The ways torch computes ``x @ W.T + b`` from a row-major ``x`` [K, in] on the CPU: MKL's ``addmm`` with ``W.T``
stored contiguous, or as a transposed view of ``W``, or computing the transposed output ``W @ x.T + b`` [out, K];
oneDNN's linear."""


def _product(form: str, inputs: Tensor, weight: Tensor, bias: Tensor, out: Tensor,
             activation: str = "none") -> Callable[[], object]:
    """One layer's product at the benchmark's shapes in ``form`` (:data:`FORMS`), into ``out`` (or its transpose)
    where the form takes an output, optionally with oneDNN's fused activation."""
    if activation != "none" and form != "onednn":
        raise ValueError("only oneDNN fuses an activation into the product")
    if form == "mkl":
        wt = weight.T.contiguous()
        return lambda: torch.addmm(bias, inputs, wt, out=out)
    if form == "mkl_weight_view":
        return lambda: torch.addmm(bias, inputs, weight.T, out=out)
    if form == "mkl_transposed_output":
        column, out_t = bias[:, None].contiguous(), out.T.contiguous()
        return lambda: torch.addmm(column, weight, inputs.T, out=out_t)
    return lambda: ONEDNN_LINEAR(inputs, weight, bias, activation, [], "")


def _products(model: TransitionModel, batch: int) -> list[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Random inputs and, per linear layer of the MLP, ``(inputs, weight [out, in], bias, output)``."""
    layers = [model.net[i] for i in (0, 3, 6)]
    return [(torch.randn(batch, layer.in_features), layer.weight.detach().contiguous(), layer.bias.detach(),
             torch.empty(batch, layer.out_features)) for layer in layers]


def _repeat(fn: Callable[[], object], times: int) -> None:
    """``fn`` ``times`` times, each result dropped at once (a list of them would time the allocator)."""
    for _ in range(times):
        fn()


def fastest_forms(model: TransitionModel, batch: int, calls: int = 200, rounds: int = 5) -> dict[str, dict]:
    """Per layer, each form's median microseconds a product over ``rounds`` (forms alternating) and the fastest."""
    layers = {}
    for i, layer in enumerate(_products(model, batch), start=1):
        runs = {form: _product(form, *layer) for form in FORMS}
        times: dict[str, list[float]] = {form: [] for form in runs}
        for _ in range(rounds):
            for form, run in runs.items():
                run()
                times[form].append(timed(lambda run=run: _repeat(run, calls)) / calls * 1e6)
        us = {form: statistics.median(ts) for form, ts in times.items()}
        layers[f"layer{i}"] = {"us_per_product": us, "form": min(us, key=us.get)}
    return layers


def matmul_only(model: TransitionModel, batch: int, horizon: int,
                forms: tuple[str, str, str] = ("mkl", "mkl", "mkl")) -> Callable[[], None]:
    """The three products of a step, ``horizon`` times, layer i in ``forms[i]``."""
    first, second, third = (_product(form, *layer) for form, layer in zip(forms, _products(model, batch),
                                                                          strict=True))

    def run() -> None:
        for _ in range(horizon):
            first()
            second()
            third()

    return run


def transcendental_floor(model: TransitionModel, batch: int, horizon: int,
                         forms: tuple[str, str, str] = ("mkl", "mkl", "mkl")) -> Callable[[], None]:
    """``matmul_only`` plus one exp2 pass over the first hidden layer and one sigmoid over the second (inside
    oneDNN's product when that layer's form is oneDNN)."""
    (i1, w1, b1, h1), (i2, w2, b2, h2), (i3, w3, b3, h3) = _products(model, batch)
    exp2 = torch.empty_like(h1)
    first, third = _product(forms[0], i1, w1, b1, h1), _product(forms[2], i3, w3, b3, h3)
    if forms[1] == "onednn":
        second = _product("onednn", i2, w2, b2, h2, "sigmoid")
    else:
        product, sigmoid = _product(forms[1], i2, w2, b2, h2), torch.empty_like(h2)

        def second() -> None:
            product()
            torch.sigmoid(h2, out=sigmoid)

    def run() -> None:
        for _ in range(horizon):
            first()
            torch.exp2(h1, out=exp2)
            second()
            third()

    return run


def mppi_command(net: nn.Module, batch: int, horizon: int) -> Callable[[], None] | str:
    try:
        from pytorch_mppi import MPPI
    except ImportError:
        return "pytorch_mppi not installed: pip install pytorch_mppi==0.9.1 to measure this baseline"

    @torch.no_grad()
    def dynamics(s: Tensor, a: Tensor) -> Tensor:
        return s + net(torch.cat([s, a], dim=-1))

    def running_cost(s: Tensor, a: Tensor) -> Tensor:
        return ((s[:, :2] - GOAL) ** 2).sum(-1)

    mppi = MPPI(
        dynamics,
        running_cost,
        nx=4,
        noise_sigma=0.3 * torch.eye(2),
        num_samples=batch,
        horizon=horizon,
        lambda_=1.0,
        u_min=-torch.ones(2),
        u_max=torch.ones(2),
    )
    return lambda: mppi.command(START)


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _status_mib(key: str) -> float:
    """A memory figure of this process from /proc/self/status (VmRSS: now, VmHWM: peak), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def rss_child(samples: int, chunk: int) -> None:
    """Subprocess body: resident memory before one plan of ``samples`` sequences and its peak during it (MiB)."""
    model = build_model()
    planner = Planner(model, WORKSPACE, PlannerConfig(samples=samples, chunk=chunk))
    Planner(model, WORKSPACE, PlannerConfig(samples=10, horizon=5)).plan(START, GOAL)
    before = _status_mib("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak (VmHWM) to the current RSS
    seconds = timed(lambda: planner.plan(START, GOAL))
    peak = _status_mib("VmHWM")
    print(
        json.dumps(
            {
                "samples": samples,
                "chunk": chunk,
                "rss_mib_before": before,
                "peak_rss_mib": peak,
                "plan_peak_increase_mib": peak - before,
                "seconds": seconds,
            }
        )
    )


def peak_rss(samples: int, chunk: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--threads", str(threads), "--rss-child", str(samples), str(chunk)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


QUALITY = RESULTS.with_name("planner_quality.json")


def equal_success() -> dict:
    """The quality benchmark's median plan time at which each optimiser first reaches each success rate, as stored
    (its own command, machine and model), or why there is none."""
    if not QUALITY.is_file():
        return {"note": f"no {QUALITY.name}: run bench/bench_planner_quality.py"}
    quality = json.loads(QUALITY.read_text())
    return {"source": f"bench/results/{QUALITY.name}", "command": quality.get("command"),
            "machine": quality.get("machine"), "time_to_rate": quality.get("time_to_rate")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rss-samples", type=int, default=100_000, help="K of the peak-RSS runs (0: skip them)")
    parser.add_argument("--rss-child", type=int, nargs=2, metavar=("SAMPLES", "CHUNK"), help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.rss_child:
        rss_child(*args.rss_child)
        return

    load_start = os.getloadavg()
    k, horizon = args.samples, args.horizon
    model = build_model()
    net = model.net
    gen = torch.Generator().manual_seed(0)
    x0 = START.expand(k, 4).contiguous()
    actions = torch.rand(k, horizon, 2, generator=gen) * 2 - 1
    planner = Planner(model, WORKSPACE, PlannerConfig(samples=k, horizon=horizon))
    one_round = Planner(model, WORKSPACE, PlannerConfig(samples=k, horizon=horizon, refine_iterations=0))
    fused = FusedRollout(model)
    forms = fastest_forms(model, k)
    fastest = tuple(forms[f"layer{i}"]["form"] for i in (1, 2, 3))
    cases: dict[str, Callable[[], object]] = {
        "planner_default": lambda: planner.plan(START, GOAL),
        "planner_one_round": lambda: one_round.plan(START, GOAL),
        "fused_rollout": lambda: fused(x0, actions),
        "eager_loop": lambda: eager_loop(net, x0, actions),
        "matmul_bound": matmul_only(model, k, horizon, fastest),
        "matmul_bound_mkl": matmul_only(model, k, horizon),
        "transcendental_floor": transcendental_floor(model, k, horizon, fastest),
    }
    mppi = mppi_command(net, k, horizon)
    notes = {}
    if isinstance(mppi, str):
        notes["mppi"] = mppi
    else:
        cases["mppi"] = mppi
    for fn in cases.values():  # warm-up: allocator, first-call dispatch
        fn()
    rollouts = {name: k for name in cases}  # sequences of the whole horizon rolled out per call
    rollouts.update(planner_default=planner.plan(START, GOAL).evaluated,
                    planner_one_round=one_round.plan(START, GOAL).evaluated)
    times: dict[str, list[float]] = {name: [] for name in cases}
    names = list(cases)
    for r in range(args.repeats):
        for name in names[r % len(names) :] + names[: r % len(names)]:  # rotate the order
            times[name].append(timed(cases[name]))

    rate = {name: rollouts[name] * horizon / statistics.median(ts) for name, ts in times.items()}
    best = {name: rollouts[name] * horizon / min(ts) for name, ts in times.items()}

    def paired(a: str, b: str) -> float:
        """Median over rounds of rate a / rate b (sample-steps of rollouts made per second): both ran back to
        back under the same load."""
        return statistics.median((rollouts[a] / ta) / (rollouts[b] / tb)
                                 for ta, tb in zip(times[a], times[b], strict=True))

    pairs = [(p, b) for p in ("planner_default", "planner_one_round") for b in ("eager_loop", "matmul_bound", "mppi")]
    pairs += [("fused_rollout", "matmul_bound"), ("fused_rollout", "matmul_bound_mkl"),
              ("matmul_bound_mkl", "matmul_bound"), ("transcendental_floor", "matmul_bound"),
              ("fused_rollout", "transcendental_floor")]
    pairs = [(a, b) for a, b in pairs if b in times]
    ratios = {f"{a}_vs_{b}": paired(a, b) for a, b in pairs}
    described = {f"{a}_vs_{b}": f"sample-steps per second of the rollouts {a} made, over those of {b}"
                 for a, b in pairs}
    rss = []
    if args.rss_samples:
        rss = [
            peak_rss(args.rss_samples, CHUNK, args.threads),
            peak_rss(args.rss_samples, args.rss_samples, args.threads),
        ]

    result = {
        "benchmark": "planner",
        "command": " ".join(["python", *map(shlex.quote, sys.argv)]),
        "machine": {**machine_info(), "load_average_at_start": load_start},
        "parameters": {
            "samples": k,
            "horizon": horizon,
            "repeats": args.repeats,
            "dtype": "float32",
            "hidden": 128,
            "weights": "random (seeded)",
            "sampler": planner.config.sampler,
            "chunk": planner.config.chunk,
            "torch_compile": False,
        },
        "matmul_forms": forms,
        "rollouts_per_call": rollouts,
        "sample_steps_per_s": rate,
        "best_sample_steps_per_s": best,
        "ms_per_call": {name: 1e3 * statistics.median(ts) for name, ts in times.items()},
        "ratios": ratios,
        "ratios_described": described,
        "targets": {
            "fused_rollout_vs_matmul_bound >= 0.8": ratios["fused_rollout_vs_matmul_bound"] >= 0.8,
            "planner_default_vs_matmul_bound >= 0.5": ratios["planner_default_vs_matmul_bound"] >= 0.5,
        },
        "latency_at_equal_success": equal_success(),
        "peak_rss": rss,
        "notes": notes,
        "repeats_s": times,
    }
    result["machine"]["load_average_at_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(
        json.dumps(
            {k: result[k] for k in ("sample_steps_per_s", "ms_per_call", "ratios", "targets", "peak_rss", "notes")},
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
