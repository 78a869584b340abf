"""End the process with a chosen exit code if it is still alive after a deadline, even with the GIL held.

Releasing rclpy's handles can block inside the middleware (a node's ``rcl_node_fini`` waiting in
Fast DDS, seen in a busy graph after the node had closed its work cleanly). rclpy holds the GIL
there, so no Python thread, timer or signal handler can run; only native threads can.  glibc's
``timer_create`` with ``SIGEV_THREAD`` calls a C function on a thread of its own when the timer
fires: here ``_exit(code)``, so the process ends with the status its node earned (0 after a clean
close), not a watchdog's 1.  :mod:`faulthandler` prints the stuck stack just before, so the hang
stays visible.  Where ``timer_create`` is missing (not glibc), faulthandler alone ends the process
(exit 1).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import faulthandler
import math

CLOCK_MONOTONIC = 1
SIGEV_THREAD = 2
TRACEBACK_LEAD_S = 0.5
"""The stuck stack is printed this long before the exit."""


class _SigEvent(ctypes.Structure):
    """glibc's ``struct sigevent`` (64 bytes on Linux): value, signo, notify, then the thread function."""

    _fields_ = [
        ("sigev_value", ctypes.c_void_p),
        ("sigev_signo", ctypes.c_int),
        ("sigev_notify", ctypes.c_int),
        ("sigev_notify_function", ctypes.c_void_p),
        ("sigev_notify_attributes", ctypes.c_void_p),
        ("_pad", ctypes.c_int * 8),
    ]


class _TimeSpec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _ITimerSpec(ctypes.Structure):
    _fields_ = [("it_interval", _TimeSpec), ("it_value", _TimeSpec)]


class ExitWatchdog:
    """``arm(seconds, code)`` before a step that may hang; ``disarm()`` after it.  One armed timer at a time."""

    def __init__(self) -> None:
        self._libc = _libc()
        self._timer: ctypes.c_void_p | None = None
        self.native = self._libc is not None
        """Whether the exit code is kept (glibc); otherwise faulthandler exits with 1."""

    def arm(self, seconds: float, code: int) -> None:
        if not (math.isfinite(seconds) and seconds > TRACEBACK_LEAD_S) or not 0 <= code <= 255:
            raise ValueError(f"need seconds > {TRACEBACK_LEAD_S} and an exit code 0-255, got {seconds}, {code}")
        self.disarm()
        if self.native and self._start_timer(seconds, code):
            faulthandler.dump_traceback_later(seconds - TRACEBACK_LEAD_S, exit=False)
        else:
            faulthandler.dump_traceback_later(seconds, exit=True)

    def _start_timer(self, seconds: float, code: int) -> bool:
        """Whether the native timer calling ``_exit(code)`` in ``seconds`` is set."""
        libc = self._libc
        event = _SigEvent(sigev_value=code, sigev_notify=SIGEV_THREAD,
                          sigev_notify_function=ctypes.cast(libc._exit, ctypes.c_void_p).value)
        timer = ctypes.c_void_p()
        if libc.timer_create(CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
            return False
        whole = int(seconds)
        when = _ITimerSpec(it_value=_TimeSpec(whole, int((seconds - whole) * 1e9)))
        if libc.timer_settime(timer, 0, ctypes.byref(when), None) != 0:
            libc.timer_delete(timer)
            return False
        self._timer = timer
        return True

    def disarm(self) -> None:
        faulthandler.cancel_dump_traceback_later()
        if self._timer is not None:
            self._libc.timer_delete(self._timer)
            self._timer = None


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.timer_create, libc.timer_settime, libc.timer_delete  # noqa: B018 (glibc 2.34+ has them in libc)
    except (OSError, AttributeError):
        return None
    libc.timer_create.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    libc.timer_settime.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    libc.timer_delete.argtypes = [ctypes.c_void_p]
    return libc
