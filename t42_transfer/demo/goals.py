"""One peg-in-hole goal on the running suite: reset, a reachable goal sent as a ``t42/reach`` action goal, the
plan, its open-loop execution (the action's feedback), the verdict; and the bags a recording closed, as the
recorder announces them (``recorder/bag_closed``)."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from msg_adapters import grasp_seed, names, status_event
from msg_adapters.events import SNAPSHOT, STOP, BagClosedEvent
from msg_adapters.reach import reach_goal, reach_outcome, reach_progress
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.demo.settings import (
    GRASP_MATCH_MM,
    HOLD_STEPS,
    MIN_GOAL_DISTANCE_MM,
    SETTLE_STEPS,
    TOLERANCE_MM,
    TRIES_PER_GRASP,
)
from t42_transfer.demo.suite import Suite


@dataclass
class GoalRun:
    steps: int
    grasp_seed: int | None
    """The mock driver's grasp seed; None on servos (a grasp as the hand falls)."""
    goal_mm: list[float]
    start_mm: list[float]
    accepted: bool
    status: str
    reason: str
    horizon: int = 0
    predicted_error_mm: float | None = None
    planning_time_s: float = 0.0
    """The planner's own planning time."""
    goal_to_result_s: float = 0.0
    """Wall time from sending the Reach goal to receiving its plan result (``t42/plan_result``, published after the
    sequence)."""
    final_mm: list[float] | None = None
    """Where the object ended: the simulator's truth where a node publishes it (``sim/object_pose``), else the
    hand's pose."""
    error_mm: float | None = None
    seen_error_mm: float | None = None
    """The final error as the suite saw it (``hand/object_pose``: the tracked pose on a camera)."""
    end: str = ""
    success: bool = False
    verdict: str = ""
    """:func:`~t42_transfer.evaluation.peg_in_hole.verdict` at ``TOLERANCE_MM``."""
    still_error_mm: float = 0.0
    """Where holding still for the goal's steps leaves the object, from the goal (the same grasp and noise)."""
    still_verdict: str = ""
    """The same rule applied to doing nothing."""
    round: int = 1
    sim_pose_error_mm: float | None = None
    """On a camera: the final error of the same goal run again from the same grasp with the simulator's pose."""
    sim_pose_verdict: str = ""
    planned: list[list[float]] = field(default_factory=list)
    executed: list[list[float]] = field(default_factory=list)
    reach_verdict: str = ""
    """The planner's own verdict in the Reach result (at its tolerance, from the state after the last step;
    ``refused`` when never executed); the demo's is ``verdict``."""
    reach_error_mm: float | None = None
    """The Reach result's final error (the pose the planner saw after the last step)."""
    reach_reason: str = ""
    feedback: int = 0
    """Reach feedback messages received (one per executed step)."""
    feedback_steps: int = 0
    """The steps executed, as the last feedback counted them."""

    @property
    def start_distance_mm(self) -> float:
        return float(np.linalg.norm(np.subtract(self.goal_mm, self.start_mm)))


def closed_bags(op: Any, suite: Suite, since: int, timeout_s: float = 30.0) -> list[BagClosedEvent]:
    """The bags a recording closed, as the recorder announced them on ``recorder/bag_closed`` from event ``since``
    on, through the one its stop closed (reason ``stop``: the recording's last; a stop completes after the step in
    progress).  Each is closed and final when announced, so a transfer may use it at once.  Snapshots (reason
    ``snapshot``: seconds the bags hold too) are not among them."""
    def stopped() -> int | None:
        return next((k for k, e in enumerate(op.bags_closed[since:], since) if e.reason == STOP), None)

    op.wait_until(lambda: stopped() is not None, timeout_s,
                  f"the recorder to announce the bag its stop closed on {names.BAG_CLOSED}", suite.check)
    return [e for e in op.bags_closed[since: stopped() + 1] if e.reason != SNAPSHOT]


