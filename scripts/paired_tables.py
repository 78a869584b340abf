"""Paired comparisons of the methods in stored experiment runs: the tables behind "Does the paper's ranking hold?".

For each run directory given (its ``results.json``), each divergence threshold
(4 mm, the paper's figure; 10 mm, the authors' scripts) and each reference
(``direct``: no adaptation; ``naive_finetune``: the method the paper says
fails), every other method's difference to the reference over the matched
cells (same amount and seed: same training subset and test episodes; seeds
that drew the same training episodes are one cell, where the rows say so), pooled
over amounts: mean difference in steps, 95 % t interval, the paired t test's p
and, in brackets, its Holm adjustment over the table's methods (a conclusion
survives the multiple comparisons where that is below 0.05), cells won / lost,
exact sign-test p; then the mean difference per amount.  Markdown to stdout.

    .venv/bin/python scripts/paired_tables.py docs/experiments/abrupt_paper_random docs/experiments/smooth_paper_random

``--grid``: one table, a column per run: each method's mean over the run's cells and,
in brackets, its paired difference to the reference with the 95 % t interval.
``--winners``: per run and amount, the method with the longest mean horizon, its lead
over the runner-up (paired over the seeds, 95 % t interval) and the runner-up.
``--ranking``: a row per run, the methods ordered by their paired difference to the
reference at each threshold, ``*`` where the 95 % t interval lies above 0 and ``!``
where it lies below, ``†`` after either where it does not survive Holm's adjustment
over the run's methods at that threshold (the verdict's headline table).
``--adjusted``: the ranking's numbers in full, a row per run and method: the paired
difference with its 95 % t interval, p and its Holm adjustment over the run's methods,
and whether an interval that excludes 0 survives the adjustment (``-``: it does not exclude 0).
``--means``: each method's mean per amount (over its cells) at both thresholds, unpaired.
``--crossovers``: where pooling over the amounts hides a crossover: each comparison with
the reference whose per-amount mean differences take both signs (each by a step or more),
the pooled difference beside every amount's.
``--variants BASE``: each run given (e.g. one setting of a sweep) paired, cell by
cell, against BASE's reference (e.g. the direct cells of the full run it extends); a
run of the reference method itself in another setting is paired with it too.

    .venv/bin/python scripts/paired_tables.py --grid --metric divergence_mean_10mm docs/experiments/*_paper_random
    .venv/bin/python scripts/paired_tables.py --variants docs/experiments/abrupt_paper_random \\
        docs/experiments/abrupt_cumres_*

``--sources``: runs that differ only in their source model (e.g. its training seed): each method against the
reference paired within each source, per source, pooled over all cells, and over the sources (their mean
differences as the sample: the interval that counts a source model as the unit it is).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from t42_transfer.evaluation.stats import PairedComparison, compare_methods, holm, one_per_draw, t_interval

METRICS = {"divergence_mean_4mm": "4 mm", "divergence_mean_10mm": "10 mm"}
GRID_METRICS = {**METRICS, "position_mse_mean": "position MSE, mm² (lower is better; won = higher)"}
REFERENCES = ("direct", "naive_finetune")


def tables(run_dir: Path) -> str:
    stored = json.loads((run_dir / "results.json").read_text())
    rows = one_per_draw(stored["rows"])
    methods = list(dict.fromkeys(r["method"] for r in rows))
    amounts = sorted({r["amount"] for r in rows})
    config = stored.get("config", {})
    out = [f"### `{run_dir.name}` (definition {config.get('definition', 'paper')}, "
           f"target {config.get('target', {}).get('hand')}, test {'given' if config.get('test') else 'held out'})\n"]
    for metric, label in METRICS.items():
        if not all(metric in r for r in rows):
            continue
        for reference in REFERENCES:
            if reference not in methods:
                continue
            out.append(f"\n{label}, against {reference} (steps; pooled over {len(amounts)} amounts x seeds)\n\n")
            out.append("| method | cells | mean difference | 95 % t interval | t p (Holm) | won / lost | sign p | "
                       + " | ".join(f"{a:g}" for a in amounts) + " |\n")
            out.append("|---|---|---|---|---|---|---|" + "---|" * len(amounts) + "\n")
            others = [m for m in methods if m != reference]
            pooled = {m: compare_methods(rows, metric, m, reference)["all"] for m in others}
            adjusted = dict(zip(others, holm([pooled[m].t_p for m in others]), strict=True))
            for method in others:
                paired, per = pooled[method], compare_methods(rows, metric, method, reference, by="amount")
                low, high = paired.t_interval
                cells = " | ".join(f"{per[a].mean_difference:+.1f}" if a in per else "-" for a in amounts)
                out.append(f"| {method} | {paired.n} | {paired.mean_difference:+.1f} | {low:+.1f} to {high:+.1f} "
                           f"| {paired.t_p:.2g} ({adjusted[method]:.2g}) | {paired.wins} / {paired.losses} "
                           f"| {paired.sign_p:.2g} | {cells} |\n")
    return "".join(out)


def _rows(run_dir: Path) -> list[dict]:
    """A run's rows, seeds that drew the same training episodes merged into one cell."""
    return one_per_draw(json.loads((run_dir / "results.json").read_text())["rows"])


