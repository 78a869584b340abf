"""ROS 2 launch file of the node suite: simulated hand driver, recorder, transfer server and planner.

``ros2 launch t42_transfer t42_suite.launch.py [params_file:=/path/suite.yaml] [namespace:=/left]``.
The same params file runs without a ROS install as ``t42 up configs/suite.yaml
[--namespace /left]``.  Each executable is a console script of setup.py, one per entry
of t42_transfer.nodes.registry.NODES; every name the nodes use is relative, so a
namespace puts a whole suite (one hand) beside another.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = ("mock_driver", "recorder", "transfer_server", "planner")
"""The suite: every node of configs/suite.yaml (the explorer is run on its own, it ends when done)."""


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("t42_transfer"), "config", "suite.yaml")
    params_file = LaunchConfiguration("params_file")
    namespace = LaunchConfiguration("namespace")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS params file with a section per node"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the whole suite (one hand)"),
        *[
            Node(package="t42_transfer", executable=name, name=name, namespace=namespace,
                 parameters=[params_file], output="screen", emulate_tty=True)
            for name in NODES
        ],
    ])