def run_goal(op: Any, suite: Suite, steps: int, index: int, workspace: Any, round_: int = 1,
             after_reset: Callable[[], None] | None = None) -> GoalRun:
    """Reset the hand, make a goal from its grasp, and reach it through the planner's action; ``after_reset`` runs
    once the reset has succeeded (a round starts its recording there, so no bag holds the hand before it)."""
    from t42_transfer.evaluation.peg_in_hole import progress_towards, verdict

    response = op.call(names.HAND_RESET, 30.0, suite.check)
    if not response.success:
        raise RuntimeError(f"reset failed: {response.message}")
    if after_reset is not None:
        after_reset()
    seed = grasp_seed(response.message)
    reset_stamp = op.latest_pose()[0]
    settled = reset_stamp + SETTLE_STEPS * CONTROL_PERIOD_NS
    action_seeds = (int(np.random.SeedSequence([7, round_, index, attempt]).generate_state(1)[0])
                    for attempt in range(50))
    if seed is None:
        goal, start, still_from = _goal_from_the_settled_hand(op, suite, steps, index, workspace, action_seeds,
                                                              settled)
    else:
        goal, start, still_from = _goal_from_the_same_grasp(op, suite, steps, index, workspace, action_seeds,
                                                            settled, seed)
    still_error = float(np.linalg.norm(goal.position - goal.still))
    still_verdict = verdict(float(np.linalg.norm(goal.position - still_from)), still_error,
                            progress_towards(still_from, goal.position, goal.still), True, TOLERANCE_MM)
    feedback: list[Any] = []
    statuses = len(op.statuses)
    stamp = op.now_ns()
    sent = time.perf_counter()
    handle = op.send_goal(op.reach_client, names.REACH, reach_goal(goal.position, stamp, TOLERANCE_MM, steps),
                          30.0, suite.check,
                          lambda message: feedback.append(reach_progress(message)))
    outcome = reach_outcome(op.goal_result(handle, 180.0, f"the result of the {names.REACH} goal", suite.check))
    op.wait_until(lambda: op.plan_result_for(stamp) is not None, 10.0, f"the goal's {names.PLAN_RESULT}",
                  suite.check)
    answered, result = op.plan_result_for(stamp)
    run = GoalRun(steps, seed, goal.position.tolist(), start.tolist(), result.accepted, result.status,
                  result.reason, result.horizon, result.predicted_error_mm, result.planning_time_s,
                  goal_to_result_s=answered - sent, still_error_mm=still_error, still_verdict=still_verdict,
                  round=round_, reach_verdict=outcome.verdict, reach_error_mm=outcome.final_error_mm,
                  reach_reason=outcome.reason, feedback=len(feedback),
                  feedback_steps=feedback[-1].step if feedback else 0)
    if not run.accepted:
        run.end = "not executed"
        run.verdict = "incomplete"
        return run
    run.planned = outcome.predicted_mm.tolist()
    plan_stamp = outcome.predicted_start_ns  # when the plan was sent: its first step runs after this
    settle = plan_stamp + (run.horizon + 5) * CONTROL_PERIOD_NS  # the plan, then five steps of holding still

    def ends() -> list[str]:  # the episode's end events (a drop...): trajectory_done is not one
        return [e for e in map(status_event, op.statuses[statuses:]) if e in names.END_EVENTS]

    op.wait_until(lambda: op.latest_pose()[0] >= settle or ends(), 120.0, "the plan's execution", suite.check)
    run.executed = [xy.tolist() for stamp, xy in op.poses if stamp >= plan_stamp]
    seen = op.latest_pose()[1]
    truth = op.latest_truth()  # a camera's error must not grade its own plan: the truth does where it is known
    run.final_mm = (seen if truth is None else truth).tolist()
    run.seen_error_mm = float(np.linalg.norm(seen - goal.position))
    run.error_mm = float(np.linalg.norm(np.subtract(run.final_mm, run.goal_mm)))
    ended = ends()
    run.end = ended[0] if ended else "completed"
    run.verdict = verdict(run.start_distance_mm, run.error_mm,
                          progress_towards(np.asarray(run.start_mm), goal.position, np.asarray(run.final_mm)),
                          not ended, TOLERANCE_MM)
    run.success = run.verdict == "hit"
    return run


