"""A ROS 2 user's plain rclpy script against the suite on (emulated) hardware; it imports nothing of the project.

    python hardware_user.py

Drives the Dynamixel driver's lifecycle (started without autostart) through the stock services: configure
(then inactive), activate (then active); lists and sets parameters, resets the hand, measures the hand
topics' rates from their header stamps (the graph's clock) and on arrival, sends a JointTrajectory, then one
whose targets lie past the position limit (refused on hand/status with the reason, the finger stopping at
the limit), and bad commands (refused on hand/status and /rosout).  Prints one JSON object with what it saw;
exit 0 when every step got an answer.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time

import rclpy
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.msg import Log, Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

DRIVER = "/dynamixel_driver"
STEP_NS = 100_000_000


class User(Node):
    def __init__(self) -> None:
        super().__init__("hardware_user")
        self.joints: list[JointState] = []
        self.poses: list[PoseStamped] = []
        self.actions: list[JointState] = []
        self.statuses: list[str] = []
        self.logs: list[Log] = []
        self.create_subscription(JointState, "/hand/joint_states", self.joints.append, 100)
        self.create_subscription(PoseStamped, "/hand/object_pose", self.poses.append, 100)
        self.create_subscription(JointState, "/hand/applied_action", self.actions.append, 100)
        self.create_subscription(String, "/hand/status", lambda m: self.statuses.append(m.data),
                                 QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.create_subscription(Log, "/rosout", self.logs.append, 1000)
        self.trajectory = self.create_publisher(JointTrajectory, "/hand/trajectory", 10)
        self.command = self.create_publisher(JointState, "/hand/command", 10)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(self, timeout_sec=0.02)

    def call(self, srv_type, name: str, request, timeout_s: float = 30.0):  # noqa: ANN001
        client = self.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise RuntimeError(f"no service {name}")
        future = client.call_async(request)
        end = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > end:
                raise RuntimeError(f"no answer from {name}")
            rclpy.spin_once(self, timeout_sec=0.05)
        return future.result()


def double(name: str, value: float) -> Parameter:
    return Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value))


def stamp_ns(msg) -> int:  # noqa: ANN001
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def gaps(msgs: list) -> list[int]:
    stamps = [stamp_ns(m) for m in msgs]
    return [b - a for a, b in zip(stamps, stamps[1:], strict=False)]


def stamp_rate(msgs: list) -> float:
    """Messages per second of their header stamps' clock (the driver's: the graph's)."""
    if len(msgs) < 2:
        return 0.0
    return (len(msgs) - 1) / ((stamp_ns(msgs[-1]) - stamp_ns(msgs[0])) / 1e9)


def change(user: User, transition: int) -> bool:
    return user.call(ChangeState, f"{DRIVER}/change_state",
                     ChangeState.Request(transition=Transition(id=transition))).success


def state_of(user: User) -> str:
    return user.call(GetState, f"{DRIVER}/get_state", GetState.Request()).current_state.label


def lifecycle(user: User) -> dict:
    """Configure, then activate, through the stock services; the state after each.  A configure is tried
    again while it fails (the emulator's port may not be there yet when the suite has just started)."""
    seen: dict = {"initial": state_of(user), "configure_failures": 0}
    for _ in range(20):
        if change(user, Transition.TRANSITION_CONFIGURE):
            break
        seen["configure_failures"] += 1
        user.spin_for(1.0)
    seen["configured"] = state_of(user)
    seen["activate"] = change(user, Transition.TRANSITION_ACTIVATE)
    seen["activated"] = state_of(user)
    return seen


