"""Broken stretches in recorded paths: frozen object tracking, one-step jumps and late steps.

The real hands' object pose came from a camera tracker.  When it lost the marker
the pose stayed exactly where it was for hundreds of steps while the hand went
on moving, and when it found the marker again the pose jumped by up to 26 mm in
one step (hand B's path 0 in the public files: frozen for steps 0-198, then a
26.3 mm jump).  Such stretches pass every file check, yet a model rolled out
along them is scored against positions nobody measured.  This module finds them
(:func:`find_problems`), summarises them for people (:func:`summarise`) and, on
request, drops the episodes that hold them or splits the episodes there
(:func:`handle_flagged`).  Nothing is changed unless asked: ``keep`` is the default.

A late step (a recording's driver stepped more than ``LATE_STEP_NS`` after the step before: a stall, a busy
machine; :attr:`Trajectory.late_steps`) is no step of the 0.1 s model either: the object goes on moving while the
hand waits.  On the simulated hands (random actions, each held on) a 0.2 s step moves it 0.6 mm further than a
0.1 s one on average, a 0.5 s step 1.9-2.4 mm (up to 6 mm).  A transfer leaves such transitions out
(:func:`usable_stretches`), where it also ends episodes at a drop.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from t42_transfer.conventions import CONTROL_PERIOD_NS, DROP_JUMP_MM, DROPPED, MIN_EPISODE_STEPS
from t42_transfer.data.trajectory import Trajectory, TrajectorySet

FROZEN = "frozen"
JUMP = "jump"
LATE = "late_step"
KINDS = (FROZEN, JUMP, LATE)

HANDLING = ("keep", "drop", "split")
"""What an experiment does with a flagged episode: keep it as it is, drop it, or split it at each flagged stretch."""


@dataclass(frozen=True)
class Thresholds:
    """When a stretch counts as broken; the defaults are set from the public real-hand files and the simulated hands."""

    jump_mm: float = DROP_JUMP_MM
    """A one-step x,y move above this is a jump: the paper's drop rule (8 mm); a late step may move this far a
    period it lasted (:func:`jumps`).  The clean real paths move at most 4.1 mm in a step, the simulated hands
    4.7 mm; the tracker's re-acquisitions move 8-26 mm."""
    frozen_eps_mm: float = 1e-3
    """Steps that move x,y by at most this count as standing still.  The tracker reports either exactly the same
    pose or a move of at least 0.05 mm; 1 micrometre is far below any real move and far above float32 rounding."""
    frozen_min_steps: int = 50
    """Standing still this many steps in a row (5 s) is suspect.  The camera ran below 10 Hz, so clean real paths
    stand still for up to 18 steps in a row (a third of their steps show no move); the lost tracking lasted 198."""
    frozen_min_load_range: float = 10.0
    """...while the loads range over at least this many raw units (a real hand's loads vary by 100 or more over
    such a stretch); a hand whose loads and actuators also stay put is holding still, not lost."""
    frozen_min_angle_range_rad: float = 0.05
    """...or, where actuator angles are recorded, while an actuator turns at least this far (two action steps)."""


THRESHOLDS = Thresholds()


@dataclass(frozen=True)
class Finding:
    """A broken stretch of one episode: transitions ``start .. end - 1`` are not to be trusted.

    For a jump that is the one transition that jumps (``end = start + 1``); for frozen tracking it
    is every transition out of a stale pose, the last one included (it holds all the motion the
    tracker missed).  A late step is the one transition that took too long.  ``size``: the jump in mm, for frozen
    tracking how far the loads ranged, for a late step its duration in ms.
    """

    kind: str
    start: int
    end: int
    size: float

    @property
    def steps(self) -> int:
        return self.end - self.start

    def describe(self) -> str:
        if self.kind == JUMP:
            return f"jump of {self.size:.1f} mm at step {self.start}"
        if self.kind == LATE:
            return f"late step {self.start} ({self.size:.0f} ms)"
        last = self.end - 1
        return f"frozen tracking at steps {self.start}-{last} ({self.steps} steps, loads ranged {self.size:.0f})"

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(first, one past last)`` of every run of True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def jumps(traj: Trajectory, jump_mm: float = DROP_JUMP_MM) -> tuple[np.ndarray, np.ndarray]:
    """Every transition's x,y move (mm) and the transitions that jump: over ``jump_mm`` a control period the
    step lasted (at least one: a late step may move on as far a period, the object moving while the hand waits)."""
    moves = np.linalg.norm(np.diff(traj.states[:, :2].astype(np.float64), axis=0), axis=1)
    periods = np.maximum(traj.durations_ns / CONTROL_PERIOD_NS, 1.0)
    return moves, np.flatnonzero(moves > jump_mm * periods)