def _mean_and_difference(rows: list[dict], metric: str, method: str, reference: str) -> str:
    own = [r[metric] for r in rows if r["method"] == method]
    if not own:
        return "-"
    if method == reference or not any(r["method"] == reference for r in rows):  # nothing to pair with: the mean
        return f"{sum(own) / len(own):.1f}"
    paired = compare_methods(rows, metric, method, reference)["all"]
    low, high = paired.t_interval
    return (f"{paired.mean_a:.1f} ({paired.mean_difference:+.1f}, {low:+.1f} to {high:+.1f}; "
            f"{paired.wins}/{paired.losses})")


def grid_table(runs: list[Path], metric: str, reference: str) -> str:
    """Methods down, runs across: mean over the matched cells (paired difference to ``reference``, 95 % t, won/lost)."""
    stored = {run: _rows(run) for run in runs}
    methods = list(dict.fromkeys(r["method"] for rows in stored.values() for r in rows))
    methods.sort(key=lambda m: (m != reference, m != "hold_still"))
    out = [f"| {GRID_METRICS[metric]} | " + " | ".join(run.name for run in runs) + " |\n",
           "|---|" + "---|" * len(runs) + "\n"]
    for method in methods:
        out.append(f"| {method} | " + " | ".join(_mean_and_difference(stored[run], metric, method, reference)
                                                 for run in runs) + " |\n")
    return "".join(out)


SHORT = {"new_model": "new", "direct": "direct", "naive_finetune": "naive", "trajectory_finetune": "trajectory",
         "cumulative_residual": "cumres", "recurrent_residual": "recres", "l2_finetune": "L2", "hold_still": "hold"}


def winners_table(runs: list[Path], metric: str) -> str:
    """Runs down, amounts across: the best method by mean, and its paired lead over the runner-up."""
    stored = {run: _rows(run) for run in runs}
    amounts = sorted({r["amount"] for rows in stored.values() for r in rows})
    out = [f"| {METRICS.get(metric, metric)}: best (mean), lead over the runner-up (95 % t) | "
           + " | ".join(f"{a:g}" for a in amounts) + " |\n", "|---|" + "---|" * len(amounts) + "\n"]
    for run, rows in stored.items():
        cells = []
        for amount in amounts:
            at = [r for r in rows if r["amount"] == amount]
            means = {m: sum(r[metric] for r in at if r["method"] == m) / sum(1 for r in at if r["method"] == m)
                     for m in dict.fromkeys(r["method"] for r in at)}
            if len(means) < 2:
                cells.append("-")
                continue
            best, second = sorted(means, key=means.get, reverse=True)[:2]
            lead = compare_methods(at, metric, best, second)["all"]
            low, high = lead.t_interval
            cells.append(f"{SHORT.get(best, best)} ({means[best]:.0f}), +{lead.mean_difference:.1f} ({low:+.1f} to "
                         f"{high:+.1f}) over {SHORT.get(second, second)}")
        out.append(f"| {run.name} | " + " | ".join(cells) + " |\n")
    return "".join(out)


