"""The explorer node drives the mock driver through whole random episodes (real rclpy, in-process)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from msg_adapters import applied_action, names
from t42_transfer.conventions import ACTION_UNIT_RAD, AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.bag import read_bag
from t42_transfer.data.trajectory import Trajectory
from t42_transfer.hand.collect import RandomPolicy
from t42_transfer.hand.sim import SimulatedHand
from t42_transfer.nodes.explorer import Explorer
from t42_transfer.nodes.mock_driver import MockDriver
from t42_transfer.nodes.recorder import Recorder
from t42_transfer.ros.qos import profile

RATE = 10.0
"""The driver steps 10x faster than real time: a 30-step episode takes 0.3 s."""
DRIVER = {"hand": "target", "rate_factor": RATE, "max_command_age_s": 30.0}
EXPLORER = {"rate_factor": RATE, "timeout_margin_s": 30.0}
"""A loaded test machine may deliver a trajectory late or step slowly: staleness and timeouts are not under test."""


class Watcher:
    """The test's node: every applied action and driver status, in arrival order."""

    def __init__(self, ros: Any, namespace: str = "") -> None:
        self.node = ros.node("tester", namespace=namespace)
        self.actions: list[np.ndarray] = []
        self.statuses: list[str] = []
        self.node.create_subscription(JointState, names.APPLIED_ACTION,
                                      lambda m: self.actions.append(applied_action(m)), 1000)
        self.node.create_subscription(String, names.HAND_STATUS, lambda m: self.statuses.append(m.data),
                                      profile(names.LATCHED))

    def explored(self) -> np.ndarray:
        """The non-zero applied actions (the driver applies zeros while no trajectory runs)."""
        acts = np.asarray(self.actions).reshape(-1, 2)
        return acts[np.abs(acts).sum(axis=1) > 0]


def sampled(seed: int, steps: int, hold_max: int = 5, limit: float = 1.0) -> np.ndarray:
    return RandomPolicy(hold_max=hold_max, limit=limit).sample(np.random.default_rng(seed), steps)


def test_episodes_run_through_the_driver_with_the_sampled_actions(ros) -> None:
    """In the unit of the model the data are for: the authors' actions step the actuators 0.155 of the suite's."""
    watcher = Watcher(ros)
    driver = ros.add(MockDriver, {**DRIVER, "seed": 7})
    explorer = ros.add(Explorer, {**EXPLORER, "episodes": 2, "steps": 30, "seed": 3,
                                  "action_unit_rad": AUTHORS_ACTION_UNIT_RAD})
    assert ros.spin_until(lambda: explorer.finished, 90.0), f"not finished: {explorer.completed}"
    assert explorer.completed == [{"episode": 1, "applied": 30, "end": "complete"},
                                  {"episode": 2, "applied": 30, "end": "complete"}]
    assert driver.episode == 2, "one reset per episode after the driver's own first grasp"
    # Exactly the sampled actions, in order: each trajectory started from the new grasp's angles.
    expected = np.vstack([sampled(3, 30), sampled(4, 30)]) * (AUTHORS_ACTION_UNIT_RAD / ACTION_UNIT_RAD)
    np.testing.assert_allclose(watcher.explored(), expected, atol=1e-6)  # (applied actions are in the suite's unit)
    events = [s.split(":")[0] for s in watcher.statuses]
    assert events.count("trajectory_done") == 2 and events.count("reset") >= 2
    assert events.index("reset", 1) < events.index("trajectory_done"), events
    ros.spin_for(0.3)
    assert len(watcher.explored()) == 60, "nothing is sent after the last episode"


def replays(trajectory: Trajectory, seed: int) -> bool:
    """Whether the recorded states are the simulation's: grasp ``seed``, hold (zero actions), the recorded actions.

    The bag may begin a few held steps after the grasp (the recorder starts after the first reset).
    """
    hand = SimulatedHand("target")
    state = hand.reset(seed)
    for _ in range(100):
        if np.array_equal(np.float32(state), trajectory.states[0]):
            break
        hand.step(np.zeros(2))
        state = hand.state
    else:
        return False
    states = [state]
    for action in trajectory.actions.astype(np.float64):
        hand.step(action)
        states.append(hand.state)
    return np.array_equal(np.asarray(states, np.float32), trajectory.states)


def test_recorded_episodes_are_one_bag_each_and_replay_the_simulation(ros, tmp_path: Path) -> None:
    """Driver (the graph's clock), recorder in episode mode and explorer: the explorer's episodes, nothing else."""
    sim = {"use_sim_time": True}
    driver = ros.add(MockDriver, {**DRIVER, "seed": 7, "sim_time": True, "max_command_age_s": 300.0})
    recorder = ros.add(Recorder, {"out_dir": str(tmp_path), "mode": "episode", "start_immediately": False, **sim})
    ros.spin_for(0.5)  # the hand idles before the explorer starts: not recorded
    explorer = ros.add(Explorer, {**EXPLORER, "episodes": 2, "steps": 20, "seed": 3, **sim,
                                  "record_start_service": "recorder/start", "record_stop_service": "recorder/stop"})
    assert ros.spin_until(lambda: explorer.finished, 90.0), f"not finished: {explorer.completed}"
    assert ros.spin_until(lambda: not recorder.recording and not recorder.waiting_changes, 10.0)
    assert [e["end"] for e in explorer.completed] == ["complete", "complete"] and driver.episode == 2
    assert len(recorder.bags) == 2, recorder.bags
    for k, bag in enumerate(recorder.bags):
        (episode,) = read_bag(bag)
        moved = episode.actions[np.abs(episode.actions).sum(axis=1) > 0]
        np.testing.assert_allclose(moved, sampled(3 + k, 20), atol=1e-6)
        assert replays(episode, 7 + k + 1), f"{bag.name} is not the simulated episode"


