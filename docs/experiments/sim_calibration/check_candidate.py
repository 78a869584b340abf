"""A fitted candidate hand against both real hands on everything `t42 sim compare-real` compares.

The fit scores held-move speeds, waits and load rates on hand A. This replays the six real paths at the
authors' step on the candidate (a JSON object of fit.py's parameters, e.g. friction_centre.json) and prints the
side-by-side table (spans, steps, load ranges, drops) and the held moves' waits and moving speeds, real hands
first. The unit is written into the simulator module for this process only, as in scan.py.

    .venv/bin/python docs/experiments/sim_calibration/check_candidate.py \
        docs/experiments/sim_calibration/friction_centre.json --out docs/experiments/sim_calibration/check_centre.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import fit  # noqa: E402  (this folder's fit.py: the candidate's hand, as the fit built it)

import t42_transfer.hand.sim as simulator  # noqa: E402
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir  # noqa: E402
from t42_transfer.data.trajectory import TrajectorySet  # noqa: E402
from t42_transfer.hand import realism  # noqa: E402
from t42_transfer.hand.collect import run_episode  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("candidate", type=Path, help="JSON object of fit.py's parameters")
    parser.add_argument("--unit", type=float, default=0.0039, help="rad per action unit per step (authors' 0.0039)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    candidate = {k: float(v) for k, v in json.loads(args.candidate.read_text()).items()}
    simulator.ACTION_UNIT_RAD, simulator.GRASP_INCREMENT = args.unit, fit.GRASP_STEP_RAD / args.unit
    simulator.GRASP_MAX_STEPS = 4000
    simulator.LOAD_UNIT_NM = fit.LOAD_UNIT_NM * candidate.get("load_unit_scale", 1.0)
    hand = simulator.SimulatedHand(fit.hand_params(candidate))
    real = {name: load_t42_testpaths(real_data_dir() / file) for name, file in REAL_FILES.items()}
    replayed = TrajectorySet(run_episode(hand, t.actions, seed) for seed, t in enumerate(real["A"]))
    named = {**{f"real {k}": v for k, v in real.items()}, f"candidate {args.candidate.stem}": replayed}
    rows = [realism.summarise(name, data) for name, data in named.items()]
    onsets = [r for name, data in named.items() for r in realism.held_move_onsets(name, data)]
    print(realism.markdown_table(rows))
    print(realism.held_onsets_table(onsets))
    summary = {"candidate": candidate, "unit_rad": args.unit, "paths": realism.rows_as_dicts(rows),
               "onsets": realism.rows_as_dicts(onsets)}
    args.out.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
