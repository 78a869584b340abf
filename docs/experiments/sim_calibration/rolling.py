"""Does resistance to rolling the object slow the simulated hand's held moves?  Replays real hand A's six paths on
the source hand at the authors' step with, per setting ``ROLL,YAW_SCALE``, every geom's contact made 6-dimensional
(sliding, torsional and rolling friction) with rolling friction ``ROLL`` (m; 0 keeps the 3-dimensional contacts),
and the object's yaw damping scaled by ``YAW_SCALE``.  The compiled MuJoCo model is edited in this process only;
the unit is written into the simulator module as in scan.py.

    .venv/bin/python docs/experiments/sim_calibration/rolling.py 0,1 0.0001,1 0.002,1 0.01,1 0.05,1 0,100 0,10000
"""

from __future__ import annotations

import argparse

import mujoco

import t42_transfer.hand.sim as simulator
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import run_episode
from t42_transfer.hand.realism import held_move_rates

GRASP_STEP_RAD = simulator.GRASP_INCREMENT * simulator.ACTION_UNIT_RAD


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("settings", nargs="+", help="ROLL,YAW_SCALE pairs")
    parser.add_argument("--unit", type=float, default=0.0039)
    parser.add_argument("--window", type=int, default=30)
    args = parser.parse_args()
    real = load_t42_testpaths(real_data_dir() / REAL_FILES["A"])
    reference = {r.action: max(r.speed_mm_per_step, 0.01) for r in held_move_rates("real A", real, args.window)}
    simulator.ACTION_UNIT_RAD, simulator.GRASP_INCREMENT = args.unit, GRASP_STEP_RAD / args.unit
    for setting in args.settings:
        roll, yaw_scale = (float(v) for v in setting.split(","))
        hand = simulator.SimulatedHand("source")
        model = hand._model  # the compiled model: contact dimensions and damping have no HandParams field
        if roll > 0:
            model.geom_condim[:] = 6
            model.geom_friction[:, 2] = roll
        yaw = model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "object_yaw")]
        model.dof_damping[yaw] *= yaw_scale
        replayed = TrajectorySet(run_episode(hand, t.actions, seed) for seed, t in enumerate(real))
        rates = held_move_rates("sim", replayed, args.window)
        moves = "  ".join(f"{list(r.action)} {r.speed_mm_per_step / reference[r.action]:.1f}x" for r in rates)
        print(f"rolling friction {roll:g} m, yaw damping x{yaw_scale:g}: path steps {[len(t) for t in replayed]}, "
              f"grasp y {replayed[0].states[0, 1]:.0f} mm | speed / real A: {moves}", flush=True)


if __name__ == "__main__":
    main()
