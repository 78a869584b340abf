"""Peg-in-hole results: success per model, distance and tolerance with intervals, paired comparisons, figure.

Everything here works on the :class:`~t42_transfer.evaluation.peg_in_hole.Trial` records an
evaluation produced, so a stored ``peg_in_hole.json`` rebuilds the same tables and figure.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t42_transfer.evaluation.peg_in_hole import BASELINES, DO_NOTHING, Row, Trial, summarise
from t42_transfer.files import json_number, read_json


@dataclass(frozen=True)
class Paired:
    """One contender against another on the same goals: the difference of their success rates."""

    model: str
    against: str
    tolerance_mm: float
    goals: int
    difference: float
    """Success rate of ``model`` minus that of ``against``."""
    ci_low: float
    ci_high: float
    """95 % bootstrap interval of the difference (goals resampled, fixed seed)."""
    wins: int
    """Goals ``model`` hit and ``against`` missed."""
    losses: int
    sign_p: float
    """Exact two-sided sign test on the discordant goals."""


def paired(trials: Sequence[Trial], tolerances_mm: Sequence[float], reference: str = "direct") -> list[Paired]:
    """Every contender against ``reference``, and each variant (``name+...``) against its own model, goal by goal."""
    from t42_transfer.evaluation.stats import compare_paired

    by_model: dict[str, dict[tuple[int, int], Trial]] = {}
    for t in trials:
        by_model.setdefault(t.model, {})[(t.steps, t.trial)] = t
    out = []
    for name in by_model:
        if name in BASELINES:
            continue
        against = name.split("+")[0] if "+" in name else reference
        if against == name or against not in by_model:
            continue
        goals = sorted(set(by_model[name]) & set(by_model[against]))
        if len(goals) < 2:
            continue
        for tol in tolerances_mm:
            a = [float(by_model[name][g].success(tol)) for g in goals]
            b = [float(by_model[against][g].success(tol)) for g in goals]
            c = compare_paired(a, b)
            out.append(Paired(name, against, float(tol), len(goals), c.mean_difference, *c.bootstrap_interval,
                              c.wins, c.losses, c.sign_p))
    return out


def paired_table(comparisons: Sequence[Paired]) -> str:
    if not comparisons:
        return ""
    lines = ["Paired on the same goals (all distances): success-rate difference, 95 % bootstrap interval, "
             "goals won / lost, exact sign test\n\n",
             "| model | against | tolerance mm | goals | difference | 95 % interval | won / lost | sign p |\n",
             "|---|---|---|---|---|---|---|---|\n"]
    for c in comparisons:
        lines.append(f"| {c.model} | {c.against} | {c.tolerance_mm:g} | {c.goals} | {c.difference:+.0%} "
                     f"| {c.ci_low:+.0%} to {c.ci_high:+.0%} | {c.wins} / {c.losses} | {c.sign_p:.2g} |\n")
    return "".join(lines) + "\n"


def markdown_table(rows: Sequence[Row]) -> str:
    """One table per tolerance: success with its Wilson interval beside the median final error."""
    out = []
    for tol in dict.fromkeys(r.tolerance_mm for r in rows):
        out.append(
            f"Tolerance {tol:g} mm\n\n"
            "| model | goal steps | median goal distance mm | trials | success | 95 % interval "
            "| median final error mm | median error / distance | miss / no progress / incomplete |\n"
            "|---|---|---|---|---|---|---|---|---|\n"
        )
        for r in (r for r in rows if r.tolerance_mm == tol):
            error = "-" if r.final_error_mm is None else f"{r.final_error_mm:.1f}"
            rel = "-" if r.relative_error is None else f"{r.relative_error:.2f}"
            v = r.verdicts
            out.append(
                f"| {r.model} | {r.steps} | {r.goal_distance_mm:.1f} | {r.trials} "
                f"| {r.successes} ({r.success_rate:.0%}) "
                f"| {r.ci_low:.0%}-{r.ci_high:.0%} | {error} | {rel} "
                f"| {v['miss']} / {v['no_progress']} / {v['incomplete']} |\n"
            )
        out.append("\n")
    return "".join(out)


def plot_success(rows: Sequence[Row], path: Path) -> Path:
    """Per tolerance: success rate (Wilson interval bars) against goal distance; below, median error / distance.

    Baselines are dashed squares; variants of a model (``name+...``) share its colour, dotted (closed loop)
    or dash-dotted (uncertainty-aware); the legend has its own panel."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()
    tolerances = list(dict.fromkeys(r.tolerance_mm for r in rows))
    columns = max(2, len(tolerances))
    fig, axes = plt.subplots(2, columns, figsize=(5.2 * columns, 6.8), squeeze=False)
    names = list(dict.fromkeys(r.model for r in rows))
    bases = list(dict.fromkeys(n.split("+")[0] for n in names))
    tab20 = plt.get_cmap("tab20").colors
    palette = [tab20[j] for j in (*range(0, 20, 2), *range(1, 20, 2)) if j not in (14, 15)]  # no greys
    colour = {b: palette[i % len(palette)] for i, b in enumerate(bases)}

    def style(name: str) -> dict:
        base, _, variant = name.partition("+")
        if name in BASELINES:
            return dict(linestyle="--", marker="s", color="black" if name == DO_NOTHING else "grey")
        line = ":" if variant.startswith("mpc") else "-." if variant else "-"
        marker = "^" if variant.startswith("mpc") else "v" if variant else "o"
        return dict(linestyle=line, marker=marker, color=colour[base], markersize=4)

    for col, tol in enumerate(tolerances):
        top = axes[0, col]
        for name in names:
            mine = sorted((r for r in rows if r.model == name and r.tolerance_mm == tol), key=lambda r: r.steps)
            steps = np.array([r.steps for r in mine], float)
            rate = np.array([r.success_rate for r in mine])
            err = np.array([[r.success_rate - r.ci_low for r in mine], [r.ci_high - r.success_rate for r in mine]])
            top.errorbar(steps, rate, yerr=err, capsize=2, elinewidth=0.6, label=name, **style(name))
        top.set_title(f"Peg-in-hole, tolerance {tol:g} mm (95 % Wilson)", fontsize=9)
        top.set_ylabel("success rate")
        top.set_xlabel("goal distance (control steps = plan length)")
        top.set_ylim(-0.03, 1.03)
    bottom = axes[1, 0]
    for name in names:
        mine = sorted((r for r in rows if r.model == name and r.tolerance_mm == tolerances[0]), key=lambda r: r.steps)
        rel = [np.nan if r.relative_error is None else r.relative_error for r in mine]
        bottom.plot([r.steps for r in mine], rel, label=name, **style(name))
    bottom.set_xlabel("goal distance (control steps = plan length)")
    bottom.set_ylabel("median final error / start distance")
    bottom.axhline(1.0, color="grey", linewidth=0.6)
    for ax in axes[1, 1:]:
        ax.axis("off")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    axes[1, -1].legend(handles, labels, fontsize=7, loc="center", ncol=2, frameon=False)
    fig.tight_layout()
    return save(fig, path)


