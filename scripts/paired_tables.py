"""Paired comparisons of the methods in stored experiment runs: the tables behind "Does the paper's ranking hold?".

For each run directory given (its ``results.json``), each divergence threshold
(4 mm, the paper's figure; 10 mm, the authors' scripts) and each reference
(``direct``: no adaptation; ``naive_finetune``: the method the paper says
fails), every other method's difference to the reference over the matched
cells (same amount and seed: same training subset and test episodes), pooled
over amounts: mean difference in steps, 95 % t interval, cells won / lost,
exact sign-test p; then the mean difference per amount.  Markdown to stdout.

    .venv/bin/python scripts/paired_tables.py docs/experiments/abrupt_paper_random docs/experiments/smooth_paper_random
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from t42_transfer.evaluation.stats import compare_methods

METRICS = {"divergence_mean_4mm": "4 mm", "divergence_mean_10mm": "10 mm"}
REFERENCES = ("direct", "naive_finetune")


def tables(run_dir: Path) -> str:
    stored = json.loads((run_dir / "results.json").read_text())
    rows = stored["rows"]
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
            out.append("| method | cells | mean difference | 95 % t interval | won / lost | sign p | "
                       + " | ".join(f"{a:g}" for a in amounts) + " |\n")
            out.append("|---|---|---|---|---|---|" + "---|" * len(amounts) + "\n")
            for method in methods:
                if method == reference:
                    continue
                pooled = compare_methods(rows, metric, method, reference)["all"]
                per = compare_methods(rows, metric, method, reference, by="amount")
                low, high = pooled.t_interval
                cells = " | ".join(f"{per[a].mean_difference:+.1f}" if a in per else "-" for a in amounts)
                out.append(f"| {method} | {pooled.n} | {pooled.mean_difference:+.1f} | {low:+.1f} to {high:+.1f} "
                           f"| {pooled.wins} / {pooled.losses} | {pooled.sign_p:.2g} | {cells} |\n")
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="experiment run directories (with results.json)")
    args = parser.parse_args(argv)
    for run in args.runs:
        if not (run / "results.json").is_file():
            parser.error(f"{run}: no results.json")
        print(tables(run))
    return 0


if __name__ == "__main__":
    sys.exit(main())
