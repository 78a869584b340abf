"""Does dry friction in the transmission give the simulated hand the real hands' wait before the object moves?

The real hands stand still for 35-73 steps after each change of move, then move the object 0.07-0.13 mm a
step (``realism.held_move_onsets``). A tendon routed through printed channels, or a flexure's hysteresis,
holds a finger until the change of tension passes its friction: a dead band. This replays real hand A's six
paths on the source hand at the authors' step with, per setting ``TENDON_N,JOINT_NM[,SPOOL_MM[,ARM_SCALE]]``,
dry friction (``HandParams.tendon_friction_n``, ``joint_friction_nm``: MuJoCo's ``frictionloss``, made
to hold, see ``hand/mjcf.py``) on each finger's tendon (N) and on each finger joint (N m), the spool radius
(mm, default the hand's) and a scale of the tendon's moment arms at both joints (default 1). The unit is
written into the simulator module for this process only, as in scan.py. The grasp runs with the
friction, so a setting can change where the object is held.

    .venv/bin/python docs/experiments/sim_calibration/friction.py 0,0 2,0 5,0 10,0 0,0.02 0,0.05 \
        --out docs/experiments/sim_calibration/friction.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import t42_transfer.hand.sim as simulator
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import run_episode
from t42_transfer.hand.params import variant
from t42_transfer.hand.realism import held_move_onsets, held_move_rates, rows_as_dicts

GRASP_STEP_RAD = simulator.GRASP_INCREMENT * simulator.ACTION_UNIT_RAD


def run_setting(real: TrajectorySet, tendon_n: float, joint_nm: float, spool_mm: float | None = None,
                arm_scale: float = 1.0) -> dict:
    base = variant("source")
    fingers = {side: dataclasses.replace(f, r_proximal_mm=f.r_proximal_mm * arm_scale,
                                         r_distal_mm=f.r_distal_mm * arm_scale)
               for side, f in (("left", base.left), ("right", base.right))}
    params = dataclasses.replace(base, spool_radius_mm=spool_mm or base.spool_radius_mm, tendon_friction_n=tendon_n,
                                 joint_friction_nm=joint_nm, **fingers)
    hand = simulator.SimulatedHand(params)
    setting = {"tendon_frictionloss_n": tendon_n, "joint_frictionloss_nm": joint_nm,
               "spool_mm": params.spool_radius_mm, "moment_arm_scale": arm_scale}
    try:
        replayed = TrajectorySet(run_episode(hand, t.actions, seed) for seed, t in enumerate(real))
    except simulator.GraspFailed as err:
        return {**setting, "failed": str(err)}
    return {
        **setting, "path_steps": [len(t) for t in replayed], "end_reasons": [t.end_reason for t in replayed],
        "grasp_state": [round(float(v), 1) for v in replayed[0].states[0]],
        "held_moves": rows_as_dicts(held_move_rates("sim source", replayed, 30)),
        "onsets": rows_as_dicts(held_move_onsets("sim source", replayed)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("settings", nargs="+", help="TENDON_N,JOINT_NM[,SPOOL_MM[,ARM_SCALE]]")
    parser.add_argument("--unit", type=float, default=0.0039, help="rad per action unit per step (authors' 0.0039)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    real = load_t42_testpaths(real_data_dir() / REAL_FILES["A"])
    real_onsets = {o.action: o for o in held_move_onsets("real A", real)}
    real_rates = {r.action: r for r in held_move_rates("real A", real, 30)}
    simulator.ACTION_UNIT_RAD, simulator.GRASP_INCREMENT = args.unit, GRASP_STEP_RAD / args.unit
    simulator.GRASP_MAX_STEPS = 4000
    rows = []
    for text in args.settings:
        tendon, joint, *rest = (float(v) for v in text.split(","))
        row = run_setting(real, tendon, joint, *rest)
        rows.append(row)
        head = (f"tendon {tendon:g} N, joints {joint:g} N m, spool {row['spool_mm']:g} mm, "
                f"moment arms x{row['moment_arm_scale']:g}")
        if "failed" in row:
            print(f"{head}: {row['failed']}", flush=True)
            continue
        print(f"{head}: path steps {row['path_steps']}, grasp {row['grasp_state']}", flush=True)
        rates = {tuple(r["action"]): r for r in row["held_moves"]}
        for o in row["onsets"]:
            move, steps, speed = tuple(o["action"]), o["onset_steps"], o["moving_speed_mm_per_step"]
            want, rate, want_rate = real_onsets[move], rates.get(move), real_rates[move]
            waited = "never moved 2 mm" if steps is None else f"{steps:g} steps to move 2 mm"
            ratio = "" if speed is None or math.isnan(want.moving_speed_mm_per_step) else (
                f" ({speed / want.moving_speed_mm_per_step:.1f}x real)")
            then = "" if speed is None else f", then {speed:.3f} mm/step{ratio}"
            loads = (f"; loads {rate['load1_per_step']:+.1f} {rate['load2_per_step']:+.1f} /step (real "
                     f"{want_rate.load1_per_step:+.1f} {want_rate.load2_per_step:+.1f})" if rate else "")
            print(f"  {list(move)}: {waited} (real {want.onset_steps:g}){then}{loads}", flush=True)
    summary = {"unit_rad": args.unit, "fit_hand": "A",
               "real_onsets": rows_as_dicts(list(real_onsets.values())), "settings": rows}
    args.out.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
