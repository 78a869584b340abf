"""Planner node: object goals in, open-loop actuator trajectories out, planned with the latest model.

Wiring (defaults; every name is a :class:`PlannerNodeParams` field):

* ``/t42/goal`` (geometry_msgs/msg/PointStamped): subscribed; the goal of the
  object centre, metres in ``t42_base`` (other frames and non-finite values are refused);
* ``/hand/object_pose``, ``/hand/joint_states``: subscribed; the latest hand state
  ``(x mm, y mm, load1, load2)`` (the ``STATE_NAMES`` layout :func:`load_model`
  checks in every checkpoint) and the actuator angles;
* ``/t42/model_updated`` (std_msgs/msg/String, latched): subscribed with
  TRANSIENT_LOCAL; a model file path to plan with from now on;
* ``/hand/trajectory`` (trajectory_msgs/msg/JointTrajectory): published for an
  accepted plan; actuator-angle targets one per control period, starting from the
  angles of the state planned from, stamped when published (the driver refuses it stale);
* ``/t42/planned_path`` (nav_msgs/msg/Path): published with each trajectory; the
  predicted object positions (horizon + 1 poses, the start included), metres in
  ``t42_base``, stamped from the trajectory's stamp one control period apart;
* ``/t42/plan_result`` (std_msgs/msg/String): exactly one JSON line per goal,
  :class:`PlanResult`: accepted, or refused with a status code and a reason.

Decisions, and why:

* Plans run in one worker thread, not in the goal callback: K samples x T steps
  take 0.1-1 s, and a blocked spin would stop the node from tracking the hand
  state and model announcements meanwhile.  Publishers are thread-safe on every
  backend; the state and model are swapped under a lock.
* The latest goal wins.  A goal arriving while another waits replaces it; one
  arriving while a plan runs lets that plan finish (the planner cannot be
  interrupted) and then discards it unpublished.  Either way the older goal
  gets the result ``superseded``: a stale plan must not move the hand.
* A model file without a stored workspace (``extra.workspace``) is refused like
  an unreadable one, keeping the previous model: the workspace is the planner's
  only guard against trusting extrapolations, and no default box can know where
  a given model was trained.
* Only plans the planner calls ``ok`` (a safe prediction within ``tolerance_mm``)
  are executed; ``unreachable`` ones are refused with their predicted error.
* Hand state older than ``max_state_age_s`` (driver stopped, episode ended) is
  refused: an open-loop plan from an old state is a plan for another hand.

Nothing here raises from a callback: failures are logged and, for goals, answered
on the result topic.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msg_adapters import (
    JOINT_STATE,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY,
    OBJECT_POSE_TOPIC,
    PATH,
    POINT_STAMPED,
    POSE_STAMPED,
    TYPESTORE,
    actions_to_joint_trajectory,
    goal_xy_mm,
    joint_state_arrays,
    object_xy_mm,
    path_msg,
    stamp_to_ns,
)
from t42_transfer.models.checkpoint import load_model
from t42_transfer.planning import Planner, PlannerConfig, Workspace
from t42_transfer.ros import qos
from t42_transfer.ros.naming import validate_name
from t42_transfer.ros.transport import Transport

STRING = "std_msgs/msg/String"

GOAL_TOPIC = "/t42/goal"
MODEL_UPDATED_TOPIC = "/t42/model_updated"
TRAJECTORY_TOPIC = "/hand/trajectory"
PATH_TOPIC = "/t42/planned_path"
RESULT_TOPIC = "/t42/plan_result"

_String = TYPESTORE.types[STRING]
_DEFAULTS = PlannerConfig()


@dataclass(frozen=True)
class PlannerNodeParams:
    """Parameters of :class:`PlannerNode` (the node's ROS parameters)."""

    model: str = ""
    """Model file to start with; empty or missing: wait for ``model_updated_topic`` (goals are refused meanwhile)."""
    samples: int = _DEFAULTS.samples
    horizon: int = _DEFAULTS.horizon
    horizon_search: bool = True
    """Plan the shortest sequence that reaches the goal (PlannerConfig's default, False, always plans ``horizon`` steps)."""
    tolerance_mm: float = _DEFAULTS.tolerance_mm
    seed: int = _DEFAULTS.seed
    max_state_age_s: float = 0.5
    """Plan only from a hand state at most this old (or this far in the future)."""
    goal_topic: str = GOAL_TOPIC
    model_updated_topic: str = MODEL_UPDATED_TOPIC
    object_pose_topic: str = OBJECT_POSE_TOPIC
    joint_states_topic: str = JOINT_STATES_TOPIC
    trajectory_topic: str = TRAJECTORY_TOPIC
    path_topic: str = PATH_TOPIC
    result_topic: str = RESULT_TOPIC

    def __post_init__(self) -> None:
        _ = self.planner_config  # PlannerConfig validates the planner fields
        if not (math.isfinite(self.max_state_age_s) and self.max_state_age_s > 0):
            raise ValueError(f"max_state_age_s must be positive and finite, got {self.max_state_age_s!r}")
        for field in ("goal_topic", "model_updated_topic", "object_pose_topic", "joint_states_topic",
                      "trajectory_topic", "path_topic", "result_topic"):
            validate_name(getattr(self, field))

    @property
    def planner_config(self) -> PlannerConfig:
        return PlannerConfig(samples=self.samples, horizon=self.horizon, horizon_search=self.horizon_search,
                             tolerance_mm=self.tolerance_mm, seed=self.seed)


@dataclass(frozen=True)
class PlanResult:
    """What became of one goal; published as one JSON line."""

    accepted: bool
    status: str
    """``ok`` when accepted; else a planner status (``unreachable``, ``goal_outside_workspace``, ...) or
    ``bad_goal``, ``no_model``, ``no_state``, ``stale_state``, ``superseded``, ``error``."""
    reason: str
    goal_mm: list[float] | None
    """None when the goal message could not be read."""
    goal_stamp_ns: int
    start_mm: list[float] | None = None
    predicted_error_mm: float | None = None
    horizon: int = 0
    """Steps of the plan (of the published trajectory when accepted)."""
    samples_evaluated: int = 0
    planning_time_s: float = 0.0
    model: str = ""
    method: str = ""

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))


