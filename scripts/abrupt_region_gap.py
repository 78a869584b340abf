#!/usr/bin/env python3
"""How target_abrupt differs from the source: one step from the same instant, inside and outside its region.

Prints the two tables of docs/simulated_hands.md ("target_abrupt: a hand that
differs in one region only").  About 20 s on one core.

    .venv/bin/python scripts/abrupt_region_gap.py
"""

from __future__ import annotations

import numpy as np

from t42_transfer.hand.collect import DROP_REASONS, POLICIES, collect
from t42_transfer.hand.params import variant
from t42_transfer.hand.sim import SimulatedHand

EPISODES, STEPS = 30, 300


def one_step_gaps(policy: str) -> str:
    """A markdown row: from each instant of source episodes, one step of each hand with the same action and noise."""
    source, abrupt = SimulatedHand("source"), SimulatedHand("target_abrupt")
    gaps: dict[bool, list[np.ndarray]] = {True: [], False: []}
    steps = []
    for episode in range(EPISODES):
        source.reset(300 + episode)
        for action in POLICIES[policy]().sample(np.random.default_rng([9, episode]), STEPS):
            snap, before = source.snapshot(), source.state
            expected = source.step(action)
            steps.append(np.linalg.norm(expected[:2] - before[:2]))
            abrupt.restore(snap)
            inside = abrupt.in_region
            got = abrupt.step(action)
            gaps[inside].append(np.r_[np.linalg.norm(got[:2] - expected[:2]), np.abs(got[2:] - expected[2:]).max()])
            if source.done:
                break
    inside, outside = np.array(gaps[True]), np.array(gaps[False])
    xy, load = np.percentile(inside[:, 0], [50, 90]), np.percentile(inside[:, 1], [50, 90])
    return (f"| {policy} | {len(steps)} | {len(inside) / len(steps):.0%} | {np.median(steps):.2f} mm "
            f"| {outside.max():.3g} | {xy[0]:.1f} mm, {xy[1]:.1f} mm | {load[0]:.0f}, {load[1]:.0f} |")


def on_its_own(hand: str) -> str:
    """Random-policy episodes of ``hand`` alone: time in the region, boundary crossings, steps there, drops."""
    region = variant("target_abrupt").region
    data, stats = collect(hand, EPISODES, STEPS, seed=3, workers=1, progress=False)
    inside_steps, crossings, steps_in = 0, 0, []
    total = 0
    for t in data:
        inside = np.array([region.contains(s) for s in t.states])  # tracked positions, 0.05 mm noise
        step = np.linalg.norm(np.diff(t.states[:, :2], axis=0), axis=1)
        steps_in += list(step[inside[:-1]])
        inside_steps += int(inside[:-1].sum())
        total += len(step)
        crossings += int(np.sum(inside[1:] != inside[:-1]))
    drops = sum(stats.end_reasons.get(r, 0) for r in DROP_REASONS)
    return (f"| {hand} | {inside_steps / total:.0%} | {crossings} | {np.percentile(steps_in, 99):.1f} mm "
            f"| {drops} of {stats.requested} |")


def main() -> None:
    print("| policy | steps | in region | source step median | gap outside | gap inside: x-y median, p90 "
          "| load median, p90 |\n|---|---|---|---|---|---|---|")
    for policy in ("random", "sustained"):
        print(one_step_gaps(policy))
    print("\n| hand | time in region | boundary crossings | p99 step in region | episodes dropped |"
          "\n|---|---|---|---|---|")
    for hand in ("source", "target_abrupt"):
        print(on_its_own(hand))


if __name__ == "__main__":
    main()
