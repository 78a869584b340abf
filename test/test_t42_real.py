"""t42_real: the public real-hand pickles, read safely and carried into bags unchanged."""

from __future__ import annotations

import os
import pickle
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD, CONTROL_PERIOD_NS
from t42_transfer.data.bag import EPISODE_GAP_NS, read_bag
from t42_transfer.data.errors import PickleFileError
from t42_transfer.data.t42_real import import_t42_to_bag, load_t42_testpaths

FILES = {"cyl35": "testpaths_cyl35_d_v0.pkl", "cyl35_red": "testpaths_cyl35_red_d_v0.pkl"}
ACTION_SET = {(1, 1), (-1, -1), (-1, 1), (1, -1), (1.5, 0), (-1.5, 0), (0, 1.5), (0, -1.5)}


def py2_pickle(actions: list, states: list, name: str, flags: list, dtype: str = "f8") -> bytes:
    """``[actions, states, name, flags]`` as Python 2's numpy wrote the real files: protocol 0, latin-1 STRINGs.

    ``dtype`` is the name the file gives numpy's dtype; the array bytes stay float64's.
    """
    memo: dict[tuple[bytes, bytes], int] = {}

    def glob(module: bytes, name: bytes) -> bytes:  # named once, then taken from the memo as the files do
        if (module, name) in memo:
            return b"g%d\n" % memo[module, name]
        memo[module, name] = len(memo)
        return b"c%s\n%s\np%d\n" % (module, name, memo[module, name])

    def string(raw: bytes) -> bytes:
        return b"S" + repr(raw)[1:].encode("latin-1") + b"\n"  # Python 2's repr of a str is Python 3's of bytes

    def array(a: np.ndarray) -> bytes:
        shape = b"".join(b"I%d\n" % n for n in a.shape)
        return (
            glob(b"numpy.core.multiarray", b"_reconstruct")
            + b"("
            + glob(b"numpy", b"ndarray")
            + b"(I0\nt"
            + string(b"b")
            + b"tR(I1\n("
            + shape
            + b"t"
            + glob(b"numpy", b"dtype")
            + b"("
            + string(dtype.encode())
            + b"I0\nI1\ntR(I3\n"
            + string(b"<")
            + b"NNNI-1\nI-1\nI0\ntbI00\n"
            + string(np.ascontiguousarray(a, "<f8").tobytes())
            + b"tb"
        )

    def listing(items: list) -> bytes:
        return b"(l" + b"".join(item + b"a" for item in items)

    return (
        listing(
            [
                listing([array(a) for a in actions]),
                listing([array(s) for s in states]),
                string(name.encode("latin-1")),
                listing([b"I01\n" if f else b"I00\n" for f in flags]),
            ]
        )
        + b"."
    )


@pytest.fixture(scope="module", params=sorted(FILES))
def real(request, t42_real_dir):
    hand = request.param
    return hand, t42_real_dir / FILES[hand], load_t42_testpaths(t42_real_dir / FILES[hand])


def test_real_files_become_six_episodes_per_hand(real):
    hand, _, data = real
    assert data.hand == hand and len(data) == 6
    assert [t.end_reason for t in data] == ["length"] * 4 + ["dropped", "length"]
    assert all(t.hand == hand and t.actuator_angles is None for t in data)
    assert all(795 <= len(t) <= 1518 for t in data)
    for traj in data:
        assert {tuple(a) for a in traj.actions.tolist()} <= ACTION_SET
        loads = traj.states[:, 2:]
        assert np.median(loads[:, 0]) > 0 > np.median(loads[:, 1])  # load1 > 0, load2 < 0 (README)
        assert 0 < np.median(np.abs(loads)) < 280
    for before, after in zip(data, data[1:], strict=False):
        assert after.start_ns == before.start_ns + len(before) * CONTROL_PERIOD_NS + 2 * EPISODE_GAP_NS


def test_both_hands_received_the_same_actions(t42_real_dir):
    blue, red = (load_t42_testpaths(t42_real_dir / FILES[h]) for h in sorted(FILES))
    for a, b in zip(blue, red, strict=True):
        n = min(len(a), len(b))
        assert np.array_equal(a.actions[:n], b.actions[:n])


def test_import_survives_a_bag_round_trip_exactly(real, tmp_path):
    _, source, data = real
    bag = import_t42_to_bag(source, tmp_path / "bag")
    got = read_bag(bag)  # the steps their driver took, in the unit the bag declares: theirs
    assert got.hand == data.hand and len(got) == len(data)
    assert all(a == b for a, b in zip(got, data, strict=True))
    in_ours = read_bag(bag, ACTION_UNIT_RAD)  # the same steps in the suite's unit: 0.155 of the actions
    for ours, theirs in zip(in_ours, data, strict=True):
        np.testing.assert_allclose(ours.actions, theirs.actions * (AUTHORS_ACTION_UNIT_RAD / ACTION_UNIT_RAD),
                                   rtol=1e-6)


