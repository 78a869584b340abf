"""The suite's ROS interface by name: topics, services, status words and QoS, each defined once.

Every node, the demo and the tests take their names from here, so a rename is one
edit and two nodes cannot disagree.  Names are relative (remappable with
``--ros-args -r``, prefixed by ``__ns``); only ``/clock`` is absolute, as ROS
defines it.  ``~/...`` names are private to the node that serves them; others
reach them as ``<node name>/...`` (:func:`private_of`).

QoS is given as plain data (:class:`Qos`) so this module needs no rclpy: the bag
and science layers import names too.  ``t42_transfer.ros.qos`` turns a
:class:`Qos` into an rclpy profile.
"""

from __future__ import annotations

from typing import NamedTuple

# ------------------------------------------------------------------ the hand driver
OBJECT_POSE = "hand/object_pose"
"""geometry_msgs/PoseStamped: the object's position, metres in ``t42_base``, one per step."""
JOINT_STATES = "hand/joint_states"
"""sensor_msgs/JointState: actuator angles (rad) and loads as effort (N m), one per step."""
APPLIED_ACTION = "hand/applied_action"
"""sensor_msgs/JointState: the action applied at the step, as actuator velocities (rad/s)."""
HAND_COMMAND = "hand/command"
"""sensor_msgs/JointState: an actuator-velocity command held until the next one."""
HAND_TRAJECTORY = "hand/trajectory"
"""trajectory_msgs/JointTrajectory: actuator-angle targets, one point per control period."""
HAND_STATUS = "hand/status"
"""std_msgs/String: the driver's events (:data:`RESET`, :data:`END_EVENTS`, ...)."""
HAND_RESET = "hand/reset"
"""std_srvs/Trigger: open the hand, then close it until the grasp load (a new episode)."""
CLOCK = "/clock"
"""rosgraph_msgs/Clock: the simulated driver's time, when it runs on sim time."""
TRACKER_POSE = "tracker/object_pose"
"""geometry_msgs/PoseStamped: the object as a tracker or motion capture sees it, at its own rate; the real
driver publishes the newest fresh one each step as :data:`OBJECT_POSE`."""
SIM_POSE = "sim/object_pose"
"""geometry_msgs/PoseStamped: the emulated hand's true object pose, for checks only."""

# ------------------------------------------------------------------ camera and object tracker
CAMERA_IMAGE = "camera/image_raw"
"""sensor_msgs/Image: camera frames as captured (stamped at the grab), ``bgr8``/``mono8`` from the camera node."""
CAMERA_INFO = "camera/camera_info"
"""sensor_msgs/CameraInfo: the camera's calibration, one per frame with the frame's stamp."""

GET_STATE = "~/get_state"
"""lifecycle_msgs/GetState: a lifecycle node's state (the Dynamixel driver's), served by rclpy."""

HAND_TOPICS = (OBJECT_POSE, JOINT_STATES, APPLIED_ACTION)
"""The hand's recorded topics, in per-step publish order."""

# ------------------------------------------------------------------ recorder
RECORDER_START = "~/start"
RECORDER_STOP = "~/stop"
RECORDER_SPLIT = "~/split"
RECORDER_PAUSE = "~/pause"
"""std_srvs/Trigger: drop incoming messages (counted), the bag kept open, after the step in progress."""
RECORDER_RESUME = "~/resume"
"""std_srvs/Trigger: record again, into the same bag, from the next whole step."""
RECORDER_SNAPSHOT = "~/snapshot"
"""std_srvs/Trigger: write the steps of the last ``snapshot_s`` seconds as a bag (snapshot mode), as rosbag2's
``~/snapshot``."""
BAG_CLOSED = "recorder/bag_closed"
"""t42_interfaces/BagClosed (:data:`EVENTS`): a bag the recorder closed and finalised, with why; relative to the
recorder's namespace, as rosbag2's ``events/write_split``."""

# ------------------------------------------------------------------ transfer server
TRANSFER = "t42/transfer"
"""t42_interfaces/action/Transfer: transfer the source model with a method and bags (none: those recorded since
the last transfer), with feedback per epoch, cancel (the previous model stays) and the held-out scores."""
TRANSFER_NOW = "t42/transfer_now"
"""std_srvs/Trigger: the same transfer with the server's method and the bags recorded since the last one; a
one-line answer (for callers without t42_interfaces)."""
MODEL_UPDATED = "t42/model_updated"
"""t42_interfaces/ModelUpdated (latched): the newest model file (absolute path), when it was saved, its method and
episodes."""
DIAGNOSTICS = "diagnostics"
"""diagnostic_msgs/DiagnosticArray: progress and state of long work."""

