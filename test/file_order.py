"""The parallel batch's test files handed out longest first, by the seconds each took in a measured batch.

pytest-xdist's ``--dist loadfile`` gives a worker one whole file at a time, by default the files with the most
tests first.  The few-test files that start whole suites (test_stock_graph.py, test_hardware_suite.py) then come
last, and the batch ends on one of them while the other workers have nothing left.  Handed out longest first
(the LPT rule), the short files fill the end instead.  ``scripts/test.sh`` runs the batch with
``--no-loadscope-reorder`` so that xdist keeps this order, and ``--record-file-seconds PATH`` writes a run's
seconds per file for the next (:data:`SECONDS` is the committed one).
"""

from __future__ import annotations

import json
import statistics
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytest

SECONDS = Path(__file__).with_name("file_seconds.json")
"""Seconds per test file (setup, call and teardown added up) in a 4-worker batch, keyed by path from the root."""


def load_seconds(path: Path = SECONDS) -> dict[str, float]:
    """The recorded seconds per file; none when the file is missing (every file then counts alike)."""
    return json.loads(path.read_text()) if path.is_file() else {}


def files_longest_first(files: Sequence[str], seconds: Mapping[str, float]) -> list[str]:
    """``files`` longest first.  A file not measured (a new one) counts as the median measured file; files that
    count alike keep their order."""
    measured = [seconds[f] for f in files if f in seconds]
    default = statistics.median(measured) if measured else 0.0
    return sorted(files, key=lambda f: -seconds.get(f, default))


def order_items(items: list[pytest.Item], seconds: Mapping[str, float]) -> None:
    """Sort ``items`` in place by their files, longest first; the tests of a file keep their order."""
    files = list(dict.fromkeys(item.nodeid.split("::")[0] for item in items))
    rank = {f: i for i, f in enumerate(files_longest_first(files, seconds))}
    items.sort(key=lambda item: rank[item.nodeid.split("::")[0]])


class FileSeconds:
    """A plugin adding up each test file's seconds from the reports (under xdist the controller gets every
    worker's), written as JSON at the session's end."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.seconds: dict[str, float] = defaultdict(float)

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        self.seconds[report.nodeid.split("::")[0]] += report.duration

    def pytest_sessionfinish(self) -> None:
        self.path.write_text(json.dumps({f: round(s, 1) for f, s in sorted(self.seconds.items())}, indent=1) + "\n")
