"""The runnable nodes: name -> where its params and node classes live.

Adding a node is one :data:`NODES` entry.  ``setup.py`` parses this file (so
NODES stays a literal dict) to install one console script per node,
``ros2 run t42_transfer <name>``, each pointing at
:func:`t42_transfer.ros.runner.main`.  Classes are named by import path so listing
nodes loads none of them.  This module is data only: the runner imports it, never
the other way round.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class NodeSpec:
    node: str
    """``module:Class`` of the node: an ``rclpy.node.Node`` constructed as ``Class(**node_kwargs)``
    (``context=``, ``namespace=``, ``parameter_overrides=``...), with a ``close()``; a node with a
    ``finished`` property that turns true ends its process (exit 0)."""
    description: str
    finishes: bool = False
    """The node class has that ``finished`` property: its exit 0 is its end, so a launch file must not respawn it.
    Said here so planning a launch imports no node module (torch, mujoco); a test checks it against the class."""

    @staticmethod
    def _load(path: str) -> Any:
        module, _, name = path.partition(":")
        return getattr(importlib.import_module(module), name)

    def node_class(self) -> type:
        return self._load(self.node)


NODES: dict[str, NodeSpec] = {
    "mock_driver": NodeSpec("t42_transfer.nodes.mock_driver:MockDriver",
                            "simulated hand behind the real driver's topics"),
    "dynamixel_driver": NodeSpec("t42_transfer.nodes.dynamixel_driver:DynamixelDriver",
                                 "a real T42's Dynamixel servos behind the driver's topics (a lifecycle node)"),
    "hw_emulator": NodeSpec("t42_transfer.nodes.hw_emulator:HwEmulator",
                            "emulated T42 hardware: servo bus on a pty with the simulated hand, and a tracker"),
    "recorder": NodeSpec("t42_transfer.nodes.recorder:Recorder",
                         "records the hand topics into rosbag2 MCAP bags"),
    "explorer": NodeSpec("t42_transfer.nodes.explorer:Explorer",
                         "random-action episodes through the driver; exits when done", finishes=True),
    "transfer_server": NodeSpec("t42_transfer.nodes.transfer_server:TransferServer",
                                "transfers the source model to the recorded hand on /t42/transfer"),
    "planner": NodeSpec("t42_transfer.nodes.planner_node:PlannerNode",
                        "plans open-loop action sequences to goals with the current model"),
    "camera": NodeSpec("t42_transfer.nodes.camera:Camera",
                       "an OpenCV capture (device or video file) on camera/image_raw and camera/camera_info",
                       finishes=True),
    "object_tracker": NodeSpec("t42_transfer.nodes.object_tracker:ObjectTracker",
                               "the object's pose in t42_base from ArUco markers in camera images"),
    "view": NodeSpec("t42_transfer.nodes.view:View",
                     "the live graph in Foxglove (a WebSocket server), with the hand drawn as markers"),
}