def write_report(out: Path, rows: Sequence[Row], trials: Sequence[Trial], tolerances_mm: Sequence[float],
                 wrote: str = "peg_in_hole.json, .md and .png") -> int:
    """``peg_in_hole.md`` (tables, paired comparisons) and ``.png`` beside the JSON; prints the tables."""
    table = markdown_table(rows) + paired_table(paired(trials, tolerances_mm))
    (out / "peg_in_hole.md").write_text(table)
    plot_success(rows, out / "peg_in_hole.png")
    print(table)
    print(f"wrote {wrote} in {out}")
    return 0


_FIELD_CHECKS = {
    "str": lambda v: isinstance(v, str),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    "float": json_number,
    "float | None": lambda v: v is None or json_number(v),
}
"""A stored trial's field, by its annotation in :class:`Trial`: whether a value read back from JSON is one."""


def stored_trials(path: Path) -> tuple[list[Trial], tuple[float, ...]]:
    """The trials and tolerances of a ``peg_in_hole.json``, checked field by field; ValueError naming the file."""
    stored = read_json(path, "peg-in-hole results")

    def refuse(problem: str) -> ValueError:
        return ValueError(f"{path}: not the results of `t42 peg-in-hole`: {problem}")

    if not isinstance(stored, dict) or not isinstance(stored.get("config"), dict):
        raise refuse("no 'config' object")
    tolerances = stored["config"].get("tolerances_mm")
    if (not isinstance(tolerances, list) or not tolerances
            or not all(json_number(t) and 0 < t < float("inf") for t in tolerances)):
        raise refuse(f"its config's tolerances_mm {tolerances!r} are not positive numbers")
    raw = stored.get("trials")
    if not isinstance(raw, list) or not raw:
        raise refuse("no 'trials' (a list, at least one)")
    fields = {f.name: f.type for f in dataclasses.fields(Trial)}
    trials = []
    for i, trial in enumerate(raw):
        if not isinstance(trial, dict) or set(trial) != set(fields):
            raise refuse(f"trial {i} is not an object with the fields {', '.join(fields)}")
        wrong = [name for name, kind in fields.items() if not _FIELD_CHECKS[kind](trial[name])]
        if wrong:
            raise refuse(f"trial {i}: {', '.join(f'{n} {trial[n]!r}' for n in wrong)}")
        trials.append(Trial(**trial))
    return trials, tuple(float(t) for t in tolerances)


def report_from_json(path: Path) -> int:
    """Rebuild the tables and the figure from a stored ``peg_in_hole.json`` (nothing is planned again)."""
    trials, tolerances = stored_trials(path)
    return write_report(Path(path).parent, summarise(trials, tolerances), trials, tolerances,
                        wrote="peg_in_hole.md and .png")
