"""The recorder's messages written as they come, not grouped into steps: ``hand/status`` (whose words also split
bags in episode mode and trigger snapshots), the typed events of ``topics`` (``t42/plan_result``,
``t42/model_updated``), and a step's message that came after the step was written.  A part of
:class:`~t42_transfer.nodes.recorder.Recorder` (a mixin: it uses the node's bag, lock, step buffer and
snapshots), kept apart to keep modules short; see that module's docstring.

A status goes only into a bag that holds a step, yet a bag's first step is written late: it waits for its step to
complete, and in episode mode half ``step_hold_s`` more for a status that would split before it.  A driver's
``late`` for the second step (a first step slow to follow, as at a driver's start) comes in that time, and a bag
without it reads as two episodes.  So a status naming a step (``[last step N ns]``) that comes while the bag holds
no step is held, and goes into the bag once its first step is written when it names that step or a later one."""

from __future__ import annotations

from collections import deque
from typing import Any

from msg_adapters import STRING, TYPESTORE, last_step_stamp, names, status_event


class LooseMessages:
    """``hand/status`` and the typed events, as the recorder handles them (see the module docstring)."""

    _buffer: Any
    _changes: Any
    _closed: bool
    _first_stamp: int | None
    _held: deque[tuple[str, int, bytes, str, int]]
    _lock: Any
    _status_topic: str
    dropped: int
    late_kept: int
    log: Any
    _pause: Any
    per_message: Any
    _series: Any
    snapshots: Any
    _written: Any

    def _on_status(self, data: bytes) -> None:
        try:
            try:
                text = str(TYPESTORE.deserialize_cdr(data, STRING).data)
            except Exception as err:
                self.per_message.warning(f"ignored a message on {names.HAND_STATUS}: "
                                         f"not a {STRING} ({type(err).__name__}: {err})")
                return
            if self.paused:  # neither written nor splitting
                self._pause.dropped += 1  # counted where the pause is kept
                return
            event, after = status_event(text), last_step_stamp(text)  # the driver says where the border is
            self._write_loose(self._status_topic, bytes(data), STRING, after)
            episode = self.params.mode == "episode" and event in self.params.split_on
            if not episode and self.snapshots.buffer is None:
                return
            with self._lock:
                if self._closed or (after is not None and (self._first_stamp is None or after < self._first_stamp)):
                    return  # a border before anything recorded (the history a late joiner hears)
                if self.snapshots.due(event, after, self._changes.waiting("snapshot")):
                    self._request("snapshot", self._border(event, after), f"status {event!r}", event)
                if not episode or not self._changes.will_record:
                    return
                waiting = self._changes.waiting("episode")
                # one split per episode border: a reset right after an end status names the same last step
                # (a driver that names none: no second split while one waits)
                if (after in waiting) if after is not None else waiting:
                    return
                self._request("episode", self._border(event, after), f"status {event!r}", event)
        except Exception as err:  # never raise from a callback
            self.log.error(f"could not handle a message on {names.HAND_STATUS}: {err!r}")

    def _border(self, event: str, after: int | None) -> int | None:
        """The last step before a status's border: the one it names, else the newest step heard (or, at an end,
        now: the final state may still be on its way, stamped before now)."""
        if after is not None:
            return after
        after = self._buffer.latest_stamp
        if event in names.END_EVENTS:
            now = self.get_clock().now().nanoseconds
            after = now if after is None else max(now, after)
        return after

    def _decoded(self, topic: str, msgtype: str, data: bytes) -> Any:
        """``data`` as a ``msgtype``; None, the message dropped with a warning, when it is none."""
        try:
            return TYPESTORE.deserialize_cdr(data, msgtype)
        except Exception as err:  # the decoder raises whatever it trips over
            self.dropped += 1
            self.per_message.warning(f"dropped a message on {topic}: its {len(data)} bytes are not a {msgtype} "
                                     f"({type(err).__name__}: {err})")
            return None

    def _on_event(self, topic: str, msgtype: str, data: bytes) -> None:
        """A typed event (``t42/plan_result``...): written as it comes, as a status."""
        try:
            if self._decoded(topic, msgtype, data) is None:
                return
            if self.paused:
                self._pause.dropped += 1  # counted where the pause is kept
                return
            self._write_loose(topic, bytes(data), msgtype)
        except Exception as err:  # never raise from a callback
            self.dropped += 1
            self.log.error(f"could not record a message on {topic}: {err!r}")

    def _write_loose(self, topic: str, data: bytes, msgtype: str, step: int | None = None) -> None:
        """A status or an event goes into the open bag as it came (a reader learns from a status which steps were
        late, not lost), and into the snapshot buffer.

        Only into a bag that holds steps: a status has no step to qualify before the first one, and a bag of
        statuses alone would count as holding messages (episode mode splits only those).  One that names its
        ``step`` is held until the bag's first step is written (the module docstring)."""
        with self._lock:
            if self._closed:
                return
            log_ns = self.get_clock().now().nanoseconds
            self.snapshots.add_loose(topic, log_ns, data, msgtype)
            bag = self._series.bag
            if bag is None or bag.count == 0:
                if step is not None:
                    self._held.append((topic, log_ns, data, msgtype, step))
                return
            try:
                self._series.write(topic, log_ns, data, msgtype)
            except OSError as err:  # a full disk: stop writing, say so once
                self._series.failed(bag.path, err)

    def _write_held(self, first_stamp: int) -> None:
        """After the open bag's first step, stamped ``first_stamp``: the statuses held meanwhile that name it or a
        later step go in at their receive times (raises what the bag raises); the rest were of earlier steps."""
        held = [m for m in self._held if m[4] >= first_stamp]
        self._held.clear()
        for topic, log_ns, data, msgtype, _ in held:
            self._series.write(topic, log_ns, data, msgtype)

    def _write_late(self, topic: str, stamp: int, log_ns: int, data: bytes) -> None:
        """A message whose step was already written: into that step's bag while it is open and lacks the topic,
        else dropped with a warning (the recorder's module docstring)."""
        bag = self._series.bag
        if bag is None or not self._written.join(stamp, topic, bag):
            self.dropped += 1
            self.per_message.warning(f"dropped a message on {topic} stamped {stamp} ns: its step was already "
                                     f"written to a closed bag (step_hold_s {self.params.step_hold_s} s passed), "
                                     "or it is a duplicate")
            return
        try:
            self._series.write(topic, log_ns, data)
        except OSError as err:
            self.dropped += 1
            self._series.failed(bag.path, err)
            return
        self.late_kept += 1
        self.per_message.info(f"a message on {topic} stamped {stamp} ns came after its step was written: it joined "
                              f"the step in {bag.path.name}")
