"""Snapshot mode: the last S seconds of whole steps kept in memory and written as a bag on a trigger.

As rosbag2's snapshot mode (``ros2 bag record --snapshot-mode``, its ``~/snapshot`` service), a recorder keeps
what it received in a ring buffer instead of (here: beside) writing it, and writes the buffer as a new bag when
asked.  :class:`SnapshotBuffer` holds the steps released by :class:`~t42_transfer.data.bag.steps.StepBuffer`
(whole steps, in stamp order) and the messages written as they come (``hand/status``, events), and forgets what
is older than the window:

* steps: those stamped within ``window_s`` of the newest step, the half-open window ``(newest - S, newest]``
  (S / period steps at a steady rate);
* loose messages: those logged within ``window_s`` of the newest log time held;
* at most ``max_bytes`` of message payloads in all: beyond it the oldest go first, so memory is bounded however
  fast the topics are.

:meth:`SnapshotBuffer.snapshot` gives the steps from the first one holding the whole state (a bag never begins
with an action alone, as the recorder's bags), with the loose messages logged from that step on, and
:func:`write_snapshot` writes them as the recorder writes a bag.  :func:`wants_snapshot` is the rule for
automatic snapshots on ``hand/status`` words: one per border, so the ``reset`` that follows a ``dropped`` (naming
the same last step) makes no second bag.  Needs no ROS; times are passed in.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from msg_adapters import names
from msg_adapters.events import SNAPSHOT
from t42_transfer.data.bag.steps import Step
from t42_transfer.data.bag.writer import BagWriter

__all__ = ["SNAPSHOT", "Loose", "Snapshot", "SnapshotBuffer", "wants_snapshot", "write_snapshot"]


@dataclass(frozen=True)
class Loose:
    """A message written as it came, not part of a step (a status, an event)."""

    topic: str
    log_ns: int
    data: bytes
    msgtype: str


@dataclass
class Snapshot:
    """What a snapshot bag holds: whole steps in stamp order and loose messages in log-time order."""

    steps: list[Step] = field(default_factory=list)
    loose: list[Loose] = field(default_factory=list)

    @property
    def messages(self) -> int:
        return sum(len(s.messages) for s in self.steps) + len(self.loose)


def _step_bytes(step: Step) -> int:
    return sum(len(data) for _, _, data in step.messages)


def _first_log(step: Step) -> int:
    return min(log_ns for _, log_ns, _ in step.messages)


class SnapshotBuffer:
    """The last ``window_s`` of steps and loose messages, at most ``max_bytes`` of payload (module docstring)."""

    def __init__(self, window_s: float, max_bytes: int) -> None:
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s must be a positive finite number, got {window_s!r}")
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be at least 1, got {max_bytes!r}")
        self.window_s, self.max_bytes = window_s, max_bytes
        self._steps: deque[Step] = deque()
        self._loose: deque[Loose] = deque()
        self.bytes = 0
        """Payload bytes held."""
        self.forgotten_steps = 0
        """Steps dropped for being out of the window or over ``max_bytes``."""
        self.covered: int | None = None
        """The newest step stamp of the last snapshot taken (None: none yet)."""

    @property
    def window_ns(self) -> int:
        return round(self.window_s * 1e9)

    @property
    def steps(self) -> list[Step]:
        return list(self._steps)

    @property
    def loose(self) -> list[Loose]:
        return list(self._loose)

    def add_step(self, step: Step) -> None:
        """A released step (stamp order); an older stamp than the newest held means the clock restarted: the
        buffer starts over."""
        if self._steps and step.stamp <= self._steps[-1].stamp:
            self.forgotten_steps += len(self._steps)
            self.clear()
        self._steps.append(step)
        self.bytes += _step_bytes(step)
        self._forget()

    def add_loose(self, topic: str, log_ns: int, data: bytes, msgtype: str) -> None:
        self._loose.append(Loose(topic, log_ns, bytes(data), msgtype))
        self.bytes += len(data)
        self._forget()

    def resize(self, window_s: float, max_bytes: int) -> None:
        """A new window or cap (a parameter changed at run time); what no longer fits goes at once."""
        probe = SnapshotBuffer(window_s, max_bytes)  # checks the values
        self.window_s, self.max_bytes = probe.window_s, probe.max_bytes
        self._forget()

    def clear(self) -> None:
        self._steps.clear()
        self._loose.clear()
        self.bytes = 0

    def _forget(self) -> None:
        if self._steps:
            oldest_kept = self._steps[-1].stamp - self.window_ns  # exclusive
            while self._steps and self._steps[0].stamp <= oldest_kept:
                self._drop_step()
        if self._loose:
            newest = max(self._loose[-1].log_ns, _first_log(self._steps[-1])) if self._steps else self._loose[-1].log_ns
            while self._loose and self._loose[0].log_ns <= newest - self.window_ns:
                self._drop_loose()
        while self.bytes > self.max_bytes and (self._steps or self._loose):
            step_first = _first_log(self._steps[0]) if self._steps else None
            if step_first is not None and (not self._loose or step_first <= self._loose[0].log_ns):
                self._drop_step()
            else:
                self._drop_loose()

    def _drop_step(self) -> None:
        step = self._steps.popleft()
        self.bytes -= _step_bytes(step)
        self.forgotten_steps += 1

    def _drop_loose(self) -> None:
        self.bytes -= len(self._loose.popleft().data)

    def snapshot(self, state_topics: Collection[str], until: int | None = None) -> Snapshot:
        """The steps held (stamped up to ``until``), from the first that holds every ``state_topics``, and the loose
        messages logged from that step's first message on (none without a step); marks them covered."""
        steps = [s for s in self._steps if until is None or s.stamp <= until]
        while steps and not set(state_topics) <= steps[0].topics:
            steps.pop(0)
        if not steps:
            return Snapshot()
        self.covered = steps[-1].stamp
        begin = _first_log(steps[0])
        return Snapshot(steps, [m for m in self._loose if m.log_ns >= begin])


