"""A ROS 2 user's plain rclpy script against the t42 suite: it imports nothing from the project.

    python stock_user.py graph [NAMESPACE]     nodes, parameters, /rosout, hand state, hand/reset
    python stock_user.py transfer [NAMESPACE]  t42/transfer_now, then a goal -> JointTrajectory and Path

It prints one JSON object with what it saw; exit 0 when every step got an answer.
Only stock interfaces are used: the standard parameter services, /rosout,
std_srvs/Trigger, geometry_msgs, sensor_msgs, trajectory_msgs, nav_msgs.
"""

from __future__ import annotations

import json
import math
import sys
import time

import rclpy
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import Log, Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from t42_interfaces.msg import PlanResult
from trajectory_msgs.msg import JointTrajectory

SUITE = ("mock_driver", "recorder", "transfer_server", "planner")


class User(Node):
    def __init__(self, ns: str) -> None:
        super().__init__("stock_user")
        self.ns = ns.rstrip("/")
        self.logs: list[Log] = []
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

    def call(self, srv_type, name: str, request, timeout_s: float = 30.0):
        client = self.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError(f"service {name} not available")
        future = client.call_async(request)
        self.wait(future.done, timeout_s, f"answer from {name}")
        return future.result()

    def set_param(self, node: str, name: str, value) -> tuple[bool, str]:
        if isinstance(value, float):
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        else:
            pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
        result = self.call(SetParameters, f"{self.ns}/{node}/set_parameters",
                           SetParameters.Request(parameters=[Parameter(name=name, value=pv)])).results[0]
        return result.successful, result.reason

    def get_param(self, node: str, name: str):
        value = self.call(GetParameters, f"{self.ns}/{node}/get_parameters",
                          GetParameters.Request(names=[name])).values[0]
        return {ParameterType.PARAMETER_DOUBLE: value.double_value,
                ParameterType.PARAMETER_INTEGER: value.integer_value}.get(value.type)


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
    started = time.monotonic()
    answer = user.call(Trigger, user.name("t42/transfer_now"), Trigger.Request(), timeout_s=600.0)
    out["transfer"] = [answer.success, answer.message, time.monotonic() - started]
    if not answer.success:
        return out
    poses: list[PoseStamped] = []
    trajectories: list[JointTrajectory] = []
    paths: list[Path] = []
    statuses: list[String] = []
    results: list[PlanResult] = []
    user.create_subscription(PlanResult, user.name("t42/plan_result"), results.append, 10)
    user.create_subscription(String, user.name("hand/status"), statuses.append,
                             QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    user.create_subscription(PoseStamped, user.name("hand/object_pose"), poses.append, 10)
    user.create_subscription(JointTrajectory, user.name("hand/trajectory"), trajectories.append, 10)
    user.create_subscription(Path, user.name("t42/planned_path"), paths.append, 10)
    goal_pub = user.create_publisher(PointStamped, user.name("t42/goal"), 10)
    user.wait(lambda: poses and goal_pub.get_subscription_count() > 0, 30.0, "hand state and the planner")
    time.sleep(1.0)  # let the planner load the announced model
    here = poses[-1]
    goal = PointStamped()
    goal.header.frame_id = here.header.frame_id
    goal.header.stamp = here.header.stamp
    goal.point.x, goal.point.y = here.pose.position.x + 0.004, here.pose.position.y + 0.004
    goal_pub.publish(goal)
    try:
        user.wait(lambda: trajectories and paths, 120.0, "a JointTrajectory and a Path")
    except TimeoutError as err:
        raise TimeoutError(f"{err}; plan results: {[(r.status, r.reason) for r in results]}") from None
    out["trajectory"] = {"joint_names": list(trajectories[0].joint_names), "points": len(trajectories[0].points)}
    out["path"] = {"frame_id": paths[0].header.frame_id, "poses": len(paths[0].poses)}
    # the driver executes it: its status says when the last point is applied
    user.wait(lambda: any(s.data.startswith("trajectory_done") for s in statuses), 60.0, "trajectory_done")
    out["driver_status"] = [s.data for s in statuses]
    return out


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
