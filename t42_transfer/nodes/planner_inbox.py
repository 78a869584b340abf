"""What the planner node's threads share, under one lock: the model, the latest hand state and the driver's
statuses (the executor's callbacks put them), the goal waiting and the model announced (the worker and the
loader take them), and the worker's waits on them while a goal executes (:class:`Watch`).

No rclpy here (:mod:`t42_transfer.nodes.planner_node` is the node; its docstring says why the latest goal wins
and why plans and model reads run in threads of their own).  Two things are done under the lock on purpose: a
piece is sent only after checking that its goal goes on, and a cancel stops the hand, so that no piece ever
overtakes a stop.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.nodes.planner_parts import Goal, HandState, LoadedModel, Refused, hand_state

if TYPE_CHECKING:
    from t42_transfer.nodes.reach import ReachRun

T = TypeVar("T")
Pose = tuple[int, np.ndarray]
"""``(stamp ns, object xy mm)``."""
Joints = tuple[int, np.ndarray, "np.ndarray | None"]
"""``(stamp ns, loads, actuator angles or None)``."""
KEPT = 10
"""The newest trajectory_done stamps and episode ends kept."""


class Inbox:
    """The planner node's shared state and the waits on it (see the module docstring); thread-safe."""

    def __init__(self, now_ns: Callable[[], int], warn: Callable[[str], None]) -> None:
        self._now_ns, self._warn = now_ns, warn
        self._cond = threading.Condition()
        self._model: LoadedModel | None = None
        self._pose: Pose | None = None
        self._joints: Joints | None = None
        self._pending: Goal | None = None
        self._planning = False
        self._stopping = False
        self._announced: str | None = None
        """A model path announced and not yet read (the loader thread reads it)."""
        self._loading = False
        """The loader is reading an announced model (goals wait for it)."""
        self._done_stamps: list[int] = []
        """Last-step stamps of the driver's trajectory_done statuses, newest last (the ten newest)."""
        self._dones = 0
        """trajectory_done statuses received in all: a piece has run when this grew."""
        self._active: ReachRun | None = None
        """The action goal being planned or executed."""
        self._episode_ends: list[str] = []
        """The driver's episode-end events (dropped, ...), newest last (the ten newest)."""
        self._ends = 0
        """Episode-end events received in all."""

    # ------------------------------------------------------------------ what the callbacks put
    @property
    def model(self) -> LoadedModel | None:
        return self._model

    @model.setter
    def model(self, loaded: LoadedModel) -> None:
        with self._cond:
            self._model = loaded

    def put_pose(self, pose: Pose) -> ReachRun | None:
        """The latest object pose; the action goal that runs (it records the pose), if any."""
        with self._cond:
            self._pose = pose
            return self._active

    def put_joints(self, joints: Joints) -> None:
        with self._cond:
            self._joints = joints

    def episode_ended(self, event: str) -> None:
        """The driver's episode ended (``dropped``...): an action goal executing ends."""
        with self._cond:
            self._episode_ends = [*self._episode_ends[-(KEPT - 1):], event]
            self._ends += 1
            self._cond.notify_all()

    def piece_done(self, last_step_ns: int | None) -> None:
        """The driver's ``trajectory_done``, naming the stamp of the piece's last step (None: -1, none named)."""
        with self._cond:
            self._done_stamps = [*self._done_stamps[-(KEPT - 1):], -1 if last_step_ns is None else last_step_ns]
            self._dones += 1
            self._cond.notify_all()

    def announce(self, path: str) -> None:
        """A model to read; it replaces one not yet read: only the newest is worth reading."""
        with self._cond:
            self._announced = path
            self._cond.notify_all()

    def submit(self, goal: Goal) -> Goal | None:
        """Queue ``goal``; the goal it replaced (it waited), if any.  The one executing ends (:class:`Watch`)."""
        with self._cond:
            replaced, self._pending = self._pending, goal
            self._cond.notify_all()
        return replaced

    def cancel(self, handle: Any, stop_hand: Callable[[], None]) -> tuple[Goal | None, bool]:
        """Cancel the action goal of ``handle``: (the goal taken out if it waited, whether it was the one planned or
        executing: it is marked cancelled and ``stop_hand()`` runs, under the lock)."""
        with self._cond:
            pending = self._pending if self._pending is not None and self._pending.run is not None \
                and self._pending.run.handle == handle else None
            if pending is not None:
                self._pending = None
            active = self._active if self._active is not None and self._active.handle == handle else None
            if active is not None:
                active.cancel_asked = True
                stop_hand()
            self._cond.notify_all()
        return pending, active is not None

    # ------------------------------------------------------------------ what the worker and the loader take
    @property
    def stopping(self) -> bool:
        return self._stopping

    def stop(self) -> None:
        """The node stops: the waits end (a plan under way sees :attr:`stopping` at its next chunk)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()

    @property
    def idle(self) -> bool:
        """No goal waiting or being planned."""
        with self._cond:
            return self._pending is None and not self._planning

    @property
    def state_stamp_ns(self) -> int | None:
        """Stamp of the older of the latest object pose and joint states (None before both arrived)."""
        with self._cond:
            if self._pose is None or self._joints is None:
                return None
            return min(self._pose[0], self._joints[0])

    def latest(self) -> tuple[LoadedModel | None, Pose | None, Joints | None]:
        """The model, object pose and joint states to plan with, read at once."""
        with self._cond:
            return self._model, self._pose, self._joints

    def newer(self) -> bool | None:
        """Whether a newer goal waits (None: the node stops)."""
        with self._cond:
            return None if self._stopping else self._pending is not None

    def next_model(self) -> str | None:
        """Wait for a model announced (None: the node stops); goals wait until :meth:`model_read`."""
        return self._wait_for(self._take_announced)

    def model_read(self) -> None:
        with self._cond:
            self._loading = False
            self._cond.notify_all()

    def next_goal(self) -> Goal | None:
        """Wait for the goal to plan next (None: the node stops); it is planned until :meth:`goal_done`."""
        return self._wait_for(self._take_goal)

    def goal_done(self) -> None:
        with self._cond:
            self._planning, self._active = False, None

    def watch(self, run: ReachRun | None) -> Watch:
        """What the worker watches while the goal of ``run`` (None: a ``t42/goal`` goal) executes, from now."""
        with self._cond:
            return Watch(self, run, self._ends)

    def _take_announced(self) -> str | None:
        path, self._announced = self._announced, None
        self._loading = path is not None
        return path

    def _take_goal(self) -> Goal | None:
        """The goal waiting, now planned; none while an announced model is read (a goal after it is planned with it)."""
        if self._announced is not None or self._loading:
            return None
        goal, self._pending = self._pending, None
        if goal is not None:
            self._planning, self._active = True, goal.run
        return goal

    def _wait_for(self, take: Callable[[], T | None]) -> T | None:
        """Under the lock, wait until ``take()`` gives something (not None) or the node stops (None)."""
        with self._cond:
            while not self._stopping:
                taken = take()
                if taken is not None:
                    return taken
                self._cond.wait()
            return None


@dataclass(frozen=True)
class Stop:
    """Why an executing goal stops: the node stops, its action was cancelled, its episode ended (and no newer goal
    waits), or else a newer goal waits."""

    stopping: bool
    cancelled: bool
    episode_ended: bool


class Watch:
    """One executing goal's view of the :class:`Inbox`: whether it must stop, the pieces sent, and the hand state
    after each has run.  Only the worker uses it."""

    def __init__(self, inbox: Inbox, run: ReachRun | None, ends_before: int) -> None:
        self._inbox, self._cond, self.run = inbox, inbox._cond, run
        self._ends_before = ends_before
        self._done_before, self._steps = 0, 0
        """trajectory_done statuses before the piece sent last, and its steps."""

    def send(self, steps: int, publish: Callable[[], int], stopped: Callable[[Stop], None] | None = None) -> int | Stop:
        """``publish()`` a piece of ``steps`` and give its stamp (what ``publish`` returns), or why the goal stops
        instead, after ``stopped(why)``; both under the lock, so that a cancel's stop is never overtaken by a piece,
        and a goal's last word comes before a newer goal's."""
        with self._cond:
            stop = self._stop()
            if stop is not None:
                if stopped is not None:
                    stopped(stop)
                return stop
            self._done_before, self._steps = self._inbox._dones, steps
            return publish()

    def after_piece(self, timeout_s: float, max_age_ns: int) -> HandState | None:
        """The hand state after the piece sent last has run (None: stopping, a newer goal, a cancel, the episode's
        end, or a timeout: the piece's own length at 10 Hz, then ``timeout_s``)."""
        inbox = self._inbox
        deadline = time.monotonic() + self._steps * CONTROL_PERIOD_NS / 1e9 + timeout_s
        with self._cond:
            while self._stop() is None and inbox._dones <= self._done_before and time.monotonic() < deadline:
                self._cond.wait(timeout=0.05)
            if self._stop() is not None:
                return None
            if inbox._dones <= self._done_before:
                inbox._warn(f"a {self._steps}-step piece did not finish within its time and "
                            f"{timeout_s} s more; the hand is stopped")
                return None
            last = inbox._done_stamps[-1]
        after = last + 1  # the next state published after the piece's last step: where its last action led
        while time.monotonic() < deadline:
            with self._cond:
                if self._stop() is not None:
                    return None
                pose, joints = inbox._pose, inbox._joints
            if pose is not None and joints is not None and min(pose[0], joints[0]) >= after:
                try:
                    return hand_state(pose, joints, inbox._now_ns(), max_age_ns)
                except Refused as refused:
                    inbox._warn(f"closed loop ends: {refused.reason}")
                    return None
            with self._cond:
                self._cond.wait(timeout=0.005)
        inbox._warn("no hand state after the piece in time; closed loop ends")
        return None

    def end(self, stop_hand: Callable[[], None] | None) -> tuple[list[str], bool]:
        """The goal ends: (the episode ends since it started, whether a newer goal waits); ``stop_hand()``, given
        when it ends without its final state, runs under the lock unless it was cancelled (the cancel stopped the
        hand)."""
        inbox = self._inbox
        with self._cond:
            new_ends = min(inbox._ends - self._ends_before, len(inbox._episode_ends))
            ends = inbox._episode_ends[len(inbox._episode_ends) - new_ends:]
            pending = inbox._pending is not None
            if stop_hand is not None and not (self.run is not None and self.run.cancelled):
                stop_hand()
        return ends, pending

    def _stop(self) -> Stop | None:
        """Why the goal must stop now, if it must (the lock held)."""
        inbox, run = self._inbox, self.run
        cancelled = run is not None and run.cancelled
        ended = inbox._ends > self._ends_before
        if not (inbox._stopping or inbox._pending is not None or cancelled or (run is not None and ended)):
            return None
        return Stop(inbox._stopping, cancelled, inbox._pending is None and ended)
