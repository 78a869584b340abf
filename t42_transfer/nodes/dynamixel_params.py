"""The Dynamixel driver's parameters (:mod:`t42_transfer.nodes.dynamixel_driver` is the node)."""

from __future__ import annotations

from dataclasses import dataclass

from t42_transfer.conventions import DROP_JUMP_MM, MM_PER_M
from t42_transfer.driver.servo_hand import HandGeometry
from t42_transfer.hardware.servos import SDK_LATENCY_TIMER_MS
from t42_transfer.ros.params import param

_T42 = HandGeometry()
"""The parameters' defaults: the hand's geometry as it ships (its ranges are checked there, once)."""


@dataclass(frozen=True)
class DynamixelDriverParams:
    """The driver's ROS parameters (the hand's geometry is checked by :class:`HandGeometry`)."""

    port: str = param("/dev/ttyUSB0", "the servo bus (a U2D2 or similar USB adapter)", configure=True)
    baud: int = param(1_000_000, "the servos' baud rate", min=9600, max=4_500_000, configure=True)
    latency_timer_ms: float = param(SDK_LATENCY_TIMER_MS, "the USB adapter's latency timer: an answer is awaited "
                                    "2x this + 2 ms + its bytes' time (an emulated bus: more)", min=0.0, max=1000.0,
                                    configure=True)
    servo_ids: tuple[int, ...] = param(_T42.servo_ids, "servo ids in action order (hands A and B are mirrored)",
                                       configure=True)
    open_ticks: tuple[int, ...] = param(_T42.open_ticks, "Present Position of each servo with its finger open",
                                        configure=True)
    directions: tuple[int, ...] = param(_T42.directions, "+1: ticks above open close the finger, -1: below",
                                        configure=True)
    max_angle_rad: tuple[float, ...] = param(_T42.max_angle_rad, "position limit of each servo from open (rad); "
                                             "at run time lowered at once, raised only unconfigured")
    load_limit: float = param(_T42.load_limit, "no finger closes further with a load over this, in the servos' raw "
                              "load units (0.1 % of stall torque, 0.0041 N m: 280 is 1.15 N m of effort on "
                              "hand/joint_states)", min=1.0, max=2000.0)
    grasp_load: float = param(_T42.grasp_load, "a reset closes each finger until its load passes this, in raw load "
                              "units as load_limit (100 is 0.41 N m)", min=1.0, max=2000.0)
    max_pose_age_s: float = param(0.3, "a tracker pose older than this is never published as current",
                                  min=0.01, max=10.0)
    drop_jump_m: float = param(DROP_JUMP_MM / MM_PER_M, "an object pose farther than this a control period "
                               "(between the two frames' stamps) from the step before's ends the episode (dropped), "
                               "the paper's drop rule; 0: never", min=0.0, max=1.0)
    max_command_age_s: float = param(0.5, "commands stamped further than this from now are refused",
                                     min=1e-3, max=3600.0)
    autostart: bool = param(False, "configure and activate at start (a suite without a lifecycle manager)",
                            read_only=True)

    def geometry(self) -> HandGeometry:
        return HandGeometry(tuple(self.servo_ids), tuple(self.open_ticks), tuple(self.directions),  # type: ignore[arg-type]
                            tuple(self.max_angle_rad), self.load_limit,  # type: ignore[arg-type]
                            self.grasp_load)

    def __post_init__(self) -> None:
        self.geometry()  # ValueError naming the setting, as ros2 param set reports it
