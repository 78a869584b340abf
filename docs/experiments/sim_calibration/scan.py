"""How the simulated source hand's held-move rates change with its step per action unit, its spool radius and its
tendon's moment arms.

For each setting ``UNIT_RAD,SPOOL_MM[,MOMENT_ARM_SCALE[,START_Y_MM]]``, real hand A's six test-path action sequences are
replayed open loop on the simulated source hand (as ``t42 sim compare-real`` does), and each move's rates over
the first ``--window`` steps of its runs are set beside the real hands' (``hand/realism.py``). A scan, not a
calibration: the unit is written into the simulator module for this process only (the suite's wire unit,
``ACTION_UNIT_RAD``, is what the mock and Dynamixel drivers use), and the grasp routine keeps its servo increment
per step in radians.

    .venv/bin/python docs/experiments/sim_calibration/scan.py 0.025,20 0.0039,20 0.0039,8 \
        --out docs/experiments/sim_calibration/scan.json
    .venv/bin/python docs/experiments/sim_calibration/scan.py 0.0039,20,2 0.0039,20,4 0.0039,10,2 0.0039,10,4 \
        --out docs/experiments/sim_calibration/scan_moment_arms.json
    .venv/bin/python docs/experiments/sim_calibration/scan.py 0.0039,20,1,110 0.0039,10,4,110 0.0039,10,4,125 \
        0.0039,10,2,110 --out docs/experiments/sim_calibration/scan_placement.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

import t42_transfer.hand.sim as simulator
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import run_episode
from t42_transfer.hand.params import variant
from t42_transfer.hand.realism import held_move_onsets, held_move_rates, rows_as_dicts

GRASP_STEP_RAD = simulator.GRASP_INCREMENT * simulator.ACTION_UNIT_RAD
START_Y_MM = simulator.OBJECT_START_MM[1]


def run_setting(real: TrajectorySet, unit_rad: float, spool_mm: float, window: int, arm_scale: float = 1.0,
                start_y_mm: float = START_Y_MM) -> dict:
    simulator.ACTION_UNIT_RAD = unit_rad
    simulator.OBJECT_START_MM = (simulator.OBJECT_START_MM[0], start_y_mm)
    simulator.GRASP_INCREMENT = GRASP_STEP_RAD / unit_rad
    simulator.GRASP_MAX_STEPS = 4000
    base = variant("source")
    fingers = {side: dataclasses.replace(f, r_proximal_mm=f.r_proximal_mm * arm_scale,
                                         r_distal_mm=f.r_distal_mm * arm_scale)
               for side, f in (("left", base.left), ("right", base.right))}
    hand = simulator.SimulatedHand(dataclasses.replace(base, spool_radius_mm=spool_mm, **fingers))
    try:
        replayed = TrajectorySet(run_episode(hand, t.actions, seed) for seed, t in enumerate(real))
    except simulator.GraspFailed as err:
        return {"unit_rad": unit_rad, "spool_mm": spool_mm, "moment_arm_scale": arm_scale,
                "start_y_mm": start_y_mm, "failed": str(err)}
    return {
        "unit_rad": unit_rad, "spool_mm": spool_mm, "moment_arm_scale": arm_scale, "start_y_mm": start_y_mm,
        "path_steps": [len(t) for t in replayed], "end_reasons": [t.end_reason for t in replayed],
        "grasp_state": [round(float(v), 1) for v in replayed[0].states[0]],
        "held_moves": rows_as_dicts(held_move_rates("sim source", replayed, window)),
        "onsets": rows_as_dicts(held_move_onsets("sim source", replayed)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("settings", nargs="+", help="UNIT_RAD,SPOOL_MM[,MOMENT_ARM_SCALE[,START_Y_MM]] (the tendon's "
                                                    "moment arms at both joints scaled, default 1; where the object "
                                                    "is placed before the grasp, default the simulator's)")
    parser.add_argument("--window", type=int, default=30)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    folder = real_data_dir()
    real = {name: load_t42_testpaths(folder / file) for name, file in REAL_FILES.items()}
    speeds: dict[tuple, list[float]] = {}
    for name, data in real.items():
        for r in held_move_rates(f"real {name}", data, args.window):
            speeds.setdefault(r.action, []).append(r.speed_mm_per_step)
    reference = {move: float(np.mean(v)) for move, v in speeds.items()}
    moving: dict[tuple, list[float]] = {}
    onset: dict[tuple, list[float]] = {}
    for name, data in real.items():
        for o in held_move_onsets(f"real {name}", data):
            moving.setdefault(o.action, []).append(o.moving_speed_mm_per_step)
            onset.setdefault(o.action, []).append(o.onset_steps)
    moving_reference = {move: float(np.nanmean(v)) for move, v in moving.items()}
    real_onset = {move: float(np.nanmean(v)) for move, v in onset.items()}
    rows = []
    for setting in args.settings:
        unit, spool, *arm_and_start = (float(v) for v in setting.split(","))
        rows.append(run_setting(real["A"], unit, spool, args.window, *arm_and_start))
    for row in rows:
        if "failed" in row:
            print(f"unit {row['unit_rad']} rad, spool {row['spool_mm']} mm, moment arms x{row['moment_arm_scale']:g}, "
                  f"object placed at y {row['start_y_mm']:g} mm: {row['failed']}")
            continue
        print(f"unit {row['unit_rad']} rad, spool {row['spool_mm']} mm, moment arms x{row['moment_arm_scale']:g}, "
              f"object placed at y {row['start_y_mm']:g} mm: path steps {row['path_steps']} "
              f"(real {[len(t) for t in real['A']]}), grasp at {row['grasp_state']}")
        for m in row["held_moves"]:
            move = tuple(m["action"])
            ratio = m["speed_mm_per_step"] / reference[move]
            print(f"  {list(move)}: {m['speed_mm_per_step']:.3f} mm/step ({ratio:.1f}x real), "
                  f"loads {m['load1_per_step']:+.2f} {m['load2_per_step']:+.2f} /step ({m['runs']} runs)")
        for o in row["onsets"]:
            move, steps, speed = tuple(o["action"]), o["onset_steps"], o["moving_speed_mm_per_step"]
            waited = "never moved 2 mm" if steps is None else f"{steps:g} steps to move 2 mm"
            then = "" if speed is None else f", then {speed:.3f} mm/step ({speed / moving_reference[move]:.1f}x real)"
            print(f"  {list(move)}: {waited} (real {real_onset[move]:g}){then}")
    real_speeds = {str(list(move)): speed for move, speed in reference.items()}
    real_moving = {str(list(move)): None if np.isnan(speed) else speed for move, speed in moving_reference.items()}
    summary = {"window": args.window, "real_speed_mm_per_step": real_speeds,
               "real_moving_speed_mm_per_step": real_moving,
               "real_onset_steps": {str(list(move)): steps for move, steps in real_onset.items()}, "settings": rows}
    args.out.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
