"""The recorder's continuous bags, one after another (:mod:`t42_transfer.nodes.recorder` is the node and says when a
bag opens, splits or closes): the next opened under a free name, its messages written at their log times, closed and
announced on ``recorder/bag_closed``; and the write failure (a full disk, a removed ``out_dir``, a bag that does not
open) that stops writing until there is room again or ``~/start``.  Kept apart from the node so that what a failure
does to the bag can be tested without ROS; the node's diagnostics and lock stay in the node.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from contextlib import suppress
from pathlib import Path
from typing import Any

from msg_adapters import names
from msg_adapters.events import WRITE_FAILED, BagClosedEvent
from t42_transfer.data.bag import BagWriter
from t42_transfer.data.bag.recording import LogTimes, open_next_bag, room
from t42_transfer.data.bag.steps import Step
from t42_transfer.nodes.recorder_params import Announcer, RecorderParams, next_bag_path

Report = Callable[[str, str], None]
"""``(level, message)`` on the node's diagnostics: ``ERROR`` when writing fails, ``OK`` when it resumes."""


class BagSeries:
    """The open bag of a recorder, the bags it closed, and why writing stopped (see the module docstring).  Not
    thread-safe: the node calls it under its lock."""

    def __init__(self, params: RecorderParams, out_dir: Path, types: Mapping[str, str],
                 offered: Mapping[str, names.Qos], custom: Mapping[str, str], announcer: Announcer, log: Any,
                 report: Report) -> None:
        self.out_dir = out_dir
        self._types, self._offered, self._custom = dict(types), dict(offered), dict(custom)
        self._announcer, self._log, self._report = announcer, log, report
        self._params = params
        self.bag: BagWriter | None = None
        """The open bag (None: not writing)."""
        self.closed: list[Path] = []
        """Every bag closed and announced, in order."""
        self.failure: str | None = None
        """Why writing stopped (a full disk): steps are dropped until space returns or ``~/start``."""
        self._span: list[int] = []
        """Log times of the open bag's first and last message (min and max)."""
        self._log_times = LogTimes()

    def configure(self, params: RecorderParams) -> None:
        """Take (changed) parameters: the next bag's prefix, the free space a resume waits for."""
        self._params = params

    # ------------------------------------------------------------------ opening and closing
    def open(self, say: bool = True) -> tuple[bool, str]:
        """Open the next bag; (whether it opened, what happened), on /rosout too unless ``say`` is False."""
        try:  # a name another writer took first is passed over; any other failure is a write failure
            bag = open_next_bag(lambda: next_bag_path(self.out_dir, self._params.bag_prefix), self._types,
                                self._offered, self._custom)
        except Exception as err:
            self.failed(self.out_dir, err)
            return False, f"could not open a bag: {self.failure}"
        self.bag, self._span = bag, []
        self._log_times.new_bag()
        if say:
            self._log.info(f"recording to {bag.path}")
        return True, f"recording to {bag.path}"

    def close(self, reason: str, say: bool = True) -> tuple[bool, str]:
        """Close the open bag and announce it (``reason``); (whether it closed, what happened), on /rosout too
        unless ``say`` is False (the caller says it)."""
        bag, self.bag = self.bag, None
        assert bag is not None
        try:
            bag.close()
        except Exception as err:  # its directory was removed...: nothing final to announce
            self._log.error(f"closing {bag.path} failed: {err!r}")
            self._report("ERROR", f"closing {bag.path} failed: {type(err).__name__}: {err}")
            return False, f"closing {bag.path} failed: {type(err).__name__}: {err}"
        self.closed.append(bag.path)
        self._announce(bag, reason)
        if say:
            self._log.info(f"closed {bag.path} ({bag.count} messages)")
        return True, f"closed {bag.path} ({bag.count} messages)"

    # ------------------------------------------------------------------ writing
    def write(self, topic: str, log_ns: int, data: bytes, msgtype: str | None = None) -> None:
        """One message into the open bag at ``log_ns`` (a status, an event, a step's late message); raises what
        the bag raises (OSError: a full disk, for :meth:`failed`)."""
        assert self.bag is not None
        self.bag.write(topic, log_ns, data, msgtype)
        self._spanned(log_ns)

    def write_step(self, step: Step) -> None:
        """A whole step into the open bag, each message at its log time (:class:`LogTimes`)."""
        for topic, received_ns, data in step.messages:
            self.write(topic, self._log_times(topic, received_ns, step.stamp), data)

    def restart(self, log_ns: int, stamp: int) -> None:
        """The stamps restarted behind those written at ``stamp``, received at ``log_ns`` (see :class:`LogTimes`)."""
        self._log_times.restart(log_ns, stamp)

    def flush(self, will_record: bool) -> None:
        """Write out what the open bag holds so far; failures are logged.  A bag whose file is gone (``out_dir``
        removed) is a write failure; after one, a bag opens again here once there is room (``will_record``)."""
        bag = self.bag
        if bag is not None and (gone := bag.lost()) is not None:
            self.bag = None  # out_dir removed: the bag cannot be finalised, a write failure
            with suppress(Exception):
                bag.abort()
            self.failed(bag.path, FileNotFoundError(f"{gone}: its {bag.count} messages are lost"))
        if self.failure is not None and will_record and room(self.out_dir, self._params.resume_free_mb):
            self.resume("space is back" if bag is self.bag else "a new bag")
        if self.bag is None:
            return
        try:
            self.bag.flush()
        except OSError as err:  # a full disk: stop writing, say so once
            self.failed(self.bag.path, err)
        except Exception as err:
            self._log.error(f"flushing {self.bag.path} failed: {err!r}")

    # ------------------------------------------------------------------ write failures
    def failed(self, where: Path, err: Exception) -> None:
        """Writing failed (a full disk): leave the bag as it is (repairable), drop steps until there is room."""
        bag, self.bag = self.bag, None
        if bag is not None:
            try:
                bag.close()
                self._announce(bag, WRITE_FAILED)
            except Exception:  # its summary cannot be written either: the bag stays as a killed one, repairable
                pass
        if self.failure is not None:
            return
        self.failure = f"writing to {where} failed: {getattr(err, 'strerror', None) or err}"
        kept = "" if isinstance(err, FileNotFoundError) else "; what was written stays readable (t42 bag repair)"
        self._log.error(f"{self.failure}; recording stops until {self._params.resume_free_mb:g} MB are free on "
                        f"{self.out_dir} (or ~/start){kept}")
        self._report("ERROR", self.failure)

    def resume(self, why: str) -> tuple[bool, str]:
        """Open a bag again after a write failure (``why``: what ended it); (whether it opened, what happened)."""
        failure, self.failure = self.failure, None
        ok, message = self.open(say=False)  # said here, with why
        if ok:
            self._log.info(f"{why}: {message} (writing had failed: {failure})")
            self._report("OK", message)
        return ok, message

    # ------------------------------------------------------------------ bag events
    def _announce(self, bag: BagWriter, reason: str) -> None:
        """Queue ``recorder/bag_closed`` for a bag just closed and final: the announcer reads it (its episodes)."""
        first, last = (self._span[0], self._span[-1]) if self._span else (0, 0)
        self._announcer.put(BagClosedEvent(str(bag.path), 0, bag.count, first, last, reason))

    def _spanned(self, log_ns: int) -> None:
        span = self._span
        self._span = [log_ns, log_ns] if not span else [min(span[0], log_ns), max(span[1], log_ns)]
