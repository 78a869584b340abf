"""Per-message warnings that a flood cannot turn into a flood of log lines.

rclpy's ``throttle_duration_sec`` drops repeats silently; a user reading /rosout after a burst of bad messages
should know how many there were.  :class:`ThrottledLog` lets one line of a kind through per period and says, on
the next line of that kind, how many it held back.  A kind is the message with its finite numbers masked, so a
flood of NaN commands is one kind and a different refusal reason is another.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from typing import Any

NUMBERS = re.compile(r"[-+]?\d+\.?\d*(?:e[-+]?\d+)?", re.IGNORECASE)
"""Finite numbers: masked out of a message's kind (a NaN and an inf stay apart, as their causes may)."""
PERIOD_S = 1.0


class ThrottledLog:
    """``warning`` / ``error`` on ``logger`` at most once per ``period_s`` per kind of message, with the count
    of those held back since the last line of the kind; thread-safe."""

    def __init__(self, logger: Any, period_s: float = PERIOD_S, clock: Callable[[], float] = time.monotonic) -> None:
        self._logger, self._period_s, self._clock = logger, period_s, clock
        self._kinds: dict[str, tuple[float, int]] = {}
        """kind -> (when its last line went out, lines held back since)."""
        self._lock = threading.Lock()

    def warning(self, message: str) -> None:
        self._emit(self._logger.warning, message)

    def error(self, message: str) -> None:
        self._emit(self._logger.error, message)

    def _emit(self, write: Callable[[str], Any], message: str) -> None:
        kind, now = NUMBERS.sub("#", message), self._clock()
        with self._lock:
            last, held = self._kinds.get(kind, (-float("inf"), 0))
            if now - last < self._period_s:
                self._kinds[kind] = (last, held + 1)
                return
            self._kinds[kind] = (now, 0)
        write(message if not held else f"{message} ({held} more like it in the last {now - last:.1f} s)")