def _methods(rows: list[dict], reference: str) -> list[str]:
    """The run's methods compared with ``reference``: every one but it and hold-still, in the rows' order."""
    return [m for m in dict.fromkeys(r["method"] for r in rows) if m not in (reference, "hold_still")]


def _against(rows: list[dict], metric: str, reference: str) -> dict[str, tuple[PairedComparison, float]]:
    """Each of the run's methods paired with ``reference`` over all cells, with its t test's p adjusted by Holm
    over those methods (the family of one run at one threshold)."""
    methods = _methods(rows, reference)
    paired = [compare_methods(rows, metric, m, reference)["all"] for m in methods]
    return dict(zip(methods, zip(paired, holm([c.t_p for c in paired]), strict=True), strict=True))


def _ranked(rows: list[dict], metric: str, reference: str) -> str:
    """Methods by paired difference to ``reference``: ``*`` / ``!`` where the 95 % t interval lies above / below 0,
    then ``†`` where that conclusion does not survive Holm's adjustment over the run's methods at this threshold."""
    against = _against(rows, metric, reference)
    paired = {m: c for m, (c, _) in against.items()}
    adjusted = {m: a for m, (_, a) in against.items()}
    methods = list(against)
    ranked = []
    for method in methods:
        low, high = paired[method].t_interval
        mark = "*" if low > 0 else "!" if high < 0 else ""
        mark += "†" if mark and adjusted[method] >= 0.05 else ""
        d = paired[method].mean_difference
        ranked.append((d, f"{SHORT.get(method, method)} {d:+.{0 if abs(d) >= 10 else 1}f}{mark}"))
    return ", ".join(text for _, text in sorted(ranked, reverse=True))


def ranking_table(runs: list[Path], reference: str) -> str:
    """Runs down, thresholds across: methods by paired difference to ``reference`` (``*`` above, ``!`` below)."""
    out = ["| run | " + " | ".join(f"{label}: difference to {reference} (steps)" for label in METRICS.values())
           + " |\n", "|---|" + "---|" * len(METRICS) + "\n"]
    for run in runs:
        rows = _rows(run)
        out.append(f"| {run.name} | " + " | ".join(_ranked(rows, metric, reference) for metric in METRICS) + " |\n")
    return "".join(out)


def adjusted_table(runs: list[Path], reference: str) -> str:
    """The ranking's numbers in full: per run and method, at each threshold, the paired difference to ``reference``
    with its 95 % t interval, the paired t test's p and its Holm adjustment over the run's methods at that
    threshold, and whether the interval's conclusion survives the adjustment."""
    out = ["| run, method | cells | " + " | ".join(f"{label}: difference, 95 % t, p (Holm), survives"
                                                  for label in METRICS.values()) + " |\n",
           "|---|---|" + "---|" * len(METRICS) + "\n"]
    for run in runs:
        rows = _rows(run)
        methods = _methods(rows, reference)
        cells: dict[str, list[str]] = {m: [] for m in methods}
        counts: dict[str, int] = {}
        for metric in METRICS:
            for method, (paired, adjusted) in _against(rows, metric, reference).items():
                low, high = paired.t_interval
                excludes_zero = low > 0 or high < 0
                verdict = ("yes" if adjusted < 0.05 else "no") if excludes_zero else "-"
                cells[method].append(f"{paired.mean_difference:+.1f} ({low:+.1f} to {high:+.1f}), "
                                     f"{paired.t_p:.2g} ({adjusted:.2g}), {verdict}")
                counts[method] = paired.n
        for method in methods:
            out.append(f"| {run.name}, {SHORT.get(method, method)} | {counts[method]} | "
                       + " | ".join(cells[method]) + " |\n")
    return "".join(out)