def wants_snapshot(word: str, after: int | None, snapshot_on: Iterable[str], waiting: Collection[int | None],
                   covered: int | None) -> bool:
    """Whether a ``hand/status`` whose first word is ``word`` and whose border is the step stamped ``after`` (None: the
    driver named none) triggers a snapshot: its word is in ``snapshot_on``, and its border is neither that of a
    snapshot ``waiting`` to be taken nor within the last one taken (``covered``)."""
    if word not in tuple(snapshot_on):
        return False
    if after is None:
        return not waiting  # a driver that names no border: no second snapshot while one waits
    return after not in waiting and (covered is None or after > covered)


def write_snapshot(path: Path, types: Mapping[str, str], snapshot: Snapshot,
                   offered: Mapping[str, names.Qos] | None = None,
                   custom: Mapping[str, str] | None = None) -> tuple[int, int, int]:
    """Write ``snapshot`` as a new bag at ``path`` (steps in stamp order, each loose message before the first step
    logged after it), declaring the step topics ``types``; (messages, first log time, last log time).  A failure
    leaves what was written readable (aborted, as a killed recorder's bag) and raises."""
    loose = deque(snapshot.loose)
    first, last = math.inf, -math.inf
    with BagWriter(path, types, custom=custom, offered=offered) as bag:
        def write(topic: str, log_ns: int, data: bytes, msgtype: str | None = None) -> None:
            nonlocal first, last
            bag.write(topic, log_ns, data, msgtype)
            first, last = min(first, log_ns), max(last, log_ns)

        for step in snapshot.steps:
            begin = _first_log(step)
            while loose and loose[0].log_ns < begin:
                m = loose.popleft()
                write(m.topic, m.log_ns, m.data, m.msgtype)
            for topic, log_ns, data in step.messages:
                write(topic, log_ns, data)
        for m in loose:
            write(m.topic, m.log_ns, m.data, m.msgtype)
        count = bag.count
    return (count, int(first), int(last)) if count else (0, 0, 0)