def past_the_limit(user: User, names: list[str]) -> dict:
    """A trajectory opening actuator 2 to -0.5 rad, past its position limit at 0 (open; the limits are
    [0, max_angle_rad] from open): the steps past it are refused on hand/status with the reason, and the finger
    stops at the limit."""
    (limits,) = user.call(GetParameters, f"{DRIVER}/get_parameters",
                          GetParameters.Request(names=["max_angle_rad"])).values
    start = list(user.joints[-1].position)
    targets, angle = [], start[1]
    while angle > -0.5:
        angle = max(-0.5, angle - 0.03)  # 1.2 action units a step: a valid trajectory, every point
        targets.append([start[0], angle])
    msg = JointTrajectory(joint_names=names)
    for k, target in enumerate(targets):
        msg.points.append(JointTrajectoryPoint(positions=target, time_from_start=Duration(
            sec=(k + 1) // 10, nanosec=((k + 1) % 10) * STEP_NS)))
    before, heard = len(user.statuses), len(user.joints)
    user.trajectory.publish(msg)
    end = time.monotonic() + len(targets) * 0.1 + 10.0
    while not any(s.startswith("trajectory_done") for s in user.statuses[before:]) and time.monotonic() < end:
        rclpy.spin_once(user, timeout_sec=0.05)
    user.spin_for(0.5)
    return {"max_angle_rad": list(limits.double_array_value), "start": start, "target": targets[-1],
            "trajectory_done": any(s.startswith("trajectory_done") for s in user.statuses[before:]),
            "refused": [s for s in user.statuses[before:] if s.startswith("refused")],
            "positions": [list(j.position) for j in user.joints[heard:]]}


def main() -> int:
    rclpy.init()
    user = User()
    seen: dict = {}
    try:
        seen["lifecycle"] = lifecycle(user)
        state = seen["lifecycle"]["activated"]
        seen["state"] = state
        seen["parameters"] = sorted(user.call(ListParameters, f"{DRIVER}/list_parameters",
                                              ListParameters.Request()).result.names)
        results = user.call(SetParameters, f"{DRIVER}/set_parameters",
                            SetParameters.Request(parameters=[double("load_limit", 250.0),
                                                              double("grasp_load", 400.0)]))
        seen["set"] = [(r.successful, r.reason) for r in results.results]
        # A servo fault (an answer late past the latency timer on a loaded machine) interrupts a grasp or refuses
        # one; the driver recovers within a second or two and a user resets again, as on a real hand.
        seen["refused_resets"] = []
        for _ in range(3):
            reset = user.call(Trigger, "/hand/reset", Trigger.Request(), timeout_s=60.0)
            seen["reset"] = [reset.success, reset.message]
            if reset.success or not ("fault" in reset.message or "interrupted" in reset.message):
                break
            seen["refused_resets"].append(reset.message)
            user.spin_for(3.0)
        if not reset.success:
            raise RuntimeError(f"reset failed: {reset.message}")
        counts = len(user.joints), len(user.poses), len(user.actions)
        user.spin_for(2.0)
        seen["grasp_statuses"] = [s.split(":")[0] for s in user.statuses if s.startswith(("grasping", "reset"))]
        heard = (user.joints[counts[0]:], user.poses[counts[1]:], user.actions[counts[2]:])
        seen["rates_hz"] = [len(msgs) / 2.0 for msgs in heard]  # on arrival (wall time)
        seen["stamp_rates_hz"] = [stamp_rate(msgs) for msgs in heard]  # the graph's clock
        seen["stamp_median_gap_ms"] = [statistics.median(gaps(msgs)) / 1e6 if len(msgs) > 1 else 0.0
                                       for msgs in heard]
        if not user.joints:
            raise RuntimeError(f"no joint states after the reset; hand/status said {user.statuses}")
        last = user.joints[-1]
        names, start = list(last.name), list(last.position)
        msg = JointTrajectory(joint_names=names)
        targets = [[start[0], max(0.0, start[1] - 0.015 * (k + 1))] for k in range(10)]
        for k, target in enumerate(targets):
            msg.points.append(JointTrajectoryPoint(positions=target,
                                                   time_from_start=Duration(nanosec=(k + 1) * 100_000_000)))
        sent = len(user.statuses)  # (the latched ones heard on joining are not this trajectory's)
        user.trajectory.publish(msg)
        end = time.monotonic() + 5.0
        while not any(s.startswith("trajectory_done") for s in user.statuses[sent:]) and time.monotonic() < end:
            rclpy.spin_once(user, timeout_sec=0.05)
        user.spin_for(0.5)
        seen["trajectory_done"] = any(s.startswith("trajectory_done") for s in user.statuses[sent:])
        seen["followed"] = [list(user.joints[-1].position), targets[-1]]
        seen["past_limit"] = past_the_limit(user, names)
        before = len(user.statuses)
        for velocity, joint_names in (([math.nan, 0.0], names), ([0.0, 1e9], names), ([0.1, 0.1], ["elbow", "wrist"])):
            bad = JointState(name=joint_names, velocity=velocity)
            bad.header.stamp = user.get_clock().now().to_msg()
            user.command.publish(bad)
        user.spin_for(1.0)
        seen["rejections"] = sum("rejected hand/command" in log.msg
                                 for log in user.logs if log.name == "dynamixel_driver")
        seen["refused_statuses"] = [s for s in user.statuses[before:]
                                    if s.startswith("refused") and "rejected hand/command" in s]
        seen["positions_after"] = [list(j.position) for j in user.joints[-5:]]
    except RuntimeError as err:
        seen["error"] = str(err)
    print(json.dumps(seen))
    user.destroy_node()
    rclpy.shutdown()
    return 1 if "error" in seen else 0


if __name__ == "__main__":
    sys.exit(main())
