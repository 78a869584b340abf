"""``hand/status`` texts (std_msgs/String) <-> (event, detail, last step stamp).

A status is human-readable: the event word first (``reset``, ``dropped``,
``overload``, ``trajectory_done``...), then a detail, then optionally
``[last step <ns> ns]``, the stamp of the last step the driver published before
the event.  Topics are not ordered against each other, so a recorder that splits
episodes on statuses needs that stamp to split exactly between two steps.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from msg_adapters import names

STRING = "std_msgs/msg/String"
HAND_STATUS_TOPIC = "/" + names.HAND_STATUS
"""The status topic as a bag of a suite in the root namespace names it (a recorder writes it beside the steps)."""

LAST_STEP = re.compile(r"\[last step (\d+) ns\]")
"""How a status names the stamp of the last step before its event."""
GRASP_SEED = re.compile(r"\(seed (\d+)\)")
"""How a reset's detail names the seed of its grasp (a simulated hand's; a real hand has none)."""


def status_message(event: str, detail: str = "", last_step_ns: int | None = None) -> str:
    """Text of a ``hand/status`` message: the event word first (``dropped``, ``overload``, ``reset``...).

    ``last_step_ns`` is the stamp of the last step published before the event: a recorder
    splits episodes exactly there, whenever the status reaches it relative to the steps.
    """
    text = f"{event}: {detail}" if detail else event
    return text if last_step_ns is None else f"{text} [last step {last_step_ns} ns]"


def last_step_stamp(status: str) -> int | None:
    """The last-step stamp a status names, if any (one no header stamp can hold names none: a damaged text)."""
    match = LAST_STEP.search(status)
    if match is None or len(match.group(1)) > 19:  # (int() of thousands of digits is refused, and slow)
        return None
    stamp = int(match.group(1))
    return stamp if stamp < 2**63 else None


def status_event(status: str) -> str:
    """The event word of a status (``"dropped: episode 3 ended"`` -> ``"dropped"``)."""
    words = status.split()
    return words[0].rstrip(":") if words else ""


def grasp_detail(episode: int, seed: int | None) -> str:
    """A reset's detail (its answer and its ``reset`` status): the episode begun and the grasp's seed, if any."""
    return f"episode {episode} grasped" + ("" if seed is None else f" (seed {seed})")


def grasping_detail(episode: int) -> str:
    """A ``grasping`` status's detail: the episode a reset begins (the hand opens, the object is placed anew)."""
    return f"episode {episode}: the hand opens, then closes on the object"


def grasp_seed(text: str) -> int | None:
    """The grasp seed a reset's answer or status names (:func:`grasp_detail`); None when it names none."""
    match = GRASP_SEED.search(text)
    return None if match is None else int(match.group(1))


def event_stamps(statuses: Iterable[str], event: str) -> set[int]:
    """The last-step stamps the statuses of one event name (``event: ... [last step <ns> ns]``)."""
    found = set()
    for text in statuses:
        stamp = last_step_stamp(text)
        if status_event(text) == event and stamp is not None:
            found.add(stamp)
    return found


def late_step_stamps(statuses: Iterable[str]) -> set[int]:
    """Stamps of the steps the driver said were late: each followed the step before it with none missing in
    between, so a reader keeps it in its episode."""
    return event_stamps(statuses, names.LATE)