# ------------------------------------------------------------------ planner
GOAL = "t42/goal"
"""geometry_msgs/PointStamped: an object goal, metres in ``t42_base``."""
PLANNED_PATH = "t42/planned_path"
"""nav_msgs/Path: the predicted object path of the plan being executed."""
PLAN_CANDIDATES = "t42/plan_candidates"
"""t42_interfaces/PlanCandidates: predicted paths of a plan's lowest-cost candidates (planner ``candidates`` > 0)."""
PLAN_RESULT = "t42/plan_result"
"""t42_interfaces/PlanResult (:data:`RESULTS`): one per goal (accepted, or refused with the status and reason)."""
REACH = "t42/reach"
"""t42_interfaces/action/Reach: move the object to a goal, with feedback, cancel and a verdict (the planner)."""

# ------------------------------------------------------------------ t42 view (Foxglove)
VIEW_MARKERS = "view/markers"
"""visualization_msgs/MarkerArray: the scene the view node draws (hand, object, goal and tolerance, planned path)."""

# ------------------------------------------------------------------ status words
# The first word of a hand/status text (msg_adapters.status): a reset began, the object is placed anew while
# the hand opens and closes (grasping); the grasp closed and a new episode starts (reset) or could not
# (reset_failed); the episode ended (dropped, lost_contact, overload); the last point of a trajectory has been
# applied (trajectory_done).  A tracker takes the object's move from grasping to the first frame after the
# grasp closed for a new placement, not a drop.
GRASPING, RESET, RESET_FAILED = "grasping", "reset", "reset_failed"
DROPPED, LOST_CONTACT, OVERLOAD = "dropped", "lost_contact", "overload"
TRAJECTORY_DONE = "trajectory_done"
# The real driver's: a servo fault stopped the hand (fault) or cleared (recovered); no fresh object pose
# this step, so none was published (stale).
FAULT, RECOVERED, STALE = "fault", "recovered", "stale"
# A step came more than 1.5 control periods after the previous one (a stall, a busy machine, bus jitter): its
# last-step stamp names the late step, which followed the previous one with no step missing in between.  A bag
# that holds this status keeps such a step in its episode instead of splitting there.
LATE = "late"
END_EVENTS = (DROPPED, LOST_CONTACT, OVERLOAD)
"""Events that end an episode (the hand stops until the next reset)."""
SPLIT_EVENTS = (RESET, *END_EVENTS, FAULT)
"""Events at which an episode-mode recorder closes one bag and opens the next."""
GRASP_EVENTS = (GRASPING, RESET, RESET_FAILED)
"""Events that begin or end a grasp (a reset)."""

SUPERSEDED = "superseded"
"""A goal's result when a newer goal replaced it before its plan ran."""


def private_of(node: str, private: str) -> str:
    """How others name ``node``'s private service or topic ``~/name``: ``("recorder", "~/start")`` ->
    ``"recorder/start"``."""
    if not private.startswith("~/"):
        raise ValueError(f"{private!r} is not a private name (~/...)")
    return f"{node}/{private[2:]}"


# ------------------------------------------------------------------ QoS
class Qos(NamedTuple):
    """A QoS profile as data: KEEP_LAST ``depth``, RELIABLE; TRANSIENT_LOCAL when ``latched``."""

    depth: int
    latched: bool = False


IMAGES = Qos(2)
"""Camera frames and their CameraInfo: a short queue, as only the newest frame matters (a flood is dropped at
the reader, not queued)."""
LATCHED = Qos(1, latched=True)
"""A late joiner still gets the last message: model announcements, and what a viewer opened later should draw at
once (the plan's path and candidates, the view's scene; RViz or Foxglove with durability transient local)."""
EVENTS = Qos(100, latched=True)
"""``hand/status`` as the driver writes it: none may be lost in a burst, which a depth of 1 allows
(a reliable KEEP_LAST 1 writer replaces an unacknowledged sample), and a late joiner gets the recent ones."""
EVENT_READER = Qos(100)
"""Reading events as they happen: deep, so none is lost in a burst; VOLATILE, so it matches any
reliable writer (a TRANSIENT_LOCAL reader would not match a real driver that publishes VOLATILE)."""
EVERY_STEP = Qos(1000)
"""Reading a per-step topic where every message counts (the explorer's applied actions): at 10x the control rate a
reader stalled 0.1 s overflowed a depth of 10 under the parallel test suite, and the one action lost made the rest of
its trajectory a mismatch."""
REQUESTS = Qos(10_000)
"""A service's request queue and a goal subscription: a burst of callers each gets an answer (rclpy's default
depth of 10 left 40 of 50 simultaneous resets unanswered, and lost goals before any result was made)."""
RESULTS = Qos(10_000, latched=True)
"""Plan results: volatile and latched subscribers both match, a late latched one gets the recent
results, and none of a burst (each goal of 2000 superseded in turn) is overwritten before it is read."""
OFFERED = {HAND_STATUS: EVENTS, MODEL_UPDATED: LATCHED, PLAN_RESULT: RESULTS}
"""What the publishers of the latched topics a recorder records offer.  A bag offers each so, as ``ros2 bag
record`` stores each publisher's offer, and a player then republishes it latched: a latched reader (the
planner's of ``t42/model_updated``) matches no volatile writer."""
