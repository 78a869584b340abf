"""The planner's ``t42/reach`` action (t42_interfaces/action/Reach): one goal's run, and the server's wiring.

The planner node owns the planning and the hand; this module holds what is per action goal
(:class:`ReachRun`: the goal handle, the measured path, feedback, how it ends) and the rclpy
ActionServer around the node (:func:`reach_server`).

Why the goal's status stays ACCEPTED while it is planned and executed: rclpy's EXECUTING state comes
with an execute callback that must not return before the result, i.e. a coroutine awaiting the
worker, and a pending coroutine makes a single-threaded executor spin without sleeping (a core
burnt per running goal, beside the planning thread).  Instead the planner's worker thread runs the
goal and, when the result is ready, calls ``execute`` with a callback that only sets the final
state and returns the result.  Feedback, cancel and pre-emption work in the ACCEPTED state alike.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from msg_adapters import names
from msg_adapters.reach import ReachRequest, reach_feedback, reach_result, reach_type
from t42_transfer.ros.qos import profile

SUCCEED, ABORT, CANCELED = "succeed", "abort", "canceled"
"""How a run ends: the goal handle's method that sets its final state."""


class ReachRun:
    """One accepted Reach goal: its handle, what it asks, the object path measured while it runs, and its end.

    ``on_pose`` is called by the node for every object pose while the run is the active one: from
    :meth:`start` on, poses are recorded and each gives a feedback (one per control step).
    """

    def __init__(self, handle: Any, request: ReachRequest | None) -> None:
        self.handle, self.request = handle, request
        self._lock = threading.Lock()
        self._finished = False
        self._closed = False
        self.cancel_asked = False
        """Set by the cancel callback before the handle turns CANCELING (the worker checks both)."""
        self.executed: list[tuple[int, np.ndarray]] = []
        self._sent_ns: int | None = None
        self._poses_after_send = 0
        self.predicted = np.zeros((0, 2), np.float32)
        self.predicted_ns = 0
        self.predicted_error_mm = float("nan")

    @property
    def cancelled(self) -> bool:
        return self.cancel_asked or self.handle.is_cancel_requested

    @property
    def steps_done(self) -> int:
        """Control steps since the plan started to run whose result has been measured (with ``replan_every``, the
        steps the hand held between pieces, while the rest was replanned, count too)."""
        with self._lock:
            return max(0, self._poses_after_send - 1)

    def start(self, stamp_ns: int, xy_mm: np.ndarray) -> None:
        """The state planned from (its stamp and position): the executed path until the first pose after the
        plan was sent, which starts it; then each pose, the state after each step."""
        with self._lock:
            self.executed = [(stamp_ns, np.asarray(xy_mm, np.float32))]

    def planned(self, predicted_mm: np.ndarray, stamp_ns: int, error_mm: float) -> None:
        with self._lock:
            self.predicted, self.predicted_ns, self.predicted_error_mm = predicted_mm, stamp_ns, error_mm

    def sent(self, stamp_ns: int) -> None:
        """A piece of the plan went to the hand at ``stamp_ns``: poses after the first such stamp are the run's."""
        with self._lock:
            if self._sent_ns is None:
                self._sent_ns = stamp_ns

    def on_pose(self, stamp_ns: int, xy_mm: np.ndarray) -> None:
        with self._lock:
            if self._closed or self._sent_ns is None or stamp_ns <= max(self._sent_ns, self.executed[-1][0]):
                return
            # the first pose after the plan was sent: where it starts to run (replaces the state planned from)
            self.executed = [*(self.executed if self._poses_after_send else []), (stamp_ns, xy_mm)]
            self._poses_after_send += 1
            predicted_error = self.predicted_error_mm
        error = float(np.linalg.norm(xy_mm - self.request.xy_mm))
        self.handle.publish_feedback(reach_feedback(self.steps_done, error, predicted_error))

    def end_at(self, final_xy: np.ndarray | None) -> None:
        """Record no more poses; with the state after the last step (``final_xy``), drop any pose that came after
        it (steps the hand held while the worker concluded)."""
        with self._lock:
            self._closed = True
            if final_xy is None:
                return
            same = [i for i, (_, xy) in enumerate(self.executed) if np.array_equal(xy, final_xy)]
            if same:
                self.executed = self.executed[: same[-1] + 1]
                self._poses_after_send = min(self._poses_after_send, len(self.executed))

    def last_xy(self) -> np.ndarray | None:
        with self._lock:
            return self.executed[-1][1] if len(self.executed) > 1 else None

    def finish(self, outcome: str, verdict: str, reason: str, final_error_mm: float | None = None) -> bool:
        """End the goal once (later calls do nothing): its final state and result, with the paths so far."""
        with self._lock:
            if self._finished:
                return False
            self._finished = True
            executed = np.array([xy for _, xy in self.executed], np.float32).reshape(-1, 2)
            start_ns = self.executed[0][0] if self.executed else 0
            result = reach_result(verdict, reason, final_error_mm, executed, start_ns, self.predicted,
                                  self.predicted_ns)

        def done(handle: Any) -> Any:
            if outcome == CANCELED and handle.is_cancel_requested:
                handle.canceled()
            elif outcome == SUCCEED:
                handle.succeed()
            else:
                handle.abort()
            return result

        try:
            self.handle.execute(done)
        except Exception:  # the node is being destroyed: no executor to run it on
            return False
        return True