def means_table(runs: list[Path]) -> str:
    """Per run and method, each amount's mean over its cells at both thresholds (``4 mm / 10 mm``, steps)."""
    stored = {run: _rows(run) for run in runs}
    amounts = sorted({r["amount"] for rows in stored.values() for r in rows})
    out = [f"| run, method: {' / '.join(METRICS.values())} | " + " | ".join(f"{a:g}" for a in amounts) + " |\n",
           "|---|" + "---|" * len(amounts) + "\n"]
    for run, rows in stored.items():
        for method in dict.fromkeys(r["method"] for r in rows):
            cells = []
            for amount in amounts:
                at = [r for r in rows if r["method"] == method and r["amount"] == amount]
                cells.append(" / ".join(f"{sum(r[m] for r in at) / len(at):.0f}" for m in METRICS) if at else "-")
            out.append(f"| {run.name}, {method} | " + " | ".join(cells) + " |\n")
    return "".join(out)


def crossovers_table(runs: list[Path], reference: str, min_steps: float = 1.0) -> str:
    """Where pooling over the amounts hides a crossover: per run, threshold and method, the comparisons with
    ``reference`` whose per-amount mean differences take both signs, each by at least ``min_steps``; the pooled
    difference beside each amount's (mean, 95 % t over its cells)."""
    out = ["| run, threshold, method | pooled (95 % t) | per amount: mean (95 % t), cells |\n", "|---|---|---|\n"]
    for run in runs:
        rows = _rows(run)
        methods = _methods(rows, reference)
        for metric, label in METRICS.items():
            for method in methods:
                per = compare_methods(rows, metric, method, reference, by="amount")
                means = [c.mean_difference for c in per.values()]
                if not (max(means) >= min_steps and min(means) <= -min_steps):
                    continue
                pooled = compare_methods(rows, metric, method, reference)["all"]
                low, high = pooled.t_interval
                amounts = []
                for amount, c in sorted(per.items()):
                    a_low, a_high = c.t_interval
                    amounts.append(f"{amount:g}: {c.mean_difference:+.1f} ({a_low:+.1f} to {a_high:+.1f}), {c.n}")
                out.append(f"| {run.name}, {label}, {SHORT.get(method, method)} | {pooled.mean_difference:+.1f} "
                           f"({low:+.1f} to {high:+.1f}) | " + "; ".join(amounts) + " |\n")
    return "".join(out)


def variants_table(base: Path, runs: list[Path], reference: str) -> str:
    """Each run's methods paired with ``base``'s ``reference`` cells, at both thresholds."""
    every = _rows(base)
    base_rows = [r for r in every if r["method"] == reference]
    labels = " | ".join(f"{label} (vs {reference} of {base.name})" for label in METRICS.values())
    out = [f"| run, method | {labels} |\n",
           "|---|" + "---|" * len(METRICS) + "\n"]
    still = [r for r in every if r["method"] == "hold_still"]
    if still:  # doing nothing, on the same cells: the floor every variant is read against
        cells = [_mean_and_difference(base_rows + still, metric, "hold_still", reference) for metric in METRICS]
        out.append(f"| {base.name}, hold_still | " + " | ".join(cells) + " |\n")
    for run in runs:
        # the reference method itself in a variant run (another setting of it) is paired as a method of its own
        rows = [r if r["method"] != reference else {**r, "method": f"{reference} ({run.name})"}
                for r in _rows(run) if r["method"] != "hold_still"]
        for method in dict.fromkeys(r["method"] for r in rows):
            cells = [_mean_and_difference(base_rows + rows, metric, method, reference) for metric in METRICS]
            out.append(f"| {run.name}, {method} | " + " | ".join(cells) + " |\n")
    return "".join(out)


