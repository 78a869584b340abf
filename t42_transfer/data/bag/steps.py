"""Messages grouped into control steps by header stamp, released whole and in stamp order: what a recorder writes.

Each topic has its own queue, so the messages of a step arrive in any order and interleaved with the next
step's; writing them as they come could begin a bag with an action whose state is in the bag before.  A step
is complete once every recorded topic has delivered its message for the stamp or a later one (one publisher
per topic delivers in order); a step still incomplete ``hold_s`` after its first message is released as it is
once no message has come for ``hold_s / 2``, if it holds every ``required`` topic (an episode's final state
lacks only its action), and after ``HOLD_CAP * hold_s`` in any case.  A step missing a required message is
not released on silence alone: a publisher stalled in the middle of a step (a loaded machine) is silent too, and
the rest of the step comes when it runs again; a message that is truly lost is proved so by its topic's next
stamp.  Steady times are passed in, so the buffer is deterministic in tests; it needs no ROS.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, field

HOLD_CAP = 4
"""A step waits at most this many ``step_hold_s`` for the rest of its messages, however busy the topics are."""
CLOCK_RESTART_NS = 1_000_000_000
"""A stamp this much older than the newest written step means the publisher's clock restarted."""


@dataclass
class Step:
    """The messages of one header stamp: ``(topic, log_ns, cdr)`` in arrival order."""

    stamp: int
    first_seen_s: float
    """Steady time of its first message."""
    messages: list[tuple[str, int, bytes]] = field(default_factory=list)

    @property
    def topics(self) -> set[str]:
        return {topic for topic, _, _ in self.messages}


class StepBuffer:
    """Groups messages by header stamp and releases whole steps in stamp order (see the module docstring).

    ``topics`` are the recorded topics; a step is complete once each of them
    delivered its message for the stamp or a later one.  Steady times are passed
    in, so the buffer is deterministic in tests.
    """

    def __init__(self, topics: Iterable[str], hold_s: float, min_age_s: float = 0.0,
                 required: Iterable[str] = ()) -> None:
        self.topics = tuple(topics)
        self.required = frozenset(required)
        """Topics a step must hold to be released on silence (the state's); see the module docstring."""
        self.hold_s = hold_s
        self.min_age_s = min_age_s
        """A complete step still waits this long (steady time) after its first message: room for a status
        that splits the recording before it to arrive (topics are not ordered against each other)."""
        self._latest: dict[str, int] = {}
        """Newest stamp delivered per topic."""
        self._pending: dict[int, Step] = {}
        self._last_add_s = -math.inf
        """Steady time of the latest message."""
        self.released_stamp: int | None = None
        """Stamp of the newest step released."""
        self.restarts = 0
        """Times the stamps restarted (:meth:`add`): a caller that sees it grow keeps the steps apart."""

    @property
    def latest_stamp(self) -> int | None:
        """The newest stamp received on any topic (released or not)."""
        return max(self._latest.values(), default=None)

    @property
    def oldest_pending(self) -> int | None:
        return min(self._pending, default=None)

    def add(self, topic: str, stamp: int, log_ns: int, data: bytes, now_s: float) -> tuple[list[Step], bool]:
        """File one message; (the steps now released in stamp order, whether the message came too late or is a
        duplicate: a second message on a topic for a step not yet released is not filed, the first one stands).

        A stamp over ``CLOCK_RESTART_NS`` older than the newest step released means the publisher's clock restarted
        (a respawned sim-time driver): the steps waiting are released first, then the step of this message if it
        is complete already, and :attr:`restarts` counts one more."""
        released: list[Step] = []
        if self.released_stamp is not None and stamp <= self.released_stamp:
            if stamp > self.released_stamp - CLOCK_RESTART_NS:
                return [], True
            released = self.drain()  # the publisher's clock restarted: what waits is all there will be
            self._latest.clear()
            self.released_stamp = None
            self.restarts += 1
        step = self._pending.get(stamp)
        if step is not None and topic in step.topics:
            return released, True
        if step is None:
            step = self._pending[stamp] = Step(stamp, now_s)
        step.messages.append((topic, log_ns, data))
        self._latest[topic] = max(stamp, self._latest.get(topic, stamp))
        self._last_add_s = now_s
        return released + self.release(now_s), False

    def _complete(self, step: Step, now_s: float) -> bool:
        age = now_s - step.first_seen_s
        if age >= HOLD_CAP * self.hold_s:
            return True
        if age >= self.hold_s and now_s - self._last_add_s >= self.hold_s / 2 and self.required <= step.topics:
            return True
        if age < self.min_age_s:
            return False
        have = step.topics
        return all(t in have or self._latest.get(t, step.stamp) > step.stamp for t in self.topics)

    def release(self, now_s: float) -> list[Step]:
        """Steps that are complete (or held long enough), oldest first, up to the first that is not."""
        out = []
        while self._pending:
            oldest = min(self._pending)
            if not self._complete(self._pending[oldest], now_s):
                break
            out.append(self._pending.pop(oldest))
            self.released_stamp = oldest
        return out

    def drain(self) -> list[Step]:
        """Every waiting step, oldest first (the recording ends)."""
        out = [self._pending.pop(stamp) for stamp in sorted(self._pending)]
        if out:
            self.released_stamp = out[-1].stamp
        return out


class WrittenSteps:
    """The topics of the last ``size`` steps written and the bag each went into: whether a message that comes after
    its step was written may still join it there (the bag still open, the topic not yet in the step)."""

    def __init__(self, size: int = 1000) -> None:
        self.size = size
        self._steps: OrderedDict[int, tuple[object, set[str]]] = OrderedDict()

    def add(self, step: Step, bag: object) -> None:
        self._steps[step.stamp] = (bag, step.topics)
        if len(self._steps) > self.size:
            self._steps.popitem(last=False)

    def join(self, stamp: int, topic: str, open_bag: object) -> bool:
        """Whether the message on ``topic`` stamped ``stamp`` may go into ``open_bag`` now; counts it in if so."""
        bag, topics = self._steps.get(stamp, (None, set()))
        if bag is None or bag is not open_bag or topic in topics:
            return False
        topics.add(topic)
        return True
