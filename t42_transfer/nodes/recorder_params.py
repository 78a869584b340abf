"""The recorder's parameters, bag names and bag events (:mod:`t42_transfer.nodes.recorder` is the node)."""

from __future__ import annotations

import math
import queue
import re
import threading
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msg_adapters import HAND_TOPICS, names
from msg_adapters.events import BagClosedEvent, bag_closed_msg
from msg_adapters.plan_result import PLAN_RESULT_MSG
from msg_adapters.transfer import MODEL_UPDATED_MSG
from t42_transfer.data.bag import read_bag
from t42_transfer.ros.params import param

STEP_TOPICS = {topic.lstrip("/"): msgtype for topic, msgtype in HAND_TOPICS.items()}
"""The hand topics, relative names: header-stamped, grouped into whole steps."""
EVENT_TOPICS = {names.PLAN_RESULT: PLAN_RESULT_MSG, names.MODEL_UPDATED: MODEL_UPDATED_MSG}
"""The suite's typed events (``t42_interfaces``), relative names: written as they come, as ``hand/status``."""
RECORDABLE = {**STEP_TOPICS, **EVENT_TOPICS}
"""Relative names the recorder knows the types of: the default of ``topics``."""


def latched_offers(resolve: Callable[[str], str], topics: Iterable[str]) -> dict[str, names.Qos]:
    """Resolved name -> publisher QoS of the latched topics a recorder of ``topics`` writes (``hand/status``
    always): what its bags offer for them (:data:`msg_adapters.names.OFFERED`)."""
    return {resolve(name): names.OFFERED[name] for name in (names.HAND_STATUS, *topics) if name in names.OFFERED}
SNAPSHOT_DIR = "snapshots"
"""Where snapshot bags go, under ``out_dir``: not among the continuous bags a transfer reads (their steps are
there already)."""

MODES = ("recording", "episode")


