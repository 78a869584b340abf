"""The recorder's snapshot mode (``snapshot_s`` > 0), after rosbag2's (``ros2 bag record --snapshot-mode`` and its
``~/snapshot`` service): the last ``snapshot_s`` seconds are kept in memory and written as a bag on a trigger.

* What is kept: the whole steps the recorder releases (stamped within ``snapshot_s`` of the newest, whether a bag
  is open or not) and the statuses and events of that time, at most ``snapshot_max_mb`` in all; older ones are
  forgotten (:class:`~t42_transfer.data.bag.snapshot.SnapshotBuffer`).  Paused, nothing is kept.
* Triggers: ``~/snapshot`` (std_srvs/Trigger; rosbag2's has its own type, no request fields and a ``success``), and
  a ``hand/status`` whose first word is in ``snapshot_on`` (default the episode borders: ``reset``, ``dropped``,
  ``lost_contact``, ``overload``, ``fault``), once per border (the ``reset`` after a ``dropped`` names the same
  last step: one bag).  As a split, a snapshot is taken after the step in progress (a status: after the step it
  names) is complete, so a dropped episode's final state is in it.
* The bag: ``out_dir/snapshots/snapshot_NNN`` (``<prefix>_snapshot_NNN`` with a ``prefix``), written as the
  continuous bags (MCAP, whole steps, beginning with a whole state, statuses and events beside them), readable by
  ``read_bag``; not in ``out_dir`` itself, where a transfer would read its steps a second time.  Announced on
  ``recorder/bag_closed`` with reason ``snapshot``.  The continuous recording (``start_immediately``, the
  services) goes on beside it; ``start_immediately:=false`` records only snapshots, as rosbag2's mode.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

from msg_adapters import names
from msg_adapters.events import SNAPSHOT, BagClosedEvent
from t42_transfer.data.bag.snapshot import SnapshotBuffer, wants_snapshot, write_snapshot
from t42_transfer.data.bag.steps import Step
from t42_transfer.nodes.recorder_params import SNAPSHOT_DIR, Announcer, RecorderParams, next_bag_path


class Snapshots:
    """The snapshot buffer of a recorder and the bags written from it (see the module docstring)."""

    def __init__(self, params: RecorderParams, out_dir: Path, types: Mapping[str, str], state_topics: Collection[str],
                 announcer: Announcer, log: Any, offered: Mapping[str, names.Qos] | None = None,
                 custom: Mapping[str, str] | None = None) -> None:
        self.dir = out_dir / SNAPSHOT_DIR
        self._offered, self._custom = dict(offered or {}), dict(custom or {})
        self._types, self._state_topics = dict(types), set(state_topics)
        self._announcer, self._log = announcer, log
        self.buffer: SnapshotBuffer | None = None
        """None: snapshot mode is off."""
        self.bags: list[Path] = []
        """Every snapshot bag written, in order."""
        self._params = params
        self.configure(params)

    def configure(self, params: RecorderParams) -> None:
        """Take (changed) parameters: ``snapshot_s`` 0 forgets what is kept, a new window or cap applies at once."""
        self._params = params
        max_bytes = max(1, round(params.snapshot_max_mb * 1e6))
        if params.snapshot_s <= 0:
            self.buffer = None
        elif self.buffer is None:
            self.buffer = SnapshotBuffer(params.snapshot_s, max_bytes)
        else:
            self.buffer.resize(params.snapshot_s, max_bytes)

    @property
    def prefix(self) -> str:
        return SNAPSHOT if self._params.prefix is None else f"{self._params.prefix}_{SNAPSHOT}"

    def add_step(self, step: Step) -> None:
        if self.buffer is not None:
            self.buffer.add_step(step)

    def add_loose(self, topic: str, log_ns: int, data: bytes, msgtype: str) -> None:
        if self.buffer is not None:
            self.buffer.add_loose(topic, log_ns, data, msgtype)

    def due(self, word: str, after: int | None, waiting: Collection[int | None]) -> bool:
        """Whether a status with first word ``word`` naming the border ``after`` writes a snapshot."""
        return self.buffer is not None and wants_snapshot(word, after, self._params.snapshot_on, waiting,
                                                          self.buffer.covered)

    def take(self, until: int | None, word: str = "") -> tuple[bool, str]:
        """Write the steps kept, stamped up to ``until``, as a bag and announce it; ``word``: the status that asked
        (nothing is written when no step came since the last snapshot), "" for ``~/snapshot``.  (success, what
        happened)."""
        buffer = self.buffer
        if buffer is None:
            return False, "snapshot mode is off (snapshot_s is 0): set snapshot_s to keep the last seconds"
        held = [s.stamp for s in buffer.steps if until is None or s.stamp <= until]
        if word and held and buffer.covered is not None and held[-1] <= buffer.covered:
            return True, f"status {word!r}: no step since the last snapshot"
        snap = buffer.snapshot(self._state_topics, until)
        if not snap.steps:
            return False, f"nothing to write: no whole step in the last {buffer.window_s:g} s"
        path = self.dir
        try:
            self.dir.mkdir(exist_ok=True)
            path = next_bag_path(self.dir, self.prefix)
            count, first, last = write_snapshot(path, self._types, snap, self._offered, self._custom)
        except Exception as err:  # a full disk, a removed directory: say so, keep recording
            self._log.error(f"could not write the snapshot {path}: {err!r}")
            return False, f"could not write the snapshot {path}: {type(err).__name__}: {err}"
        self.bags.append(path)
        self._announcer.put(BagClosedEvent(str(path), 0, count, first, last, SNAPSHOT))
        why = f" (status {word!r})" if word else ""
        message = (f"wrote {path}{why}: {len(snap.steps)} steps stamped {snap.steps[0].stamp} to "
                   f"{snap.steps[-1].stamp} ns, {count} messages")
        self._log.info(message)
        return True, message
