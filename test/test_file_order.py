"""The parallel batch's file order (test/file_order.py): longest first, new files in the middle, seconds recorded."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from file_order import SECONDS, FileSeconds, files_longest_first, load_seconds

ROOT = Path(__file__).parent.parent


def test_files_go_longest_first_and_a_new_file_counts_as_the_median() -> None:
    seconds = {"a.py": 1.0, "b.py": 30.0, "c.py": 5.0, "d.py": 2.0}
    assert files_longest_first(["a.py", "b.py", "c.py", "d.py"], seconds) == ["b.py", "c.py", "d.py", "a.py"]
    # new.py counts as 3.5 s (the median of the four): after c.py, before d.py
    assert files_longest_first(["new.py", "a.py", "b.py", "c.py", "d.py"], seconds) == \
        ["b.py", "c.py", "new.py", "d.py", "a.py"]


def test_files_that_count_alike_keep_their_order() -> None:
    files = [f"t{k}.py" for k in range(7)]
    assert files_longest_first(files, {}) == files
    assert files_longest_first(files, dict.fromkeys(files, 4.0)) == files


def test_every_file_recorded_is_a_test_file_here() -> None:
    """A file renamed or removed since the seconds were recorded: record them again."""
    seconds = load_seconds()
    assert seconds, f"{SECONDS} is missing"
    assert all(s >= 0 for s in seconds.values())
    missing = [f for f in seconds if not (ROOT / f).is_file()]
    assert not missing, f"{missing} are in {SECONDS.name} but not here: record it again (--record-file-seconds)"


def test_the_seconds_of_each_phase_add_up_per_file(tmp_path: Path) -> None:
    out = tmp_path / "seconds.json"
    plugin = FileSeconds(out)
    for nodeid, when, duration in (("test/test_x.py::test_a", "setup", 0.25), ("test/test_x.py::test_a", "call", 1.0),
                                   ("test/test_x.py::test_b[1]", "call", 2.0), ("test/test_y.py::test_c", "call", 0.5),
                                   ("test/test_x.py::test_b[1]", "teardown", 0.25)):
        plugin.pytest_runtest_logreport(pytest.TestReport(nodeid, ("x", 0, "x"), {}, "passed", None, when,
                                                          duration=duration))
    plugin.pytest_sessionfinish()
    assert json.loads(out.read_text()) == {"test/test_x.py": 3.5, "test/test_y.py": 0.5}
    assert load_seconds(out) == {"test/test_x.py": 3.5, "test/test_y.py": 0.5}
    assert load_seconds(tmp_path / "none.json") == {}
