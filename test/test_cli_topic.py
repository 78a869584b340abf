"""``t42 topic list/echo/pub`` as processes against the test's own graph (and in this process for input refused
before the graph): what a user of the pip-installed ROS (no ``ros2`` command) watches and drives topics with."""

from __future__ import annotations

from typing import Any

import pytest
from test_cli_graph import t42  # the graph commands' runner: a t42 process while this process's nodes spin


def test_topic_list_and_echo_print_the_graphs_topics_and_messages_as_ros2_topic_does(ros: Any) -> None:
    """A latched status gives its last message to a late echo; a best-effort stream is read best effort (a
    reliable reader would never match it); each message a YAML document."""
    import yaml
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    node = ros.node("talker")
    latched = node.create_publisher(String, "/hand/status", QoSProfile(
        depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE))
    latched.publish(String(data="reset: episode 1 grasped"))
    stream = node.create_publisher(JointState, "/hand/joint_states", qos_profile_sensor_data)
    node.create_timer(0.05, lambda: stream.publish(JointState(name=["actuator_1", "actuator_2"],
                                                              position=[0.5, 1.25], effort=[-3.0, 4.0])))
    code, out, err = t42(ros, "topic", "list")
    assert code == 0 and "/hand/status [std_msgs/msg/String]" in out.splitlines(), (out, err)
    assert "/hand/joint_states [sensor_msgs/msg/JointState]" in out.splitlines(), out

    code, out, err = t42(ros, "topic", "echo", "hand/status", "-n", "1")
    assert code == 0 and list(yaml.safe_load_all(out)) == [{"data": "reset: episode 1 grasped"}, None], (out, err)
    code, out, err = t42(ros, "topic", "echo", "/hand/joint_states", "--count", "2")
    docs = [d for d in yaml.safe_load_all(out) if d is not None]
    assert code == 0 and len(docs) == 2, (out, err)
    assert docs[0]["name"] == ["actuator_1", "actuator_2"] and docs[0]["position"] == [0.5, 1.25]
    assert docs[0]["effort"] == [-3.0, 4.0] and set(docs[0]["header"]) == {"stamp", "frame_id"}

    code, out, err = t42(ros, "topic", "echo", "/nobody/talks", "--wait", "1")
    assert code == 2 and out == "" and "/nobody/talks: no publisher on the graph after 1 s" in err, err


def test_topic_pub_sends_a_message_from_yaml_stamped_now(ros: Any) -> None:
    import time

    from nav_msgs.msg import Path as PathMsg
    from sensor_msgs.msg import JointState

    node = ros.node("listener")
    commands: list[Any] = []
    paths: list[Any] = []
    node.create_subscription(JointState, "/hand/command", commands.append, 10)
    node.create_subscription(PathMsg, "/planned", paths.append, 10)
    before_ns = time.time_ns()
    code, out, err = t42(ros, "topic", "pub", "/hand/command", "sensor_msgs/msg/JointState",
                         "{name: [actuator_1, actuator_2], velocity: [0.5, -1]}", "--stamp")
    assert code == 0 and out == "published 1 on /hand/command\n", (out, err)
    assert ros.spin_until(lambda: commands, 5.0)
    got = commands[0]
    assert list(got.name) == ["actuator_1", "actuator_2"] and list(got.velocity) == [0.5, -1.0]
    stamp_ns = got.header.stamp.sec * 10**9 + got.header.stamp.nanosec
    assert before_ns <= stamp_ns <= time.time_ns()  # stamped at publication, as a driver wants a command
    code, out, err = t42(ros, "topic", "pub", "planned", "nav_msgs/msg/Path",
                         "{header: {frame_id: t42_base}, poses: [{pose: {position: {x: 0.01, y: 0.07}}}]}",
                         "-n", "2", "-r", "20")
    assert code == 0 and ros.spin_until(lambda: len(paths) == 2, 5.0), (out, err)
    assert paths[0].header.frame_id == "t42_base" and paths[0].poses[0].pose.position.y == 0.07