class Refused(Exception):
    """A goal the node will not plan for: ``status`` code and readable ``reason``."""

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status, self.reason = status, reason


@dataclass(frozen=True)
class LoadedModel:
    path: str
    method: str
    planner: Planner


def load_planner(path: str | Path, config: PlannerConfig) -> LoadedModel:
    """A planner for the model in ``path`` inside the workspace it stores.

    Raises :class:`~t42_transfer.models.checkpoint.CheckpointError` for an unreadable
    file and ``ValueError`` for a file without a workspace (see the module docstring).
    """
    model, meta = load_model(path)
    workspace = Workspace.from_metadata(meta)
    if workspace is None:
        raise ValueError(f"{path} stores no workspace (metadata extra.workspace): "
                         "the planner cannot tell where its predictions hold")
    return LoadedModel(str(path), str(meta.get("method", "")), Planner(model, workspace, config))


@dataclass(frozen=True)
class HandState:
    state: np.ndarray
    """``[4]`` float32 in STATE_NAMES order."""
    angles: np.ndarray
    """``[2]`` actuator angles (rad) the trajectory starts from."""


def hand_state(pose: tuple[int, np.ndarray] | None, joints: tuple[int, np.ndarray, np.ndarray | None] | None,
               now_ns: int, max_age_ns: int) -> HandState:
    """The state to plan from, given the latest ``(stamp, xy)`` pose and ``(stamp, loads, angles)`` joints."""
    if pose is None or joints is None:
        missing = [name for name, got in (("object pose", pose), ("joint states", joints)) if got is None]
        raise Refused("no_state", f"no hand state yet (no {' or '.join(missing)} received)")
    (pose_ns, xy), (joints_ns, loads, angles) = pose, joints
    if angles is None:
        raise Refused("no_state", "joint states carry no actuator angles: a trajectory needs its start angles")
    age_ns = max(abs(now_ns - pose_ns), abs(now_ns - joints_ns))
    if age_ns > max_age_ns:
        raise Refused("stale_state", f"hand state is {age_ns / 1e9:.3f} s from now (limit {max_age_ns / 1e9:.3f} s): "
                                     "is the driver publishing?")
    return HandState(np.concatenate([xy, loads]).astype(np.float32), angles)


@dataclass(frozen=True)
class _Goal:
    xy: np.ndarray
    stamp_ns: int


