"""Executing plans on a hand: open loop (the paper's setting) or replanning every k steps (MPC).

Open loop plans once from the start and sends the whole sequence.  With
``replan_every = k`` the planner plans the remaining steps from the measured
state, the hand executes the first ``k`` actions, and so on until the fixed
number of steps has run: what feedback buys on the same goals.  If a replan is
refused mid-way, the rest of the previous plan is kept.

The hand is anything with a ``state`` and ``step_info(action)`` (a
:class:`~t42_transfer.hand.sim.SimulatedHand`, or a toy system in tests).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from t42_transfer.planning.planner import Plan

if TYPE_CHECKING:  # the hand's step report; the simulator itself is not needed here
    from t42_transfer.hand.sim import StepInfo


class Steppable(Protocol):
    @property
    def state(self) -> np.ndarray: ...

    def step_info(self, action: np.ndarray) -> StepInfo: ...


PlanAt = Callable[[np.ndarray, int], Plan]
"""``(measured state [4], steps left) -> Plan``: plans the remaining steps from where the hand is."""


@dataclass(frozen=True)
class Execution:
    actions: np.ndarray
    """``[L, 2]`` actions executed."""
    states: np.ndarray
    """``[L + 1, 4]`` measured states, from the start."""
    end_reason: str
    """``length`` when every step ran; the hand's reason ('dropped', ...) or ``refused`` (no plan to execute)."""
    plans: tuple[Plan, ...]
    """Every plan made, in order (one when open loop)."""

    @property
    def completed(self) -> bool:
        return self.end_reason == "length"


def execute(hand: Steppable, plan_at: PlanAt, steps: int, replan_every: int = 0) -> Execution:
    """Run ``steps`` actions on ``hand`` from its current state, planning once (``replan_every = 0``) or every k steps."""
    if steps < 1 or replan_every < 0:
        raise ValueError(f"need steps >= 1 and replan_every >= 0, got {steps} and {replan_every}")
    states, actions, plans = [hand.state.copy()], [], []
    queue = np.zeros((0, 2))
    while len(actions) < steps:
        left = steps - len(actions)
        if not plans or (replan_every and len(actions) % replan_every == 0):
            plan = plan_at(states[-1], left)
            plans.append(plan)
            if len(plan.actions):
                queue = plan.actions
        if len(queue) == 0:
            return _done(states, actions, "refused", plans)
        burst = queue[: replan_every or len(queue)]
        queue = queue[len(burst):]
        for action in burst:
            info = hand.step_info(np.asarray(action, dtype=np.float64))
            actions.append(np.asarray(action, dtype=np.float64))
            states.append(hand.state.copy())
            if info.done:
                return _done(states, actions, info.end_reason, plans)
        if not replan_every and len(queue) == 0 and len(actions) < steps:
            return _done(states, actions, "short_plan", plans)
    return _done(states, actions, "length", plans)


def _done(states: list, actions: list, reason: str, plans: list[Plan]) -> Execution:
    return Execution(np.asarray(actions, dtype=np.float64).reshape(-1, 2), np.asarray(states), reason, tuple(plans))
