"""The real-T42 pickle importer is total: issue 11's crafted pickles and mutated files, in a guarded worker.

Each case must be accepted or refused with one ``PickleFileError`` line naming the file:
no segfault, no allocation beyond the file's size, no hang, no staging folder left behind.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from fuzz_harness import DecoderWorker, fuzz, mutated
from test_t42_real import py2_pickle

from t42_transfer.data.bag import JazzyWriter
from t42_transfer.data.t42_real import REAL_FILES, import_t42_to_bag, load_t42_testpaths, real_data_dir

MEM_MB = 64


def import_beside(path: Path) -> None:
    """Worker target: import the pickle into a bag beside it; a ``.partial`` staging folder left behind is an escape."""
    try:
        import_t42_to_bag(path, path.parent / "bag")
    finally:
        left = sorted(p.name for p in path.parent.glob("*.partial"))
        if left:
            raise AssertionError(f"staging folders left behind: {left}")


@pytest.fixture(scope="module")
def importer(tmp_path_factory):
    keep = tmp_path_factory.mktemp("pickle-import-escapes")
    with DecoderWorker("test_fuzz_pickle:import_beside", mem_mb=MEM_MB, timeout_s=10, keep_dir=keep) as worker:
        yield worker


@pytest.fixture(scope="module")
def loader(tmp_path_factory):
    keep = tmp_path_factory.mktemp("pickle-load-escapes")
    target = "t42_transfer.data.t42_real:load_t42_testpaths"
    with DecoderWorker(target, mem_mb=MEM_MB, timeout_s=10, keep_dir=keep) as worker:
        yield worker


# --------------------------------------------------------------------------- crafted cases (issue 11)
def _small_content(rng: np.random.Generator) -> tuple[list, list, str, list]:
    states = [rng.normal(size=(n, 13)) for n in (5, 8)]
    actions = [rng.choice([-1.0, 1.0, 1.5], size=(n + 1, 2)) for n in (5, 8)]
    return actions, states, "cyl35", [True, False]


def _shared_levels(depth: int, container: bytes) -> bytes:
    """Memo 1..depth: each level a list (``l``) or tuple (``t``) holding the one before twice, 2**depth leaves."""
    return b"".join(b"(g%d\ng%d\n%sp%d\n" % (i, i, container, i + 1) for i in range(depth))


def _one_array_for_every_path(paths: int) -> bytes:
    states, actions = np.zeros((5000, 13)), np.zeros((5001, 2))
    return pickle.dumps([[actions] * paths, [states] * paths, "h", [True] * paths], protocol=4)


CRAFTED = {
    # dtype M8 (datetime) with a plain dtype state: numpy's _reconstruct + __setstate__ segfaulted
    "M8 array": (py2_pickle(*_small_content(np.random.default_rng(0)), dtype="M8"), "refused dtype 'M8'"),
    "m8 array": (py2_pickle(*_small_content(np.random.default_rng(0)), dtype="m8"), "refused dtype 'm8'"),
    # 71 bytes: numpy.ndarray((18000000, 13), 'f8') called directly, 1.9 GB
    "ndarray bomb": (
        b"(l(lcnumpy\nndarray\n((I18000000\nI13\ntS'f8'\ntRp0\naa(lg0\naaS'h'\na(lI01\naa.",
        "refused to call numpy.ndarray",
    ),
    # builtins.str of a list whose 40 levels each hold the level below twice: a repr of 2**40 lists
    "str of shared nested lists": (
        b"c__builtin__\nstr\n(((lp0\n" + _shared_levels(40, b"l") + b"ltR.",
        "refused to load global __builtin__.str",
    ),
    # a dict keyed by a tuple of shared nested tuples: hashing the key takes 2**31 steps (20 s, not interruptible)
    "dict key of shared tuples": (b"}()p0\n" + _shared_levels(31, b"t") + b"tNs.", "refused pickle opcode EMPTY_DICT"),
    # one 0.5 MB array named by 5000 paths: 5000 float32 copies of it
    "one array for every path": (_one_array_for_every_path(5000), "more array bytes than the file holds"),
    # a shape the data cannot fill
    "shape beyond the data": (
        py2_pickle([np.zeros((3, 2))], [np.zeros((2, 13))], "h", [True]).replace(b"I3\nI2\nt", b"I999999999\nI2\nt"),
        "dimension is larger than the file",
    ),
}


@pytest.mark.parametrize("case", sorted(CRAFTED))
def test_crafted_pickles_are_refused_in_one_line(importer, case):
    data, match = CRAFTED[case]
    verdict = importer.check_bytes(data, "paths.pkl")  # an escape (crash, bomb, hang, staging left) raises
    assert verdict.outcome == "refused" and match in verdict.detail, verdict


def test_a_fifo_is_refused_without_waiting_for_a_writer(loader):
    fifo = loader.new_case_dir() / "paths.pkl"
    os.mkfifo(fifo)
    verdict = loader.check_path(fifo)  # the old importer blocked in open() until the worker's alarm
    assert verdict.outcome == "refused" and "is a FIFO, not a regular file" in verdict.detail, verdict


def test_a_failed_write_leaves_no_staging_folder(tmp_path, monkeypatch):
    source = tmp_path / "paths.pkl"
    source.write_bytes(py2_pickle(*_small_content(np.random.default_rng(0))))

    def disk_full(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(JazzyWriter, "write", disk_full)
    with pytest.raises(OSError, match="No space left"):
        import_t42_to_bag(source, tmp_path / "out" / "bag")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == []


def test_the_crafted_seeds_are_valid_otherwise(tmp_path):
    """The crafted cases differ from loadable files only in what they attack."""
    source = tmp_path / "ok.pkl"
    source.write_bytes(py2_pickle(*_small_content(np.random.default_rng(0))))
    assert len(load_t42_testpaths(source)) == 2
    source.write_bytes(_one_array_for_every_path(1))
    assert len(load_t42_testpaths(source)) == 1


# --------------------------------------------------------------------------- mutation fuzzing
SEEDS = ("python2 layout", "protocol 4", *(f"real {hand}" for hand in sorted(REAL_FILES)))


def _seed(name: str) -> bytes:
    """A valid file to mutate: small synthetic ones always (so the fast slice runs anywhere), the real ones if here."""
    if name.startswith("real "):
        path = real_data_dir() / REAL_FILES[name.removeprefix("real ")]
        if not path.is_file():
            pytest.skip(f"real T42 test paths not found in {path.parent} (set T42_REAL_DATA)")
        return path.read_bytes()
    actions, states, hand, flags = _small_content(np.random.default_rng(0))
    if name == "protocol 4":
        return pickle.dumps([actions, states, hand, flags], protocol=4)
    return py2_pickle(actions, states, hand, flags)


def _fuzz(worker: DecoderWorker, seed: bytes, examples: int) -> dict[str, int]:
    """``examples`` mutations of ``seed`` through ``worker``; the accepted/refused counts (an escape raises)."""
    return fuzz(worker, mutated(seed), "paths.pkl", examples)


@pytest.mark.parametrize("seed", SEEDS)
def test_mutated_pickles_fast_slice(loader, seed):
    data = _seed(seed)
    counts = _fuzz(loader, data, 40 if len(data) < 2**20 else 10)
    assert sum(counts.values()) >= 10


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS)
def test_mutated_pickles_long_run(loader, seed):
    counts = _fuzz(loader, _seed(seed), 2000)
    assert sum(counts.values()) >= 2000
