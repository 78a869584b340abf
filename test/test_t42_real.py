"""t42_real: the public real-hand pickles, read safely and carried into bags unchanged."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from t42_transfer.conventions import CONTROL_PERIOD_NS
from t42_transfer.data.bag_io import EPISODE_GAP_NS, read_bag
from t42_transfer.data.errors import PickleFileError
from t42_transfer.data.t42_real import import_t42_to_bag, load_t42_testpaths

FILES = {"cyl35": "testpaths_cyl35_d_v0.pkl", "cyl35_red": "testpaths_cyl35_red_d_v0.pkl"}
ACTION_SET = {(1, 1), (-1, -1), (-1, 1), (1, -1), (1.5, 0), (-1.5, 0), (0, 1.5), (0, -1.5)}


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
    for before, after in zip(data, data[1:]):
        assert after.start_ns == before.start_ns + len(before) * CONTROL_PERIOD_NS + 2 * EPISODE_GAP_NS


def test_both_hands_received_the_same_actions(t42_real_dir):
    blue, red = (load_t42_testpaths(t42_real_dir / FILES[h]) for h in sorted(FILES))
    for a, b in zip(blue, red):
        n = min(len(a), len(b))
        assert np.array_equal(a.actions[:n], b.actions[:n])


def test_import_survives_a_bag_round_trip_exactly(real, tmp_path):
    _, source, data = real
    bag = import_t42_to_bag(source, tmp_path / "bag")
    got = read_bag(bag)
    assert got.hand == data.hand and len(got) == len(data)
    assert all(a == b for a, b in zip(got, data))


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
        ({"actions": []}, "expected a list"),
        ([[np.zeros((3, 2))], [np.zeros((3, 13))], "h", [True, False]], "differ in number"),
        ([[np.zeros((3, 2))], [np.zeros((3, 5))], "h", [True]], "at least 13 columns"),
        ([[np.zeros((2, 2))], [np.zeros((4, 13))], "h", [True]], "4 states but only 2 actions"),
        ([[np.zeros((4, 2))], [np.full((3, 13), np.nan)], "h", [True]], "non-finite"),
        ([[np.zeros((4, 2))], [np.zeros((3, 13))], 7, [True]], "hand name must be a string"),
    ],
)
def test_unexpected_layouts_are_named(tmp_path, content, match):
    path = tmp_path / "odd.pkl"
    path.write_bytes(pickle.dumps(content, protocol=4))
    with pytest.raises(PickleFileError, match=match):
        load_t42_testpaths(path)


def test_unreadable_files(tmp_path):
    with pytest.raises(PickleFileError, match="cannot be read"):
        load_t42_testpaths(tmp_path / "missing.pkl")
    (tmp_path / "junk.pkl").write_bytes(b"\x80\x02junk")
    with pytest.raises(PickleFileError, match="not a readable pickle"):
        load_t42_testpaths(tmp_path / "junk.pkl")


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