class _RunsShell:
    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def test_malicious_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps([_RunsShell(f"touch {marker}")], protocol=4))
    with pytest.raises(PickleFileError, match=r"refused to load global (posix|os|nt)\.system") as err:
        load_t42_testpaths(evil)
    assert str(evil) in str(err.value)
    assert not marker.exists()


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ((["a"], ["s"], "h", [True]), "expected a list"),
        ({"actions": []}, "refused pickle opcode EMPTY_DICT"),
        ([[np.zeros((3, 2))], [np.zeros((3, 13))], "h", [True, False]], "differ in number"),
        ([[np.zeros((3, 2))], [np.zeros((3, 5))], "h", [True]], "at least 13 columns"),
        ([[np.zeros((2, 2))], [np.zeros((4, 13))], "h", [True]], "4 states but only 2 actions"),
        ([[np.zeros((4, 2))], [np.full((3, 13), np.nan)], "h", [True]], "non-finite"),
        (
            [[np.zeros((4, 2))], [np.full((3, 13), 1e300)], "h", [True]],
            "states has a non-finite float32 value at row 0",
        ),
        ([[np.zeros((4, 2))], [np.zeros((3, 13))], 7, [True]], "hand name must be printable text"),
    ],
)
@pytest.mark.filterwarnings("error")  # refused in one line, without an overflow warning before it
def test_unexpected_layouts_are_named(tmp_path, content, match):
    path = tmp_path / "odd.pkl"
    path.write_bytes(pickle.dumps(content, protocol=4))
    with pytest.raises(PickleFileError, match=match):
        load_t42_testpaths(path)


def test_unreadable_files(tmp_path):
    with pytest.raises(PickleFileError, match="cannot be read"):
        load_t42_testpaths(tmp_path / "missing.pkl")
    with pytest.raises(PickleFileError, match="is a directory, not a regular file"):
        load_t42_testpaths(tmp_path)
    (tmp_path / "junk.pkl").write_bytes(b"\x80\x02junk")
    with pytest.raises(PickleFileError, match="not a readable pickle"):
        load_t42_testpaths(tmp_path / "junk.pkl")


def test_reading_reserves_no_more_than_the_file_size(tmp_path):
    """A read of "up to the size limit" reserved 256 MiB for any file; the fuzz run's memory guard caught it."""
    path = tmp_path / "junk.pkl"
    path.write_bytes(b"\x80\x02junk")
    tracemalloc.start()
    try:
        with pytest.raises(PickleFileError, match="not a readable pickle"):
            load_t42_testpaths(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20


def test_synthetic_file_in_the_python2_layout(tmp_path):
    """Runs without the shared data: the real files' own encoding (numpy.core globals, latin-1 strings)."""
    rng = np.random.default_rng(1)
    states = [rng.normal(size=(n, 13)) for n in (6, 9)]
    actions = [rng.choice([-1.0, 1.5], size=(n + 2, 2)) for n in (6, 9)]
    path = tmp_path / "py2.pkl"
    path.write_bytes(py2_pickle(actions, states, "cyl35", [False, True]))
    data = load_t42_testpaths(path)
    assert data.hand == "cyl35" and [len(t) for t in data] == [5, 8]
    assert [t.end_reason for t in data] == ["dropped", "length"]
    np.testing.assert_array_equal(data[1].states, states[1][:, (0, 1, 11, 12)].astype(np.float32))
    np.testing.assert_array_equal(data[0].actions, actions[0][:5].astype(np.float32))


def test_synthetic_file_in_the_real_layout(tmp_path):
    """Runs without the shared data: a Python-3 pickle (numpy._core globals) of the same layout."""
    rng = np.random.default_rng(0)
    states = [rng.normal(size=(n, 13)) for n in (20, 30)]
    actions = [rng.choice([-1.0, 1.0], size=(n + 1, 2)) for n in (20, 30)]
    path = tmp_path / "paths.pkl"
    path.write_bytes(pickle.dumps([actions, states, "handX", [True, False]], protocol=4))
    data = load_t42_testpaths(Path(path))
    assert data.hand == "handX" and [len(t) for t in data] == [19, 29]
    assert [t.end_reason for t in data] == ["length", "dropped"]
    np.testing.assert_array_equal(data[1].states, states[1][:, (0, 1, 11, 12)].astype(np.float32))
    np.testing.assert_array_equal(data[0].actions, actions[0][:19].astype(np.float32))


def test_the_real_files_flagged_stretches(t42_real_dir):
    """Hand B's path 0 lost tracking for its first 199 steps, then jumped 26.3 mm; nothing else is flagged."""
    from t42_transfer.data.quality import FROZEN, JUMP, scan
    from t42_transfer.data.t42_real import quality_lines

    blue, red = (load_t42_testpaths(t42_real_dir / FILES[h]) for h in sorted(FILES))
    assert scan(blue) == {} and quality_lines(blue) == ["none"]
    found = scan(red)
    assert list(found) == [0]
    frozen, jump = found[0]
    assert (frozen.kind, frozen.start, frozen.end) == (FROZEN, 0, 199) and frozen.size > 100
    assert (jump.kind, jump.start, jump.end) == (JUMP, 198, 199) and 26.0 < jump.size < 26.5
    assert quality_lines(red) == [
        "path 0: frozen tracking at steps 0-198 (199 steps, loads ranged 102); jump of 26.3 mm at step 198"
    ]


def test_import_records_the_quality_scan_in_the_bag(t42_real_dir, tmp_path):
    import json

    from t42_transfer.data.bag import bag_info

    bag = import_t42_to_bag(t42_real_dir / FILES["cyl35_red"], tmp_path / "bag")
    quality = json.loads(bag_info(bag)["metadata"]["data_quality"])
    assert quality["flagged_episodes"] == 1 and [f["kind"] for f in quality["findings"]["0"]] == ["frozen", "jump"]


def test_real_file_names_any_public_object():
    from t42_transfer.data.t42_real import REAL_FILES, real_file

    assert real_file("A") == REAL_FILES["A"] == "testpaths_cyl35_d_v0.pkl"
    assert real_file("B", "egg50") == "testpaths_egg50_red_d_v0.pkl"
    with pytest.raises(ValueError, match="the real hands are"):
        real_file("C")
