"""When the recorder's bag changes happen (:mod:`t42_transfer.nodes.recorder` is the node and carries them out): each
change requested (start, stop, split, an episode's split, a snapshot) waits for the step in progress, and for every
change requested before it, so that bags change between whole steps and in the order asked.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Change:
    """A bag change waiting for the steps up to ``after`` (a stamp) to be written."""

    kind: str
    """``start``, ``stop``, ``split``, ``episode`` (a split only if the bag holds messages) or ``snapshot``."""
    after: int | None
    why: str = ""
    word: str = ""
    """An episode split's ``hand/status`` word (the closed bag's reason)."""


class BagChanges:
    """The bag changes waiting, in the order requested, and whether a bag is open once they are carried out."""

    def __init__(self) -> None:
        self._waiting: deque[Change] = deque()
        self.will_record = False
        """Whether a bag is open once every waiting change is carried out."""

    def __len__(self) -> int:
        return len(self._waiting)

    def add(self, change: Change) -> Change:
        """Queue ``change``; the change as queued: never due before one requested earlier (its ``after`` is at
        least theirs; None, the step in progress unknown, takes theirs)."""
        if self._waiting and (last := self._waiting[-1].after) is not None:
            change = replace(change, after=last if change.after is None else max(change.after, last))
        self._waiting.append(change)
        if change.kind == "start":
            self.will_record = True
        elif change.kind == "stop":
            self.will_record = False
        return change

    def due(self, next_stamp: int | None) -> Iterator[Change]:
        """Take out, in order, the changes due before the step stamped ``next_stamp`` (None: every change)."""
        while self._waiting:
            after = self._waiting[0].after
            if next_stamp is not None and after is not None and after >= next_stamp:
                return
            yield self._waiting.popleft()

    def waiting(self, kind: str) -> list[int | None]:
        """The borders (``after``) of the waiting changes of ``kind``."""
        return [change.after for change in self._waiting if change.kind == kind]

    def shutting_down(self) -> None:
        """Forget the waiting changes that would open a bag (start, split, an episode's split): shutting down, it
        would close empty."""
        self._waiting = deque(change for change in self._waiting if change.kind in ("stop", "snapshot"))
