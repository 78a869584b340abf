"""The explorer node drives the mock driver through whole random episodes (in-process bus, fake clock)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from t42_transfer.data.bag_io import read_bag
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.nodes.explorer import Explorer, ExplorerParams
from t42_transfer.nodes.mock_driver import MockDriver, MockDriverParams
from t42_transfer.nodes.recorder import Recorder, RecorderParams
from t42_transfer.ros.inprocess import FakeClock, InProcessBus, InProcessTransport


class Suite:
    """Driver, recorder (episode mode) and explorer on one bus, advanced one driver period at a time."""

    def __init__(self, out_dir: Path, driver: MockDriverParams, explorer: ExplorerParams,
                 idle_ticks: int = 0) -> None:
        self.clock = FakeClock(1_000_000_000)
        self.bus = InProcessBus(clock=self.clock)
        self.nodes = [InProcessTransport(self.bus, name) for name in ("mock_driver", "recorder", "explorer")]
        self.driver = MockDriver(self.nodes[0], driver)
        self.recorder = Recorder(self.nodes[1], RecorderParams(out_dir=out_dir, mode="episode",
                                                                start_immediately=not explorer.record_start_service))
        for _ in range(idle_ticks):  # the hand idles before the explorer starts
            self.clock.advance(self.driver.params.period_s)
            self.nodes[0].spin_once()
            self.nodes[1].spin_once()
        self.explorer = Explorer(self.nodes[2], explorer)

    def run(self, max_ticks: int) -> int:
        for tick in range(max_ticks):
            if self.explorer.finished:
                return tick
            self.clock.advance(self.driver.params.period_s)
            for node in self.nodes:
                node.spin_once()
        return max_ticks


def replay(hand: SimulatedHand, seed: int, actions: np.ndarray) -> np.ndarray:
    states = [hand.reset(seed)]
    for action in actions:
        hand.step(action)
        states.append(hand.state)
    return np.asarray(states, np.float32)


def test_explorer_episodes_become_one_bag_each_equal_to_the_simulation(tmp_path: Path) -> None:
    suite = Suite(tmp_path, MockDriverParams(hand="target", seed=7), ExplorerParams(episodes=2, steps=30, seed=3))
    ticks = suite.run(400)
    assert suite.explorer.finished, f"not finished after {ticks} ticks: {suite.explorer.completed}"
    suite.recorder.close()
    assert [e["end"] for e in suite.explorer.completed] == ["complete", "complete"]
    assert all(e["applied"] == 30 for e in suite.explorer.completed)

    episodes = [t for bag in suite.recorder.bags for t in read_bag(bag)]
    explored = [t for t in episodes if np.abs(t.actions).sum() > 0]
    assert len(explored) == 2, [len(t) for t in episodes]
    hand = SimulatedHand("target")
    for k, trajectory in enumerate(explored):
        # The driver's reset k+1 (its construction grasped episode 0) used seed 7 + k + 1.
        expected = replay(hand, 7 + k + 1, trajectory.actions.astype(np.float64))
        np.testing.assert_array_equal(trajectory.states, expected)
        assert len(trajectory.actions) >= 30  # the 30 random actions, maybe a zero step around them
        sampled = ExplorerParams(hold_max=5).limit
        assert np.abs(trajectory.actions).max() <= sampled + 1e-6


def test_explorer_ends_an_episode_on_a_drop_and_goes_on(tmp_path: Path) -> None:
    suite = Suite(tmp_path, MockDriverParams(hand="target", seed=1),
                  ExplorerParams(episodes=2, steps=400, hold_max=40, limit=1.5, seed=0))
    suite.run(2000)
    suite.recorder.close()
    assert suite.explorer.finished
    ends = [e["end"] for e in suite.explorer.completed]
    assert len(ends) == 2
    assert any(end in ("dropped", "lost_contact", "overload") for end in ends), ends


def test_explorer_records_only_its_episodes_when_it_drives_the_recorder(tmp_path: Path) -> None:
    params = ExplorerParams(episodes=2, steps=20, record_start_service="/recorder/start",
                            record_stop_service="/recorder/stop")
    suite = Suite(tmp_path, MockDriverParams(hand="target", seed=2), params, idle_ticks=50)
    suite.run(300)
    assert suite.explorer.finished and not suite.recorder.recording
    lengths = [len(read_bag(bag)[0]) for bag in suite.recorder.bags]
    assert len(lengths) == 2 and all(20 <= n <= 24 for n in lengths), lengths  # no 50-step idle bag


@pytest.mark.parametrize("field, value", [("episodes", 0), ("steps", -1), ("limit", 2.0), ("rate_factor", 0.0),
                                          ("trajectory_topic", "no_slash"),
                                          ("record_stop_service", "stop")])
def test_bad_parameters_are_refused(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field.split("_")[0]):
        ExplorerParams(**{field: value})
