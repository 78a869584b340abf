"""Progress bars for long work: tqdm's bar on a terminal, whole lines in a log file.

tqdm redraws its bar in place with carriage returns ten times a second.  Written to a file (a job
queue's log, ``t42 demo > log 2>&1``) that is one line growing by hundreds of kilobytes that no
``tail`` or ``grep`` reads.  Off a terminal each redraw here is one line, at most every
:data:`LOG_INTERVAL_S`, and the bar's last state is always written when it closes.
"""

from __future__ import annotations

import math
import re
import sys
import time
from typing import Any, TextIO

LOG_INTERVAL_S = 30.0
_LOG_FORMAT = "{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]"
_CURSOR_MOVES = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")  # tqdm's moves between stacked bars


class _LogLines:
    """A file for tqdm that writes its redraws to ``out`` as whole lines, at most one each ``interval`` s.

    tqdm's own ``mininterval`` does not hold back a redraw forced by ``set_postfix``, so the throttle is
    here.  A redraw held back is written when the bar ends (tqdm then writes its final state and a newline).
    """

    def __init__(self, out: TextIO, interval: float) -> None:
        self.out, self.interval = out, interval
        self._pending, self._written_at = "", -math.inf

    def write(self, text: str) -> int:
        parts = _CURSOR_MOVES.sub("", text).replace("\n", "\r\n").split("\r")
        for part in parts:
            if part.startswith("\n"):
                self._emit()
            elif part.strip():
                self._pending = part.rstrip()
                if time.monotonic() - self._written_at >= self.interval:
                    self._emit()
        return len(text)

    def _emit(self) -> None:
        if self._pending:
            self.out.write(self._pending + "\n")
            self._pending, self._written_at = "", time.monotonic()

    def flush(self) -> None:
        self.out.flush()


def _is_terminal(out: Any) -> bool:
    isatty = getattr(out, "isatty", None)
    return bool(callable(isatty) and isatty())


def progress_bar(*, file: TextIO | None = None, **kwargs: Any) -> Any:
    """A tqdm bar (``kwargs`` as tqdm's) on ``file`` (standard error by default).

    On a terminal, or in a notebook (tqdm.auto's widget), tqdm's own bar.  Elsewhere a line per
    redraw, at most one each :data:`LOG_INTERVAL_S` unless ``mininterval`` says otherwise, and the
    final count kept (``leave``) so the log says how far the work went.
    """
    from tqdm.auto import tqdm

    out = sys.stderr if file is None else file
    if _is_terminal(out) or "ipykernel" in sys.modules:
        return tqdm(file=out, **kwargs)
    lines = _LogLines(out, kwargs.pop("mininterval", LOG_INTERVAL_S))
    if kwargs.get("total") is not None:
        kwargs.setdefault("bar_format", _LOG_FORMAT)
    # position 0: a bar opened inside another would move the cursor a line down and back at every redraw
    return tqdm(file=lines, **{**kwargs, "leave": True, "position": 0})
