"""driver.pose.NewestPose: which tracker pose a step may publish as its own, for every driver."""

from __future__ import annotations

import numpy as np
import pytest

from msg_adapters import RCLPY, object_pose_msg
from t42_transfer.driver.pose import DropWatch, NewestPose

S = 1_000_000_000


def test_a_fresh_pose_goes_out_and_a_stale_stretch_is_said_once() -> None:
    pose = NewestPose()
    assert pose.for_step(10 * S, 0.3) == (None, "no pose received")
    assert pose.for_step(11 * S, 0.3) == (None, None)  # still stale: said once
    pose.receive(11 * S, np.array([1.0, 2.0]))
    xy, why = pose.for_step(11 * S + S // 5, 0.3)
    np.testing.assert_array_equal(xy, [1.0, 2.0])
    assert why is None and not pose.stale
    xy, why = pose.for_step(12 * S, 0.3)
    assert xy is None and why == "the newest is 1.00 s old" and pose.stale


def test_a_pose_stamped_after_the_step_by_more_than_the_limit_is_not_the_steps() -> None:
    pose = NewestPose()
    pose.receive(20 * S, np.array([0.0, 80.0]))
    assert pose.for_step(20 * S - S // 10, 0.3)[0] is not None  # a frame a little ahead (sim time) is its own
    assert pose.for_step(10 * S, 0.3) == (None, "the newest is stamped 10.00 s after the step")


def test_a_new_grasp_forgets_the_old_pose() -> None:
    pose = NewestPose()
    pose.receive(S, np.array([0.0, 80.0]))
    pose.forget()
    assert pose.for_step(S, 0.3) == (None, "no pose received")


def test_after_a_new_grasp_the_old_grasps_frames_are_left_out() -> None:
    pose = NewestPose()
    pose.forget(before_ns=2 * S)  # the new grasp's first frame is stamped 2 s
    assert not pose.receive(S + 1, np.array([0.0, 80.0]))  # an old frame, tracked late
    assert pose.stamp_ns is None
    assert pose.receive(2 * S, np.array([5.0, 70.0]))
    np.testing.assert_allclose(pose.for_step(2 * S, 0.3)[0], [5.0, 70.0])


@pytest.mark.parametrize("frame, xy, stamp, reason", [
    ("world", (0.0, 80.0), S, "object pose is in frame 'world'"),
    ("t42_base", (float("nan"), 80.0), S, "non-finite"),
    ("t42_base", (1e33, 80.0), S, "1e+30 m from t42_base cannot be in the hand"),
    ("t42_base", (-1001.0, 80.0), S, "cannot be in the hand"),
    ("t42_base", (0.0, 80.0), 0, "its header stamp is unset (0)"),
])
def test_a_pose_that_cannot_be_a_steps_is_refused_with_the_reason(frame, xy, stamp, reason) -> None:
    pose = NewestPose()
    msg = object_pose_msg(np.array([0.0, 80.0]), stamp, RCLPY)
    msg.header.frame_id = frame
    msg.pose.position.x = xy[0] / 1000.0
    why = pose.receive_msg(msg)
    assert why is not None and reason in why, why
    assert pose.for_step(S, 0.3) == (None, "no pose received")  # nothing kept


def test_a_good_pose_message_is_kept_in_millimetres() -> None:
    pose = NewestPose()
    assert pose.receive_msg(object_pose_msg(np.array([3.0, 81.0]), 5 * S, RCLPY)) is None
    np.testing.assert_allclose(pose.for_step(5 * S, 0.3)[0], [3.0, 81.0], atol=1e-4)


def test_a_new_grasp_says_stale_again_and_a_plain_forget_keeps_the_grasps_bound() -> None:
    pose = NewestPose()
    assert pose.receive(2 * S, np.array([5.0, 70.0]))
    assert pose.for_step(4 * S, 0.3)[1] is not None and pose.for_step(5 * S, 0.3) == (None, None)  # said once
    pose.forget(before_ns=6 * S)
    assert pose.for_step(6 * S, 0.3) == (None, "no pose received")  # the new grasp's stretch is said again
    pose.forget()  # (a pose source switched): the old grasp's frames stay out
    assert not pose.receive(5 * S, np.array([0.0, 80.0]))
    assert pose.receive(90 * S, np.array([0.0, 80.0])) and pose.receive(7 * S, np.array([1.0, 80.0]))  # the newest
    np.testing.assert_allclose(pose.for_step(7 * S, 0.3)[0], [1.0, 80.0])  # a future stamp does not block the rest


def test_a_move_over_the_jump_a_period_between_the_frames_is_a_drop() -> None:
    watch, period = DropWatch(), S // 10
    assert watch.moved_mm(np.array([0.0, 80.0]), S, 8.0) is None  # the episode's first pose: nothing before
    assert watch.moved_mm(np.array([7.0, 80.0]), S + period, 8.0) is None
    assert watch.moved_mm(np.array([16.0, 80.0]), S + 2 * period, 8.0) == (pytest.approx(9.0), pytest.approx(0.1))
    assert watch.moved_mm(np.array([16.0, 80.0]), S + 2 * period, 8.0) is None  # the same frame again: no move
    assert watch.moved_mm(np.array([31.0, 80.0]), S + 4 * period, 8.0) is None  # 15 mm between frames 0.2 s apart
    assert watch.moved_mm(np.array([31.0, 63.0]), S + 6 * period, 8.0) == (pytest.approx(17.0), pytest.approx(0.2))
    assert watch.moved_mm(np.array([31.0, 73.0]), S + 6 * period + period // 2, 8.0)[0] == pytest.approx(10.0)
    assert watch.moved_mm(np.array([31.0, 93.0]), S + 7 * period, 0.0) is None  # the rule off


def test_a_stale_step_or_a_new_episode_leaves_the_next_pose_nothing_to_compare_with() -> None:
    watch = DropWatch()
    watch.moved_mm(np.array([0.0, 80.0]), S, 8.0)
    assert watch.moved_mm(None, 0, 8.0) is None
    assert watch.moved_mm(np.array([20.0, 80.0]), S + S // 10, 8.0) is None  # after a stale step
    assert watch.moved_mm(np.array([40.0, 80.0]), S + S // 5, 8.0)[0] == pytest.approx(20.0)
    watch.start()
    assert watch.moved_mm(np.array([0.0, 80.0]), S + 3 * S // 10, 8.0) is None  # a new episode