def reach_server(node: Any, on_goal: Any, on_cancel: Any) -> ActionServer:
    """The ``t42/reach`` ActionServer of ``node``, in a callback group of its own.

    Every goal request is accepted (a goal the planner refuses ends ABORTED with the verdict
    ``refused`` and the reason, which a rejection could not carry); ``on_goal(handle)`` takes each
    accepted goal, ``on_cancel(handle)`` each cancel request (True: accepted).
    """
    return ActionServer(
        node, reach_type(), names.REACH, execute_callback=_unused,
        goal_callback=lambda request: GoalResponse.ACCEPT,
        handle_accepted_callback=on_goal,
        cancel_callback=lambda handle: CancelResponse.ACCEPT if on_cancel(handle) else CancelResponse.REJECT,
        callback_group=MutuallyExclusiveCallbackGroup(),
        # a burst of callers each gets an answer (rclpy's default depth of 10 loses requests, as for services)
        goal_service_qos_profile=profile(names.REQUESTS), cancel_service_qos_profile=profile(names.REQUESTS),
        result_service_qos_profile=profile(names.REQUESTS),
    )


def _unused(handle: Any) -> Any:
    """Never called: each goal's ``execute`` names its own callback (see the module docstring)."""
    handle.abort()
    return reach_type().Result()


def refused_verdict() -> str:
    """The verdict of a goal never executed."""
    return reach_type().Result.VERDICT_REFUSED


def judge(run: ReachRun, start_xy: np.ndarray, final_xy: np.ndarray | None, tolerance_mm: float,
          episode_ends: list[str], pre_empted: bool) -> tuple[str, str, str, float | None]:
    """How an executed goal ends: ``(outcome, verdict, reason, final error mm)``.

    With the state after its last step (``final_xy``) the verdict is :func:`peg_in_hole.verdict`'s, and the goal
    SUCCEEDS on a hit and is ABORTED otherwise; without it the run is ``incomplete``: CANCELED when the client
    cancelled it, else ABORTED with why (a newer goal, the episode's end, no state in time).
    """
    from t42_transfer.evaluation.peg_in_hole import progress_towards, verdict

    goal = run.request.xy_mm
    measured = final_xy if final_xy is not None else run.last_xy()
    error = None if measured is None else float(np.linalg.norm(np.asarray(measured, float) - goal))
    steps = run.steps_done
    if final_xy is None:
        if run.cancelled:
            outcome, reason = CANCELED, f"cancelled by the client after {steps} steps; the hand was stopped"
        elif pre_empted:
            outcome, reason = ABORT, f"pre-empted by a newer goal after {steps} steps; the hand was stopped"
        elif episode_ends:
            outcome, reason = ABORT, f"the episode ended ({episode_ends[0]}) after {steps} steps"
        else:
            outcome, reason = ABORT, f"no hand state after the plan's last step in time ({steps} steps measured)"
        return outcome, "incomplete", reason, error
    distance = float(np.linalg.norm(np.asarray(start_xy, float) - goal))
    word = verdict(distance, error, progress_towards(start_xy, goal, final_xy), True, tolerance_mm)
    if word == reach_type().Result.VERDICT_HIT:
        return SUCCEED, word, "", error
    return ABORT, word, f"{word}: ended {error:.2f} mm from the goal (tolerance {tolerance_mm:.2f} mm, " \
                        f"started {distance:.2f} mm away)", error