def sources_table(runs: list[Path], reference: str) -> str:
    """Runs that differ only in the source model (its training seed): every method against ``reference`` paired
    cell by cell within each source, per source and pooled, and over the sources (their means as the sample)."""
    rows = [{**r, "source": i} for i, run in enumerate(runs) for r in _rows(run)]
    match = ("source", "amount", "seed")
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m != reference]
    out = [f"Sources: {', '.join(f'{i}: {run.name}' for i, run in enumerate(runs))}\n"]
    for metric, label in METRICS.items():
        out.append(f"\n{label}, against {reference} (steps; cells paired within each source)\n\n")
        out.append("| method | " + " | ".join(f"source {i}" for i in range(len(runs)))
                   + " | pooled: cells, mean, 95 % t, p (Holm) | over sources: mean, 95 % t (df "
                   + f"{len(runs) - 1}) | sources below 0 |\n")
        out.append("|---|" + "---|" * len(runs) + "---|---|---|\n")
        pooled = {m: compare_methods(rows, metric, m, reference, match=match)["all"] for m in methods}
        adjusted = dict(zip(methods, holm([pooled[m].t_p for m in methods]), strict=True))
        for method in methods:
            per = compare_methods(rows, metric, method, reference, match=match, by="source")
            cells = []
            for i in range(len(runs)):
                if i not in per:
                    cells.append("-")
                    continue
                low, high = per[i].t_interval
                cells.append(f"{per[i].mean_difference:+.1f} ({low:+.1f} to {high:+.1f})")
            means = [per[i].mean_difference for i in per]
            between = "-"
            if len(means) >= 2:
                low, high = t_interval(means)
                between = f"{sum(means) / len(means):+.1f} ({low:+.1f} to {high:+.1f})"
            low, high = pooled[method].t_interval
            out.append(f"| {method} | " + " | ".join(cells) + f" | {pooled[method].n}, "
                       f"{pooled[method].mean_difference:+.1f}, {low:+.1f} to {high:+.1f}, {pooled[method].t_p:.2g} "
                       f"({adjusted[method]:.2g}) | {between} | {sum(m < 0 for m in means)} of {len(means)} |\n")
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="experiment run directories (with results.json)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--grid", action="store_true", help="one table, a column per run")
    mode.add_argument("--winners", action="store_true", help="the best method per run and amount")
    mode.add_argument("--ranking", action="store_true", help="methods ordered by their difference to the reference")
    mode.add_argument("--adjusted", action="store_true",
                      help="the ranking in full: intervals, p and Holm-adjusted p, what survives")
    mode.add_argument("--means", action="store_true", help="each method's mean per amount at both thresholds")
    mode.add_argument("--crossovers", action="store_true",
                      help="comparisons whose per-amount differences take both signs (what pooling hides)")
    mode.add_argument("--variants", type=Path, metavar="BASE", help="pair every run with BASE's reference cells")
    mode.add_argument("--sources", action="store_true",
                      help="the runs differ only in their source model: pair within each, pool over them")
    parser.add_argument("--metric", choices=sorted(GRID_METRICS), default="divergence_mean_4mm",
                        help="for --grid and --winners (position MSE: --grid only)")
    parser.add_argument("--reference", default="direct", help="for --grid and --variants (default: direct)")
    args = parser.parse_args(argv)
    for run in [*args.runs, *([args.variants] if args.variants else [])]:
        if not (run / "results.json").is_file():
            parser.error(f"{run}: no results.json")
    if args.metric not in METRICS and not args.grid:
        parser.error("--metric position_mse_mean is for --grid only")
    if args.grid:
        print(grid_table(args.runs, args.metric, args.reference))
    elif args.ranking:
        print(ranking_table(args.runs, args.reference))
    elif args.adjusted:
        print(adjusted_table(args.runs, args.reference))
    elif args.means:
        print(means_table(args.runs))
    elif args.crossovers:
        print(crossovers_table(args.runs, args.reference))
    elif args.winners:
        print(winners_table(args.runs, args.metric))
    elif args.variants:
        print(variants_table(args.variants, args.runs, args.reference))
    elif args.sources:
        print(sources_table(args.runs, args.reference))
    else:
        for run in args.runs:
            print(tables(run))
    return 0


if __name__ == "__main__":
    sys.exit(main())
