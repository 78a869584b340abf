"""The planner node's inbox without ROS: the latest goal wins, goals wait for an announced model, cancels, and what
the worker watches while a goal executes (pieces sent, the state after them, why a goal stops)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from t42_transfer.nodes.planner_inbox import Inbox, Stop
from t42_transfer.nodes.planner_parts import Goal

NOW_NS = 10_000_000_000
ANGLES = np.array([0.1, 0.2])


class FakeRun:
    """What the inbox reads of a :class:`~t42_transfer.nodes.reach.ReachRun`."""

    def __init__(self) -> None:
        self.handle = object()
        self.cancel_asked = False

    @property
    def cancelled(self) -> bool:
        return self.cancel_asked


class Rig:
    def __init__(self) -> None:
        self.warnings: list[str] = []
        self.inbox = Inbox(lambda: NOW_NS, self.warnings.append)


@pytest.fixture
def rig() -> Rig:
    return Rig()


def goal(x: float = 1.0, run: FakeRun | None = None) -> Goal:
    return Goal(np.array([x, 0.0]), 0, run)


def in_thread(call: Callable[[], Any]) -> tuple[threading.Thread, list[Any]]:
    got: list[Any] = []
    thread = threading.Thread(target=lambda: got.append(call()), daemon=True)
    thread.start()
    return thread, got


def put_state(inbox: Inbox, stamp: int, xy: tuple[float, float] = (3.0, 4.0)) -> None:
    inbox.put_pose((stamp, np.array(xy, np.float32)))
    inbox.put_joints((stamp, np.array([5.0, 6.0], np.float32), ANGLES))


def test_the_latest_goal_wins_and_the_one_it_replaced_is_handed_back(rig: Rig) -> None:
    first, second = goal(1.0), goal(2.0)
    assert rig.inbox.idle and rig.inbox.submit(first) is None
    assert rig.inbox.submit(second) is first and not rig.inbox.idle
    assert rig.inbox.next_goal() is second
    assert not rig.inbox.idle and rig.inbox.newer() is False  # planned until done
    rig.inbox.goal_done()
    assert rig.inbox.idle


def test_a_goal_waits_while_an_announced_model_is_read_and_stop_ends_every_wait(rig: Rig) -> None:
    rig.inbox.announce("a.safetensors")
    rig.inbox.announce("b.safetensors")  # the newest replaces one not yet read
    assert rig.inbox.next_model() == "b.safetensors"
    rig.inbox.submit(goal())
    worker, got = in_thread(rig.inbox.next_goal)
    worker.join(0.2)
    assert worker.is_alive() and got == []  # the model is being read
    rig.inbox.model_read()
    worker.join(2.0)
    assert got and got[0].xy[0] == 1.0

    loader, models = in_thread(rig.inbox.next_model)
    worker, goals = in_thread(rig.inbox.next_goal)
    rig.inbox.stop()
    loader.join(2.0), worker.join(2.0)
    assert models == [None] and goals == [None] and rig.inbox.stopping and rig.inbox.newer() is None


def test_state_stamp_is_the_older_of_pose_and_joints_and_latest_reads_them_with_the_model(rig: Rig) -> None:
    assert rig.inbox.state_stamp_ns is None
    rig.inbox.put_pose((5, np.zeros(2)))
    assert rig.inbox.state_stamp_ns is None
    rig.inbox.put_joints((3, np.zeros(2), ANGLES))
    assert rig.inbox.state_stamp_ns == 3
    model, pose, joints = rig.inbox.latest()
    assert model is None and pose[0] == 5 and joints[0] == 3


def test_a_cancel_takes_out_a_waiting_goal_and_stops_the_hand_for_the_running_one(rig: Rig) -> None:
    stops: list[int] = []
    waiting, running = FakeRun(), FakeRun()
    rig.inbox.submit(goal(run=waiting))
    assert rig.inbox.cancel(waiting.handle, lambda: stops.append(1))[0].run is waiting
    assert stops == [] and rig.inbox.idle
    rig.inbox.submit(goal(run=running))
    rig.inbox.next_goal()
    assert rig.inbox.put_pose((1, np.zeros(2))) is running  # the running goal records the poses
    assert rig.inbox.cancel(running.handle, lambda: stops.append(1)) == (None, True)
    assert stops == [1] and running.cancel_asked
    assert rig.inbox.cancel(object(), lambda: stops.append(1)) == (None, False) and stops == [1]


def test_a_piece_goes_out_until_its_goal_must_stop_and_says_why(rig: Rig) -> None:
    run = FakeRun()
    action, topic = rig.inbox.watch(run), rig.inbox.watch(None)
    assert action.send(3, lambda: 42) == 42
    rig.inbox.episode_ended("dropped")  # ends the action goal, not a t42/goal goal
    assert action.send(3, lambda: pytest.fail("sent after the episode ended")) == Stop(False, False, True)
    assert topic.send(3, lambda: 43) == 43
    rig.inbox.submit(goal())
    assert topic.send(3, lambda: 44) == Stop(False, False, False)  # a newer goal waits
    run.cancel_asked = True
    assert action.send(3, lambda: 45) == Stop(False, True, False)
    rig.inbox.stop()
    assert topic.send(3, lambda: 46).stopping


def test_a_piece_a_cancels_stop_and_a_stopped_goals_last_word_go_out_under_the_lock(rig: Rig) -> None:
    """What the node publishes from these callbacks must not be overtaken: a piece by a cancel's stop, a goal's
    'never sent' result by a newer goal's."""
    owned: list[str] = []

    def note(what: str, value: Any = None) -> Any:
        owned.append(what if rig.inbox._cond._is_owned() else f"{what} without the lock")
        return value

    run = FakeRun()
    rig.inbox.submit(goal(run=run))
    rig.inbox.next_goal()
    watch = rig.inbox.watch(run)
    assert watch.send(1, lambda: note("piece", 7), lambda stop: note("stopped")) == 7
    rig.inbox.cancel(run.handle, lambda: note("stop"))
    assert watch.send(1, lambda: note("piece"), lambda stop: note(f"stopped {stop}")) == Stop(False, True, False)
    assert owned == ["piece", "stop", f"stopped {Stop(False, True, False)}"]


