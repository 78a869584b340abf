"""Benchmark: latencies of the online suite of rclpy nodes, from a run of ``t42 demo``.

Writes bench/results/suite_latency.json with the middleware the demo ran on (its
``demo.json`` ``middleware``: rclpy's RMW implementation).  Two figures, each
against a baseline measured in the same run:

* transfer to model ready (``service_call_to_model_ready``, named when it was a service): wall time of the
  ``/t42/transfer`` action goal (until its result, sent after the model was saved and announced) against the
  server's own elapsed time for the transfer (its last diagnostics ``elapsed_s``);
* goal to plan result: wall time from sending a ``/t42/reach`` goal to receiving its
  plan result on ``/t42/plan_result`` (published after the JointTrajectory and the Path)
  against the planner's own planning time.

The machine's load average is recorded before and after: on a shared machine the
figures vary with it.

    .venv/bin/python bench/bench_suite_latency.py            # the quick demo
    .venv/bin/python bench/bench_suite_latency.py --full     # the full demo
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from machine import machine_info  # noqa: E402

from t42_transfer.demo import run_demo  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "suite_latency.json"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the full demo instead of --quick")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    machine = machine_info()
    with tempfile.TemporaryDirectory() as tmp:
        log = io.StringIO()
        with contextlib.redirect_stdout(log):
            code = run_demo(Path(tmp), quick=not args.full, workers=1)
        if code != 0:
            print(log.getvalue())
            return code
        (run_dir,) = [p for p in Path(tmp).iterdir() if (p / "demo.json").is_file()]
        summary = json.loads((run_dir / "demo.json").read_text())
    transfer = summary["transfer"]
    server_s = float(transfer["diagnostics"]["elapsed_s"])
    goals = [g for g in summary["goals"] if g["accepted"]]
    goal_s = [g["goal_to_result_s"] for g in goals]
    plan_s = [g["planning_time_s"] for g in goals]
    result = {
        "command": ".venv/bin/python bench/bench_suite_latency.py" + (" --full" if args.full else ""),
        "machine": machine,
        "load_average_after": os.getloadavg(),
        "demo": summary["mode"],
        "middleware": summary["middleware"],
        "service_call_to_model_ready": {
            "call_s": transfer["seconds"], "server_elapsed_s": server_s,
            "ratio_call_over_server": transfer["seconds"] / server_s if server_s > 0 else None,
        },
        "goal_to_plan_result": {
            "goals": len(goals),
            "median_s": statistics.median(goal_s), "max_s": max(goal_s),
            "planning_median_s": statistics.median(plan_s),
            "ratio_median_over_planning": statistics.median(goal_s) / statistics.median(plan_s),
        },
        "whole_demo_s": summary["seconds"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
