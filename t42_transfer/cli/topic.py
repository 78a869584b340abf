"""``t42 topic list/echo/pub``: the ``ros2 topic list/echo/pub`` a pip-installed ROS lacks (no ros2cli wheel), for
any topic; the graph node, Ctrl-C and name handling are :mod:`t42_transfer.cli.graph`'s."""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import yaml

from t42_transfer.cli.args import float_arg, int_arg
from t42_transfer.cli.graph import INTERRUPTED, absolute_name, graph_node, yaml_value


def _cmd_topic_list(args: argparse.Namespace) -> int:
    with graph_node() as node:
        deadline = time.monotonic() + args.wait  # discovery: the graph fills in over the first moments
        while time.monotonic() < deadline:
            time.sleep(0.1)
        for topic, types in sorted(node.get_topic_names_and_types()):
            print(f"{topic} [{', '.join(types)}]")
    return 0


def _cmd_topic_echo(args: argparse.Namespace) -> int:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from msg_adapters import message_fields, rclpy_class

    topic = absolute_name(args.topic)
    with graph_node() as node:
        deadline = time.monotonic() + args.wait
        while not (writers := node.get_publishers_info_by_topic(topic)):
            if time.monotonic() > deadline:
                raise ValueError(f"{topic}: no publisher on the graph after {args.wait:g} s (ROS_DOMAIN_ID "
                                 f"{os.environ.get('ROS_DOMAIN_ID', '0')}; t42 topic list shows what there is)")
            if INTERRUPTED.is_set():
                return 130
            time.sleep(0.1)
        qos = QoSProfile(depth=10)  # as ros2 topic echo adapts: what every publisher offers, latched ones' history
        if all(w.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for w in writers):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        if any(w.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for w in writers):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        seen: list[Any] = []
        node.create_subscription(rclpy_class(writers[0].topic_type), topic, seen.append, qos)
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        shown = 0
        try:
            while not INTERRUPTED.is_set() and (args.count == 0 or shown < args.count):
                executor.spin_once(timeout_sec=0.1)
                while seen and (args.count == 0 or shown < args.count):
                    print(yaml.safe_dump(message_fields(seen.pop(0)), sort_keys=False, width=120) + "---",
                          flush=True)
                    shown += 1
        finally:
            executor.shutdown(timeout_sec=1.0)
    return 130 if INTERRUPTED.is_set() else 0


def _cmd_topic_pub(args: argparse.Namespace) -> int:
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from rclpy.serialization import serialize_message

    from msg_adapters import RCLPY, message_from_fields, ns_to_stamp, rclpy_class

    try:
        cls = rclpy_class(args.type)
    except (ImportError, AttributeError, ValueError):
        raise ValueError(f"{args.type}: no such message type (pkg/msg/Name, e.g. std_msgs/msg/String)") from None
    fields = yaml_value(args.values)
    message = message_from_fields(cls, fields)
    if args.stamp and not hasattr(message, "header"):
        raise ValueError(f"--stamp: a {args.type} has no header")
    try:
        serialize_message(message)  # a value no field can hold: said before anything is sent
    except Exception as err:
        raise ValueError(f"{args.values!r}: not a {args.type} ({err})") from None
    topic = absolute_name(args.topic)
    qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL if args.latched else
                     DurabilityPolicy.VOLATILE)
    with graph_node() as node:
        publisher = node.create_publisher(cls, topic, qos)
        deadline = time.monotonic() + args.wait  # as ros2 topic pub: the first message for a reader that is there
        while not publisher.get_subscription_count() and time.monotonic() < deadline and not INTERRUPTED.is_set():
            time.sleep(0.05)
        sent = 0
        while not INTERRUPTED.is_set() and (args.count == 0 or sent < args.count):
            if args.stamp:
                message.header.stamp = ns_to_stamp(node.get_clock().now().nanoseconds, RCLPY)
            publisher.publish(message)
            sent += 1
            print(f"published {sent} on {topic}", flush=True)
            if args.count and sent >= args.count:
                break
            INTERRUPTED.wait(1.0 / args.rate)
        publisher.wait_for_all_acked(Duration(seconds=2))  # a reliable reader has what was sent before we leave
    return 130 if INTERRUPTED.is_set() else 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    topic = commands.add_parser("topic", help="the graph's topics, or one topic's messages (as ros2 topic list / "
                                              "echo)").add_subparsers(dest="topic_command", metavar="VERB")
    listing = topic.add_parser("list", help="every topic on the graph with its type")
    listing.add_argument("--wait", type=float_arg(0, 60), default=1.0, metavar="S",
                         help="how long to let discovery fill the graph in first (default 1 s)")
    listing.set_defaults(func=_cmd_topic_list)
    echo = topic.add_parser("echo", help="print a topic's messages as YAML until Ctrl-C (its type and QoS taken "
                                         "from its publishers; a latched topic gives first the last 10 it keeps)")
    echo.add_argument("topic", metavar="TOPIC", help="e.g. /hand/status (a relative name is taken from /)")
    echo.add_argument("-n", "--count", type=int_arg(0), default=0, metavar="N",
                      help="stop after N messages (default 0: until Ctrl-C)")
    echo.add_argument("--wait", type=float_arg(0, 3600), default=10.0, metavar="S",
                      help="how long to wait for a publisher to appear on the graph (default 10 s)")
    echo.set_defaults(func=_cmd_topic_echo)
    pub = topic.add_parser("pub", help="publish a message given as YAML (as ros2 topic pub), by default once")
    pub.add_argument("topic", metavar="TOPIC", help="e.g. /hand/command (a relative name is taken from /)")
    pub.add_argument("type", metavar="TYPE", help="e.g. sensor_msgs/msg/JointState")
    pub.add_argument("values", nargs="?", default="{}", metavar="VALUES",
                     help="the fields as YAML, e.g. \"{name: [actuator_1, actuator_2], velocity: [0.125, 0.125]}\" "
                          "(unset fields keep their defaults)")
    pub.add_argument("-n", "--count", type=int_arg(0), default=1, metavar="N",
                     help="publish N times (default 1; 0: until Ctrl-C)")
    pub.add_argument("-r", "--rate", type=float_arg(0.001, 1000.0), default=1.0, metavar="HZ",
                     help="publications a second when N > 1 (default 1)")
    pub.add_argument("--stamp", action="store_true",
                     help="set header.stamp to now at each publication (a driver refuses stale commands)")
    pub.add_argument("--latched", action="store_true", help="transient-local durability (a late reader gets it)")
    pub.add_argument("--wait", type=float_arg(0, 3600), default=2.0, metavar="S",
                     help="wait up to S s for a subscriber before the first message (default 2)")
    pub.set_defaults(func=_cmd_topic_pub)
