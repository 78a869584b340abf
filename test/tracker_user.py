"""A ROS 2 user's plain rclpy script against the camera and object tracker nodes; it imports nothing of the project.

    python tracker_user.py [POSES]

With ``t42 node camera`` and ``t42 node object_tracker`` running (root namespace): lists both nodes' parameters
and reads some (the standard ListParameters / GetParameters services), sets bad values on each and sees them
refused with a reason, sets a good value on each and sees it accepted (the camera's new frame_id on
``/camera/camera_info``), then receives POSES (default 5) ``/tracker/object_pose`` messages.  Prints one JSON
object with what it saw; exit 0 when every step got an answer, 1 (with "error" in the JSON) when one did not.
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo

CAMERA, TRACKER = "/camera", "/object_tracker"
NEW_FRAME_ID = "hand_camera_optical"


class User(Node):
    def __init__(self) -> None:
        super().__init__("tracker_user")
        self.poses: list[PoseStamped] = []
        self.infos: list[CameraInfo] = []

    def wait(self, condition, timeout_s: float, what: str) -> None:  # noqa: ANN001
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {what} within {timeout_s} s")
            rclpy.spin_once(self, timeout_sec=0.05)

    def call(self, srv_type, name: str, request, timeout_s: float = 30.0):  # noqa: ANN001
        client = self.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise TimeoutError(f"service {name} not available")
        future = client.call_async(request)
        self.wait(future.done, timeout_s, f"answer from {name}")
        self.destroy_client(client)
        return future.result()

    def list_params(self, node: str) -> list[str]:
        return sorted(self.call(ListParameters, f"{node}/list_parameters", ListParameters.Request()).result.names)

    def get_params(self, node: str, names: list[str]) -> dict:
        values = self.call(GetParameters, f"{node}/get_parameters", GetParameters.Request(names=names)).values
        return dict(zip(names, (plain(v) for v in values), strict=True))

    def set_param(self, node: str, name: str, value: object) -> list:
        """[successful, reason] of setting one parameter."""
        request = SetParameters.Request(parameters=[Parameter(name=name, value=ros_value(value))])
        result = self.call(SetParameters, f"{node}/set_parameters", request).results[0]
        return [result.successful, result.reason]


def ros_value(value: object) -> ParameterValue:
    if isinstance(value, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    if isinstance(value, int):
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
    if isinstance(value, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=str(value))


def plain(value: ParameterValue) -> object:
    return {ParameterType.PARAMETER_NOT_SET: None,
            ParameterType.PARAMETER_BOOL: value.bool_value,
            ParameterType.PARAMETER_INTEGER: value.integer_value,
            ParameterType.PARAMETER_DOUBLE: value.double_value,
            ParameterType.PARAMETER_STRING: value.string_value,
            ParameterType.PARAMETER_INTEGER_ARRAY: list(value.integer_array_value),
            ParameterType.PARAMETER_DOUBLE_ARRAY: list(value.double_array_value)}.get(value.type, f"type {value.type}")


def stamp_ns(message: PoseStamped | CameraInfo) -> int:
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


def counted(poses: list[PoseStamped], first_info_ns: int) -> list[PoseStamped]:
    return [p for p in poses if stamp_ns(p) >= first_info_ns]


def main(argv: list[str]) -> int:
    want_poses = int(argv[0]) if argv else 5
    rclpy.init()
    user = User()
    seen: dict = {}
    try:
        user.wait(lambda: {CAMERA, TRACKER} <= {f"{ns.rstrip('/')}/{n}"
                                               for n, ns in user.get_node_names_and_namespaces()},
                  60.0, "camera and object_tracker nodes")
        seen["parameters"] = {node: user.list_params(node) for node in (CAMERA, TRACKER)}
        seen["tracker_subscribes"] = sorted(topic for topic, _ in  # as `ros2 node info` lists them
                                            user.get_subscriber_names_and_types_by_node("object_tracker", "/"))
        seen["camera_values"] = user.get_params(CAMERA, ["device", "fps", "loop", "frame_id", "calibration_file"])
        seen["tracker_values"] = user.get_params(TRACKER, ["object_id", "max_jump_m", "object_marker_height_m"])

        # the object tracker: a jump limit out of range, a read-only marker id; then a good jump limit
        seen["tracker_bad"] = [user.set_param(TRACKER, "max_jump_m", -1.0),
                               user.set_param(TRACKER, "object_id", 5)]
        seen["tracker_after_bad"] = user.get_params(TRACKER, ["max_jump_m", "object_id"])
        seen["tracker_good"] = user.set_param(TRACKER, "max_jump_m", 0.012)
        seen["tracker_after_good"] = user.get_params(TRACKER, ["max_jump_m"])

        # the camera: frame ids tf2 refuses, a read-only rate; then a good frame id, which the next frames carry
        seen["camera_bad"] = [user.set_param(CAMERA, "frame_id", ""),
                              user.set_param(CAMERA, "frame_id", "/camera"),
                              user.set_param(CAMERA, "fps", 5.0)]
        seen["camera_after_bad"] = user.get_params(CAMERA, ["frame_id", "fps"])
        user.create_subscription(CameraInfo, "/camera/camera_info", user.infos.append, 10)
        seen["camera_good"] = user.set_param(CAMERA, "frame_id", NEW_FRAME_ID)
        seen["camera_after_good"] = user.get_params(CAMERA, ["frame_id"])
        user.wait(lambda: any(i.header.frame_id == NEW_FRAME_ID for i in user.infos), 20.0,
                  f"camera_info with frame_id {NEW_FRAME_ID}")

        # A pose may come from an image whose camera_info went out before this script's subscription matched
        # (the tracker lags the camera under load): count only poses of images after the first info seen, and
        # wait until the infos of the counted poses' images have arrived too.
        user.create_subscription(PoseStamped, "/tracker/object_pose", user.poses.append, 10)
        first_info_ns = stamp_ns(user.infos[0])
        user.wait(lambda: len(counted(user.poses, first_info_ns)) >= want_poses, 30.0, f"{want_poses} object poses")
        poses = counted(user.poses, first_info_ns)
        user.wait(lambda: stamp_ns(user.infos[-1]) >= max(stamp_ns(p) for p in poses), 10.0,
                  "camera_info of the last pose's image")
        seen["poses"] = [{"frame_id": p.header.frame_id, "stamp_ns": stamp_ns(p),
                          "xyz_m": [p.pose.position.x, p.pose.position.y, p.pose.position.z]} for p in poses]
        seen["camera_info_stamps_ns"] = [stamp_ns(i) for i in user.infos]
    except TimeoutError as err:
        seen["error"] = str(err)
    print(json.dumps(seen))
    user.destroy_node()
    rclpy.shutdown()
    return 1 if "error" in seen else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
