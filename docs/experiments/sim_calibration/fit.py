"""A random search for simulated-hand parameters whose held-move rates match a real hand's, at the authors' step.

Each candidate is the source hand with the step per action unit fixed (``--unit``, the authors' driver's) and
the ``--free`` parameters drawn log-uniform from the ranges below (by default six: the spool radius, the
tendon's stiffness, the servo's lag, a common scale of every finger spring, the object's damping in the plane
and the joints' damping; also the load unit's scale and the tendons' and joints' dry friction), or drawn near
the values of ``--around`` (a local search). It
replays a real hand's six test paths (``t42 sim compare-real``'s replay) and is scored against that hand's
held-move table (``hand/realism.py``):

    score = mean over moves of log(sim speed / real speed)^2            (speeds floored at 0.01 mm/step)
          + 0.5 * mean over moves and loads of ((sim - real load rate) / 2 units)^2
          + 2 * mean over paths of the fraction of the real path's steps the simulated path did not last
          + ((70 mm - the grasp's object y) / 20 mm)^2 when the grasp holds the object nearer the palm than 70 mm

With ``--speed moving`` the speed term compares each move's speed once the object has moved 2 mm
(``realism.held_move_onsets``), and an onset term, weighted ``--onset-weight``, the steps until then. A move the
real hand holds at least ``--window`` steps that the simulated path never reaches counts as a speed ratio of 20
and a load error of 10 units. The best candidates found on the fitting hand are then
scored on the other hand (its own paths and table). As in scan.py, the unit is written into the simulator
module for this process only; nothing here changes the suite's simulated hands.

    .venv/bin/python docs/experiments/sim_calibration/fit.py --candidates 200 --best 8 \
        --out docs/experiments/sim_calibration/fit_all.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

import t42_transfer.hand.sim as simulator
from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir
from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import run_episode
from t42_transfer.hand.params import HandParams, variant
from t42_transfer.hand.realism import held_move_onsets, held_move_rates

RANGES = {  # log-uniform
    "spool_radius_mm": (4.0, 25.0),
    "tendon_stiffness": (300.0, 1e5),
    "servo_time_constant_s": (0.02, 0.6),
    "spring_scale": (0.3, 3.0),
    "object_damping": (0.3, 60.0),
    "joint_damping": (0.002, 0.4),
    "load_unit_scale": (0.1, 10.0),
    "tendon_friction_n": (1.0, 20.0),
    "joint_friction_nm": (0.001, 0.03),
}
SIMULATOR_ONLY = ("spring_scale", "load_unit_scale")
"""Parameters that are no HandParams field: the springs' common scale, and a scale of the torque one raw load
unit stands for in the simulator (the real hands' load readings may not be 0.1 % of stall torque)."""
FINGERTIP_GRASP_Y_MM = 70.0
"""A grasp whose object centre sits nearer the palm than this (the design's grasp is at about 85 mm; the object
touches the palm at 47.5) holds the object against the palm, not between the pads: penalised."""
GRASP_STEP_RAD = simulator.GRASP_INCREMENT * simulator.ACTION_UNIT_RAD
LOAD_UNIT_NM = simulator.LOAD_UNIT_NM
MISSING_SPEED_RATIO, MISSING_LOAD_ERROR, SPEED_FLOOR = 20.0, 10.0, 0.01


def hand_params(candidate: dict[str, float]) -> HandParams:
    base = variant("source")
    scale = candidate.get("spring_scale", 1.0)
    fingers = {side: dataclasses.replace(getattr(base, side), k_proximal=getattr(base, side).k_proximal * scale,
                                         k_distal=getattr(base, side).k_distal * scale) for side in ("left", "right")}
    own = {k: v for k, v in candidate.items() if k not in SIMULATOR_ONLY}
    return dataclasses.replace(base, **own, **fingers)


def moving_speeds(name: str, data: TrajectorySet) -> dict[tuple[float, float], tuple[float, float]]:
    """Per move held 100 steps or more: (steps before the object has moved 2 mm, mm/step over the next 20)."""
    return {o.action: (o.onset_steps, o.moving_speed_mm_per_step) for o in held_move_onsets(name, data)
            if np.isfinite(o.moving_speed_mm_per_step)}


def score(candidate: dict[str, float], real: TrajectorySet, unit_rad: float, window: int, palm_weight: float,
          speed_measure: str = "first", onset_weight: float = 0.0, later_loads: bool = False) -> dict:
    """The candidate's score against ``real`` (lower is better) and what went into it.

    ``speed_measure``: ``first``, each move's speed over its runs' first ``window`` steps; ``moving``, its speed
    once the object has moved 2 mm (``realism.held_move_onsets``), the real hands' wait before that scored
    apart as the onset term, mean over moves of log((sim steps + 1) / (real steps + 1))^2, weighted
    ``onset_weight``. ``later_loads``: the load term over each path's later holds only (the real first hold's
    loads drop as the authors' hand node re-bases its goals after the grasp)."""
    simulator.ACTION_UNIT_RAD = unit_rad
    simulator.GRASP_INCREMENT = GRASP_STEP_RAD / unit_rad
    simulator.GRASP_MAX_STEPS = 4000
    simulator.LOAD_UNIT_NM = LOAD_UNIT_NM * candidate.get("load_unit_scale", 1.0)
    try:
        hand = simulator.SimulatedHand(hand_params(candidate))
        replayed = TrajectorySet(run_episode(hand, t.actions, seed) for seed, t in enumerate(real))
    except Exception as err:  # a grasp that fails, an unstable model: no score
        return {**candidate, "score": math.inf, "failed": f"{type(err).__name__}: {err}"[:200]}
    want = {r.action: r for r in held_move_rates("real", real, window)}
    got = {r.action: r for r in held_move_rates("sim", replayed, window)}
    want_loads = {r.action: r for r in held_move_rates("real", real, window, later_loads)}
    got_loads = {r.action: r for r in held_move_rates("sim", replayed, window, later_loads)}
    speed, load, onset = [], [], []
    for move, r in want_loads.items():
        s = got_loads.get(move)
        if s is None:
            load.append((MISSING_LOAD_ERROR / 2.0) ** 2)
            continue
        load += [((s.load1_per_step - r.load1_per_step) / 2.0) ** 2, ((s.load2_per_step - r.load2_per_step) / 2.0) ** 2]
    if speed_measure == "moving":
        real_moving, sim_moving = moving_speeds("real", real), moving_speeds("sim", replayed)
        speed_of = {m: v[1] for m, v in sim_moving.items()}
        wanted_speed = {m: v[1] for m, v in real_moving.items()}
        for move, (steps, _) in real_moving.items():
            sim_steps = sim_moving[move][0] if move in sim_moving else 10 * steps
            onset.append(math.log((sim_steps + 1) / (steps + 1)) ** 2)
    else:
        speed_of = {m: r.speed_mm_per_step for m, r in got.items()}
        wanted_speed = {m: r.speed_mm_per_step for m, r in want.items()}
    ratios = {}
    for move, r in wanted_speed.items():
        ratio = (max(speed_of[move], SPEED_FLOOR) / max(r, SPEED_FLOOR) if move in speed_of
                 else MISSING_SPEED_RATIO)
        ratios[str(list(move))] = round(ratio, 2) if move in speed_of else None
        speed.append(math.log(ratio) ** 2)
    short = float(np.mean([1.0 - len(s) / len(r) for s, r in zip(replayed, real, strict=True)]))
    grasp_y = float(replayed[0].states[0, 1])
    palm = max(0.0, (FINGERTIP_GRASP_Y_MM - grasp_y) / 20.0) ** 2
    onset_term = float(np.mean(onset)) if onset else 0.0
    total = float(np.mean(speed) + 0.5 * np.mean(load) + 2.0 * short + palm_weight * palm + onset_weight * onset_term)
    row = {
        **candidate, "score": total, "speed_term": float(np.mean(speed)), "load_term": float(np.mean(load)),
        "short_fraction": short, "grasp_y_mm": round(grasp_y, 1), "palm_term": palm, "speed_ratios": ratios,
    }
    if speed_measure == "moving":
        row |= {"onset_term": onset_term, "onset_steps": {str(list(m)): v[0] for m, v in sim_moving.items()}}
    return row


FIRST_SIX = list(RANGES)[:6]
"""Drawn from the main stream, six a candidate, as before ``load_unit_scale`` was added (the committed runs
reproduce); later parameters come from streams of their own, so that adding one changes no earlier draw."""
STREAM = {"load_unit_scale": 1, "tendon_friction_n": 2, "joint_friction_nm": 2}


def draw(rngs: tuple[np.random.Generator, ...], free: list[str]) -> dict[str, float]:
    """One candidate: every parameter of ``RANGES`` drawn (the same draws whatever is free), the free ones kept."""
    drawn = {k: float(math.exp(rngs[STREAM.get(k, 0)].uniform(math.log(lo), math.log(hi))))
             for k, (lo, hi) in RANGES.items()}
    return {k: drawn[k] for k in free}


def draw_around(rng: np.random.Generator, centre: dict[str, float], spread: float) -> dict[str, float]:
    """One candidate near ``centre``: each parameter times exp(N(0, ``spread``)), kept inside ``RANGES``."""
    return {k: float(np.clip(v * math.exp(rng.normal(0.0, spread)), *RANGES[k])) for k, v in centre.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fit", default="A", choices=sorted(REAL_FILES))
    parser.add_argument("--check", default="B", choices=sorted(REAL_FILES))
    parser.add_argument("--unit", type=float, default=0.0039, help="rad per action unit per step (authors' 0.0039)")
    parser.add_argument("--candidates", type=int, default=60)
    parser.add_argument("--best", type=int, default=5, help="candidates scored on the check hand")
    parser.add_argument("--window", type=int, default=30)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--free", nargs="+", choices=sorted(RANGES), default=FIRST_SIX,
                        help="parameters drawn (the others keep the source hand's values; default the first six)")
    parser.add_argument("--palm-weight", type=float, default=1.0, help="weight of the grasp-against-the-palm term")
    parser.add_argument("--speed", choices=("first", "moving"), default="first",
                        help="speed over each hold's first --window steps, or once the object moves (see score)")
    parser.add_argument("--onset-weight", type=float, default=0.0, help="weight of the onset term (--speed moving)")
    parser.add_argument("--later-loads", action="store_true", help="load term over each path's later holds only")
    parser.add_argument("--around", type=Path, default=None,
                        help="a JSON object of the --free parameters: draw candidates near it instead (a local search)")
    parser.add_argument("--spread", type=float, default=0.25, help="log-normal spread of --around's draws")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    folder = real_data_dir()
    fit_set, check_set = (load_t42_testpaths(folder / REAL_FILES[h]) for h in (args.fit, args.check))
    rngs = tuple(np.random.default_rng(args.seed if k == 0 else [args.seed, k]) for k in range(3))
    if args.around is None:
        candidates = [draw(rngs, args.free) for _ in range(args.candidates)]
    else:
        centre = json.loads(args.around.read_text())
        centre = {k: float(centre[k]) for k in args.free}
        candidates = [centre] + [draw_around(rngs[0], centre, args.spread) for _ in range(args.candidates - 1)]
    with ProcessPoolExecutor(args.workers) as pool:
        def scored(sets: list[dict[str, float]], real: TrajectorySet) -> list[dict]:
            n = len(sets)
            return list(pool.map(score, sets, [real] * n, [args.unit] * n, [args.window] * n, [args.palm_weight] * n,
                                 [args.speed] * n, [args.onset_weight] * n, [args.later_loads] * n))

        fitted = sorted(scored(candidates, fit_set), key=lambda r: r["score"])
        checked = scored([{k: r[k] for k in args.free} for r in fitted[: args.best]], check_set)
    for f, c in zip(fitted, checked, strict=False):
        if "failed" in f or "failed" in c:  # the best are scored first; a failure can only be a checked one
            print(f"fit {f['score']:.3f}: {f.get('failed') or 'checked: ' + c['failed']}")
            continue
        print(f"fit {f['score']:.3f} (speed {f['speed_term']:.2f}, load {f['load_term']:.2f}, short "
              f"{f['short_fraction']:.2f}, grasp y {f['grasp_y_mm']}) check {c['score']:.3f} (speed "
              f"{c['speed_term']:.2f}, load {c['load_term']:.2f}) | " + ", ".join(f"{k} {f[k]:.4g}" for k in args.free))
    summary = {"unit_rad": args.unit, "window": args.window, "fit_hand": args.fit, "check_hand": args.check,
               "seed": args.seed, "free": args.free, "palm_weight": args.palm_weight, "speed": args.speed,
               "onset_weight": args.onset_weight, "later_loads": args.later_loads, "ranges": RANGES,
               "around": None if args.around is None else centre, "spread": args.spread,
               "fitted": fitted, "checked": checked}
    for row in (*fitted, *checked):  # JSON has no infinity: a candidate that failed has no score
        row["score"] = None if math.isinf(row["score"]) else row["score"]
    args.out.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