class PlannerNode:
    """Plans for goals with the latest model and hand state; see the module docstring for behaviour."""

    def __init__(self, transport: Transport, params: PlannerNodeParams | None = None) -> None:
        self.transport = transport
        self.params = params if params is not None else PlannerNodeParams()
        p = self.params
        self.log = transport.logger
        self._cond = threading.Condition()
        self._model: LoadedModel | None = None
        self._pose: tuple[int, np.ndarray] | None = None
        self._joints: tuple[int, np.ndarray, np.ndarray | None] | None = None
        self._pending: _Goal | None = None
        self._planning = False
        self._stopping = False

        self._trajectory_pub = transport.publisher(p.trajectory_topic, JOINT_TRAJECTORY, qos.DEFAULT)
        self._path_pub = transport.publisher(p.path_topic, PATH, qos.DEFAULT)
        self._result_pub = transport.publisher(p.result_topic, STRING, qos.DEFAULT)
        if p.model and Path(p.model).exists():
            self.load(p.model)
        else:
            self.log.info("no model file %r yet; waiting for %s", p.model, p.model_updated_topic)
        transport.subscribe(p.object_pose_topic, POSE_STAMPED, qos.DEFAULT, self._on_pose)
        transport.subscribe(p.joint_states_topic, JOINT_STATE, qos.DEFAULT, self._on_joints)
        transport.subscribe(p.model_updated_topic, STRING, qos.TRANSIENT_LOCAL, self._on_model_updated)
        transport.subscribe(p.goal_topic, POINT_STAMPED, qos.DEFAULT, self._on_goal)
        self._worker = threading.Thread(target=self._work, name=f"{transport.node_name}_planner", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ state
    @property
    def model(self) -> LoadedModel | None:
        return self._model

    @property
    def idle(self) -> bool:
        """No goal waiting or being planned."""
        with self._cond:
            return self._pending is None and not self._planning

    def load(self, path: str) -> bool:
        """Plan with the model in ``path`` from now on; on failure keep the current one and log why."""
        try:
            loaded = load_planner(path, self.params.planner_config)
        except Exception as err:
            kept = self._model.path if self._model else "none"
            self.log.warning("could not load model %s (%s); keeping model %s", path, err, kept)
            return False
        with self._cond:
            self._model = loaded
        self.log.info("planning with model %s (method %r)", path, loaded.method)
        return True

    def close(self) -> None:
        """Stop the worker after its current plan (unpublished); the transport's owner closes the transport."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        self._worker.join()

    # ------------------------------------------------------------------ callbacks
    def _on_pose(self, msg: Any) -> None:
        try:
            pose = (stamp_to_ns(msg.header.stamp), object_xy_mm(msg))
        except Exception as err:
            self.log.warning("ignored %s: %s", self.params.object_pose_topic, err)
            return
        with self._cond:
            self._pose = pose

    def _on_joints(self, msg: Any) -> None:
        try:
            joints = (stamp_to_ns(msg.header.stamp), *joint_state_arrays(msg))
        except Exception as err:
            self.log.warning("ignored %s: %s", self.params.joint_states_topic, err)
            return
        with self._cond:
            self._joints = joints

    def _on_model_updated(self, msg: Any) -> None:
        self.load(msg.data.strip())

    def _on_goal(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            goal = _Goal(goal_xy_mm(msg), stamp)
        except ValueError as err:
            self._publish_result(PlanResult(False, "bad_goal", str(err), None, stamp))
            return
        with self._cond:
            replaced, self._pending = self._pending, goal
            self._cond.notify_all()
        if replaced is not None:
            self._publish_result(_superseded(replaced))

    # ------------------------------------------------------------------ the worker
    def _work(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                goal, self._pending, self._planning = self._pending, None, True
            try:
                self._serve(goal)
            except Exception as err:  # the worker outlives any one goal
                self.log.exception("planning failed")
                self._publish_result(PlanResult(False, "error", f"planning failed: {err!r}", goal.xy.tolist(),
                                                goal.stamp_ns))
            finally:
                with self._cond:
                    self._planning = False

    def _serve(self, goal: _Goal) -> None:
        """Plan for ``goal``, then publish the trajectory and path (accepted) and the result."""
        goal_mm = goal.xy.tolist()
        with self._cond:
            loaded, pose, joints = self._model, self._pose, self._joints
        try:
            if loaded is None:
                raise Refused("no_model", f"no model loaded yet; waiting for {self.params.model_updated_topic}")
            hand = hand_state(pose, joints, self.transport.now_ns(), round(self.params.max_state_age_s * 1e9))
        except Refused as refused:
            self._publish_result(PlanResult(False, refused.status, refused.reason, goal_mm, goal.stamp_ns))
            return
        started = time.perf_counter()
        plan = loaded.planner.plan(hand.state, goal.xy)
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
        )
        with self._cond:
            if self._stopping:
                return
            if self._pending is not None:
                self._publish_result(_superseded(goal, result))
                return
        if plan.ok:
            stamp = self.transport.now_ns()
            self._trajectory_pub.publish(actions_to_joint_trajectory(plan.actions, hand.angles, stamp))
            self._path_pub.publish(path_msg(plan.predicted[:, :2], stamp))
        self._publish_result(result)

    def _publish_result(self, result: PlanResult) -> None:
        if self.transport.closed:  # the owner closed the transport before this node
            return
        if result.accepted:
            self.log.info("goal %s mm: %d-step plan, predicted error %.2f mm", result.goal_mm, result.horizon,
                          result.predicted_error_mm)
        else:
            self.log.warning("refused goal %s mm (%s): %s", result.goal_mm, result.status, result.reason)
        self._result_pub.publish(_String(data=result.to_json()))


def _superseded(goal: _Goal, planned: PlanResult | None = None) -> PlanResult:
    """The result of a goal a newer one replaced (``planned``: what its finished plan had been)."""
    base = planned or PlanResult(False, "", "", goal.xy.tolist(), goal.stamp_ns)
    reason = "a newer goal arrived" + (" while it was planned; the plan was discarded" if planned else "")
    return PlanResult(**{**asdict(base), "accepted": False, "status": "superseded", "reason": reason})