def find_problems(traj: Trajectory, thresholds: Thresholds = THRESHOLDS) -> tuple[Finding, ...]:
    """Every frozen stretch, jump and late step of ``traj``, in order of their start."""
    moves, jumped = jumps(traj, thresholds.jump_mm)
    found = [Finding(JUMP, k, k + 1, float(moves[k])) for k in jumped.tolist()]
    found += _late(traj)
    for first, last in _runs(moves <= thresholds.frozen_eps_mm):  # states first..last share one pose
        if last - first < thresholds.frozen_min_steps:
            continue
        loads = float(np.ptp(traj.states[first : last + 1, 2:], axis=0).max())
        turned = traj.actuator_angles is not None and bool(
            np.ptp(traj.actuator_angles[first : last + 1], axis=0).max() >= thresholds.frozen_min_angle_range_rad
        )
        if loads >= thresholds.frozen_min_load_range or turned:
            found.append(Finding(FROZEN, first, min(last + 1, len(traj)), loads))
    return tuple(sorted(found, key=lambda f: (f.start, f.kind)))


def _late(traj: Trajectory) -> list[Finding]:
    return [Finding(LATE, k, k + 1, traj.durations_ns[k] / 1e6) for k in traj.late_steps.tolist()]


def scan(data: TrajectorySet, thresholds: Thresholds = THRESHOLDS) -> dict[int, tuple[Finding, ...]]:
    """The findings of every flagged episode, by episode index (clean episodes are left out)."""
    found = {i: find_problems(traj, thresholds) for i, traj in enumerate(data)}
    return {i: f for i, f in found.items() if f}


def summarise(data: TrajectorySet, findings: dict[int, tuple[Finding, ...]]) -> dict[str, Any]:
    """A JSON-ready record of what :func:`scan` found: counts and each finding by episode."""
    flagged = sum(f.steps for fs in findings.values() for f in fs)
    return {
        "episodes": len(data),
        "transitions": data.num_transitions,
        "flagged_episodes": len(findings),
        "flagged_transitions": flagged,
        "findings": {str(i): [f.as_dict() for f in fs] for i, fs in sorted(findings.items())},
    }


def summary_lines(findings: dict[int, tuple[Finding, ...]], unit: str = "episode") -> list[str]:
    """One line per flagged episode (called ``unit``), for a terminal; ``["none"]`` when nothing was found."""
    return [f"{unit} {i}: " + "; ".join(f.describe() for f in fs) for i, fs in sorted(findings.items())] or ["none"]


@dataclass(frozen=True)
class Handled:
    """The data after :func:`handle_flagged`, and where each of its episodes came from."""

    data: TrajectorySet
    origins: tuple[int, ...]
    """The index, in the data as given, of the episode each episode here was taken from."""
    findings: dict[int, tuple[Finding, ...]]
    """What was found, by index in the data as given."""


def _pieces(traj: Trajectory, findings: tuple[Finding, ...]) -> list[Trajectory]:
    """``traj`` without its flagged transitions: the stretches between them at least MIN_EPISODE_STEPS long."""
    cuts: list[list[int]] = []
    for f in findings:  # merge overlapping ranges (a jump often ends a frozen stretch)
        if cuts and f.start <= cuts[-1][1]:
            cuts[-1][1] = max(cuts[-1][1], f.end)
        else:
            cuts.append([f.start, f.end])
    bounds, begin = [], 0
    for start, end in cuts:
        bounds.append((begin, start))  # states begin..start: transitions begin..start-1 are clean
        begin = end
    bounds.append((begin, len(traj)))
    pieces = []
    for first, last in bounds:
        if last - first < MIN_EPISODE_STEPS:
            continue
        angles = None if traj.actuator_angles is None else traj.actuator_angles[first : last + 1]
        pieces.append(
            Trajectory(
                states=traj.states[first : last + 1],
                actions=traj.actions[first:last],
                actuator_angles=angles,
                start_ns=traj.start_ns + int(traj.durations_ns[:first].sum()),
                end_reason=traj.end_reason if last == len(traj) else "",
                hand=traj.hand,
                step_ns=None if traj.step_ns is None else traj.step_ns[first:last],
            )
        )
    return pieces


def handle_flagged(data: TrajectorySet, how: str, thresholds: Thresholds = THRESHOLDS) -> Handled:
    """``data`` with its flagged episodes kept (``keep``), dropped (``drop``) or split at each finding (``split``).

    A split keeps the clean stretches between findings that are at least MIN_EPISODE_STEPS long
    (the paper's rule for short episodes).
    """
    if how not in HANDLING:
        raise ValueError(f"flagged must be one of {HANDLING}, got {how!r}")
    findings = scan(data, thresholds)
    kept: list[Trajectory] = []
    origins: list[int] = []
    for i, traj in enumerate(data):
        if i not in findings or how == "keep":
            parts = [traj]
        elif how == "drop":
            parts = []
        else:
            parts = _pieces(traj, findings[i])
        kept.extend(parts)
        origins.extend([i] * len(parts))
    return Handled(TrajectorySet(kept, hand=data.hand), tuple(origins), findings)


