"""The newest object pose from a tracker, and whether it may go out as a step's: one rule for every driver.

A driver that takes the object's pose from a tracker (the Dynamixel driver always; the mock driver with
``pose_source: topic``) publishes, at each step, the newest pose it received, stamped with the step.  A pose
older than the driver's limit is never published as current: that step goes out without a pose, and the
driver says ``stale`` once per stale stretch (a recorder's step then lacks its pose, so the bag reader leaves
it out and splits the episode there, saying so).  Nothing here needs ROS.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msg_adapters import object_xy_mm, stamp_to_ns
from t42_transfer.conventions import CONTROL_PERIOD_NS, MAX_OBJECT_DISTANCE_MM


class NewestPose:
    """The newest tracked object position (mm, ``t42_base``) with its stamp, and the stale-stretch state.

    A pose stamped more than the age limit after the step is not the step's either: its stamp is on another
    clock (a tracker on wall time beside a driver on sim time)."""

    def __init__(self) -> None:
        self._pose: tuple[int, np.ndarray] | None = None
        self._not_before_ns = 0
        self.stale = False
        """Whether the last step asked went out without a pose."""

    def receive(self, stamp_ns: int, xy_mm: np.ndarray) -> bool:
        """Keep a pose from the tracker (its stamp is the image's, or the arrival time when it had none); False,
        not kept, when it is of a frame before a :meth:`forget`'s bound (the old grasp's, tracked late)."""
        if stamp_ns < self._not_before_ns:
            return False
        self._pose = (stamp_ns, np.asarray(xy_mm, dtype=np.float64))
        return True

    def receive_msg(self, msg: Any) -> str | None:
        """Take a ``PoseStamped`` from the tracker; the reason it was refused (None: taken).  A pose in another
        frame, with a non-finite value, farther from the palm than any held object, or with an unset stamp is
        refused: none of them can be a step's pose.  One of a frame before the new grasp is taken and left out
        (:meth:`receive`): the tracker was late, not wrong."""
        try:
            xy = object_xy_mm(msg)
        except ValueError as err:
            return str(err)
        distance_mm = float(np.hypot(*xy))
        if distance_mm > MAX_OBJECT_DISTANCE_MM:
            return (f"the object at {distance_mm / 1000:.3g} m from t42_base cannot be in the hand (at most "
                    f"{MAX_OBJECT_DISTANCE_MM / 1000:g} m)")
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp <= 0:
            return "its header stamp is unset (0)"
        self.receive(stamp, xy)  # one of the old grasp's frames is no fault of the tracker's: left out quietly
        return None

    @property
    def stamp_ns(self) -> int | None:
        """The stamp of the pose held (None: none)."""
        return None if self._pose is None else self._pose[0]

    def forget(self, before_ns: int = 0) -> None:
        """Drop the pose held: the object was moved where the tracker has not seen it yet (a new grasp).  Poses
        stamped before ``before_ns`` (the new grasp's first frame) are refused from now on: a tracker still
        working through the old grasp's frames sends them after the grasp."""
        self._pose = None
        self._not_before_ns = max(self._not_before_ns, before_ns)  # (a forget without a bound keeps the grasp's)
        self.stale = False  # a stale stretch of the old grasp is over: the new one's is said again

    def for_step(self, stamp_ns: int, max_age_s: float) -> tuple[np.ndarray | None, str | None]:
        """The position to publish with the step stamped ``stamp_ns`` (None: stale), and the reason when this
        step starts a stale stretch (None otherwise: say ``stale`` once per stretch)."""
        pose = self._pose
        age_s = None if pose is None else (stamp_ns - pose[0]) / 1e9
        if pose is None or age_s is None or abs(age_s) > max_age_s:  # a future stamp: another clock's pose
            starts = not self.stale
            self.stale = True
            if not starts:
                return None, None
            if pose is None or age_s is None:
                return None, "no pose received"
            return None, f"the newest is {age_s:.2f} s old" if age_s > 0 else f"the newest is stamped " \
                                                                              f"{-age_s:.2f} s after the step"
        self.stale = False
        return pose[1], None


class DropWatch:
    """The paper's drop rule on the poses a driver publishes: an object that moved more than ``jump_mm`` a control
    period fell out of the grasp (the episode ends there).  The move is judged over the time between the two poses'
    own stamps (their frames'), not between the steps that carried them: a tracker slower than the steps, or a frame
    lost, gives one step the move of several periods.  A step without a pose (stale) leaves nothing to compare the
    next one with, so a drop hidden from the tracker ends the episode only if seen (the bag reader splits at the
    stale steps anyway)."""

    def __init__(self) -> None:
        self._last: tuple[int, np.ndarray] | None = None

    def start(self) -> None:
        """A new episode: its first pose is compared with nothing."""
        self._last = None

    def moved_mm(self, xy_mm: np.ndarray | None, stamp_ns: int, jump_mm: float) -> tuple[float, float] | None:
        """(the move in mm, over how many seconds) when the pose ``xy_mm`` stamped ``stamp_ns`` is a drop: farther
        from the step before's than ``jump_mm`` times the control periods between their stamps (at least one);
        None otherwise, and always with ``jump_mm`` 0 (no rule) or no pose now or at the step before."""
        last = self._last
        self._last = None if xy_mm is None else (stamp_ns, np.asarray(xy_mm, dtype=np.float64))
        if last is None or self._last is None or jump_mm <= 0:
            return None
        moved = float(np.hypot(*(self._last[1] - last[1])))
        periods = max((stamp_ns - last[0]) / CONTROL_PERIOD_NS, 1.0)
        return (moved, (stamp_ns - last[0]) / 1e9) if moved > jump_mm * periods else None
