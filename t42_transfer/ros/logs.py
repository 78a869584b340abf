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
    """``info`` / ``warning`` / ``error`` on ``logger`` at most once per ``period_s`` per kind of message, with
    the count of those held back since the last line of the kind; thread-safe."""

    def __init__(self, logger: Any, period_s: float = PERIOD_S, clock: Callable[[], float] = time.monotonic) -> None:
        self._logger, self._period_s, self._clock = logger, period_s, clock
        self._kinds: dict[str, tuple[float, int]] = {}
        """kind -> (when its last line went out, lines held back since)."""
        self._lock = threading.Lock()

    # Each level writes from its own line: rclpy keeps one severity per call site and raises on another.
    def info(self, message: str) -> None:
        if (line := self._line(message)) is not None:
            self._logger.info(line)

    def warning(self, message: str) -> None:
        if (line := self._line(message)) is not None:
            self._logger.warning(line)

    def error(self, message: str) -> None:
        if (line := self._line(message)) is not None:
            self._logger.error(line)

    def _line(self, message: str) -> str | None:
        """The line to write for ``message`` now, or None while its kind is held back."""
        kind, now = NUMBERS.sub("#", message), self._clock()
        with self._lock:
            last, held = self._kinds.get(kind, (-float("inf"), 0))
            if now - last < self._period_s:
                self._kinds[kind] = (last, held + 1)
                return None
            self._kinds[kind] = (now, 0)
        return message if not held else f"{message} ({held} more like it in the last {now - last:.1f} s)"
