"""held_lock, the one locking step: it waits for another holder, or, given ``busy``, refuses at once with the error
``busy`` makes from the held lock file, and lets go however its block ends."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from t42_transfer.files import held_lock


def _in_use(fd: int) -> ValueError:
    return ValueError(os.pread(fd, 64, 0).decode())


def test_a_held_lock_refuses_a_second_holder_that_will_not_wait(tmp_path: Path) -> None:
    path = tmp_path / ".lock"
    with held_lock(path) as fd:
        os.pwrite(fd, b"pid 1", 0)
        with pytest.raises(ValueError, match="pid 1"), held_lock(path, busy=_in_use):
            pass
    with held_lock(path, busy=_in_use):  # let go: a second holder gets it
        pass


def test_a_lock_is_let_go_when_its_block_raises(tmp_path: Path) -> None:
    path = tmp_path / ".lock"
    with pytest.raises(RuntimeError), held_lock(path):
        raise RuntimeError
    with held_lock(path, busy=_in_use):
        pass


def test_a_second_holder_without_busy_waits_for_the_first_to_let_go(tmp_path: Path) -> None:
    """Two experiments collecting one data set rely on this wait (experiment.py)."""
    import threading

    path, order = tmp_path / ".lock", []
    got_second = threading.Event()

    def second() -> None:
        with held_lock(path):
            order.append("second")
            got_second.set()

    with held_lock(path):
        waiter = threading.Thread(target=second)
        waiter.start()
        assert not got_second.wait(0.3), "the second holder got a lock that was held"
        order.append("first lets go")
    assert got_second.wait(10.0)
    waiter.join(10.0)
    assert order == ["first lets go", "second"]
