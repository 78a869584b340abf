"""Executing plans on a hand: open loop (the paper's setting) or replanning every k steps (MPC).

Open loop plans once from the start and sends the whole sequence.  With
``replan_every = k`` the planner plans the remaining steps from the measured
state, the hand executes the first ``k`` actions, and so on until the fixed
number of steps has run: what feedback buys on the same goals.  If a replan is
refused mid-way, the rest of the previous plan is kept.  The rule is
:func:`receding_horizon`, which the planner node runs too.

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


PlanAt = Callable[[np.ndarray, int, np.ndarray], Plan]
"""``(measured state [4], steps left, previous [n, 2]) -> Plan``: plans the remaining steps from where the hand is;
``previous`` is what the plan being replaced still had to send (``[0, 2]`` for the first plan), for a planner
that starts its search there (:attr:`~t42_transfer.planning.planner.PlannerConfig.warm_start`)."""


@dataclass(frozen=True)
class Execution:
    actions: np.ndarray
    """``[L, 2]`` actions executed."""
    states: np.ndarray
    """``[L + 1, 4]`` measured states, from the start."""
    end_reason: str
    """How :func:`receding_horizon` ended: ``length`` when every step ran, the hand's reason ('dropped', ...),
    ``short_plan``, ``refused`` (no plan to execute) or ``no_state``."""
    plans: tuple[Plan, ...]
    """Every plan made, in order (one when open loop)."""

    @property
    def completed(self) -> bool:
        return self.end_reason == "length"


Send = Callable[[np.ndarray], str]
"""Executes a piece of actions on the hand; the hand's end reason if the episode ended in it, else ``""``."""
Measure = Callable[[], "np.ndarray | None"]
"""The measured state after the pieces sent so far (None: no state to plan from, the loop ends)."""


def receding_horizon(plan_at: PlanAt, send: Send, measure: Measure, steps: int, replan_every: int = 0,
                     first: Plan | None = None) -> tuple[list[Plan], str]:
    """The one MPC rule, for :func:`execute` and the planner node: the plans made and why the loop ended.

    Plan ``steps`` from the measured state (or take ``first``), send the first ``replan_every``
    actions (all of them with 0: open loop), then plan what is left from the state measured
    after them, and so on.  A replan without actions (refused: no safe sequence) keeps the
    rest of the previous plan, which was checked safe when it was made; the loop ends when
    every step has run (``length``), when the hand ends the episode (its reason), when a
    plan is used up before ``steps`` (``short_plan``: a plan that reaches early), when there
    is nothing to send (``refused``) or no state to plan from (``no_state``).
    """
    if steps < 1 or replan_every < 0:
        raise ValueError(f"need steps >= 1 and replan_every >= 0, got {steps} and {replan_every}")
    plans: list[Plan] = []
    queue = np.zeros((0, 2), np.float32)
    done = 0
    while done < steps:
        if not plans or replan_every:
            if plans or first is None:
                state = measure()
                if state is None:
                    return plans, "no_state"
                plan = plan_at(state, steps - done, queue)
            else:
                plan = first
            plans.append(plan)
            if len(plan.actions):
                queue = plan.actions
        if len(queue) == 0:
            return plans, "refused"
        piece, queue = queue[: replan_every or len(queue)], queue[replan_every or len(queue):]
        reason = send(piece)
        done += len(piece)
        if reason:
            return plans, reason
        if len(queue) == 0 and done < steps:
            return plans, "short_plan"
    return plans, "length"


def execute(hand: Steppable, plan_at: PlanAt, steps: int, replan_every: int = 0) -> Execution:
    """Run ``steps`` actions on ``hand`` from its current state, planning once (``replan_every = 0``)
    or every k steps."""
    states, actions = [hand.state.copy()], []

    def send(piece: np.ndarray) -> str:
        for action in piece:
            info = hand.step_info(np.asarray(action, dtype=np.float64))
            actions.append(np.asarray(action, dtype=np.float64))
            states.append(hand.state.copy())
            if info.done:
                return info.end_reason
        return ""

    plans, reason = receding_horizon(plan_at, send, lambda: states[-1], steps, replan_every)
    return Execution(np.asarray(actions, dtype=np.float64).reshape(-1, 2), np.asarray(states), reason, tuple(plans))
