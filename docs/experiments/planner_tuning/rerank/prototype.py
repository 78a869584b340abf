"""Prototype of the planner's ``rerank`` (docs/experiments/planner_tuning/README.md): the default search, then the
top K of its final population (K < 0: of every sequence it evaluated) predicted by M dropout members; the answer is
the one with the lowest ``mean + risk * std`` of their final distances, whatever its own prediction.  Members draw
fresh masks at every step (``DropoutRollout``, as ``uncertainty="dropout"``), or with ``fixed`` keep one draw each
(as ``rerank`` does).  It stands in for the benchmark's ``default_robust`` optimiser:

    cd bench && ../.venv/bin/python ../docs/experiments/planner_tuning/rerank/prototype.py K M RISK [fixed] \
        --goals 20 --seed 1 --model MODEL --budgets 300 --optimisers default default_robust --out OUT.json --quiet
"""
import copy
import math
import sys
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor

sys.path.insert(0, ".")  # run from bench/
import bench_planner_quality as bpq  # noqa: E402

from t42_transfer.planning import planner as pl  # noqa: E402
from t42_transfer.planning.members import DropoutRollout  # noqa: E402

K, M, RISK = (int(sys.argv.pop(1)), int(sys.argv.pop(1)), float(sys.argv.pop(1)))
FIXED = len(sys.argv) > 1 and sys.argv[1] == "fixed" and bool(sys.argv.pop(1))
ALPHA = 1.7580993408473766


def member(model: Any, gen: torch.Generator) -> Any:
    """The model with fixed dropout masks folded into its 2nd and 3rd layers (an eval-mode copy)."""
    m = copy.deepcopy(model).eval()
    p = model.dropout
    l2, l3 = m.net[3], m.net[6]
    H = l2.weight.shape[1]
    with torch.no_grad():
        m1 = (torch.rand(H, generator=gen) >= p).float()
        m2 = (torch.rand(H, generator=gen) >= p).float()
        a = 1.0 / math.sqrt((ALPHA * ALPHA * p + 1) * (1 - p))
        c = a * ALPHA * (m1 - 1 + p)
        l2.bias += l2.weight @ c
        l2.weight *= (a * m1)[None, :]
        l3.weight *= (m2 / (1 - p))[None, :]
    return m


def rerank_plan(model: Any, workspace: Any, x0: Tensor, goal: Tensor, steps: int, seed: int,
                config: Any) -> Any:
    cfg = replace(config, horizon=steps, horizon_search=False)
    planner = pl.Planner(model, workspace, cfg)
    gen = torch.Generator().manual_seed(seed)
    search = pl._Search(planner._rollouts(seed), workspace, x0, goal, cfg, None, None)
    count = cfg.samples
    actions = pl.sample_actions(cfg.sampler, count, steps, gen, cfg.hold_steps, cfg.init_std, cfg.noise_beta)
    cost = search.evaluate(actions)
    seen_a, seen_c = [actions], [cost]
    elite_count = max(2, int(cfg.elite_fraction * count))
    for _ in range(cfg.refine_iterations):
        order = pl._elites(cost, elite_count)
        if len(order) < 2:
            break
        elites, elite_cost = actions[order], cost[order]
        mean, std = elites.mean(0), elites.std(0).clamp_min(cfg.refine_min_std)
        noise = pl.colored_noise(max(1, count - len(order)), steps, cfg.noise_beta, gen)
        fresh = pl.project(cfg.sampler, mean + std * noise)
        fresh_cost = search.evaluate(fresh)
        seen_a.append(fresh)
        seen_c.append(fresh_cost)
        actions, cost = torch.cat([elites, fresh]), torch.cat([elite_cost, fresh_cost])
    if K < 0:
        actions, cost = torch.cat(seen_a), torch.cat(seen_c)
    order = pl._elites(cost, abs(K))
    extra = 0
    if len(order) > 1:
        cands = actions[order]
        if FIXED:
            g = torch.Generator().manual_seed(seed + 12345)
            ds = []
            for _ in range(M):
                states = member(model, g).rollout(x0.expand(len(cands), -1), cands).transpose(0, 1)
                final = states[-1, :, :2].float() - goal
                ds.append(torch.hypot(final[:, 0], final[:, 1]))
            d = torch.stack(ds)
        else:
            draw = DropoutRollout(model, seed)
            batch = cands.repeat(M, 1, 1)  # [M * K, T, 2]: each copy gets masks of its own
            states = draw(x0.expand(len(batch), -1), batch)  # [T+1, M*K, 4]
            final = states[-1, :, :2].float() - goal
            d = torch.hypot(final[:, 0], final[:, 1]).view(M, len(cands))
        extra = M * len(cands)
        score = d.mean(0) + RISK * d.std(0)
        chosen = int(torch.argmin(score))
        search.answer_with(cands[chosen][None])
    plan = search.result()
    return bpq.Outcome(plan.actions, plan.error_mm, len(plan.actions) > 0, plan.evaluated + extra, plan.status)


orig = bpq.optimise


def optimise(name: str, model: Any, workspace: Any, x0: Tensor, goal: Tensor, steps: int, budget: int, seed: int,
             setting: Any) -> Any:
    if name == "default_robust":  # stands for the re-ranked default in this prototype
        default = bpq.PegInHoleConfig().planner
        cfg = replace(default, samples=max(2, budget // (default.refine_iterations + 1)))
        return rerank_plan(model, workspace, x0, goal, steps, seed, cfg)
    return orig(name, model, workspace, x0, goal, steps, budget, seed, setting)


bpq.optimise = optimise
sys.exit(bpq.main())
