"""The exit watchdog ends a process stuck with the GIL held, with the exit code it was armed with."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from t42_transfer.ros.exit_watchdog import ExitWatchdog

STUCK = """
import ctypes, sys
from t42_transfer.ros.exit_watchdog import ExitWatchdog
watchdog = ExitWatchdog()
print("native", watchdog.native, flush=True)
watchdog.arm(1.0, int(sys.argv[1]))
ctypes.PyDLL(None).sleep(60)  # a C call that keeps the GIL: no Python thread or signal handler can run
print("woke up", flush=True)
"""

DISARMED = """
import sys, time
from t42_transfer.ros.exit_watchdog import ExitWatchdog
watchdog = ExitWatchdog()
watchdog.arm(1.0, 0)
time.sleep(0.1)
watchdog.disarm()
time.sleep(1.5)
print("still here", flush=True)
sys.exit(7)
"""


def _run(script: str, *args: str) -> tuple[subprocess.CompletedProcess[str], float]:
    begin = time.monotonic()
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=30)
    return done, time.monotonic() - begin


@pytest.mark.skipif(not ExitWatchdog().native, reason="timer_create is glibc's; elsewhere faulthandler exits 1")
@pytest.mark.parametrize("code", [0, 3])
def test_a_process_stuck_holding_the_gil_exits_with_the_armed_code_and_its_stack(code: int) -> None:
    done, seconds = _run(STUCK, str(code))
    assert done.returncode == code, done.stderr
    assert "native True" in done.stdout and "woke up" not in done.stdout
    assert "Timeout" in done.stderr and "line 7" in done.stderr, done.stderr  # where it was stuck
    assert seconds < 20


def test_a_disarmed_watchdog_leaves_the_process_its_own_exit() -> None:
    done, _ = _run(DISARMED)
    assert done.returncode == 7 and "still here" in done.stdout, done.stderr
    assert "Timeout" not in done.stderr


@pytest.mark.parametrize(("seconds", "code"), [(0.1, 0), (float("nan"), 0), (5.0, 256), (5.0, -1)])
def test_bad_deadlines_and_codes_are_refused(seconds: float, code: int) -> None:
    with pytest.raises(ValueError, match="exit code 0-255"):
        ExitWatchdog().arm(seconds, code)
