"""What a recorder keeps track of about the bag it writes, needing no ROS (:mod:`t42_transfer.nodes.recorder` is
the node): the next free bag name (another writer may take a name first), the log times of the steps after the
publishers' clock restarted, free space, and a pause's border.  (Whether the open bag's file is still there is
:meth:`BagWriter.lost`.)
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path

from msg_adapters import names
from t42_transfer.data.bag.hand_topics import HAND_ROLES, recorded_topics_custom
from t42_transfer.data.bag.steps import CLOCK_RESTART_NS
from t42_transfer.data.bag.writer import BagWriter

CLOCK_RESTART = "clock_restart"
"""The reason of a bag closed because the stamps restarted behind it (a respawned sim-time driver): its steps
and the next bag's would not read as one recording (a bag's stamps increase)."""
NAME_TRIES = 100
"""Bag names tried in a row before opening counts as a failure."""


def recorded_hand_topics(resolve: Callable[[str], str]) -> dict[str, str]:
    """Custom data writing down the name each hand topic is recorded under (``resolve`` applies the recorder's
    namespace and remapping), so that a bag of remapped topics reads as one of the usual names."""
    return recorded_topics_custom({role: resolve(role.lstrip("/")) for role in HAND_ROLES})


def open_next_bag(choose: Callable[[], Path], types: Mapping[str, str], offered: Mapping[str, names.Qos],
                  custom: Mapping[str, str], tries: int = NAME_TRIES) -> BagWriter:
    """A new bag at the path ``choose()`` gives.  A path another writer took first (it exists when the bag
    opens: a second recorder on the same ``out_dir``) is passed over for the next ``choose()`` gives, which counts
    on past it; whatever else fails is raised, as is the last of ``tries`` names taken."""
    for _ in range(tries - 1):
        path = choose()
        if os.path.lexists(path):  # taken since it was chosen (rosbags refuses a path that exists)
            continue
        try:
            return BagWriter(path, types, custom=custom, offered=offered)
        except Exception as err:
            if not _taken(err):
                raise
    return BagWriter(choose(), types, custom=custom, offered=offered)


def _taken(err: BaseException) -> bool:
    """Whether opening a bag failed because another writer made its directory after :func:`open_next_bag` found
    the path free: rosbags' mkdir raised FileExistsError, and rosbags (0.11) raises its WriterError from it (the
    error's context), whatever its words.  One made in the microseconds between that check and rosbags' own
    check is not told apart from any other failure to open."""
    return isinstance(err, FileExistsError) or isinstance(err.__context__, FileExistsError)


def room(out_dir: Path, free_mb: float) -> bool:
    """Whether the file system of ``out_dir`` (of its nearest existing parent, when it was removed: a bag would
    make it again) has ``free_mb`` MB free."""
    where = out_dir
    while not where.exists() and where.parent != where:
        where = where.parent
    try:
        return shutil.disk_usage(where).free >= free_mb * 1e6
    except OSError:
        return False


class LogTimes:
    """The log times a bag's step messages are written at: their receive times (the node's ROS time), but never
    going back on a topic, and, after the stamps restarted behind the steps written (:meth:`restart`), a message
    received on the old clock is logged at its stamp.

    A respawned sim-time driver's first steps can reach the recorder before its first ``/clock``: they are
    received at the old, later time, and a reader, which orders a topic by log time, would find their stamps
    after the next steps'.  Under the recorder's assumption that the driver stamps with its clock, such a message
    is one received over ``CLOCK_RESTART_NS`` after its stamp, at or after the time the restart was seen."""

    def __init__(self) -> None:
        self._last: dict[str, int] = {}
        self._old_clock_from: int | None = None

    def new_bag(self) -> None:
        self._last.clear()
        self._old_clock_from = None

    def restart(self, log_ns: int, stamp: int) -> None:
        """The step stamped ``stamp``, received at ``log_ns``, is the first after the stamps restarted."""
        self._last.clear()
        self._old_clock_from = log_ns if log_ns > stamp + CLOCK_RESTART_NS else None

    def __call__(self, topic: str, log_ns: int, stamp: int) -> int:
        """The log time to write the message on ``topic`` stamped ``stamp``, received at ``log_ns``, at."""
        old = self._old_clock_from
        if old is not None and log_ns >= old and log_ns > stamp + CLOCK_RESTART_NS:
            log_ns = stamp
        log_ns = max(log_ns, self._last.get(topic, log_ns))
        self._last[topic] = log_ns
        return log_ns


class Pause:
    """``~/pause`` and ``~/resume`` by stamp: pause drops the messages of the steps after the newest stamp received,
    resume records again from the first step after the newest stamp received then.  The node holds the lock."""

    def __init__(self) -> None:
        self.latest_seen: int | None = None
        """The newest stamp received (paused or not): where a pause or a resume draws its border."""
        self.window: tuple[int, int | None] | None = None
        """Messages stamped after the first and up to the second (None: until resume) are dropped."""
        self.dropped = 0
        """Messages dropped while paused (recorded topics and statuses), in all."""
        self._from = 0

    @property
    def paused(self) -> bool:
        return self.window is not None and self.window[1] is None

    def drops(self, stamp: int) -> bool:
        """Note a message stamped ``stamp``; whether it is dropped (counted)."""
        if self.latest_seen is None or stamp > self.latest_seen:
            self.latest_seen = stamp
        window = self.window
        if window is not None and stamp > window[0] and (window[1] is None or stamp <= window[1]):
            self.dropped += 1
            return True
        return False

    def pause(self, bag: object) -> tuple[bool, str]:
        if self.window is not None and self.window[1] is None:
            return False, (f"already paused after the step stamped {self.window[0]} ns "
                           f"({self.dropped - self._from} messages dropped since)")
        after = -1 if self.latest_seen is None else self.latest_seen
        self.window, self._from = (after, None), self.dropped
        return True, f"paused after the step stamped {after} ns: messages are dropped, {bag} stays open"

    def resume(self, bag: object) -> tuple[bool, str]:
        if self.window is None or self.window[1] is not None:
            return False, "not paused"
        until = max(self.window[0], -1 if self.latest_seen is None else self.latest_seen)
        self.window = (self.window[0], until)
        return True, (f"resumed {bag}: {self.dropped - self._from} messages dropped while paused; recording from "
                      f"the first step after {until} ns")

    def restart(self, stamp: int) -> None:
        """The stamps restarted behind those received, at ``stamp``: the borders are drawn on the new clock (a
        pause goes on after ``stamp``; a past pause's window, on the old clock, is forgotten)."""
        self.latest_seen = stamp
        if self.window is not None:
            self.window = (stamp, None) if self.window[1] is None else None
