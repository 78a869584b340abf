"""ROS 2 launch file of the node suite: simulated hand driver, recorder, transfer server and planner.

``ros2 launch t42_transfer t42_suite.launch.py [params_file:=/path/suite.yaml]``.
The same params file runs without ROS as ``t42 up configs/suite.yaml``.  Each
executable is a console script of setup.py, one per entry of
t42_transfer.nodes.registry.NODES.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


NODES = ("mock_driver", "recorder", "transfer_server", "planner")
"""The suite: every node of configs/suite.yaml (the explorer is run on its own, it ends when done)."""


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("t42_transfer"), "config", "suite.yaml")
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS params file with a section per node"),
        *[
            Node(package="t42_transfer", executable=name, name=name,
                 parameters=[params_file], output="screen", emulate_tty=True)
            for name in NODES
        ],
    ])