def test_an_episode_ends_on_a_drop_and_the_next_one_runs(ros) -> None:
    driver = ros.add(MockDriver, {**DRIVER, "seed": 1, "rate_factor": 20.0})
    explorer = ros.add(Explorer, {**EXPLORER, "episodes": 2, "steps": 400, "hold_max": 40, "limit": 1.5,
                                  "rate_factor": 20.0})
    assert ros.spin_until(lambda: explorer.finished, 90.0), f"not finished: {explorer.completed}"
    ends = [e["end"] for e in explorer.completed]
    assert len(ends) == 2 and driver.episode == 2
    assert any(end in ("dropped", "lost_contact", "overload") for end in ends), ends
    dropped = next(e for e in explorer.completed if e["end"] != "complete")
    assert dropped["applied"] < 400


def test_it_records_only_its_episodes_under_a_namespace(ros) -> None:
    """Recorder services resolved in the node's namespace: start after the first reset, stop after the last."""
    watcher = Watcher(ros, namespace="/left")
    calls: list[tuple[str, int, int, bool]] = []
    driver = ros.add(MockDriver, {**DRIVER, "seed": 2}, namespace="/left")
    explorer: Explorer | None = None

    def service(name: str):
        def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            calls.append((name, driver.episode, len(watcher.explored()), explorer.finished))
            response.success, response.message = True, f"{name} ok"
            return response
        return answer

    for name in ("start", "stop"):
        watcher.node.create_service(Trigger, f"recorder/{name}", service(name))
    ros.spin_for(0.5)  # the hand idles before the explorer starts
    explorer = ros.add(Explorer, {**EXPLORER, "episodes": 2, "steps": 20,
                                  "record_start_service": "recorder/start",
                                  "record_stop_service": "recorder/stop"}, namespace="/left")
    assert ros.spin_until(lambda: explorer.finished, 90.0), f"not finished: {explorer.completed}"
    assert [e["end"] for e in explorer.completed] == ["complete", "complete"]
    # start: after the explorer's first reset, before any explored action; stop: after all, before finishing.
    assert calls == [("start", 1, 0, False), ("stop", 2, 40, False)], calls
    assert explorer.get_fully_qualified_name() == "/left/explorer"


def test_an_absent_recorder_and_failed_resets_do_not_stop_exploring(ros) -> None:
    tester = ros.node("tester")
    resets: list[int] = []

    def refuse(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        resets.append(1)
        response.success, response.message = False, "grasp failed: nothing to hold"
        return response

    tester.create_service(Trigger, names.HAND_RESET, refuse)
    explorer = ros.add(Explorer, {"episodes": 2, "record_start_service": "nobody/start",
                                  "record_stop_service": "nobody/stop"})
    explorer.SERVICE_TIMEOUT_S = 0.3
    assert ros.spin_until(lambda: explorer.finished, 10.0), explorer.completed
    assert explorer.completed == [{"episode": 1, "applied": 0, "end": "reset_failed"},
                                  {"episode": 2, "applied": 0, "end": "reset_failed"}]
    assert len(resets) == 2


def test_without_a_driver_it_says_what_it_waits_for(ros, monkeypatch: pytest.MonkeyPatch) -> None:
    """No hand/reset service anywhere: the explorer waits (a driver may come) and says so on /rosout."""
    from ros_rig import Rosout

    from t42_transfer.nodes import explorer as module

    monkeypatch.setattr(module, "WAITING_NOTE_S", 0.3)
    log = Rosout(ros, "explorer")
    explorer = ros.add(Explorer, {"episodes": 1})

    def notes() -> list[str]:
        return [m.msg for m in log.lines if m.name.endswith("explorer") and "waiting" in m.msg]

    assert ros.spin_until(lambda: len(notes()) >= 2, 5.0), [m.msg for m in log.lines]
    assert f"for /{names.HAND_RESET} (is the hand's driver running" in notes()[0]
    assert not explorer.finished and explorer.completed == []


@pytest.mark.parametrize("field, value", [
    ("episodes", 0), ("steps", -1), ("steps", 10_001), ("hold_max", 0), ("limit", 2.0), ("limit", 0.0),
    ("rate_factor", 0.0), ("action_unit_rad", 0.0), ("action_unit_rad", 0.25), ("action_unit_rad", 0.05),
    ("seed", -1), ("record_stop_service", "1stop"), ("record_start_service", "with space"),
])
def test_bad_parameters_are_refused_at_start(ros, field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        ros.add(Explorer, {field: value})


def test_parameters_change_at_run_time_with_a_reason_when_refused(ros) -> None:
    explorer = ros.add(Explorer, {"episodes": 3})
    explorer.close()  # no driver here: only the parameters are looked at
    ok = explorer.set_parameters([Parameter("steps", value=10), Parameter("episodes", value=1)])
    assert all(r.successful for r in ok) and (explorer.params.steps, explorer.params.episodes) == (10, 1)
    limit = explorer.set_parameters([Parameter("limit", value=0.0)])[0]
    assert not limit.successful and "limit" in limit.reason and explorer.params.limit == 1.0
    hold = explorer.set_parameters([Parameter("hold_max", value=0)])[0]
    assert not hold.successful and explorer.params.hold_max == 5
    fixed = explorer.set_parameters([Parameter("record_start_service", value="recorder/start")])[0]
    assert not fixed.successful and "read-only" in fixed.reason and explorer.params.record_start_service == ""