def _goal_from_the_same_grasp(op: Any, suite: Suite, steps: int, index: int, workspace: Any, action_seeds: Any,
                              settled: int, seed: int) -> tuple[Any, np.ndarray, np.ndarray]:
    """The mock driver names its grasp's seed: the goal is made on a copy of the hand grasped the same way,
    and doing nothing is scored by where that copy ends up holding still.  ``(goal, start, where doing nothing
    starts)``."""
    from t42_transfer.evaluation.peg_in_hole import reachable_goal
    from t42_transfer.hand.sim import SimulatedHand

    goal = reachable_goal(SimulatedHand("target"), steps, HOLD_STEPS, action_seeds, workspace, grasp_seed=seed,
                          trial=index, settle_steps=SETTLE_STEPS, min_distance_mm=MIN_GOAL_DISTANCE_MM)
    # After a grasp the object sinks into the fingers for a few seconds: the goal is made from the
    # settled state (the same seed grasps and settles identically here and in the driver), and the
    # goal is sent once the driver's hand has held still that long and rests there.

    def at_grasp() -> bool:
        stamp, xy = op.latest_pose()
        return stamp > settled and float(np.linalg.norm(xy - goal.grasp[:2])) < GRASP_MATCH_MM

    op.wait_until(at_grasp, 30.0, f"the object at the new grasp {goal.grasp[:2].round(1).tolist()} mm", suite.check)
    return goal, op.latest_pose()[1], goal.grasp[:2]


def _goal_from_the_settled_hand(op: Any, suite: Suite, steps: int, index: int, workspace: Any, action_seeds: Any,
                                settled: int) -> tuple[Any, np.ndarray, np.ndarray]:
    """A driver on servos grasps as the hand falls (no seed to copy): once the object has settled, the goal is
    one that a copy of the same hand model reaches in ``steps`` from a grasp of its own, at least twice the
    tolerance from where the object rests, which is where holding still leaves it.  ``(goal, start, where doing
    nothing starts)``, the goal's ``still`` being that rest.

    The copy grasps once (the next seed) and tries up to ``TRIES_PER_GRASP`` action sequences from its settled
    grasp; a goal too near the object's rest takes the next grasp.  A grasp settled once for every try costs a
    fifth of a grasp made anew for each (the quick emulated demo's goals took 17 of its 47 s that way)."""
    from t42_transfer.evaluation.peg_in_hole import NoGoal, reachable_goal
    from t42_transfer.hand.sim import SimulatedHand

    op.wait_until(lambda: op.latest_pose()[0] > settled, 30.0, "the object to settle in the new grasp",
                  suite.check)
    start = op.latest_pose()[1]
    hand = SimulatedHand("target")
    while (grasp := next(action_seeds, None)) is not None:
        tries = itertools.islice(action_seeds, TRIES_PER_GRASP)
        try:
            goal = reachable_goal(hand, steps, HOLD_STEPS, tries, workspace, grasp_seed=grasp, trial=index,
                                  settle_steps=SETTLE_STEPS, min_distance_mm=MIN_GOAL_DISTANCE_MM)
        except NoGoal:  # none from this grasp: the next seed grasps anew
            continue
        if np.linalg.norm(goal.position - start) >= MIN_GOAL_DISTANCE_MM:
            return replace(goal, grasp=np.concatenate([start, goal.grasp[2:]]), still=start), start, start
    raise RuntimeError(f"no goal {steps} steps away at least {MIN_GOAL_DISTANCE_MM:g} mm from the object's rest at "
                       f"{start.round(1).tolist()} mm (trial {index}): the action seeds ran out")
