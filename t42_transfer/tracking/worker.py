"""Heavy per-frame work off the caller's thread, on the newest frame only.

:class:`LatestOnly` keeps one pending slot: a frame submitted while another waits replaces it (the older one
is dropped and counted), so when the work cannot keep up the backlog never grows past one frame and the
result is always about the newest image.  The object tracker node hands its images to one of these, so the
ROS executor is never blocked by detection.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any


class LatestOnly:
    """One worker thread running ``work(item)`` on the newest submitted item; results go to ``done``."""

    def __init__(self, work: Callable[[Any], Any], done: Callable[[Any], None] | None = None,
                 failed: Callable[[Any, BaseException], None] | None = None, name: str = "latest-only") -> None:
        self._work, self._done, self._failed = work, done, failed
        self._cond = threading.Condition()
        self._pending: Any = None
        self._has_pending = False
        self._busy = False
        self._closed = False
        self.counts = {"submitted": 0, "processed": 0, "dropped": 0, "failed": 0}
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item: Any) -> bool:
        """Queue ``item`` for the worker; False when it replaced one still waiting (that one is dropped)."""
        with self._cond:
            if self._closed:
                raise RuntimeError("the worker is closed")
            replaced = self._has_pending
            self._pending, self._has_pending = item, True
            self.counts["submitted"] += 1
            self.counts["dropped"] += replaced
            self._cond.notify()
        return not replaced

    @property
    def backlog(self) -> int:
        """Items waiting (0 or 1)."""
        with self._cond:
            return int(self._has_pending)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until nothing waits and nothing runs; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._has_pending and not self._busy, timeout)

    def close(self, timeout: float | None = 5.0) -> None:
        """Stop after the item in hand (a waiting one is dropped); joins the thread."""
        with self._cond:
            if self._has_pending:
                self.counts["dropped"] += 1
            self._closed, self._has_pending, self._pending = True, False, None
            self._cond.notify_all()
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._has_pending or self._closed)
                if self._closed:
                    return
                item, self._pending, self._has_pending = self._pending, None, False
                self._busy = True
            try:
                result = self._work(item)
                with self._cond:
                    self.counts["processed"] += 1
                if self._done is not None:
                    self._done(result)
            except Exception as err:  # the worker outlives a bad item or a failing callback; the owner hears of it
                with self._cond:
                    self.counts["failed"] += 1
                if self._failed is not None:
                    with contextlib.suppress(Exception):
                        self._failed(item, err)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