def test_the_state_after_a_piece_is_the_first_stamped_after_its_last_step(rig: Rig) -> None:
    watch = rig.inbox.watch(None)
    put_state(rig.inbox, 900)
    watch.send(2, lambda: 0)

    def driver() -> None:
        time.sleep(0.05)
        rig.inbox.piece_done(1000)  # the piece's last step was stamped 1000
        put_state(rig.inbox, 1000, (7.0, 8.0))  # the state that step was applied from: not the one after it
        time.sleep(0.05)
        put_state(rig.inbox, 1100, (9.0, 10.0))

    threading.Thread(target=driver, daemon=True).start()
    after = watch.after_piece(5.0, max_age_ns=NOW_NS)
    assert after is not None and after.state.tolist() == [9.0, 10.0, 5.0, 6.0]
    assert after.angles.tolist() == ANGLES.tolist() and rig.warnings == []


@pytest.mark.parametrize("case, warning", [
    ("never_done", "a 0-step piece did not finish within its time and 0.1 s more; the hand is stopped"),
    ("no_state", "no hand state after the piece in time; closed loop ends"),
    ("stale", "closed loop ends: hand state is"),
])
def test_a_piece_without_a_state_after_it_ends_the_loop_with_why(rig: Rig, case: str, warning: str) -> None:
    watch = rig.inbox.watch(None)
    watch.send(0, lambda: 0)
    if case != "never_done":
        rig.inbox.piece_done(None)  # no stamp named: any state after -1
    if case == "stale":
        put_state(rig.inbox, 0)
    assert watch.after_piece(0.1, max_age_ns=1_000_000) is None
    assert len(rig.warnings) == 1 and rig.warnings[0].startswith(warning)


def test_a_newer_goal_ends_the_wait_for_a_piece_at_once_and_silently(rig: Rig) -> None:
    watch = rig.inbox.watch(None)
    watch.send(0, lambda: 0)
    threading.Timer(0.05, rig.inbox.submit, (goal(),)).start()
    started = time.monotonic()
    assert watch.after_piece(10.0, max_age_ns=NOW_NS) is None
    assert time.monotonic() - started < 5.0 and rig.warnings == []


def test_the_end_gives_the_episode_ends_since_the_goal_began_and_stops_the_hand_unless_cancelled(rig: Rig) -> None:
    stops: list[int] = []
    rig.inbox.episode_ended("overload")  # before the goal: not its end
    run = FakeRun()
    watch = rig.inbox.watch(run)
    rig.inbox.episode_ended("dropped")
    assert watch.end(lambda: stops.append(1)) == (["dropped"], False) and stops == [1]
    rig.inbox.submit(goal())
    assert watch.end(None) == (["dropped"], True) and stops == [1]  # ended with its final state
    run.cancel_asked = True
    watch.end(lambda: stops.append(1))
    assert stops == [1]  # the cancel stopped the hand already