@pytest.mark.parametrize("argv, problem", [
    (["/x", "sensor_msgs/msg/JointState", "{velocty: [1]}"], "velocty: no such field"),
    (["/x", "sensor_msgs/msg/JointState", "{name: [1]}"], "name[0]: 1 is no string"),
    (["/x", "std_msgs/msg/Nope", "{}"], "std_msgs/msg/Nope: no such message type"),
    (["/x", "std_msgs/msg/String", "{data: x}", "--stamp"], "has no header"),
    (["/x", "std_msgs/msg/String", "{data: [oops"], "not YAML"),
])
def test_topic_pub_refuses_a_bad_message_in_one_line_before_it_joins_the_graph(
        argv: list[str], problem: str, capsys: pytest.CaptureFixture[str]) -> None:
    from t42_transfer.cli import main

    assert main(["topic", "pub", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and problem in captured.err and captured.err.count("\n") == 1, captured.err


@pytest.mark.parametrize("argv, problem", [
    (["std_msgs/msg/UInt8", "{data: 300}"], "data: 300 is out of range for uint8 [0, 255]"),
    (["std_msgs/msg/UInt8", "{data: -1}"], "data: -1 is out of range for uint8 [0, 255]"),
    (["std_msgs/msg/Int8", "{data: 1000}"], "data: 1000 is out of range for int8 [-128, 127]"),
    (["std_msgs/msg/Int64", "{data: 99999999999999999999}"],
     "data: 99999999999999999999 is out of range for int64 [-9223372036854775808, 9223372036854775807]"),
    (["std_msgs/msg/UInt8MultiArray", "{data: [1, 300]}"], "data[1]: 300 is out of range for uint8 [0, 255]"),
    (["std_msgs/msg/UInt8MultiArray", "{layout: {dim: [{label: x, size: -1}]}}"],
     "layout.dim[0].size: -1 is out of range for uint32 [0, 4294967295]"),
    (["geometry_msgs/msg/PoseStamped", "{header: {stamp: {sec: 2147483648}}}"],
     "header.stamp.sec: 2147483648 is out of range for int32 [-2147483648, 2147483647]"),
])
def test_topic_pub_refuses_an_integer_out_of_its_fields_range_in_one_line(
        argv: list[str], problem: str, ros_domain: int, capsys: pytest.CaptureFixture[str]) -> None:
    """rclpy checks no range: 300 went out as a uint8 44, or ended in an OverflowError or an unnamed
    serialization error."""
    from t42_transfer.cli import main

    assert main(["topic", "pub", "/x", *argv, "--wait", "0"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == f"t42: error: {problem}\n", captured.err


def test_topic_pub_publishes_nothing_out_of_range_and_the_range_s_ends(ros: Any) -> None:
    from std_msgs.msg import Int8, UInt8

    node = ros.node("listener")
    got: list[Any] = []
    node.create_subscription(UInt8, "/u8", got.append, 10)
    node.create_subscription(Int8, "/i8", got.append, 10)
    code, out, err = t42(ros, "topic", "pub", "/u8", "std_msgs/msg/UInt8", "{data: 300}")
    assert code == 2 and out == "" and err == "t42: error: data: 300 is out of range for uint8 [0, 255]\n", err
    for topic, kind, value in (("/u8", "UInt8", 255), ("/i8", "Int8", -128)):
        code, out, err = t42(ros, "topic", "pub", topic, f"std_msgs/msg/{kind}", f"{{data: {value}}}")
        assert code == 0 and out == f"published 1 on {topic}\n", (out, err)
    assert ros.spin_until(lambda: len(got) == 2, 5.0)
    ros.spin_for(0.3)
    assert sorted(m.data for m in got) == [-128, 255]  # not a 44 from the refused 300


@pytest.mark.parametrize("verb", [["pub", "bad topic", "std_msgs/msg/String", "{}"], ["echo", "bad topic"]])
def test_topic_pub_and_echo_say_a_name_ros_refuses_in_one_line(verb: list[str], ros_domain: int,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    from t42_transfer.cli import main

    assert main(["topic", *verb, "--wait", "0"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ("t42: error: 'bad topic': not a valid ROS name (topic name must "
                                                   "not contain characters other than alphanumerics, '_', or '/')\n")


def test_the_readmes_first_hand_command_is_one_the_drivers_accept() -> None:
    """The README's one hands-on command for a first move on a real hand (it once asked for action 2: refused)."""
    import re
    from pathlib import Path

    import yaml
    from sensor_msgs.msg import JointState

    from msg_adapters import RCLPY, message_from_fields, ns_to_stamp
    from t42_transfer.driver.commands import validate_command

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    (fields,) = re.findall(r'`t42 topic pub\s+/hand/command sensor_msgs/msg/JointState "([^"]+)" --stamp`', readme)
    command = message_from_fields(JointState, yaml.safe_load(fields))
    command.header.stamp = ns_to_stamp(10**18, RCLPY)
    action = validate_command(command, 10**18, 500_000_000)
    assert 0 < abs(action).max() <= 1.0, action  # a small move, inside the planner's own range