_PREFIX = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class RecorderParams:
    """The recorder's ROS parameters."""

    out_dir: Path = param(description="directory the bags are created in (made if missing); a relative one is "
                                      "taken under the node's namespace (recordings/left)", read_only=True)
    share_dirs: bool = param(False, "record into out_dir even when a suite under another namespace holds it "
                                    "(two suites sharing a directory on purpose)", read_only=True)
    mode: str = param("recording", "recording: bags change only on the services; "
                                   "episode: also split on hand/status events (one bag per episode)")
    prefix: str | None = param(None, "bag name prefix (unset: the mode, e.g. episode_000)")
    start_immediately: bool = param(True, "open the first bag at start (else wait for ~/start)", read_only=True)
    topics: tuple[str, ...] = param(tuple(RECORDABLE), "recorded topics, relative names (remap to rename): the "
                                    "hand's, written as whole steps (" + ", ".join(STEP_TOPICS) + "), and typed "
                                    "events, written as they come (" + ", ".join(EVENT_TOPICS) + "); hand/status "
                                    "is always recorded", read_only=True)
    split_on: tuple[str, ...] = param(names.SPLIT_EVENTS, "hand/status first words that split the bag in episode mode")
    flush_period_s: float = param(1.0, "the open chunk reaches the file this often: at most this much "
                                       "recording is lost when the process is killed", min=1e-3, max=3600.0)
    step_hold_s: float = param(0.5, "a step still missing a message this long after its first (steady time) "
                                    "is written as it is once nothing has come for half of it; a step missing "
                                    "part of its state waits up to 4x for it", min=1e-3, max=60.0)
    resume_free_mb: float = param(16.0, "after a write failed (a full disk), recording resumes by itself once "
                                        "out_dir's file system has this many MB free (or on ~/start)",
                                  min=0.0, max=1e6)
    snapshot_s: float = param(0.0, "snapshot mode: keep the whole steps of the last this many seconds (by stamp) "
                                   "in memory and write them as a bag in out_dir/snapshots on ~/snapshot or a "
                                   "snapshot_on status; 0: off", min=0.0, max=3600.0)
    snapshot_on: tuple[str, ...] = param(names.SPLIT_EVENTS, "hand/status first words that write a snapshot "
                                                           "(once per episode border); empty: only ~/snapshot")
    snapshot_max_mb: float = param(256.0, "the snapshot buffer holds at most this many MB of messages (the oldest "
                                          "steps go first)", min=0.001, max=1e5)
    queue_depth: int = param(1000, "KEEP_LAST depth of each recorded subscription: messages it holds while "
                                   "the node is busy", read_only=True, min=1, max=1_000_000)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not _PREFIX.match(self.bag_prefix):
            raise ValueError(f"prefix must be a plain file name part ([A-Za-z0-9_.-]), got {self.prefix!r}")
        if not self.topics:
            raise ValueError("topics must name at least one topic")
        unknown = [t for t in self.topics if t not in RECORDABLE]
        if unknown:
            raise ValueError(f"topics {unknown} are not recordable; topics are relative names among "
                             f"{', '.join(RECORDABLE)} (remap them to record other names)")
        if not any(t in STEP_TOPICS for t in self.topics):
            raise ValueError(f"topics must name a hand topic ({', '.join(STEP_TOPICS)}): events are written only "
                             f"beside steps, got {list(self.topics)}")
        for name, value in (("snapshot_s", self.snapshot_s), ("snapshot_max_mb", self.snapshot_max_mb)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.snapshot_max_mb < 0.001:
            raise ValueError(f"snapshot_max_mb must be at least 0.001, got {self.snapshot_max_mb!r}")
        if len(set(self.topics)) != len(self.topics):
            raise ValueError(f"topics must not repeat, got {list(self.topics)}")
        for name, value in (("flush_period_s", self.flush_period_s), ("step_hold_s", self.step_hold_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not isinstance(self.queue_depth, int) or self.queue_depth < 1:
            raise ValueError(f"queue_depth must be an int >= 1, got {self.queue_depth!r}")

    @property
    def bag_prefix(self) -> str:
        return self.prefix if self.prefix is not None else self.mode


def next_bag_path(out_dir: str | Path, prefix: str) -> Path:
    """``out_dir/<prefix>_<NNN>`` with ``NNN`` one past the highest index there (000 when none)."""
    pattern = re.compile(rf"^{re.escape(prefix)}_(\d{{3,}})$")
    directory = Path(out_dir)
    taken = [int(m.group(1)) for p in directory.iterdir() if (m := pattern.match(p.name))] \
        if directory.is_dir() else []
    return directory / f"{prefix}_{max(taken, default=-1) + 1:03d}"


class Announcer:
    """Publishes ``recorder/bag_closed`` for each bag put, in order, from its own thread: it first reads the bag's
    episodes with read_bag (off the executor: a long bag takes seconds), so a bag is final and readable when its
    event arrives."""

    def __init__(self, publisher: Any, log: Any) -> None:
        self._publisher, self._log = publisher, log
        self._queue: queue.SimpleQueue[BagClosedEvent | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="bag_closed", daemon=True)
        self._thread.start()

    def put(self, event: BagClosedEvent) -> None:
        self._queue.put(event)

    def close(self, timeout_s: float = 30.0) -> None:
        """Announce the bags put so far, then end."""
        self._queue.put(None)
        self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        while (event := self._queue.get()) is not None:
            said: list[warnings.WarningMessage] = []
            try:
                with warnings.catch_warnings(record=True) as said:  # on /rosout, not as a warning of the process
                    warnings.simplefilter("always")
                    episodes = len(read_bag(event.path)) if event.messages else 0
            except Exception as err:  # a bag of no whole episode: announced with 0
                self._log.warning(f"{event.path} holds no episode read_bag reads ({type(err).__name__}: {err})")
                episodes = 0
            finally:
                for warning in said:  # (a short last episode, a step that lost a message: the reader's view)
                    self._log.info(f"read back: {warning.message}")
            try:
                self._publisher.publish(bag_closed_msg(event._replace(episodes=episodes)))
            except Exception as err:  # the node is being destroyed
                self._log.error(f"could not announce {event.path} on {names.BAG_CLOSED}: {err!r}")

