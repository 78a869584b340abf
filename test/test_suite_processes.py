"""Integration over rclpy: driver, explorer and recorder as separate `t42 node` processes.

The driver runs ten times faster than real time as the graph's clock (sim_time);
the other nodes use_sim_time.  The recorded episodes must be exactly what the simulated hand did: replaying a
bag's applied actions on a fresh hand grasped with the same seed gives the bag's
states bit for bit (float32 on the wire).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from t42_transfer.data.bag import read_bag
from t42_transfer.hand.sim import SimulatedHand

REPO = Path(__file__).resolve().parents[1]
T42 = [sys.executable, "-m", "t42_transfer.cli", "node"]


def _start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    """A node process on the test's domain (the ``ros_domain`` fixture set it in the environment)."""
    with log.open("wb") as out:
        return subprocess.Popen([*T42, *args], cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=out,
                                stderr=subprocess.STDOUT)


def test_driver_explorer_and_recorder_processes_record_what_the_hand_simulated(tmp_path: Path, ros_domain: int) -> None:
    out_dir = tmp_path / "bags"
    logs = {name: tmp_path / f"{name}.log" for name in ("driver", "recorder", "explorer")}
    driver = _start(["mock_driver", "--ros-args", "-p", "rate_factor:=10.0", "-p", "seed:=5", "-p", "sim_time:=true",
                     "-p", "max_command_age_s:=5.0"], logs["driver"])
    recorder = _start(["recorder", "--ros-args", "-p", f"out_dir:={out_dir}", "-p", "mode:=episode",
                       "-p", "use_sim_time:=true"], logs["recorder"])
    try:
        # the explorer's first reset must find the recorder listening: wait for both to run, then discovery
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not all("running on" in logs[n].read_text() for n in ("driver",
                                                                                                    "recorder")):
            time.sleep(0.1)
        time.sleep(1.0)
        explorer = _start(["explorer", "--ros-args", "-p", "episodes:=2", "-p", "steps:=40", "-p", "seed:=11",
                           "-p", "rate_factor:=10.0", "-p", "use_sim_time:=true"], logs["explorer"])
        code = explorer.wait(timeout=120)
        time.sleep(0.5)  # the last messages reach the recorder
    finally:
        for proc in (driver, recorder):
            proc.send_signal(signal.SIGINT)
        codes = [proc.wait(timeout=30) for proc in (driver, recorder)]
    text = {name: log.read_text() for name, log in logs.items()}
    assert code == 0 and codes == [0, 0], text
    applied = re.findall(r"40 actions applied( \(\d+ other steps\))?, complete", text["explorer"])
    assert len(applied) == 2, text["explorer"]

    bags = sorted(out_dir.glob("episode_*"))
    assert all((bag / "metadata.yaml").is_file() for bag in bags)
    episodes = [t for bag in bags for t in read_bag(bag)]  # sim time: stamps exactly one period apart
    explored = [t for t in episodes if np.count_nonzero(t.actions) >= 40]
    assert len(explored) == 2, [(len(t), np.count_nonzero(t.actions)) for t in episodes]
    hand = SimulatedHand("target")
    for k, trajectory in enumerate(explored):
        states = [hand.reset(5 + k + 1)]  # the driver's resets 1 and 2 (its start grasped with seed 5)
        for action in trajectory.actions.astype(np.float64):
            hand.step(action)
            states.append(hand.state)
        np.testing.assert_array_equal(trajectory.states, np.asarray(states, np.float32))
