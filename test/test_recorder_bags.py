"""The recorder's continuous bags without ROS: names, spans and announcements, and what a write failure does (the
bag left readable and announced, said once, recording resumed into a new bag)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from msg_adapters import STRING, TYPESTORE
from msg_adapters.events import WRITE_FAILED, BagClosedEvent
from t42_transfer.data.bag.steps import Step
from t42_transfer.nodes.recorder_bags import BagSeries
from t42_transfer.nodes.recorder_params import RecorderParams

TOPIC = "/hand/status"
DATA = TYPESTORE.serialize_cdr(TYPESTORE.types[STRING](data="x"), STRING)


class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str) -> None:
        self.lines.append(("info", message))

    def error(self, message: str) -> None:
        self.lines.append(("error", message))


class Rig:
    def __init__(self, out: Path, **params: object) -> None:
        self.out, self.log = out, Log()
        self.events: list[BagClosedEvent] = []
        self.reports: list[tuple[str, str]] = []
        self.announcer = type("Announcer", (), {"put": lambda _, event: self.events.append(event)})()
        self.series = BagSeries(RecorderParams(out_dir=out, **params), out, {TOPIC: STRING}, {}, {}, self.announcer,
                                self.log, lambda level, message: self.reports.append((level, message)))


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    made = Rig(tmp_path, resume_free_mb=0.0)
    yield made
    if made.series.bag is not None:
        made.series.bag.abort()


def test_bags_take_the_next_name_and_are_announced_with_their_span(rig: Rig) -> None:
    assert rig.series.open() == (True, f"recording to {rig.out / 'recording_000'}")
    rig.series.write(TOPIC, 5, DATA)
    rig.series.write(TOPIC, 3, DATA)
    ok, message = rig.series.close("stop")
    assert ok and message == f"closed {rig.out / 'recording_000'} (2 messages)"
    assert rig.series.closed == [rig.out / "recording_000"] and rig.series.bag is None
    assert rig.events == [BagClosedEvent(str(rig.out / "recording_000"), 0, 2, 3, 5, "stop")]
    rig.series.configure(RecorderParams(out_dir=rig.out, prefix="run"))
    rig.series.open(say=False)
    rig.series.close("split", say=False)
    assert rig.events[-1] == BagClosedEvent(str(rig.out / "run_000"), 0, 0, 0, 0, "split")  # a new span
    assert [line for _, line in rig.log.lines] == [f"recording to {rig.out / 'recording_000'}", message]


def test_a_steps_messages_never_go_back_in_log_time_on_a_topic(rig: Rig) -> None:
    rig.series.open()
    rig.series.write_step(Step(1, 0.0, [(TOPIC, 10, DATA)]))
    rig.series.write_step(Step(2, 0.0, [(TOPIC, 7, DATA)]))  # received earlier than the message before it
    rig.series.close("stop")
    assert (rig.events[0].start_ns, rig.events[0].end_ns) == (10, 10)


def test_a_write_failure_leaves_the_bag_announced_is_said_once_and_a_resume_opens_the_next(rig: Rig) -> None:
    rig.series.open()
    rig.series.write(TOPIC, 5, DATA)
    full = OSError(28, "No space left on device")
    rig.series.failed(rig.out / "recording_000", full)
    rig.series.failed(rig.out / "recording_000", full)
    assert rig.series.bag is None and rig.series.closed == []  # not closed by choice: not among the bags
    assert rig.series.failure == f"writing to {rig.out / 'recording_000'} failed: No space left on device"
    assert rig.events == [BagClosedEvent(str(rig.out / "recording_000"), 0, 1, 5, 5, WRITE_FAILED)]
    errors = [line for level, line in rig.log.lines if level == "error"]
    assert len(errors) == 1 and errors[0].endswith("what was written stays readable (t42 bag repair)")
    assert rig.reports == [("ERROR", rig.series.failure)]
    assert rig.series.resume("space is back") == (True, f"recording to {rig.out / 'recording_001'}")
    assert rig.series.failure is None and rig.reports[-1] == ("OK", f"recording to {rig.out / 'recording_001'}")
    assert rig.log.lines[-1][1].startswith(f"space is back: recording to {rig.out / 'recording_001'} (writing had")


def test_a_bag_that_does_not_open_is_a_write_failure(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    rig = Rig(tmp_path / "file")
    ok, message = rig.series.open()
    assert not ok and message.startswith(f"could not open a bag: writing to {tmp_path / 'file'} failed")
    assert rig.series.bag is None and rig.reports[0][0] == "ERROR"


@pytest.mark.parametrize("will_record", [True, False])
def test_a_flush_that_finds_the_bag_gone_fails_and_opens_a_new_one_while_recording(rig: Rig,
                                                                                   will_record: bool) -> None:
    rig.series.open()
    rig.series.write(TOPIC, 5, DATA)
    rig.series.flush(will_record)
    shutil.rmtree(rig.out)
    rig.series.flush(will_record)
    error = next(line for level, line in rig.log.lines if level == "error")
    assert "its 1 messages are lost" in error and "t42 bag repair" not in error
    assert rig.events == []  # nothing final to announce
    if will_record:
        assert rig.series.failure is None and rig.series.bag.path == rig.out / "recording_000"
        assert [level for level, _ in rig.reports] == ["ERROR", "OK"] and "a new bag: " in rig.log.lines[-1][1]
    else:
        assert rig.series.bag is None and rig.series.failure is not None