def _end_at_drop(traj: Trajectory, index: int, jump_mm: float,
                 findings: tuple[Finding, ...]) -> tuple[Trajectory | None, list[str]]:
    """``traj`` ended at its first drop (None: too little before it), and a line when it was cut.  ``findings``:
    :func:`find_problems` of ``traj`` (its jumps over ``jump_mm``), so the paths are scanned once.  A jump out of a
    frozen stretch is the tracker finding the marker again, no drop: the stretch is left out, not the rest."""
    frozen = [f for f in findings if f.kind == FROZEN]
    drops = [f for f in findings if f.kind == JUMP and not any(z.start <= f.start < z.end for z in frozen)]
    if not drops:
        return traj, []
    cut, moved = drops[0].start, drops[0].size  # findings come in order of their start
    ended = None
    if cut >= MIN_EPISODE_STEPS:
        angles = None if traj.actuator_angles is None else traj.actuator_angles[: cut + 1]
        ended = dataclasses.replace(
            traj, states=traj.states[: cut + 1], actions=traj.actions[:cut], actuator_angles=angles,
            end_reason=DROPPED, step_ns=None if traj.step_ns is None else traj.step_ns[:cut])
    what = f"kept its first {cut} transitions" if ended is not None else \
        f"left out (fewer than {MIN_EPISODE_STEPS} transitions before it)"
    return ended, [f"episode {index} (start {traj.start_ns} ns): the object moved {moved:.1f} mm in step {cut}, "
                   f"over the {jump_mm:g} mm drop rule: {what}"]


def usable_stretches(data: TrajectorySet, jump_mm: float = DROP_JUMP_MM) -> tuple[Handled, list[str]]:
    """What a transfer trains and scores on of recorded episodes: each ended before its first one-step x,y jump over
    ``jump_mm`` (the paper's drop rule: the object falling), then without its late steps and its frozen tracking
    (a jump out of a frozen stretch is the tracker finding the marker again, no drop), the stretches between them
    kept when at least MIN_EPISODE_STEPS long (the paper's rule for short episodes).  The stretches with the
    episode each came from and the late steps found (by episode), and a line per episode cut or split, naming it
    as ``data`` counts.

    A driver ends an episode at a drop it saw (the real hand's :class:`~t42_transfer.driver.pose.DropWatch`, the
    simulated hand's own), and the bag reader leaves out the state its ``dropped`` or ``lost_contact`` status
    names.  A real hand's drop its tracker did not see, or a bag of another driver or without ``hand/status``,
    still holds the fall and what followed it: no transition of a hand holding the object.  A
    late step may move ``jump_mm`` per period it lasted (the object moves on during one): a stall is no drop, a
    fall during one still is.  (The driver judges a move over its frames' stamps, which a bag does not keep: here
    a pose repeated from a slow frame then moved on is judged over the steps, as the paper's rule is.)

    A late step stays in its episode as the reader gives it (its duration in ``step_ns``): the recording is
    whole.  A model of 0.1 s transitions is trained and scored on 0.1 s transitions only."""
    kept: list[Trajectory] = []
    origins: list[int] = []
    notes: list[str] = []
    late: dict[int, tuple[Finding, ...]] = {}
    thresholds = dataclasses.replace(THRESHOLDS, jump_mm=jump_mm)
    for i, traj in enumerate(data):
        findings = find_problems(traj, thresholds)  # the one scan for jumps, late steps and frozen tracking
        ended, note = _end_at_drop(traj, i, jump_mm, findings)
        notes += note
        if ended is None:
            continue
        before_end = [f for f in findings if f.start < len(ended)]
        frozen = tuple(f for f in before_end if f.kind == FROZEN)
        late_found = tuple(f for f in before_end if f.kind == LATE)
        found = tuple(sorted(frozen + late_found, key=lambda f: f.start))
        pieces = _pieces(ended, found) if found else [ended]
        if late_found:
            late[i] = late_found
        if found:
            what = "; ".join(filter(None, (
                f"{len(late_found)} late step(s) (the longest {max(f.size for f in late_found):.0f} ms)"
                if late_found else "", ", ".join(f.describe() for f in frozen))))
            notes.append(f"episode {i} (start {traj.start_ns} ns): {what} left out: {sum(len(t) for t in pieces)} of "
                         f"its {len(ended)} transitions kept, in {len(pieces)} stretch(es) of at least "
                         f"{MIN_EPISODE_STEPS}")
        kept += pieces
        origins += [i] * len(pieces)
    return Handled(TrajectorySet(kept, hand=data.hand), tuple(origins), late), notes
