"""End to end: `t42 demo --quick`, the README's main command, as separate rclpy node processes.

Checks what a user would: the transfer service answered with a model, a model file
appeared and was announced, the planner published valid sequences that the driver
executed, and the executed final positions are closer to the goals than the starts.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from t42_transfer.cli import main
from t42_transfer.data.bag_io import read_bag
from t42_transfer.models.checkpoint import load_model


def test_demo_quick_runs_the_whole_story(tmp_path: Path, capsys: pytest.CaptureFixture[str], ros_domain: int) -> None:
    assert main(["demo", "--quick", "--out", str(tmp_path), "--workers", "1"]) == 0, capsys.readouterr()
    out = capsys.readouterr().out
    (run_dir,) = [p for p in tmp_path.iterdir() if p.is_dir() and (p / "demo.json").is_file()]
    summary = json.loads((run_dir / "demo.json").read_text())

    # the target data came through topics: one bag per explored episode, readable
    bags = sorted((run_dir / "bags").glob("episode_*"))
    assert len(bags) == summary["exploration"]["episodes"] == summary["size"]["target_episodes"]
    assert all(len(read_bag(bag)) == 1 for bag in bags)

    # the service answered with a model that exists and loads
    transfer = summary["transfer"]
    assert transfer["success"] and "divergence" in transfer["message"] and "MSE" in transfer["message"]
    models = sorted((run_dir / "models").glob("transferred_*.safetensors"))
    assert models and str(models[-1]) in transfer["message"]
    model, meta = load_model(models[-1])
    assert meta["method"] == "cumulative_residual" and "workspace" in meta.get("extra", {})

    # every goal was planned and executed; the planned paths are valid and the hand got closer
    goals = summary["goals"]
    assert len(goals) == len(summary["size"]["goal_steps"])
    executed = [g for g in goals if g["accepted"]]
    assert len(executed) >= len(goals) - 1, goals
    for goal in executed:
        planned = np.asarray(goal["planned"])
        assert planned.shape == (goal["horizon"] + 1, 2) and np.all(np.isfinite(planned))
        assert goal["end"] == "completed" and len(goal["executed"]) >= goal["horizon"]
        start_error = np.linalg.norm(np.subtract(goal["goal_mm"], goal["start_mm"]))
        assert goal["error_mm"] < start_error, goal
    assert all(code == 0 for name, code in summary["exit_codes"].items()), summary["exit_codes"]
    assert (run_dir / "paths.png").stat().st_size > 10_000
    report = (run_dir / "report.md").read_text()
    assert "## Peg-in-hole" in report
    assert summary["middleware"] == "rmw_fastrtps_cpp" and "rmw_fastrtps_cpp" in report  # what it actually used
    assert summary["discovery"] == "LOCALHOST"
    assert "[5/5] peg-in-hole" in out and "report:" in out


def test_an_unexpected_error_stops_every_node_process(tmp_path: Path, ros_domain: int,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    from t42_transfer import demo

    suites: list = []

    class Recorded(demo._Suite):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            suites.append(self)

    def broken() -> type:
        raise KeyError("a bug after the suite started")

    monkeypatch.setattr(demo, "_Suite", Recorded)
    monkeypatch.setattr(demo, "_operator_class", broken)
    with pytest.raises(KeyError):
        demo.run_demo(tmp_path, quick=True, workers=1)
    (suite,) = suites
    children = suite.supervisor.children
    alive = [c.name for c in children if c.proc.poll() is None]
    for child in children:  # never leave one behind, even when the check fails
        if child.proc.poll() is None:
            child.proc.kill()
    assert len(children) == len(demo.SUITE_NODES) and not alive, alive
