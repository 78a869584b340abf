"""Fuzzing the bag decoders: mutated copies of the target fixture bag through ``read_bag``, ``bag_info``,
``verify_bag`` (``t42 bag info --verify``) and ``repair_bag``.

Each case is the fixture bag (``bags/target_small``) with one of its two files, the
MCAP or ``metadata.yaml``, replaced by a mutation of it; the decoder runs in the
fuzz harness's guarded worker, where anything but a return or a one-line
:class:`~t42_transfer.data.errors.BagError` naming the bag is an escape (a repair
writes only inside the case's bag).  A fast
slice runs by default; ``-m slow`` runs 2000 cases per decoder and file (counts
printed, ``-s`` shows them).  An escape's input is kept under the test's tmp_path.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fuzz_harness import DecoderWorker, fuzz, mutated

REPO = Path(__file__).resolve().parents[1]
SEED_BAG = REPO / "bags" / "target_small"
PARTS = {"mcap": "target_small.mcap", "yaml": "metadata.yaml"}
DECODERS = ("bag:read_bag", "bag:bag_info", "bag:verify_bag", "bag.repair:repair_bag")


def run_fuzz(decoder: str, part: str, examples: int, keep: Path) -> dict[str, int]:
    """``examples`` mutations of the fixture bag's ``part`` through ``decoder``; the accepted/refused counts."""
    seed = (SEED_BAG / PARTS[part]).read_bytes()
    with DecoderWorker(f"t42_transfer.data.{decoder}", keep_dir=keep) as worker:

        def case(data: bytes) -> None:
            bag = Path(shutil.copytree(SEED_BAG, worker.new_case_dir() / SEED_BAG.name))
            (bag / PARTS[part]).write_bytes(data)
            worker.check_path(bag)

        return fuzz(worker, mutated(seed), PARTS[part], examples, check=case)


@pytest.mark.parametrize("part", sorted(PARTS))
@pytest.mark.parametrize("decoder", DECODERS)
def test_mutated_bags_never_escape(tmp_path: Path, decoder: str, part: str) -> None:
    counts = run_fuzz(decoder, part, 40, tmp_path / "escapes")
    assert sum(counts.values()) == 40


@pytest.mark.slow
@pytest.mark.parametrize("part", sorted(PARTS))
@pytest.mark.parametrize("decoder", DECODERS)
def test_mutated_bags_never_escape_long(tmp_path: Path, decoder: str, part: str) -> None:
    counts = run_fuzz(decoder, part, 2000, tmp_path / "escapes")
    assert sum(counts.values()) == 2000
