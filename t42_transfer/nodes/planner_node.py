"""Planner node: object goals in, open-loop actuator trajectories out, planned with the latest model.

Wiring (relative names: remap them with ``--ros-args -r``, or run under a namespace):

* ``t42/goal`` (geometry_msgs/msg/PointStamped): subscribed; the goal of the object centre, metres in
  ``t42_base`` (other frames and non-finite values are refused);
* ``hand/object_pose``, ``hand/joint_states``: subscribed; the latest hand state ``(x mm, y mm, load1, load2)``
  (the ``STATE_NAMES`` layout :func:`load_model` checks in every checkpoint) and the actuator angles;
* ``t42/model_updated`` (t42_interfaces/msg/ModelUpdated, latched): subscribed TRANSIENT_LOCAL; the model file
  (``path``) to plan with from now on (the transfer server announces there);
* ``hand/trajectory`` (trajectory_msgs/msg/JointTrajectory): published for an accepted plan; actuator-angle
  targets one per control period from the angles of the state planned from, stamped when published, each step
  the model's action times its unit (``action_unit_rad`` in its file: the authors' models step 0.00388 rad);
* ``t42/planned_path`` (nav_msgs/msg/Path, latched): published with each trajectory; the predicted object
  positions (plan length + 1 poses, the start included), metres in ``t42_base``, stamped from the trajectory's
  stamp one control period apart;
* ``t42/plan_candidates`` (t42_interfaces/msg/PlanCandidates, latched): with the parameter ``candidates`` K > 0 (0, off,
  by default), the predicted paths of each new plan's K lowest-cost sequences, the plan's own first, published
  with its first piece (the view draws them);
* ``t42/plan_result`` (t42_interfaces/msg/PlanResult): exactly one per goal (``t42/goal`` and ``t42/reach``
  alike; also for a plan a newer goal, a cancel or the episode's end stopped before it was sent),
  :class:`PlanResult` (:mod:`msg_adapters.plan_result`: metres in ``t42_base``): accepted, or refused with a
  status code and a reason, with the goal and its stamp, the start, the predicted error, the plan's steps,
  samples, planning time, model and method;
* ``hand/status`` (std_msgs/msg/String): subscribed; the driver's ``trajectory_done`` says when a
  piece has run, its episode ends (``dropped``...) end an action goal;
* ``t42/reach`` (t42_interfaces/action/Reach): served (:mod:`t42_transfer.nodes.reach`); a goal as on
  ``t42/goal`` with its tolerance, steps and ``replan_every`` (0: the node's parameter), feedback each step,
  the result after the state following the last step (verdict of ``peg_in_hole.verdict``, measured and
  predicted paths).  Cancel sends the driver an empty trajectory (its "stop") at once; a newer goal (action or
  topic) pre-empts it, stopping the hand too.  ``t42/goal`` stays as a thin mirror (Foxglove's publish panel).

Open or closed loop. By default (``replan_every: 0``, the paper's setting) the whole plan is sent at once, open
loop. With ``replan_every: k`` the node sends the first k steps of an accepted plan, waits for the driver's
``trajectory_done`` and the state after the piece's last step, plans the rest from that measured state (the
remaining steps of a fixed-length plan, or a new horizon search within what is left of ``horizon``), sends its first
k steps, and so on (model-predictive control). The goal's one result describes the first plan; each replan is logged
and its predicted path published. A replan that finds no safe sequence keeps the rest of the previous plan (the rule
of :func:`~t42_transfer.planning.execution.receding_horizon`, which the peg-in-hole evaluation runs too); a newer
goal, or a piece that does not finish in ``piece_timeout_s``, ends the loop with the hand holding still.

Parameters are :class:`PlannerNodeParams`.  ``model`` is read once at start (later
models come by announcement); the planner settings and ``max_state_age_s`` may be
changed at run time (``ros2 param set``) and apply from the next goal served.

Decisions, and why:

* Plans run in one worker thread, not in an executor callback: K samples x T steps take 0.1-1 s, and the node
  must keep tracking the hand state meanwhile (the plan for the next goal starts from it).  An announced model
  is read in a loader thread of its own (the newest announcement wins), so reading a large file stalls neither
  the executor's callbacks (state, goals, the reach action) nor a plan or run in progress; a goal waiting
  meanwhile is planned once it is read, with it.  State, model and goals are swapped under one lock
  (:class:`~t42_transfer.nodes.planner_inbox.Inbox`).
* The latest goal wins.  A goal arriving while another waits replaces it; one arriving while a plan runs lets
  that plan finish and then discards it unpublished (only stopping the node ends a plan early, at its next
  chunk), as it does one arriving before the plan's first piece went out.  Either way the older goal gets the
  result ``superseded``: a stale plan must not move the hand.
* A model file without a stored workspace (``extra.workspace``) is refused like an unreadable one, keeping the
  previous model: the workspace is the planner's only guard against trusting extrapolations, and no default box
  can know where a given model was trained.
* Only plans the planner calls ``ok`` (a safe prediction within ``tolerance_m``)
  are executed; ``unreachable`` ones are refused with their predicted error.
* Hand state further than ``max_state_age_s`` from now (driver stopped, episode
  ended) is refused: an open-loop plan from an old state is a plan for another hand.
* Results are published reliable and TRANSIENT_LOCAL with a deep queue (``names.RESULTS``): volatile and latched
  subscribers both match, and a ``superseded`` result published just before the plan's is not overwritten.

Nothing here raises from a callback: failures are logged and, for goals, answered
on the result topic.
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from t42_interfaces.msg import ModelUpdated, PlanCandidates
from t42_interfaces.msg import PlanResult as PlanResultMsg
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    actions_to_joint_trajectory,
    goal_xy_mm,
    joint_state_arrays,
    last_step_stamp,
    names,
    object_xy_mm,
    path_msg,
    stamp_to_ns,
    status_event,
)
from msg_adapters.plan_result import plan_result_msg
from msg_adapters.planning import candidates_msg
from msg_adapters.reach import reach_request
from msg_adapters.transfer import model_announcement
from t42_transfer.conventions import ACTION_UNIT_RAD, CONTROL_PERIOD_NS, MAX_PLAN_HORIZON
from t42_transfer.driver.commands import check_stamp
from t42_transfer.nodes.planner_inbox import Inbox, Stop, Watch
from t42_transfer.nodes.planner_params import PlannerNodeParams
from t42_transfer.nodes.planner_parts import (
    Goal,
    HandState,
    LoadedModel,
    PlanResult,
    Refused,
    hand_state,
    load_planner_model,
    superseded,
    unsent,
)
from t42_transfer.nodes.reach import ABORT, CANCELED, ReachRun, judge, reach_server, refused_verdict
from t42_transfer.planning import Plan, Planner, PlannerConfig, PlanStopped
from t42_transfer.planning.execution import receding_horizon
from t42_transfer.ros.dirs import file_in_namespace
from t42_transfer.ros.logs import ThrottledLog
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams
from t42_transfer.ros.qos import profile

JOIN_TIMEOUT_S = 5.0
"""How long closing waits for the worker and the loader (a plan stops at its next chunk, a read takes longer)."""


class PlannerNode(Node):
    """Plans for goals with the latest model and hand state; see the module docstring for behaviour."""

    params_class = PlannerNodeParams  # the one its LiveParams declares; t42 node NAME --help lists it

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("planner", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        self.log = self.get_logger()
        torch.set_num_threads(self.params.torch_threads)
        self.per_message = ThrottledLog(self.log)
        """Warnings about single messages: a flood gives a line a second, with a count."""
        self._inbox = Inbox(self._now_ns, self.log.warning)
        """The model, hand state, goals and driver statuses the callbacks, the worker and the loader share."""
        self._trajectory_pub = self.create_publisher(JointTrajectory, names.HAND_TRAJECTORY, 10)
        self._path_pub = self.create_publisher(PathMsg, names.PLANNED_PATH, profile(names.LATCHED))
        self._candidates_pub = self.create_publisher(PlanCandidates, names.PLAN_CANDIDATES, profile(names.LATCHED))
        self._result_pub = self.create_publisher(PlanResultMsg, names.PLAN_RESULT,
                                                 profile(names.OFFERED[names.PLAN_RESULT]))
        model = str(file_in_namespace(self.params.model, self.get_namespace())) if self.params.model else ""
        if model and Path(model).exists():
            self.load(model)
        else:
            self.log.info(f"no model file {model!r} yet; waiting for {self._model_topic}")
        self.create_subscription(PoseStamped, names.OBJECT_POSE, self._on_pose, 10)
        self.create_subscription(JointState, names.JOINT_STATES, self._on_joints, 10)
        self.create_subscription(ModelUpdated, names.MODEL_UPDATED, self._on_model_updated, profile(names.LATCHED))
        self.create_subscription(PointStamped, names.GOAL, self._on_goal, profile(names.REQUESTS))
        self.create_subscription(String, names.HAND_STATUS, self._on_status, profile(names.EVENT_READER))
        self._reach_server = reach_server(self, self._on_reach, self._on_reach_cancel)
        self._worker = threading.Thread(target=self._work, name=f"{self.get_name()}_planner", daemon=True)
        self._worker.start()
        self._loader = threading.Thread(target=self._load_announced, name=f"{self.get_name()}_loader", daemon=True)
        self._loader.start()

    # ------------------------------------------------------------------ state
    @property
    def params(self) -> PlannerNodeParams:
        return self._params.value

    @property
    def model(self) -> LoadedModel | None:
        return self._inbox.model

    @property
    def idle(self) -> bool:
        """No goal waiting or being planned."""
        return self._inbox.idle

    @property
    def state_stamp_ns(self) -> int | None:
        """Stamp of the older of the latest object pose and joint states (None before both arrived)."""
        return self._inbox.state_stamp_ns

    @property
    def _model_topic(self) -> str:
        return self.resolve_topic_name(names.MODEL_UPDATED)

    def load(self, path: str) -> bool:
        """Plan with the model in ``path`` from now on; on failure keep the current one and log why."""
        try:
            loaded = load_planner_model(path)
        except Exception as err:
            kept = self.model.path if self.model else "none"
            self.log.warning(f"could not load model {path} ({err}); keeping model {kept}")
            return False
        self._inbox.model = loaded
        assumed = " (assumed: the file was saved before units were stored)" if loaded.unit_assumed else ""
        self.log.info(f"planning with model {path} (method {loaded.method!r}, actions of "
                      f"{loaded.action_unit_rad:.3g} rad a step{assumed})")
        return True

    def close(self) -> None:
        """Stop the worker (a plan under way stops at its next chunk, unpublished) and the loader; idempotent."""
        self._inbox.stop()
        for thread in (self._worker, self._loader):
            thread.join(timeout=JOIN_TIMEOUT_S)
            if thread.is_alive():  # a daemon: it goes with the process
                self.log.warning(f"{thread.name} still runs {JOIN_TIMEOUT_S:g} s after the node was asked to stop")

    def destroy_node(self) -> None:
        """Stop the worker first, so it never publishes through destroyed publishers."""
        self.close()
        self._reach_server.destroy()
        super().destroy_node()

    # ------------------------------------------------------------------ callbacks
    def _on_params(self, old: PlannerNodeParams, new: PlannerNodeParams) -> None:
        changed = {k: v for k, v in asdict(new).items() if asdict(old)[k] != v}
        self.log.info(f"parameters changed {changed}: used from the next goal")

    def _on_pose(self, msg: PoseStamped) -> None:
        try:
            pose = (stamp_to_ns(msg.header.stamp), object_xy_mm(msg))
        except Exception as err:
            self.per_message.warning(f"ignored {names.OBJECT_POSE}: {err}")
            return
        if (active := self._inbox.put_pose(pose)) is not None:
            active.on_pose(*pose)

    def _on_joints(self, msg: JointState) -> None:
        try:
            joints = (stamp_to_ns(msg.header.stamp), *joint_state_arrays(msg))
        except Exception as err:
            self.per_message.warning(f"ignored {names.JOINT_STATES}: {err}")
            return
        self._inbox.put_joints(joints)

    def _on_status(self, msg: String) -> None:
        event = status_event(msg.data)
        if event in names.END_EVENTS:
            self._inbox.episode_ended(event)
        elif event == names.TRAJECTORY_DONE:
            self._inbox.piece_done(last_step_stamp(msg.data))

    def _on_model_updated(self, msg: ModelUpdated) -> None:
        self._inbox.announce(model_announcement(msg).path)

    def _load_announced(self) -> None:
        """The loader thread: each announced model in turn, the newest when several came during one read."""
        while (path := self._inbox.next_model()) is not None:
            try:
                self.load(path)
            finally:
                self._inbox.model_read()

    def _on_goal(self, msg: PointStamped) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            goal = Goal(goal_xy_mm(msg), stamp)
            if stamp:  # as the driver takes commands: a goal from 1970 or 2038 is no goal for now
                check_stamp(stamp, self._now_ns(), round(self.params.max_goal_age_s * 1e9), "goal")
        except ValueError as err:
            self._publish_result(PlanResult(False, "bad_goal", str(err), None, stamp))
            return
        self._submit(goal)

    def _on_reach(self, handle: Any) -> None:
        """An accepted t42/reach goal: checked as t42/goal checks its goals, then queued like one."""
        run = ReachRun(handle, None)
        try:
            request = reach_request(handle.request)
            if request.stamp_ns:
                check_stamp(request.stamp_ns, self._now_ns(), round(self.params.max_goal_age_s * 1e9), "goal")
        except ValueError as err:
            self._publish_result(PlanResult(False, "bad_goal", str(err), None, stamp_to_ns(
                handle.request.target.header.stamp)))
            run.finish(ABORT, refused_verdict(), f"bad_goal: {err}")
            return
        run.request = request
        self._submit(Goal(request.xy_mm, request.stamp_ns, run, request.tolerance_mm, request.steps,
                           request.replan_every))

    def _on_reach_cancel(self, handle: Any) -> bool:
        """A cancel request: a waiting goal ends at once; the running one stops the hand now (an empty
        trajectory, the driver's "stop") and ends in the worker."""
        pending, active = self._inbox.cancel(handle, self._stop_hand)
        if pending is not None:
            self._publish_result(superseded(pending, reason="cancelled before it was planned"))
            pending.run.finish(CANCELED, refused_verdict(), "cancelled before it was planned")
        return pending is not None or active

    def _submit(self, goal: Goal) -> None:
        """Queue ``goal``: it replaces a waiting one, and ends the one executing (the worker aborts it)."""
        if (replaced := self._inbox.submit(goal)) is not None:
            self._publish_result(superseded(replaced))
            if replaced.run is not None:
                replaced.run.finish(ABORT, refused_verdict(), "superseded: a newer goal arrived before it was planned")

    # ------------------------------------------------------------------ the worker
    def _work(self) -> None:
        while (goal := self._inbox.next_goal()) is not None:
            try:
                self._serve(goal)
            except PlanStopped:  # the node stops: nothing more goes out
                return
            except Exception as err:  # the worker outlives any one goal
                self.log.error(f"planning failed: {err!r}\n{traceback.format_exc()}")
                self._publish_result(PlanResult(False, "error", f"planning failed: {err!r}", goal.xy.tolist(),
                                                goal.stamp_ns))
                if goal.run is not None:
                    goal.run.finish(ABORT, refused_verdict(), f"error: planning failed: {err!r}")
            finally:
                self._inbox.goal_done()

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds
    def _config(self, goal: Goal) -> tuple[PlannerConfig, int]:
        """The planner settings and ``replan_every`` for ``goal``: the node's, or the action goal's where set."""
        p = self.params
        config = p.planner_config
        if goal.tolerance_mm:
            config = replace(config, tolerance_mm=goal.tolerance_mm)
        if goal.steps:
            if goal.steps > MAX_PLAN_HORIZON:
                raise Refused("bad_goal", f"steps {goal.steps}: no plan is longer than {MAX_PLAN_HORIZON}")
            config = replace(config, horizon=goal.steps, horizon_search=False)
        return config, goal.replan_every or p.replan_every

    def _serve(self, goal: Goal) -> None:
        """Plan for ``goal``, then publish the trajectory and path (accepted) and the result."""
        goal_mm = goal.xy.tolist()
        p = self.params
        loaded, pose, joints = self._inbox.latest()
        try:
            if loaded is None:
                raise Refused("no_model", f"no model loaded yet; waiting for {self._model_topic}")
            config, k = self._config(goal)
            hand = hand_state(pose, joints, self._now_ns(), p.max_state_age_ns)
            planner = loaded.planner(config)
        except (Refused, ValueError) as refused:
            status, reason = (refused.status, refused.reason) if isinstance(refused, Refused) else \
                ("bad_goal", str(refused))
            self._publish_result(PlanResult(False, status, reason, goal_mm, goal.stamp_ns))
            if goal.run is not None:
                goal.run.finish(ABORT, refused_verdict(), f"{status}: {reason}")
            return
        started = time.perf_counter()
        plan = planner.plan(hand.state, goal.xy, stop=lambda: self._inbox.stopping)
        result = PlanResult(
            accepted=plan.ok,
            status=plan.status,
            reason=plan.reason,
            goal_mm=goal_mm,
            goal_stamp_ns=goal.stamp_ns,
            start_mm=hand.state[:2].tolist(),
            predicted_error_mm=None if math.isinf(plan.error_mm) else plan.error_mm,
            horizon=len(plan.actions),
            samples_evaluated=plan.evaluated,
            planning_time_s=time.perf_counter() - started,
            model=loaded.path,
            method=loaded.method,
            replan_every=k,
        )
        if (newer := self._inbox.newer()) is None:  # the node stops
            return
        cancelled = goal.run is not None and goal.run.cancelled
        if newer or cancelled:
            why = "cancelled while it was planned" if cancelled else ""
            self._publish_result(superseded(goal, result, why))
            if goal.run is not None:
                goal.run.finish(CANCELED if cancelled else ABORT, refused_verdict(),
                                why or "superseded: a newer goal arrived while it was planned")
            return
        if not plan.ok:
            self._publish_result(result)
            if goal.run is not None:
                goal.run.planned(plan.predicted[:, :2], self._now_ns(), plan.error_mm)
                goal.run.finish(ABORT, refused_verdict(), f"{plan.status}: {plan.reason}")
            return
        if goal.run is not None:
            goal.run.start(pose[0], hand.state[:2])
        self._execute(goal, loaded, planner, plan, hand, result)

    def _execute(self, goal: Goal, loaded: LoadedModel, planner: Planner, first: Plan, hand: HandState,
                 result: PlanResult) -> None:
        """Send ``first`` whole (open loop) or piece by piece, replanning between pieces (:func:`receding_horizon`).

        The goal's result is published right after the first piece is sent; every replan is logged
        and its predicted path published with the piece sent from it.  An action goal then waits for
        the state after its last step and ends with its verdict (:meth:`_conclude`).
        """
        k = result.replan_every
        steps = planner.config.horizon if planner.config.horizon_search else len(first.actions)
        run = goal.run
        watch = self._inbox.watch(run)
        # the plan the next piece comes from, how much of it was sent, steps sent
        current, offset, executed = first, 0, 0

        def plan_at(state: np.ndarray, left: int, previous: np.ndarray) -> Plan:
            nonlocal current, offset
            plan = planner.plan(state, goal.xy, horizon=left, stop=lambda: self._inbox.stopping, previous=previous)
            if len(plan.actions) == 0:
                self.log.warning(f"goal {goal.xy.tolist()} mm: replan after {executed} steps refused "
                                 f"({plan.status}: {plan.reason}); keeping the rest of the previous plan")
            else:
                current, offset = plan, 0
                self.log.info(f"goal {goal.xy.tolist()} mm: replanned after {executed} steps from "
                              f"{state[:2].round(2).tolist()} mm, {len(plan.actions)}-step plan ({plan.status}, "
                              f"predicted error {plan.error_mm:.2f} mm)")
            return plan

        def never_sent(stop: Stop) -> None:
            if executed == 0 and not stop.stopping:  # planned, never sent: its result says why
                self._publish_result(unsent(goal, result, stop.cancelled, stop.episode_ended))

        def send(piece: np.ndarray) -> str:
            nonlocal offset, executed
            stamp = watch.send(len(piece), lambda: self._send_piece(piece, hand.angles, loaded.action_unit_rad),
                               never_sent)
            if isinstance(stamp, Stop):
                return "interrupted"
            self._path_pub.publish(path_msg(current.predicted[offset:, :2], stamp, kit=RCLPY))
            if offset == 0 and current.candidates:  # a new plan: what its search weighed
                self._candidates_pub.publish(candidates_msg(current.candidates, stamp, kit=RCLPY))
            if run is not None:
                run.planned(current.predicted[:, :2], stamp - offset * CONTROL_PERIOD_NS, current.error_mm)
                run.sent(stamp)
            if executed == 0:
                self._publish_result(result)
            offset, executed = offset + len(piece), executed + len(piece)
            return ""

        def after_piece() -> HandState | None:  # (an open-loop plan is one piece)
            return watch.after_piece(self.params.piece_timeout_s, self.params.max_state_age_ns)

        def measure() -> np.ndarray | None:
            nonlocal hand
            after = after_piece()
            if after is None:
                return None
            hand = after
            return hand.state

        _, end = receding_horizon(plan_at, send, measure, steps, k, first=first)
        if run is not None:
            self._conclude(goal, first, after_piece() if end in ("length", "short_plan") else None, watch)

    def _conclude(self, goal: Goal, first: Plan, final: HandState | None, watch: Watch) -> None:
        """End an action goal: its verdict from the measured state after its last step, or why it stopped."""
        run = goal.run
        tolerance = goal.tolerance_mm or self.params.planner_config.tolerance_mm
        # without its final state the hand stops (a piece that timed out would run on without its goal)
        ends, pending = watch.end(self._stop_hand if final is None else None)
        run.end_at(None if final is None else final.state[:2])
        outcome, verdict, reason, error = judge(run, first.predicted[0, :2], None if final is None else
                                                final.state[:2], tolerance, ends, pending)
        run.finish(outcome, verdict, reason, error)

    def _send_piece(self, piece: np.ndarray, angles: np.ndarray, unit_rad: float = ACTION_UNIT_RAD) -> int:
        """Publish ``piece`` (actions of ``unit_rad``, its model's) as the driver's trajectory from ``angles``,
        stamped now; its stamp."""
        stamp = self._now_ns()
        self._trajectory_pub.publish(actions_to_joint_trajectory(piece, angles, stamp, kit=RCLPY, unit_rad=unit_rad))
        return stamp

    def _stop_hand(self) -> None:
        """Cancel the driver's trajectory: an empty one is its "stop" (zero actions from the next step)."""
        self._send_piece(np.zeros((0, 2), np.float32), np.zeros(2))

    def _publish_result(self, result: PlanResult) -> None:
        if result.accepted:
            self.log.info(f"goal {result.goal_mm} mm: {result.horizon}-step plan, "
                          f"predicted error {result.predicted_error_mm:.2f} mm")
        else:
            goal = "" if result.goal_mm is None else f" {result.goal_mm} mm"
            self.per_message.warning(f"refused goal{goal} ({result.status}): {result.reason}")
        self._result_pub.publish(plan_result_msg(result, self._now_ns(), kit=RCLPY))
