"""ROS 2 launch file of the node suite: every node its params file has a section for.

``ros2 launch t42_transfer t42_suite.launch.py [params_file:=/path/file.yaml] [namespace:=/left]``.
The default is the simulated suite, ``share/t42_transfer/config/suite.yaml`` (mock driver, recorder,
transfer server, planner); the package installs the other params files beside it: ``suite_camera.yaml``,
``hardware_emulated.yaml`` and ``hardware_real.yaml`` (edit a copy of the last for your hand).  The same
file runs without a ROS install as ``t42 up configs/<file>.yaml [--namespace /left]``, and both start the
same nodes the same way (``t42_transfer.ros.launcher.launch_nodes``), restarted as ``t42 up`` restarts them
(``respawn``, at most 5 times), though after a fixed 1 s (launch has no backoff); a node that can finish (the
explorer) is not restarted, since launch would start it again after its exit 0 too.  Each executable is a console script
of setup.py, one per entry of t42_transfer.nodes.registry.NODES; every name the nodes use is relative, so a
namespace puts a whole suite (one hand) beside another.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from t42_transfer.ros.launcher import PACKAGE, launch_nodes


def _nodes(context: LaunchContext) -> list[Node]:
    """The file's nodes, read when the launch runs (the file is an argument)."""
    params_file = LaunchConfiguration("params_file").perform(context)
    namespace = LaunchConfiguration("namespace").perform(context)
    return [Node(**arguments) for arguments in launch_nodes(params_file, namespace)]


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory(PACKAGE), "config", "suite.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS params file with a section per node to start"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the whole suite (one hand)"),
        OpaqueFunction(function=_nodes),
    ])
