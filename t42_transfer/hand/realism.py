"""Side-by-side statistics of simulated and real hands under the same action sequences.

The real T42 test paths (two hands, the same six action sequences) are replayed
open loop on simulated hands; both are summarised by the quantities a
researcher would eyeball: workspace extent, step sizes, load ranges and drops.
The aim is credible behaviour, not a fit: frames differ (camera vs hand base), so
extents are compared as spans, not coordinates.  Time scales are compared by the
held moves: how far a move held for many steps carries the object and the loads
per step, the rate a model has to learn and the one divergence times are counted in.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from t42_transfer.data.trajectory import TrajectorySet
from t42_transfer.hand.collect import DROP_REASONS, run_episode
from t42_transfer.hand.sim import SimulatedHand


@dataclass(frozen=True)
class BehaviourStats:
    """Summary of one set of paths (one row of the comparison table)."""

    name: str
    paths: int
    steps: int
    x_span_mm: float
    y_span_mm: float
    step_median_mm: float
    step_p90_mm: float
    step_p99_mm: float
    zero_step_fraction: float
    load1_range: tuple[float, float]
    load2_range: tuple[float, float]
    drop_rate: float
    end_reasons: dict[str, int]


def summarise(name: str, data: TrajectorySet) -> BehaviourStats:
    states = [t.states for t in data]
    steps = np.concatenate([np.linalg.norm(np.diff(s[:, :2], axis=0), axis=1) for s in states])
    spans = np.array([np.ptp(s[:, :2], axis=0) for s in states])
    every = np.concatenate(states)
    return BehaviourStats(
        name=name,
        paths=len(data),
        steps=int(len(steps)),
        x_span_mm=float(np.median(spans[:, 0])),
        y_span_mm=float(np.median(spans[:, 1])),
        step_median_mm=float(np.median(steps)),
        step_p90_mm=float(np.percentile(steps, 90)),
        step_p99_mm=float(np.percentile(steps, 99)),
        zero_step_fraction=float(np.mean(steps == 0.0)),
        load1_range=(float(every[:, 2].min()), float(every[:, 2].max())),
        load2_range=(float(every[:, 3].min()), float(every[:, 3].max())),
        drop_rate=float(np.mean([t.end_reason in DROP_REASONS for t in data])),
        end_reasons=dict(Counter(t.end_reason or "unknown" for t in data)),
    )


@dataclass(frozen=True)
class HeldMoveRate:
    """How fast one move, held, carries the object and the loads (one row of the held-moves table).

    Rates are medians over the runs where the move was held at least ``window`` steps, each measured
    over the run's first ``window`` steps (net change / window), so a hand that reaches the end of its
    travel early is not averaged with the standstill that follows."""

    name: str
    action: tuple[float, float]
    runs: int
    window: int
    speed_mm_per_step: float
    load1_per_step: float
    load2_per_step: float


def held_runs(actions: np.ndarray, min_steps: int) -> list[tuple[int, int]]:
    """``(start, stop)`` of every stretch of one action repeated at least ``min_steps`` times."""
    runs, start = [], 0
    for i in range(1, len(actions) + 1):
        if i == len(actions) or not np.array_equal(actions[i], actions[start]):
            if i - start >= min_steps:
                runs.append((start, i))
            start = i
    return runs


def held_move_rates(name: str, data: TrajectorySet, window: int = 30, later_only: bool = False) -> list[HeldMoveRate]:
    """One :class:`HeldMoveRate` per move held at least ``window`` steps somewhere in ``data``, by move.

    ``later_only``: leave out each path's first hold. On the real hands its loads drop at the first move, as the
    authors' hand node re-bases the servos' goals after the grasp (docs/experiments/sim_calibration)."""
    if window < 1:
        raise ValueError(f"window must be at least 1 step, got {window}")
    changes: dict[tuple[float, float], list[np.ndarray]] = {}
    for t in data:
        for start, _ in held_runs(t.actions, window):
            if later_only and start == 0:
                continue
            delta = (t.states[start + window] - t.states[start]) / window
            move = (float(t.actions[start][0]), float(t.actions[start][1]))
            changes.setdefault(move, []).append(np.array([np.linalg.norm(delta[:2]), delta[2], delta[3]]))
    rows = []
    for move in sorted(changes):
        rates = np.median(np.array(changes[move]), axis=0)
        rows.append(HeldMoveRate(name, move, len(changes[move]), window, *(float(r) for r in rates)))
    return rows


@dataclass(frozen=True)
class HeldMoveOnset:
    """How long one held move takes to start carrying the object, and how fast it carries it then.

    The real hands take tens of steps after a change of move before the object moves at all (a tendon
    taking up slack, a grasp re-settling), then move it steadily; a rate over a hold's first steps mixes
    the two.  ``onset_steps``: the median over runs of the first step whose object position is
    ``threshold_mm`` or more from the run's start.  ``moving_speed_mm_per_step``: the median net
    displacement over the ``window`` steps from that step on, divided by ``window``, over the runs whose
    onset leaves ``window`` steps in the run.  ``stuck``: runs in which the object never moved that far.
    """

    name: str
    action: tuple[float, float]
    runs: int
    stuck: int
    threshold_mm: float
    window: int
    onset_steps: float
    moving_speed_mm_per_step: float
    moving_runs: int


def held_move_onsets(
    name: str, data: TrajectorySet, threshold_mm: float = 2.0, window: int = 20, min_steps: int = 100
) -> list[HeldMoveOnset]:
    """One :class:`HeldMoveOnset` per move held at least ``min_steps`` steps somewhere in ``data``, by move.

    ``threshold_mm`` should stand clear of the tracker's noise (the real paths' positions move in steps of
    about 0.4 mm); a median over no runs is NaN.
    """
    if not threshold_mm > 0:
        raise ValueError(f"threshold_mm must be positive, got {threshold_mm}")
    if window < 1 or min_steps < 1:
        raise ValueError(f"window and min_steps must be at least 1 step, got {window} and {min_steps}")
    onsets: dict[tuple[float, float], list[int | None]] = {}
    speeds: dict[tuple[float, float], list[float]] = {}
    for t in data:
        for start, stop in held_runs(t.actions, min_steps):
            xy = t.states[start : stop + 1, :2]
            moved = np.flatnonzero(np.linalg.norm(xy - xy[0], axis=1) >= threshold_mm)
            move = (float(t.actions[start][0]), float(t.actions[start][1]))
            onset = int(moved[0]) if len(moved) else None
            onsets.setdefault(move, []).append(onset)
            speeds.setdefault(move, [])
            if onset is not None and onset + window < len(xy):
                speeds[move].append(float(np.linalg.norm(xy[onset + window] - xy[onset])) / window)
    rows = []
    for move in sorted(onsets):
        found = [k for k in onsets[move] if k is not None]
        rows.append(HeldMoveOnset(
            name, move, len(onsets[move]), len(onsets[move]) - len(found), threshold_mm, window,
            float(np.median(found)) if found else float("nan"),
            float(np.median(speeds[move])) if speeds[move] else float("nan"), len(speeds[move]),
        ))
    return rows


def held_onsets_table(onsets: Sequence[HeldMoveOnset]) -> str:
    """Markdown, a row per move and data set; the last column is the moving speed over the real sets' mean."""
    real: dict[tuple[float, float], list[float]] = {}
    for r in onsets:
        if r.name.startswith("real") and np.isfinite(r.moving_speed_mm_per_step):
            real.setdefault(r.action, []).append(r.moving_speed_mm_per_step)
    window = onsets[0].window if onsets else 0
    head = (
        f"| move | data | runs | never moved | steps to move {onsets[0].threshold_mm if onsets else 0:g} mm "
        f"| then mm/step (next {window} steps) | speed / real |\n|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in sorted(onsets, key=lambda r: (r.action, r.name)):
        reference = float(np.mean(real[r.action])) if real.get(r.action) else 0.0
        speed = r.moving_speed_mm_per_step
        compared = reference > 0 and np.isfinite(speed) and not r.name.startswith("real")
        ratio = f"{speed / reference:.1f}x" if compared else ""
        onset = f"{r.onset_steps:g}" if np.isfinite(r.onset_steps) else "never"
        shown = f"{speed:.3f} ({r.moving_runs} runs)" if np.isfinite(speed) else "none"
        lines.append(f"| [{r.action[0]:g}, {r.action[1]:g}] | {r.name} | {r.runs} | {r.stuck} | {onset} "
                     f"| {shown} | {ratio} |")
    return head + "\n".join(lines) + "\n"


def replay(real: TrajectorySet, hand: str, seed: int = 0) -> TrajectorySet:
    """Run every real path's action sequence open loop on the simulated ``hand``."""
    sim = SimulatedHand(hand)
    return TrajectorySet((run_episode(sim, t.actions, seed + i) for i, t in enumerate(real)), hand=hand)


def compare(
    real_sets: dict[str, TrajectorySet], hands: Sequence[str] = ("source", "target"), seed: int = 0
) -> tuple[list[BehaviourStats], dict[str, TrajectorySet]]:
    """Rows for each real set, then for each simulated hand replaying the real action sequences.

    The real hands all ran the same sequences (a set may hold a path cut shorter), so each simulated hand
    replays each path's longest recorded sequence once; sets with other sequences are refused rather than mixed.
    """
    sets = list(real_sets.values())
    first = sets[0]
    for name, other in real_sets.items():
        same = len(other) == len(first) and all(
            np.array_equal(a.actions, b.actions[: len(a.actions)])
            or np.array_equal(b.actions, a.actions[: len(b.actions)])
            for a, b in zip(first, other, strict=True)
        )
        if not same:
            raise ValueError(f"real set {name!r} ran other action sequences than {next(iter(real_sets))!r}")
    longest = TrajectorySet(max((t for t in group), key=len) for group in zip(*sets, strict=True))
    replays = {f"sim {hand}": replay(longest, hand, seed) for hand in hands}
    return [summarise(name, data) for name, data in labelled(real_sets, replays).items()], replays


def labelled(real_sets: dict[str, TrajectorySet], replays: dict[str, TrajectorySet]) -> dict[str, TrajectorySet]:
    """Every set under the name its table row and figure panel give it, real ones first."""
    return {f"real {k}": v for k, v in real_sets.items()} | {f"{k} (same actions)": v for k, v in replays.items()}


def markdown_table(rows: Sequence[BehaviourStats]) -> str:
    head = (
        "| data | paths | steps | x span mm | y span mm | step median mm | p90 | p99 | zero steps | load1 range "
        "| load2 range | drop rate | episode ends |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| {r.name} | {r.paths} | {r.steps} | {r.x_span_mm:.1f} | {r.y_span_mm:.1f} | {r.step_median_mm:.2f} "
        f"| {r.step_p90_mm:.2f} | {r.step_p99_mm:.2f} | {r.zero_step_fraction:.0%} "
        f"| {r.load1_range[0]:.0f} .. {r.load1_range[1]:.0f} | {r.load2_range[0]:.0f} .. {r.load2_range[1]:.0f} "
        f"| {r.drop_rate:.0%} | {', '.join(f'{k} {v}' for k, v in sorted(r.end_reasons.items()))} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def held_moves_table(rates: Sequence[HeldMoveRate]) -> str:
    """Markdown, a row per move and data set; the last column is the speed over the real sets' mean speed."""
    real = {}
    for r in rates:
        if r.name.startswith("real"):
            real.setdefault(r.action, []).append(r.speed_mm_per_step)
    head = (
        "| move | data | runs | object mm/step | load1 /step | load2 /step | speed / real |\n"
        "|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in sorted(rates, key=lambda r: (r.action, r.name)):
        reference = float(np.mean(real[r.action])) if r.action in real else 0.0
        compared = reference > 0 and not r.name.startswith("real")  # a tracker standing still gives 0: no ratio
        ratio = f"{r.speed_mm_per_step / reference:.1f}x" if compared else ""
        lines.append(
            f"| [{r.action[0]:g}, {r.action[1]:g}] | {r.name} | {r.runs} | {r.speed_mm_per_step:.3f} "
            f"| {r.load1_per_step:+.2f} | {r.load2_per_step:+.2f} | {ratio} |"
        )
    return head + "\n".join(lines) + "\n"


def plot_paths(real_sets: dict[str, TrajectorySet], replays: dict[str, TrajectorySet], path: Path) -> Path:
    """x-y paths of every real set next to the simulated replays, one panel each, path colours matched."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    panels = list(labelled(real_sets, replays).items())
    fig, axes = plt.subplots(1, len(panels), figsize=(4.0 * len(panels), 3.8), squeeze=False)
    for ax, (title, data) in zip(axes.flat, panels, strict=True):
        for i, t in enumerate(data):
            ax.plot(t.states[:, 0], t.states[:, 1], lw=0.8, color=f"C{i}", label=f"path {i}")
            ax.plot(*t.states[0, :2], "k.", ms=4)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    axes.flat[0].legend(fontsize=6)
    fig.suptitle("Real T42 test paths and simulated hands under the same action sequences (frames differ)", fontsize=9)
    return save(fig, path)


def plot_held_moves(rates: Sequence[HeldMoveRate], path: Path) -> Path:
    """Each held move's object speed (mm per step, log scale) on every data set, real and simulated side by side:
    the time scale a model learns, at a glance."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()
    moves = sorted({r.action for r in rates})
    sets = list(dict.fromkeys(r.name for r in rates))
    speed = {(r.name, r.action): r.speed_mm_per_step for r in rates}
    fig, ax = plt.subplots(figsize=(1.2 * len(moves) + 3.0, 3.8))
    width = 0.8 / max(1, len(sets))
    for k, name in enumerate(sets):
        xs = [i + (k - (len(sets) - 1) / 2) * width for i, m in enumerate(moves) if (name, m) in speed]
        ys = [max(speed[(name, m)], 1e-3) for m in moves if (name, m) in speed]
        ax.bar(xs, ys, width, label=name, color=f"C{k}", hatch="" if name.startswith("real") else "//")
    ax.set_yscale("log")
    ax.set_xticks(range(len(moves)), [f"[{a:g}, {b:g}]" for a, b in moves])
    ax.set_xlabel("move held")
    ax.set_ylabel(f"object speed, first {rates[0].window if rates else 0} steps (mm/step; 0 at 0.001)", fontsize=8)
    ax.legend(fontsize=7)
    ax.set_title("Held moves: how far one control step carries the object, real and simulated hands", fontsize=9)
    return save(fig, path)


def plot_held_onsets(onsets: Sequence[HeldMoveOnset], path: Path) -> Path:
    """Per held move and data set: the steps before the object moves, and its speed once it moves (log scale)."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()
    moves = sorted({r.action for r in onsets})
    sets = list(dict.fromkeys(r.name for r in onsets))
    by = {(r.name, r.action): r for r in onsets}
    fig, (ax_wait, ax_speed) = plt.subplots(2, 1, figsize=(1.2 * len(moves) + 3.0, 6.4), sharex=True)
    width = 0.8 / max(1, len(sets))
    for k, name in enumerate(sets):
        shown = [(i, by[(name, m)]) for i, m in enumerate(moves) if (name, m) in by]
        xs = [i + (k - (len(sets) - 1) / 2) * width for i, _ in shown]
        style = {"color": f"C{k}", "hatch": "" if name.startswith("real") else "//"}
        ax_wait.bar(xs, [np.nan_to_num(r.onset_steps) for _, r in shown], width, label=name, **style)
        for x, (_, r) in zip(xs, shown, strict=True):
            if np.isnan(r.onset_steps):  # no bar would read as "moves at once"
                ax_wait.text(x, 0, "never", rotation=90, ha="center", va="bottom", fontsize=7, color=f"C{k}")
        ax_speed.bar(xs, [max(np.nan_to_num(r.moving_speed_mm_per_step), 1e-3) for _, r in shown], width, **style)
    first = onsets[0] if onsets else None
    ax_speed.set_xticks(range(len(moves)), [f"[{a:g}, {b:g}]" for a, b in moves])
    ax_speed.set_xlabel("move held")
    ax_wait.set_ylabel(f"steps until the object has moved {first.threshold_mm if first else 0:g} mm", fontsize=8)
    ax_speed.set_yscale("log")
    ax_speed.set_ylabel(f"then mm/step over {first.window if first else 0} steps (none at 0.001)", fontsize=8)
    ax_wait.legend(fontsize=7)
    fig.suptitle("Held moves: how long before the object moves, and how fast it moves then", fontsize=9)
    return save(fig, path)


def rows_as_dicts(rows: Sequence[BehaviourStats | HeldMoveRate | HeldMoveOnset]) -> list[dict]:
    """The rows as JSON-ready dicts: a median over no runs (NaN, which JSON lacks) becomes None."""
    return [{k: None if isinstance(v, float) and np.isnan(v) else v for k, v in asdict(r).items()} for r in rows]
