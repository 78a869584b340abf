"""The simulated hands' camera (issue 21): the mock driver and the emulated hardware render the hand with its
markers; with ``pose_source: topic`` the mock driver publishes the tracker's pose instead of the simulator's.

Checked on real rclpy, in-process: an object_tracker on the rendered frames gives each step its own frame's pose
(the frame's stamp is the step's, on sim time), within a millimetre of the truth on sim/object_pose; without a
tracker no pose goes out and the driver says ``stale``; with the camera off nothing of it is imported."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from ros_rig import Tester
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from msg_adapters import (
    RCLPY,
    actions_to_joint_trajectory,
    camera_info_calibration,
    joint_state_arrays,
    names,
    object_pose_msg,
    object_xy_mm,
    stamp_to_ns,
    status_event,
)
from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.hand.mjcf import object_marker_height_mm
from t42_transfer.hand.params import variant
from t42_transfer.nodes.hw_emulator import HwEmulator, HwEmulatorParams
from t42_transfer.nodes.mock_driver import MockDriver, MockDriverParams
from t42_transfer.nodes.object_tracker import ObjectTracker
from t42_transfer.ros.qos import profile
from t42_transfer.tracking.render import pinhole_intrinsics

MARKER_HEIGHT_M = object_marker_height_mm(variant("target")) / 1000.0


def _stamp(msg) -> int:
    return stamp_to_ns(msg.header.stamp)


@pytest.mark.executor_threads(3)
def test_each_step_gets_its_own_frames_tracked_pose_with_the_frames_stamp(ros) -> None:
    """In one process the nodes share an executor: the test listens to camera infos (each with its frame's stamp)
    rather than the frames themselves, which would keep the executor from the driver's tracker poses."""
    tester = Tester(ros)
    got = {topic: tester.listen(kind, topic, profile(names.IMAGES) if kind is CameraInfo else 100)
           for topic, kind in ((names.CAMERA_INFO, CameraInfo),
                               (names.SIM_POSE, PoseStamped), (names.TRACKER_POSE, PoseStamped),
                               (names.OBJECT_POSE, PoseStamped), (names.JOINT_STATES, JointState))}
    clock = tester.listen(Clock, names.CLOCK)
    ros.add(ObjectTracker, {"object_marker_height_m": MARKER_HEIGHT_M})
    assert tester.wait_graph(subscribers={names.CAMERA_IMAGE: 1})
    # 4x faster than real time: frames every 25 ms of wall time, which a busy machine cannot always track; in
    # lockstep with the tracker the clock waits for each frame's pose instead of stepping on without it
    driver = ros.add(MockDriver, {"sim_time": True, "rate_factor": 4.0, "camera_rate_hz": 10.0,
                                  "pose_source": "topic", "seed": 3})
    assert ros.spin_until(lambda: len(clock) > 2 and len(got[names.JOINT_STATES]) > 2, 10.0)
    # move the object: close both fingers a little, then roll it sideways (one point per step)
    actions = np.array([[0.5, 0.5]] * 6 + [[1.0, -1.0]] * 12 + [[-1.0, 1.0]] * 6, np.float32)
    angles = joint_state_arrays(got[names.JOINT_STATES][-1])[0]
    tester.tester.create_publisher(JointTrajectory, names.HAND_TRAJECTORY, 10).publish(
        actions_to_joint_trajectory(actions, angles, stamp_to_ns(clock[-1].clock), RCLPY))
    assert ros.spin_until(lambda: driver.steps >= len(actions) + 8 or not driver.running, 30.0), driver.steps
    driver.close()  # no more steps or frames: what was sent arrives
    ros.spin_for(0.5)

    images, truths = got[names.CAMERA_INFO], got[names.SIM_POSE]
    steps = [_stamp(m) for m in got[names.JOINT_STATES]]
    assert len(images) >= 20
    info = camera_info_calibration(got[names.CAMERA_INFO][0])
    np.testing.assert_allclose(info.k, pinhole_intrinsics(640, 480, 45.0).k)  # the true intrinsics
    truth_at = {_stamp(m): object_xy_mm(m) for m in truths}
    assert [_stamp(m) for m in images] == list(truth_at)  # every frame has its truth, stamp for stamp
    assert set(steps[1:]) <= set(truth_at)  # each step after the first is a frame's stamp (sim time)
    assert all(b - a == CONTROL_PERIOD_NS for a, b in zip(steps, steps[1:], strict=False))
    moved = np.ptp(np.array([truth_at[s] for s in steps[1:]]), axis=0)
    assert np.linalg.norm(moved) > 3.0, moved  # the object moved: a stale pose would be told from a fresh one

    tracked = {_stamp(m): object_xy_mm(m) for m in got[names.TRACKER_POSE]}
    errors = [np.linalg.norm(xy - truth_at[s]) for s, xy in tracked.items()]
    assert np.median(errors) < 1.0 and max(errors) < 3.0, errors
    poses = got[names.OBJECT_POSE]
    assert len(poses) >= len(steps) - 1
    own_frame = 0
    for pose in poses:
        xy = object_xy_mm(pose)
        sources = [s for s, t in tracked.items() if np.allclose(t, xy, atol=1e-6)]
        assert sources, f"a published pose at {_stamp(pose)} is no tracked pose"  # the tracker's, not the sim's
        own_frame += _stamp(pose) in sources
    assert own_frame >= len(poses) - 1, (own_frame, len(poses))  # the step's own frame, with its stamp


@pytest.mark.parametrize("wait_s", [5.0, 0.2])
def test_an_episodes_first_step_never_goes_out_with_the_old_grasps_pose(ros, wait_s: float) -> None:
    """A busy tracker sends the old grasp's last pose after a reset: the new episode's first step must not go
    out with it (it did, and the bag's first transition joined two grasps).  It waits for its own frame's pose
    (5 s); if that does not come within ``tracker_wait_s`` (0.2 s) it goes out without a pose.  The test is the
    tracker here, so it decides when each pose arrives: each frame's true pose, with the frame's stamp."""
    tester = Tester(ros)
    truths = tester.listen(PoseStamped, names.SIM_POSE)
    poses = tester.listen(PoseStamped, names.OBJECT_POSE)
    joints = tester.listen(JointState, names.JOINT_STATES)
    tracker = tester.tester.create_publisher(PoseStamped, names.TRACKER_POSE, 10)
    reset = tester.tester.create_client(Trigger, names.HAND_RESET)
    ros.add(MockDriver, {"sim_time": True, "camera_rate_hz": 10.0, "camera_width": 320, "camera_height": 240,
                         "pose_source": "topic", "tracker_wait_s": wait_s, "seed": 3})
    assert tester.wait_graph(publishers={names.SIM_POSE: 1}, subscribers={names.TRACKER_POSE: 1})

    def grasp() -> PoseStamped:
        """Reset; the new grasp's frame."""
        frames = len(truths)
        assert ros.call(reset, Trigger.Request()).success
        assert ros.spin_until(lambda: len(truths) > frames, 5.0)
        return truths[-1]

    def step_on(frame: PoseStamped) -> PoseStamped:
        """Track ``frame``; the step that follows."""
        steps = len(poses)
        tracker.publish(frame)
        assert ros.spin_until(lambda: len(poses) > steps, 5.0), "no step after the frame's pose"
        return poses[-1]

    frame = grasp()
    for _ in range(3):
        stamp = _stamp(step_on(frame))  # (tracked at once: no wait runs out)
        assert stamp == _stamp(frame)
        assert ros.spin_until(lambda s=stamp: _stamp(truths[-1]) > s, 5.0)  # the next step's frame
        frame = truths[-1]
    old = frame  # the old grasp's last frame, not tracked yet
    new = grasp()
    assert _stamp(new) > _stamp(old)  # the re-grasp took time: its frame is stamped after the old one's
    steps, states = len(poses), len(joints)
    tracker.publish(old)  # late
    ros.spin_for(0.5)
    assert len(poses) == steps, "a step went out with the old grasp's pose"
    if wait_s < 0.5:  # the wait ran out: the first step went out without a pose
        assert ros.spin_until(lambda: len(joints) > states, 5.0) and _stamp(joints[states]) == _stamp(new)
        assert len(poses) == steps
        return
    first = step_on(new)
    assert _stamp(first) == _stamp(new)
    np.testing.assert_allclose(object_xy_mm(first), object_xy_mm(new), atol=1e-6)
    assert np.linalg.norm(object_xy_mm(old) - object_xy_mm(new)) > 0.5  # the two grasps can be told apart


def test_without_a_tracker_no_pose_goes_out_and_the_driver_says_stale(ros) -> None:
    tester = Tester(ros)
    poses = tester.listen(PoseStamped, names.OBJECT_POSE)
    joints = tester.listen(JointState, names.JOINT_STATES)
    statuses = tester.listen(String, names.HAND_STATUS, profile(names.EVENTS))
    driver = ros.add(MockDriver, {"rate_factor": 1e-3, "pose_source": "topic"})
    assert tester.wait_graph(publishers={names.OBJECT_POSE: 1, names.JOINT_STATES: 1})
    for _ in range(5):
        driver.tick()
    assert ros.spin_until(lambda: len(joints) == 5, 5.0)
    stale = [m.data for m in statuses if status_event(m.data) == names.STALE]
    assert poses == [] and len(stale) == 1, (len(poses), stale)
    assert "no pose received" in stale[0]
    # a tracker pose now: the next step publishes it, with the step's stamp
    publisher = tester.tester.create_publisher(PoseStamped, names.TRACKER_POSE, 10)
    assert tester.wait_graph(subscribers={names.TRACKER_POSE: 1})
    world = object_pose_msg(np.array([1.0, 80.0]), driver.now_ns(), RCLPY)
    world.header.frame_id = "world"  # another frame: refused with a warning, and the driver steps on
    publisher.publish(world)
    ros.spin_for(0.2)
    driver.tick()
    assert ros.spin_until(lambda: len(joints) == 6, 5.0) and poses == []
    publisher.publish(object_pose_msg(np.array([1.0, 80.0]), driver.now_ns(), RCLPY))
    assert ros.spin_until(lambda: driver.pose._pose is not None, 5.0)
    driver.tick()
    assert ros.spin_until(lambda: len(poses) == 1 and len(joints) == 7, 5.0)
    np.testing.assert_allclose(object_xy_mm(poses[0]), [1.0, 80.0], atol=1e-6)
    assert _stamp(poses[0]) == _stamp(joints[-1])


def test_a_best_effort_tracker_is_heard_once_the_driver_reader_is_overridden_to_best_effort(ros) -> None:
    """As the Dynamixel driver's: ROS's QoS override makes the reader match a sensor-data (best effort) bridge."""
    from rclpy.qos import qos_profile_sensor_data

    tester = Tester(ros)
    driver = ros.add(MockDriver, {"rate_factor": 1e-3, "pose_source": "topic",
                                  f"qos_overrides./{names.TRACKER_POSE}.subscription.reliability": "best_effort"})
    bridge = tester.tester.create_publisher(PoseStamped, names.TRACKER_POSE, qos_profile_sensor_data)
    assert ros.spin_until(lambda: bridge.get_subscription_count() == 1, 5.0)
    assert driver.describe_parameter(f"qos_overrides./{names.TRACKER_POSE}.subscription.reliability").read_only
    assert ros.spin_until(lambda: bridge.publish(object_pose_msg(np.array([1.0, 80.0]), driver.now_ns(), RCLPY))
                          or driver.pose._pose is not None, 5.0)


def test_the_emulated_hardware_renders_instead_of_its_emulated_tracker(ros) -> None:
    tester = Tester(ros)
    images = tester.listen(Image, names.CAMERA_IMAGE, profile(names.IMAGES))
    truths = tester.listen(PoseStamped, names.SIM_POSE)
    tracked = tester.listen(PoseStamped, names.TRACKER_POSE)
    emulator = ros.add(HwEmulator, {"sim_time": True, "lockstep": False, "rate_factor": 2.0,
                                    "camera_rate_hz": 5.0, "camera_width": 320, "camera_height": 240})
    try:
        assert ros.spin_until(lambda: len(images) >= 6, 15.0)
        ros.spin_for(0.2)
        image_stamps = [_stamp(m) for m in images]
        assert {(m.width, m.height, m.encoding) for m in images} == {(320, 240, "rgb8")}
        assert all(b - a == 2 * CONTROL_PERIOD_NS for a, b in zip(image_stamps, image_stamps[1:], strict=False))
        truth_stamps = {_stamp(m) for m in truths}
        assert {s for s in image_stamps if s <= max(truth_stamps)} <= truth_stamps  # each frame's truth
        assert tracked == []  # the rendered camera replaces the emulated tracker
    finally:
        emulator.close()


@pytest.mark.parametrize("cls, change, message", [
    (MockDriverParams, {"pose_source": "camera"}, "pose_source must be one of sim, topic"),
    (MockDriverParams, {"camera_rate_hz": 20.0}, "camera_rate_hz must be in [0, 10.0]"),
    (MockDriverParams, {"camera_width": 8}, "the camera's size must be 16 to 4096 px"),
    (MockDriverParams, {"max_pose_age_s": float("nan")}, "max_pose_age_s must be positive"),
    (HwEmulatorParams, {"camera_noise": -1.0}, "camera_noise must be a finite number >= 0"),
    (HwEmulatorParams, {"camera_frame_id": " "}, "camera_frame_id must not be empty"),
])
def test_bad_camera_and_pose_settings_are_refused_with_the_reason(cls, change, message) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        cls(**change)


def test_with_the_camera_off_the_drivers_import_no_renderer() -> None:
    code = ("import sys, t42_transfer.nodes.mock_driver, t42_transfer.nodes.hw_emulator; "
            "print(sorted(m for m in sys.modules if m == 'cv2' or m.startswith('t42_transfer.tracking')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_a_new_seed_applies_from_the_next_reset_and_pose_source_switches_live(ros) -> None:
    """What lets the demo run a goal again on the same grasp with the simulator's pose."""
    from rclpy.parameter import Parameter

    tester = Tester(ros)
    poses = tester.listen(PoseStamped, names.OBJECT_POSE)
    driver = ros.add(MockDriver, {"rate_factor": 1e-3, "pose_source": "topic", "seed": 5})
    assert tester.wait_graph(publishers={names.OBJECT_POSE: 1})
    assert driver.reset()[1] == "episode 1 grasped (seed 6)"
    driver.tick()
    ros.spin_for(0.2)
    assert poses == []  # no tracker: nothing
    results = driver.set_parameters([Parameter("seed", value=5), Parameter("pose_source", value="sim")])
    assert all(r.successful for r in results), results
    assert driver.reset()[1] == "episode 2 grasped (seed 5)"  # the grasp of episode 0 again
    assert driver.reset()[1] == "episode 3 grasped (seed 6)"
    published = driver.hand.state[:2].copy()  # the state a step publishes, before it moves the hand
    driver.tick()
    assert ros.spin_until(lambda: len(poses) == 1, 5.0)  # the simulator's pose again
    np.testing.assert_allclose(object_xy_mm(poses[0]), published, atol=1e-3)
    refused = driver.set_parameters([Parameter("pose_source", value="camera")])
    assert not refused[0].successful and "pose_source must be one of sim, topic" in refused[0].reason
