"""bench/bench_cell.py at its smallest setting: it runs the experiment's own cell code and writes its JSON.

In the slow suite with the other benchmark checks (test_bench_smoke.py says why)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def test_bench_cell_runs_a_tiny_cell_per_method_and_writes_its_results(tmp_path: Path) -> None:
    out = tmp_path / "cell.json"
    cmd = [sys.executable, str(REPO / "bench" / "bench_cell.py"), "--source-episodes", "4", "--source-steps", "40",
           "--target-episodes", "4", "--target-steps", "40", "--amount", "0.5", "--source-epochs", "1",
           "--methods", "direct", "naive_finetune", "--repeats", "1", "--no-split", "--threads", "1", "--out", str(out)]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert set(result["results"]) == {"direct", "naive_finetune"}
    assert all(seconds > 0 for seconds in result["results"].values())
