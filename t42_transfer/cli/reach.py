"""``t42 reach``: the ``ros2 action send_goal --feedback`` a pip-installed ROS lacks, for the planner's ``t42/reach``
action; made to hold where a fresh client's requests or their answers are lost (a busy machine, :data:`ASK_AGAIN_S`)."""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from msg_adapters import names
from t42_transfer.cli.args import float_arg, int_arg
from t42_transfer.cli.graph import ASK_AGAIN_S, absolute_name, graph_node, stop_if_asked
from t42_transfer.conventions import MM_PER_M

if TYPE_CHECKING:
    from rclpy.node import Node

SERVER_GONE_S = 3.0
"""How long ``t42 reach`` waits on an action server that left the graph before it stops waiting."""
GOAL_ANSWER_S = 3.0
"""How long the goal waits for its answer, or for its id on the server's status (goals accepted), before it goes out
again with the same id: a request is dropped as its answer is (:data:`ASK_AGAIN_S`), when the server has not yet
matched the client that sent it. A server that has the goal refuses the copy, and its status shows the goal."""

class Unanswered(ValueError):
    """The goal's fate unknown to the command: it may run on the server all the same."""


Until = Callable[..., None]
"""``until(done, what, wait_s=inf)``: spin until ``done()`` (see :func:`_cmd_reach`)."""


