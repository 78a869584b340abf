"""A ROS 2 user's plain rclpy script against the t42 suite: it imports nothing from the project.

    python stock_user.py graph [NAMESPACE]     nodes, parameters, /rosout, hand state, hand/reset
    python stock_user.py transfer [NAMESPACE]  the t42/transfer action on the bags recorder/bag_closed announced,
                                               then t42/reach goals: one to its result, one cancelled

It prints one JSON object with what it saw; exit 0 when every step got an answer.
Only stock interfaces and the suite's interface package are used: the standard parameter services, /rosout,
std_srvs/Trigger, geometry_msgs, sensor_msgs, trajectory_msgs, nav_msgs, action_msgs, and t42_interfaces (the
Reach and Transfer actions, BagClosed, PlanResult) through rclpy's ActionClient.
"""

from __future__ import annotations

import json
import math
import re
import sys
import time

import rclpy
from action_msgs.msg import GoalStatus
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import Log, Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from t42_interfaces.action import Reach, Transfer
from t42_interfaces.msg import BagClosed, PlanResult
from trajectory_msgs.msg import JointTrajectory

SUITE = ("mock_driver", "recorder", "transfer_server", "planner")


class User(Node):
    def __init__(self, ns: str) -> None:
        super().__init__("stock_user")
        self.ns = ns.rstrip("/")
        self.logs: list[Log] = []
        self.action_clients: dict[str, ActionClient] = {}
        self.create_subscription(Log, "/rosout", self.logs.append,
                                 QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def name(self, relative: str) -> str:
        return f"{self.ns}/{relative}"

    def wait(self, condition, timeout_s: float, what: str):
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {what} within {timeout_s} s")
            rclpy.spin_once(self, timeout_sec=0.05)

    def call(self, srv_type, name: str, request, timeout_s: float = 30.0, again: bool = False):
        """The answer to ``request``. ``again``: a request that may be carried out twice (a parameter's get or
        set) goes out again each 2 s without an answer: a server drops its reply to a client whose reply
        subscription it has not matched yet, as a new client on a busy machine can be."""
        client = self.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError(f"service {name} not available")
        futures, deadline = [client.call_async(request)], time.monotonic() + timeout_s
        while not (answered := [f for f in futures if f.done()]):
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no answer from {name} within {timeout_s} s")
            try:
                self.wait(lambda: any(f.done() for f in futures), min(2.0, left) if again else left, "")
            except TimeoutError:
                if again:
                    futures.append(client.call_async(request))
        return answered[0].result()

    def action_client(self, action, name: str) -> ActionClient:
        """The node's client of action ``name``, made on first use: made well before its first goal, as a node
        makes its clients when it starts. The server matches a new client's feedback subscription a moment after
        the client sees the server: on a loaded machine, a goal sent at once lost its first feedback messages."""
        if name not in self.action_clients:
            self.action_clients[name] = ActionClient(self, action, name)
        return self.action_clients[name]

    def send_goal(self, action, name: str, goal, feedback: list, timeout_s: float = 30.0):
        """Send an action goal, collecting its feedback; the accepted goal handle."""
        client = self.action_client(action, name)
        if not client.wait_for_server(timeout_sec=timeout_s):
            raise TimeoutError(f"action {name} not available")
        sent = client.send_goal_async(goal, feedback_callback=lambda m: feedback.append(m.feedback))
        self.wait(sent.done, timeout_s, f"goal response from {name}")
        if not sent.result().accepted:
            raise TimeoutError(f"{name} rejected the goal")
        return sent.result()

    def result_of(self, handle, timeout_s: float, what: str, future=None):
        """The goal's status and result once it ended (``future``: its get_result_async() asked before)."""
        future = future or handle.get_result_async()
        self.wait(future.done, timeout_s, what)
        return future.result()

    def set_param(self, node: str, name: str, value) -> tuple[bool, str]:
        if isinstance(value, float):
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        else:
            pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
        result = self.call(SetParameters, f"{self.ns}/{node}/set_parameters",
                           SetParameters.Request(parameters=[Parameter(name=name, value=pv)]), again=True).results[0]
        return result.successful, result.reason

    def get_param(self, node: str, name: str):
        value = self.call(GetParameters, f"{self.ns}/{node}/get_parameters",
                          GetParameters.Request(names=[name]), again=True).values[0]
        return {ParameterType.PARAMETER_DOUBLE: value.double_value,
                ParameterType.PARAMETER_INTEGER: value.integer_value,
                ParameterType.PARAMETER_STRING: value.string_value}.get(value.type)


def graph(user: User) -> dict:
    out: dict = {}
    user.wait(lambda: {(n, ns.rstrip("/")) for n, ns in user.get_node_names_and_namespaces()}
              >= {(n, user.ns) for n in SUITE}, 60.0, "suite nodes")
    out["nodes"] = sorted(f"{ns.rstrip('/')}/{n}" for n, ns in user.get_node_names_and_namespaces())
    out["parameters"] = {
        node: sorted(user.call(ListParameters, f"{user.ns}/{node}/list_parameters",
                               ListParameters.Request()).result.names)
        for node in SUITE
    }
    before = user.get_param("mock_driver", "rate_factor")
    out["bad_set"] = user.set_param("mock_driver", "rate_factor", -1.0)
    out["after_bad_set"] = user.get_param("mock_driver", "rate_factor")
    out["good_set"] = user.set_param("mock_driver", "rate_factor", float(before) * 2)
    out["after_good_set"] = user.get_param("mock_driver", "rate_factor")
    out["planner_bad_samples"] = user.set_param("planner", "samples", 0)
    out["planner_good_samples"] = user.set_param("planner", "samples", 64)
    out["planner_samples"] = user.get_param("planner", "samples")
    out["planner_bad_replan"] = user.set_param("planner", "replan_every", -1)
    out["planner_good_replan"] = user.set_param("planner", "replan_every", 0)
    out["planner_refine"] = user.get_param("planner", "refine_iterations")

    poses: list[PoseStamped] = []
    joints: list[JointState] = []
    user.create_subscription(PoseStamped, user.name("hand/object_pose"), poses.append, 10)
    user.create_subscription(JointState, user.name("hand/joint_states"), joints.append, 10)
    user.wait(lambda: len(poses) >= 3 and len(joints) >= 3, 30.0, "hand state")
    out["pose"] = {"frame_id": poses[-1].header.frame_id, "x_m": poses[-1].pose.position.x,
                   "y_m": poses[-1].pose.position.y, "stamp_s": poses[-1].header.stamp.sec}
    out["joint_state"] = {"name": list(joints[-1].name), "effort": list(joints[-1].effort),
                          "position": list(joints[-1].position)}

    # A malformed command: the driver must say so on /rosout.
    command = user.create_publisher(JointState, user.name("hand/command"), 10)
    user.wait(lambda: command.get_subscription_count() > 0, 30.0, "the driver's command subscription")
    bad = JointState(name=["actuator_1", "actuator_2"], velocity=[math.nan, 0.0])
    bad.header.stamp = poses[-1].header.stamp  # the graph's time (the driver may be its clock)
    command.publish(bad)
    reset = user.call(Trigger, user.name("hand/reset"), Trigger.Request())
    out["reset"] = [reset.success, reset.message]
    suite_names = {f"{user.ns}/{n}".lstrip("/").replace("/", ".") for n in SUITE}
    driver = f"{user.ns}/mock_driver".lstrip("/").replace("/", ".")
    user.wait(lambda: any(m.name == driver and m.level == Log.WARN for m in user.logs), 15.0,
              "the driver's warning on /rosout")
    user.wait(lambda: {m.name for m in user.logs} >= suite_names, 15.0, "every suite node on /rosout")
    out["rosout"] = sorted({m.name for m in user.logs} & suite_names)
    out["rosout_warning"] = next(m.msg for m in user.logs if m.name == driver and m.level == Log.WARN)
    return out


def transfer(user: User) -> dict:
    out: dict = {}
    # The action clients first, well before their goals: the servers' processes have then seen their feedback
    # subscriptions (the transfer server's answer to get_parameters below, asked through a client made after them,
    # comes once its process has seen that later endpoint).
    user.action_client(Transfer, user.name("t42/transfer"))
    user.action_client(Reach, user.name("t42/reach"))
    # The bags the recorder closed (its events are latched: a late joiner gets the recent ones), each with episodes.
    closed: list[BagClosed] = []
    user.create_subscription(BagClosed, user.name("recorder/bag_closed"), closed.append,
                             QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    user.wait(lambda: any(b.reason == "stop" for b in closed), 30.0, "the recorder's bag_closed events")
    bags = [b.path for b in closed if b.episodes > 0]
    out["bags_closed"] = [[b.path, b.episodes, b.reason] for b in closed]
    # t42/transfer with the server's method named and exactly those bags; feedback per epoch.
    method = user.get_param("transfer_server", "method")
    started = time.monotonic()
    feedback: list[Transfer.Feedback] = []
    handle = user.send_goal(Transfer, user.name("t42/transfer"), Transfer.Goal(method=method, bags=bags), feedback)
    got = user.result_of(handle, 600.0, "the transfer's result")
    result = got.result
    out["transfer"] = [result.success, result.message, time.monotonic() - started]
    out["transfer_goal"] = {"method": method, "bags": len(bags), "status": got.status}
    out["transfer_feedback"] = [[f.phase, f.epoch, f.epochs, f.train_loss] for f in feedback]
    out["transfer_result"] = {"model_path": result.model_path, "model_divergence_steps": result.model_divergence_steps,
                              "source_divergence_steps": result.source_divergence_steps,
                              "hold_still_divergence_steps": result.hold_still_divergence_steps,
                              "skipped_bags": list(result.skipped_bags)}
    if not result.success:
        return out
    poses: list[PoseStamped] = []
    trajectories: list[JointTrajectory] = []
    paths: list[Path] = []
    statuses: list[String] = []
    results: list[PlanResult] = []
    applied: list[JointState] = []
    user.create_subscription(PlanResult, user.name("t42/plan_result"), results.append, 10)
    user.create_subscription(String, user.name("hand/status"), statuses.append,
                             QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    user.create_subscription(PoseStamped, user.name("hand/object_pose"), poses.append, 10)
    user.create_subscription(JointTrajectory, user.name("hand/trajectory"), trajectories.append, 10)
    user.create_subscription(Path, user.name("t42/planned_path"), paths.append, 10)
    user.create_subscription(JointState, user.name("hand/applied_action"), applied.append, 100)
    user.wait(lambda: poses, 30.0, "hand state")
    time.sleep(1.0)  # let the planner load the announced model

    def target(dx: float, dy: float) -> PointStamped:
        here = poses[-1]
        goal = PointStamped()
        goal.header.frame_id = here.header.frame_id
        goal.header.stamp = here.header.stamp
        goal.point.x, goal.point.y = here.pose.position.x + dx, here.pose.position.y + dy
        return goal

    # t42/reach: a goal 4 mm away, its feedback, its result; the driver runs the plan.
    heard = len(statuses)
    feedback = []
    handle = user.send_goal(Reach, user.name("t42/reach"), Reach.Goal(target=target(0.004, 0.004)), feedback)
    try:
        got = user.result_of(handle, 120.0, "the Reach result")
    except TimeoutError as err:
        raise TimeoutError(f"{err}; plan results: {[(r.status, r.reason) for r in results]}") from None
    out["reach"] = {"status": got.status, "verdict": got.result.verdict, "reason": got.result.reason,
                    "final_error_m": got.result.final_error_m, "executed": len(got.result.executed.poses),
                    "predicted": len(got.result.predicted.poses), "feedback": [f.step for f in feedback]}
    user.wait(lambda: trajectories and paths and results, 10.0, "a JointTrajectory, a Path and a PlanResult")
    out["trajectory"] = {"joint_names": list(trajectories[0].joint_names), "points": len(trajectories[0].points)}
    out["path"] = {"frame_id": paths[0].header.frame_id, "poses": len(paths[0].poses)}
    out["plan_result"] = {"accepted": results[0].accepted, "status": results[0].status,
                          "frame_id": results[0].header.frame_id, "horizon": results[0].horizon}
    # the driver executes it: a status of its own says when the last point is applied, or that the episode ended
    # on the way (the plan dropped the object); the statuses heard on joining (latched) are not this plan's
    ends = ("trajectory_done", "dropped", "lost_contact", "overload")
    user.wait(lambda: any(s.data.startswith(ends) for s in statuses[heard:]), 60.0,
              "trajectory_done or an episode's end after the plan")
    out["driver_status"] = [s.data for s in statuses]
    # a fresh grasp for the next goal, as a user does between goals (the first plan may have dropped the object)
    resets = sum(s.data.startswith("reset:") for s in statuses)
    reset = user.call(Trigger, user.name("hand/reset"), Trigger.Request())
    if not reset.success:
        raise TimeoutError(f"hand/reset failed before the cancel: {reset.message}")
    # The next goal is placed from the new grasp: a pose stamped after the last step that the reset's status names
    # ("reset: ... [last step N ns]"), not one of the old grasp's poses still queued here.
    user.wait(lambda: sum(s.data.startswith("reset:") for s in statuses) > resets, 10.0, "the reset's status")
    status = [s.data for s in statuses if s.data.startswith("reset:")][-1]
    if not (named := re.search(r"\[last step (\d+) ns\]", status)):
        raise TimeoutError(f"the reset's status names no last step: {status!r}")
    last_step_ns = int(named[1])
    user.wait(lambda: Time.from_msg(poses[-1].header.stamp).nanoseconds > last_step_ns, 10.0,
              "a pose of the new grasp")
    out["cancel"] = cancel_one(user, target, applied)
    return out


def cancel_one(user: User, target, applied: list) -> dict:
    """A 10-step Reach goal cancelled once it runs, on a driver slowed to half real time (a step each 0.2 s):
    the result is CANCELED; the goal's applied actions, in the order the driver applied them, are one run of
    moving steps, then the hand holding still.  The planner's tolerance is widened for the goal, so that a
    model trained on a few seconds of exploration does not refuse it as unreachable: what runs is checked here,
    not how well it reaches."""
    rate, tolerance = user.get_param("mock_driver", "rate_factor"), user.get_param("planner", "tolerance_m")
    slowed, why = user.set_param("mock_driver", "rate_factor", 0.5)
    if not slowed:
        raise TimeoutError(f"the driver refused rate_factor 0.5: {why}")
    widened, why = user.set_param("planner", "tolerance_m", 0.05)
    if not widened:
        raise TimeoutError(f"the planner refused tolerance_m 0.05: {why}")

    def moving() -> list[bool]:
        return [any(v != 0.0 for v in m.velocity) for m in applied[before:]]

    def held_after_moving(steps: int) -> bool:
        flags = moving()
        return True in flags and flags[::-1].index(True) >= steps

    try:
        before = len(applied)
        feedback: list = []
        handle = user.send_goal(Reach, user.name("t42/reach"), Reach.Goal(target=target(0.002, 0.002), steps=10),
                                feedback)
        result = handle.get_result_async()
        user.wait(lambda: len(feedback) >= 2 or result.done(), 60.0, "the goal to run")
        if result.done() and not feedback:
            ended = result.result().result
            raise TimeoutError(f"the goal to cancel ended before it ran: {ended.verdict}: {ended.reason}")
        cancel = handle.cancel_goal_async()
        user.wait(cancel.done, 10.0, "the cancel's answer")
        got = user.result_of(handle, 30.0, "the cancelled goal's result", result)
        # the driver's messages can come well after the planner's on a busy machine: its moving steps, then four
        user.wait(lambda: held_after_moving(4), 10.0, "moving steps of the goal, then four held ones,")
    finally:
        user.set_param("mock_driver", "rate_factor", float(rate))
        user.set_param("planner", "tolerance_m", float(tolerance))
    return {"status": got.status, "canceled": got.status == GoalStatus.STATUS_CANCELED,
            "verdict": got.result.verdict, "reason": got.result.reason, "moving": moving(),
            "executed": len(got.result.executed.poses), "steps_at_cancel": feedback[-1].step if feedback else -1,
            "cancelling": len(cancel.result().goals_canceling)}


def main() -> int:
    mode, ns = sys.argv[1], (sys.argv[2] if len(sys.argv) > 2 else "")
    rclpy.init()
    user = User(ns)
    try:
        result = {"graph": graph, "transfer": transfer}[mode](user)
    except TimeoutError as err:
        print(json.dumps({"error": str(err)}))
        return 1
    finally:
        user.destroy_node()
        rclpy.shutdown()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
