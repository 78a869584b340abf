"""Fuzzing the YAML readers: experiment configs (``load_config``) and ROS params files (``read_params_file``).

Each mutated file must load or raise ValueError with one line naming the file: no other
exception, hang, memory bomb or stray file (the harness's rule).  Inputs are the shipped
``configs/sim_small.yaml`` and ``configs/suite.yaml`` mutated two ways: as bytes (syntax,
encodings, truncation) and as trees (one value replaced by a hostile one: NaN, a huge or
negative number, a path out of the run directory, a wrong type, deep nesting), which reach
the checks behind the parser.  A fast slice runs by default; ``-m slow`` runs 2000 cases
per reader and prints the counts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from fuzz_harness import DecoderWorker, fuzz, mutated
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[1]
READERS = {
    "experiment": ("t42_transfer.evaluation.experiment_config:load_config", REPO / "configs" / "sim_small.yaml"),
    "params": ("t42_transfer.ros.launcher:read_params_file", REPO / "configs" / "suite.yaml"),
}
MEM_MB = 256

HOSTILE = st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), -1, 0, 2**31, 10**30, -(10**30), 1e308, True, None,
                     "", "../../../../escape", "/abs/path", "a/b", "..", "\x00", "x" * 5000, [], {}, [float("nan")],
                     ["direct", "direct"], {"ros__parameters": 5}, [[1]], [1, "x"]]),
    st.integers(), st.floats(), st.text(max_size=20), st.booleans(),
    st.lists(st.one_of(st.integers(), st.floats(), st.text(max_size=5)), max_size=4),
    st.recursive(st.integers(0, 3), lambda inner: st.lists(inner, max_size=2) | st.dictionaries(
        st.text(max_size=4), inner, max_size=2), max_leaves=60),
)


def _slots(node: Any) -> list[tuple[Any, Any]]:
    """Every (container, key) of a parsed YAML tree, so one value anywhere can be replaced."""
    slots: list[tuple[Any, Any]] = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        slots.append((node, key))
        slots.extend(_slots(value))
    return slots


@st.composite
def mutated_yaml(draw: st.DrawFn, seed: bytes) -> bytes:
    """``seed`` mutated as bytes, or as a tree with one value replaced, removed, or a key added."""
    if draw(st.booleans()):
        return draw(mutated(seed))
    tree = yaml.safe_load(seed)
    container, key = draw(st.sampled_from(_slots(tree)))
    action = draw(st.sampled_from(("replace", "replace", "delete", "add")))
    if action == "delete" and isinstance(container, dict):
        del container[key]
    elif action == "add" and isinstance(container, dict):
        container[draw(st.text(max_size=12) | st.integers())] = draw(HOSTILE)
    else:
        container[key] = draw(HOSTILE)
    return yaml.safe_dump(tree, allow_unicode=draw(st.booleans())).encode()


@pytest.fixture(scope="module", params=list(READERS))
def reader(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, DecoderWorker,
                                                                                                bytes]:
    target, seed_file = READERS[request.param]
    keep = tmp_path_factory.mktemp(f"escapes_{request.param}")
    with DecoderWorker(target, errors="builtins:ValueError", mem_mb=MEM_MB, timeout_s=10, keep_dir=keep) as worker:
        yield request.param, worker, seed_file.read_bytes()


def test_the_seed_files_load(reader: tuple[str, DecoderWorker, bytes]) -> None:
    name, worker, seed = reader
    assert worker.check_bytes(seed, f"{name}.yaml").outcome == "accepted"


@pytest.mark.parametrize("content", [
    b"name: [unclosed\n", b"a: b: c\n", b"\xff\xfe\x00", b"x: &a [*a]\n", b"x: " + b"9" * 5000 + b"\n",
    b"[" * 5000, b"{a: " * 3000, b"x: !!python/object/apply:os.system [echo]\n", b"x: 2001-13-45\n",
    b"- &a [&b [&c [*a, *a]]]\n", b"? '\n\n  '\n: .nan\n",
], ids=["unclosed", "mapping in a value", "utf-16 bom", "self-reference", "5000 digits", "deep lists",
        "deep mappings", "python tag", "bad date", "aliases", "a key of line breaks"])
def test_crafted_yaml_is_refused_in_one_line(reader: tuple[str, DecoderWorker, bytes], content: bytes) -> None:
    name, worker, _ = reader
    assert worker.check_bytes(content, f"{name}.yaml").outcome == "refused"


def _fuzz(reader: tuple[str, DecoderWorker, bytes], examples: int) -> dict[str, int]:
    name, worker, seed = reader
    counts = fuzz(worker, mutated_yaml(seed), f"{name}.yaml", examples)
    assert sum(counts.values()) >= examples
    return counts


def test_mutated_configs_fast_slice(reader: tuple[str, DecoderWorker, bytes]) -> None:
    _fuzz(reader, 40)


@pytest.mark.slow
def test_mutated_configs(reader: tuple[str, DecoderWorker, bytes]) -> None:
    counts = _fuzz(reader, 2000)
    assert counts["refused"] > 0 and counts["accepted"] > 0