class _Goal:
    """One goal on the action server: sent again with its id until answered, followed on the server's status, and
    its result asked for again once the status says the goal ended without the result coming."""

    def __init__(self, node: Node, client: Any, action: str, goal: Any, said: Callable[[Any], None]) -> None:
        import uuid

        from action_msgs.msg import GoalStatusArray
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from unique_identifier_msgs.msg import UUID

        self.id = UUID(uuid=list(uuid.uuid4().bytes))
        self.sends: list[Any] = []  # the goal requests' futures, the first one first
        self.status: int | None = None  # the goal's last status on the server; None: not seen there
        self._client, self._action, self._goal, self._said = client, action, goal, said
        self._sent_at = self._copy_refused_at = math.inf
        self._copy_refusal_stands = False
        self._status_subscription = node.create_subscription(
            GoalStatusArray, f"{action}/_action/status", self._on_status,
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))  # the last status, on matching too

    def _on_status(self, message: Any) -> None:
        for s in message.status_list:
            if bytes(s.goal_info.goal_id.uuid) == bytes(self.id.uuid):
                self.status = s.status

    def send(self) -> None:
        self.sends.append(self._client.send_goal_async(self._goal, feedback_callback=self._said, goal_uuid=self.id))
        self._sent_at = time.monotonic()

    def handle(self) -> Any:
        """The accepted goal's handle: its answer's, or one made from its id once the status shows it (the answer
        lost); None while neither."""
        from rclpy.action.client import ClientGoalHandle

        from msg_adapters.reach import reach_type

        for future in self.sends:
            if future.done() and future.result().accepted:
                return future.result()
        if self.status is None:
            return None
        return ClientGoalHandle(self._client, self.id, reach_type().Impl.SendGoalService.Response(accepted=True))

    def refused(self) -> bool:
        """The first request answered no and so did every copy sent while it was slow to (a server may say no,
        then yes); or a copy did while the first's answer was lost (the server's no, or a goal it has) and, the
        server's status matched, the goal has not shown on it for :data:`GOAL_ANSWER_S`."""
        first = bool(self.sends) and self.sends[0].done() and not self.sends[0].result().accepted
        return (first and all(f.done() for f in self.sends)) or self._copy_refusal_stands

    def answered(self, until: Until, answer_s: float) -> Any:
        """Send the goal; its handle once accepted, None once refused (:meth:`refused`).  :class:`Unanswered`
        after ``answer_s`` without an answer, or when a copy was refused and the server's status is out of reach:
        the goal may run all the same."""
        self.send()
        start = self._sent_at

        def settled() -> bool:
            now = time.monotonic()
            if self.handle() is not None or self.refused():
                return True
            first_answered = self.sends[0].done()
            if not first_answered and any(f.done() for f in self.sends[1:]):  # a copy refused: a no, or a goal it has
                self._copy_refused_at = min(self._copy_refused_at, now)
                if now - self._copy_refused_at > GOAL_ANSWER_S:
                    if self._status_subscription.get_publisher_count() == 0:  # the status could not have shown it
                        raise Unanswered(f"{self._action}: the goal's answer was lost and the server refused a copy "
                                         "of it, with its status out of reach")
                    self._copy_refusal_stands = True
                    return True
            elif now - start > answer_s:
                raise Unanswered(f"{self._action}: no answer to the goal after {answer_s:g} s, nor the goal among "
                                 "the server's (its requests lost?)")
            elif not first_answered and now - self._sent_at > GOAL_ANSWER_S:
                self.send()
            return False

        until(settled, "before it answered the goal")
        return self.handle()

    def result(self, handle: Any, until: Until) -> Any:
        """The goal's result, asked for again each :data:`ASK_AGAIN_S` once its status says it ended (a request
        for it can be lost as the goal's can)."""
        from action_msgs.msg import GoalStatus

        ended = (GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED)
        asks, asked = [handle.get_result_async()], time.monotonic()

        def came() -> bool:
            nonlocal asked
            if any(f.done() for f in asks):
                return True
            if self.status in ended and time.monotonic() - asked > ASK_AGAIN_S:
                asks.append(handle.get_result_async())
                asked = time.monotonic()
            return False

        until(came, "before the goal's result (the hand may still run the plan)")
        return next(f for f in asks if f.done()).result()

    def cancelled(self, executor: Any, answer_s: float = 5.0) -> str:
        """Cancel the goal once answered (waiting up to ``answer_s`` for that, then 5 s for the cancel's answer;
        unanswered: by its id all the same); what became of it, for the user."""
        from rclpy.action.client import ClientGoalHandle

        from msg_adapters.reach import reach_type

        if not self.sends:
            return "no goal sent"

        def wait(done: Callable[[], bool], wait_s: float = 5.0) -> bool:
            deadline = time.monotonic() + wait_s
            while not done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
            return done()

        answered = wait(lambda: self.handle() is not None or self.refused(), answer_s)
        if self.refused():
            return "the goal was rejected"
        handle = self.handle() or ClientGoalHandle(self._client, self.id,
                                                   reach_type().Impl.SendGoalService.Response(accepted=True))
        cancel = handle.cancel_goal_async()
        if wait(cancel.done) and cancel.result().goals_canceling:
            return "goal cancelled (the hand holds from its next step)"
        if not answered:
            return "the goal was sent but never answered; it may still run (stop it with a new goal or hand/reset)"
        return "cancel not confirmed (the goal may have ended already)"


