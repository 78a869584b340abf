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
