"""The fuzz harness itself: each kind of escape is caught, refusals and acceptances are counted."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from fuzz_harness import DecoderWorker, Escape

from t42_transfer.data.errors import DataFileError

HERE = "test_fuzz_harness"


def decode(path: Path) -> None:
    """A toy decoder: the first byte says what to do."""
    data = path.read_bytes()
    kind = data[:1]
    if kind == b"a":
        return
    if kind == b"r":
        raise DataFileError(path, "refused properly")
    if kind == b"m":
        raise DataFileError(path, "two\nlines")
    if kind == b"c":
        os.abort()
    if kind == b"h":
        time.sleep(60)
    if kind == b"b":
        bytearray(2**31)
    if kind == b"w":
        Path("written_outside").write_text("x")
    if kind == b"s":  # stuck where no signal handler runs: only the parent's limit ends it
        import signal

        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
        time.sleep(60)
    raise KeyError("whatever")


@pytest.fixture(scope="module")
def worker():
    # A short grace (the parent's kill 3 s after the call, not 11 s): the toy answers at once unless stuck.
    with DecoderWorker(f"{HERE}:decode", mem_mb=256, timeout_s=1.0, grace_s=2.0) as w:
        yield w


@pytest.mark.parametrize("first,kind", [(b"c", "crash"), (b"h", "hang"), (b"b", "memory"), (b"k", "exception"),
                                        (b"m", "not one line"), (b"w", "wrote"), (b"s", "killed")])
def test_every_escape_is_caught(worker, first, kind):
    with pytest.raises(Escape, match=kind):
        worker.check_bytes(first + b"rest", "case.bin")
    assert worker.check_bytes(b"a", "case.bin").outcome == "accepted"  # a crashed worker is restarted


def test_accepted_and_refused_keep_the_rule(worker):
    assert worker.check_bytes(b"a", "x.bin").outcome == "accepted"
    verdict = worker.check_bytes(b"r", "x.bin")
    assert verdict.outcome == "refused" and "refused properly" in verdict.detail