def _cmd_reach(args: argparse.Namespace) -> int:
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor

    from msg_adapters.reach import reach_goal, reach_outcome, reach_progress, reach_type

    absolute_name(args.action)  # a name ROS refuses: one line, before the graph
    request = reach_goal([args.x * MM_PER_M, args.y * MM_PER_M], 0, args.tolerance * MM_PER_M, args.steps,
                         args.replan_every)  # stamp 0: now, for the planner
    with graph_node() as node:
        client = ActionClient(node, reach_type(), args.action)
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)

        def until(done: Callable[[], bool], what: str, wait_s: float = math.inf) -> None:
            """Spin until ``done()``; KeyboardInterrupt on Ctrl-C; ValueError after ``wait_s`` or once the server
            has been off the graph for SERVER_GONE_S."""
            start, gone_since = time.monotonic(), None
            while not done():
                stop_if_asked()
                executor.spin_once(timeout_sec=0.1)
                now = time.monotonic()
                if now - start > wait_s:
                    raise ValueError(f"{args.action}: {what}")
                if wait_s < math.inf or client.server_is_ready():
                    gone_since = None
                elif gone_since is None:
                    gone_since = now
                elif now - gone_since > SERVER_GONE_S:
                    raise ValueError(f"{args.action}: the action server left the graph {what}")

        def said(message: Any) -> None:
            p = reach_progress(message.feedback)
            print(f"step {p.step}: {p.error_mm:.1f} mm from the target (the plan ends {p.predicted_final_error_mm:.1f}"
                  " mm from it)", flush=True)

        goal = _Goal(node, client, args.action, request, said)
        try:
            until(client.server_is_ready,
                  f"no such action server on the graph after {args.wait:g} s (the planner's; "
                  f"ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')}; is it running?)", args.wait)
            handle = goal.answered(until, args.wait + GOAL_ANSWER_S)
            if handle is None:
                print(f"{args.action}: goal rejected (the planner logs why)")
                return 1
            got = goal.result(handle, until)
        except Unanswered as err:  # the goal may run all the same: it is cancelled
            raise ValueError(f"{err}; {goal.cancelled(executor, answer_s=0.0)}") from None
        except KeyboardInterrupt:  # as ros2 action send_goal: Ctrl-C cancels the goal, the hand holds
            print(f"t42: interrupted: {goal.cancelled(executor)}", file=sys.stderr)
            raise SystemExit(130) from None
        finally:
            executor.shutdown(timeout_sec=1.0)
            client.destroy()
    if not got.result.verdict:  # a server that failed builds no result (rclpy sends the empty default)
        ended = {GoalStatus.STATUS_ABORTED: "aborted", GoalStatus.STATUS_CANCELED: "canceled"}
        status = ended.get(got.status, str(got.status))
        print(f"{args.action}: the goal ended {status} without a result (the planner's log says why)")
        return 1
    outcome = reach_outcome(got.result)
    reason = outcome.reason.removeprefix(f"{outcome.verdict}: ")  # (a verdict's reason may begin with its word)
    if outcome.verdict == reach_type().Result.VERDICT_REFUSED:  # never executed
        print(f"{args.action}: refused: {reason}")
        return 1
    error = "unknown" if outcome.final_error_mm is None else f"{outcome.final_error_mm:.1f} mm"
    print(f"{args.action}: {outcome.verdict}{f': {reason}' if reason else ''}; final error {error} after "
          f"{len(outcome.executed_mm)} measured positions")
    return 0 if outcome.success else 1


def add_commands(commands: argparse._SubParsersAction) -> None:
    reach = commands.add_parser("reach", help="send the planner a t42/reach goal and follow it to its result (as ros2 "
                                              "action send_goal --feedback); Ctrl-C cancels it")
    for axis in ("x", "y"):
        reach.add_argument(axis, type=float_arg(-1.0, 1.0), metavar=axis.upper(),
                           help=f"the object's target {axis} in t42_base, metres (REP 103), as the action takes it")
    reach.add_argument("--tolerance", type=float_arg(0.0, 1.0), default=0.0, metavar="M",
                       help="success radius, metres (default 0: the planner's tolerance_m)")
    reach.add_argument("--steps", type=int_arg(0, 100_000), default=0, metavar="N",
                       help="plan horizon in control steps (default 0: the planner's choice)")
    reach.add_argument("--replan-every", type=int_arg(0, 100_000), default=0, metavar="K",
                       help="replan every K executed steps (default 0: the planner's replan_every)")
    reach.add_argument("--action", default=f"/{names.REACH}", metavar="NAME",
                       help=f"the action's name (default /{names.REACH}; under a namespace e.g. /left/{names.REACH})")
    reach.add_argument("--wait", type=float_arg(0, 3600), default=10.0, metavar="S",
                       help="how long to wait for the action server, then 3 s more for its goal's answer")
    reach.set_defaults(func=_cmd_reach)
