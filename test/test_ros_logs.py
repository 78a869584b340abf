"""ros.logs: a flood of one kind of warning is a line a period, and the next line counts what was held back."""

from __future__ import annotations

import pytest

from t42_transfer.ros.logs import ThrottledLog


class Lines:
    def __init__(self) -> None:
        self.infos: list[str] = []
        self.warnings: list[str] = []
        self.errors: list[str] = []

    def info(self, message: str) -> None:
        self.infos.append(message)

    def warning(self, message: str) -> None:
        self.warnings.append(message)

    def error(self, message: str) -> None:
        self.errors.append(message)


def test_a_flood_of_one_kind_is_one_line_a_period_and_the_next_counts_the_rest() -> None:
    now = [0.0]
    lines = Lines()
    log = ThrottledLog(lines, period_s=1.0, clock=lambda: now[0])
    for k in range(1000):  # 1000 NaN commands in 0.5 s, each with its own numbers
        now[0] = k * 0.0005
        log.warning(f"rejected hand/command: non-finite velocity [nan, {k}.5] at stamp {k * 100} ns")
    assert len(lines.warnings) == 1
    now[0] = 1.2
    log.warning("rejected hand/command: non-finite velocity [nan, 3.5] at stamp 7 ns")
    assert len(lines.warnings) == 2 and lines.warnings[1].endswith("(999 more like it in the last 1.2 s)")


def test_other_kinds_and_levels_are_not_held_back_by_a_flood() -> None:
    lines = Lines()
    log = ThrottledLog(lines, period_s=1.0, clock=lambda: 0.0)
    log.warning("rejected hand/command: non-finite velocity [nan, 0]")
    log.warning("rejected hand/command: non-finite velocity [nan, 1]")
    log.warning("rejected hand/command: unknown joint 'elbow'")
    log.error("rejected hand/command: could not read the message")
    log.info("step 3: a servo move was refused")
    log.info("step 4: a servo move was refused")
    assert lines.infos == ["step 3: a servo move was refused"]
    assert lines.warnings == ["rejected hand/command: non-finite velocity [nan, 0]",
                              "rejected hand/command: unknown joint 'elbow'"]
    assert lines.errors == ["rejected hand/command: could not read the message"]


def test_warnings_and_errors_mix_on_one_rclpy_logger(capfd: pytest.CaptureFixture[str]) -> None:
    """rclpy keeps one severity per call site: both levels through one write line raised ValueError."""
    from rclpy.logging import get_logger

    log = ThrottledLog(get_logger("t42_test_throttled"))
    for _ in range(2):
        log.warning("a refused command")
        log.error("a failed camera frame")
    err = capfd.readouterr().err
    assert err.count("a refused command") == 1 and err.count("a failed camera frame") == 1, err  # the second held
    assert "[WARN]" in err and "[ERROR]" in err
