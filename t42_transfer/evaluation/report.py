"""Figures and a Markdown report from an experiment run directory.

Like the paper's figures: time before divergence and position MSE against the
amount of target data (mean and standard deviation over seeds), the Lyapunov
exponent against the amount, and predicted against true paths in the x-y plane.
The Markdown states the findings in numbers, including whether the paper's
claims (naive fine-tuning can be worse than no adaptation; cumulative residual
and trajectory fine-tuning win) hold on this data.  The hold-still baseline
(the object predicted not to move) stands beside direct in every table and figure.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from t42_transfer.files import json_number, read_json
from t42_transfer.models.baselines import HoldStill

if TYPE_CHECKING:
    from t42_transfer.evaluation.experiment_config import ExperimentConfig

BASELINE = HoldStill.kind
METRICS = {
    "divergence_mean": ("time before divergence (steps)", "higher is better"),
    "position_mse_mean": ("position MSE (mm^2)", "lower is better"),
    "lyapunov_mean": ("max Lyapunov exponent (per step)", ""),
}


CONFIG_KEYS = ("name", "source", "target", "split", "seeds", "epsilon_mm")
"""What the report reads of ``results.json``'s ``config``."""
ROW_NUMBERS = ("amount", *METRICS, "covering_radius", "train_error_normalised", "train_error_xy_mm",
               "train_transitions")
"""What the report reads of each row, beside its ``method``: numbers (NaN and null allowed: a metric not defined)."""


def load_results(run_dir: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """``results.json``'s config and rows, checked for what the report reads; ValueError naming the file."""
    file = Path(run_dir) / "results.json"
    if not file.exists():
        raise ValueError(f"{file}: no results here; run `t42 experiment` first")
    content = read_json(file, "experiment's results")
    bad = _results_problem(content)
    if bad:
        raise ValueError(f"{file}: not the results of `t42 experiment`: {bad}")
    return content["config"], content["rows"]


def _results_problem(content: Any) -> str | None:
    """What is wrong with ``content`` as ``results.json``, or None."""
    if not isinstance(content, dict) or not isinstance(content.get("config"), dict):
        return "no 'config' object"
    config, rows = content["config"], content.get("rows")
    missing = [k for k in CONFIG_KEYS if k not in config]
    if missing:
        return f"its config lacks {', '.join(missing)}"
    if not isinstance(rows, list) or not rows:
        return "no 'rows' (a list of cells, at least one)"
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or not isinstance(row.get("method"), str):
            return f"row {i} is not a cell's row (an object with its 'method')"
        for key in ROW_NUMBERS:
            value = row.get(key, "missing")
            if value is not None and not json_number(value):
                return f"row {i} ({row['method']}): {key!r} is {value!r}, not a number"
    return None


def beside_direct(methods: list[str]) -> list[str]:
    """``methods`` in their order with the hold-still baseline moved next to direct (first without direct)."""
    rest = [m for m in methods if m != BASELINE]
    if BASELINE not in methods:
        return rest
    at = rest.index("direct") + 1 if "direct" in rest else 0
    return rest[:at] + [BASELINE] + rest[at:]


Summary = dict[str, dict[float, dict[str, tuple[float, float, int]]]]
"""method -> amount -> metric -> (mean, std, n) over seeds."""


def summarise(rows: list[dict[str, Any]]) -> Summary:
    """method -> amount -> metric -> (mean, std, n) over seeds; methods as :func:`beside_direct` orders them."""
    groups: dict[tuple[str, float], list[dict[str, Any]]] = defaultdict(list)
    for row in rows:
        groups[(row["method"], float(row["amount"]))].append(row)
    out: Summary = defaultdict(dict)
    for (method, amount), group in groups.items():
        stats = {}
        for key in (*METRICS, "covering_radius", "train_error_normalised", "train_error_xy_mm", "train_transitions"):
            values = np.array([r[key] for r in group], dtype=float)
            stats[key] = (float(values.mean()), float(values.std()), len(values))
        out[method][amount] = stats
    return {m: out[m] for m in beside_direct(list(out))}


def _amount_label(config: dict[str, Any]) -> str:
    return "target episodes" if config.get("split") == "paths" else "fraction of target data"


def plot_metric(summary: Summary, metric: str, config: dict[str, Any], path: Path) -> Path:
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    label, hint = METRICS[metric]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    colours = iter(f"C{i}" for i in range(len(summary)))
    for method, by_amount in summary.items():
        amounts = sorted(by_amount)
        mean = np.array([by_amount[a][metric][0] for a in amounts])
        std = np.array([by_amount[a][metric][1] for a in amounts])
        style = dict(color="0.35", ls="--") if method == BASELINE else dict(color=next(colours))
        ax.errorbar(amounts, mean, yerr=std, marker="o", ms=4, capsize=3, label=method, **style)
    if config.get("split") != "paths":
        ax.set_xscale("log")
    if metric == "position_mse_mean":
        ax.set_yscale("log")
    if metric == "lyapunov_mean":
        ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel(_amount_label(config))
    ax.set_ylabel(label)
    ax.set_title(f"{config['name']}: {label}" + (f" ({hint})" if hint else ""), fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return save(fig, path)


def plot_paths(run_dir: Path, amount: float, path: Path, episodes: int = 2) -> Path | None:
    """Predicted (seed 0) against true x-y paths of the first test episodes, one panel per method and hold-still."""
    from t42_transfer.plots import pyplot, save

    plt = pyplot()

    from t42_transfer.evaluation.experiment import Cell, cell_model_file, data_cache, load_side, load_test, target_split
    from t42_transfer.evaluation.experiment_config import load_config
    from t42_transfer.models.checkpoint import load_model

    cfg = load_config(run_dir / "config.yaml")
    sides = [load_side(cfg, side, data_cache(run_dir)) for side in ("source", "target")] + [
        load_test(cfg, data_cache(run_dir))]
    target, test_set = sides[1].data, None if sides[2] is None else sides[2].data
    # Cell keys hash the amount as the config spells it (1 and 1.0 differ).
    amount = next((a for a in cfg.amounts if float(a) == float(amount)), amount)
    methods = beside_direct([*cfg.methods, BASELINE])
    cols = min(4, len(methods))
    rows = -(-len(methods) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat[len(methods):]:
        ax.set_visible(False)
    for ax, method in zip(axes.flat, methods, strict=False):
        cell = Cell(method, amount, 0)
        if method == BASELINE:
            model = HoldStill()
        else:
            model_file = cell_model_file(cfg, run_dir, cell, *sides)
            if not model_file.exists():
                ax.set_title(f"{method}: no model", fontsize=8)
                continue
            model, _ = load_model(model_file)
        _, test = target_split(cfg, target, cell, test_set)
        for i, traj in enumerate(test.trajectories[:episodes]):
            predicted = model.rollout(torch.tensor(traj.states[:1]), torch.tensor(traj.actions[None]))[0].numpy()
            ax.plot(traj.states[:, 0], traj.states[:, 1], color=f"C{i}", lw=1.2, label="true" if i == 0 else None)
            ax.plot(predicted[:, 0], predicted[:, 1], color=f"C{i}", lw=1.0, ls="--",
                    label="predicted" if i == 0 else None)
            ax.plot(*traj.states[0, :2], "k.", ms=5)
        ax.set_title(method, fontsize=8)
        ax.set_xlabel("x (mm)", fontsize=7)
        ax.set_aspect("equal", adjustable="datalim")
    axes.flat[0].set_ylabel("y (mm)", fontsize=7)
    labelled = [ax for ax in axes.flat if ax.get_legend_handles_labels()[0]]
    if labelled:
        labelled[0].legend(fontsize=6)
    fig.suptitle(f"{cfg.name}: open-loop predictions at {amount} ({_amount_label(_as_dict(cfg))}), seed 0", fontsize=9)
    return save(fig, path, dpi=100)


def _as_dict(cfg: ExperimentConfig) -> dict[str, Any]:
    return {"split": cfg.split, "name": cfg.name}


def _fmt(stat: tuple[float, float, int], digits: int = 1) -> str:
    mean, std, _ = stat
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def findings(summary: Summary, config: dict[str, Any]) -> list[str]:
    """Plain statements, in numbers, of what the results say about the paper's claims."""
    lines = []
    amounts = sorted({a for by in summary.values() for a in by})
    div = {m: {a: summary[m][a]["divergence_mean"][0] for a in by} for m, by in summary.items()}
    for a in amounts:
        ranked = sorted((m for m in div if a in div[m]), key=lambda m: -div[m][a])
        lines.append(
            f"At {a} ({_amount_label(config)}), the longest mean time before divergence is "
            f"{ranked[0]} ({div[ranked[0]][a]:.1f} steps), then {ranked[1]} ({div[ranked[1]][a]:.1f}); "
            f"the shortest is {ranked[-1]} ({div[ranked[-1]][a]:.1f})."
        )
    if "direct" in div and "naive_finetune" in div:
        worse = [a for a in amounts if div["naive_finetune"].get(a, np.inf) < div["direct"].get(a, -np.inf)]
        lines.append(
            "Naive fine-tuning is worse than no adaptation (direct) at "
            + (", ".join(str(a) for a in worse) if worse else "no amount")
            + f" of the {len(amounts)} amounts tested (paper: it can be)."
        )
    if "cumulative_residual" in div:
        wins = [a for a in amounts if max(div, key=lambda m: div[m].get(a, -np.inf)) == "cumulative_residual"]
        lines.append(
            "Cumulative residual has the longest time before divergence at "
            + (", ".join(str(a) for a in wins) if wins else "no amount")
            + f" of the {len(amounts)} amounts (paper: at all of them)."
        )
    if "trajectory_finetune" in div and "naive_finetune" in div:
        better = [a for a in amounts
                  if div["trajectory_finetune"].get(a, -np.inf) > div["naive_finetune"].get(a, np.inf)]
        lines.append(
            "Trajectory fine-tuning beats naive fine-tuning at "
            + (", ".join(str(a) for a in better) if better else "no amount")
            + f" of the {len(amounts)} amounts (paper: at all of them)."
        )
    if BASELINE in div:
        still = div[BASELINE]
        short = {m: [a for a in amounts if a in div[m] and a in still and div[m][a] < still[a]]
                 for m in div if m != BASELINE}
        low, high = min(still.values()), max(still.values())
        lines.append(
            f"Holding still (the object predicted not to move) lasts {low:.1f}"
            + (f"-{high:.1f}" if high - low >= 0.05 else "")
            + " steps before divergence; methods that fall short of it: "
            + ("; ".join(f"{m} at {', '.join(str(a) for a in at)}" for m, at in short.items() if at) or "none") + "."
        )
    lyap = {m: {a: summary[m][a]["lyapunov_mean"][0] for a in by} for m, by in summary.items()}
    if "direct" in lyap:
        source_lambda = next(iter(lyap["direct"].values()))
        above = sorted({m for m in lyap if m != BASELINE for a in lyap[m] if lyap[m][a] > source_lambda + 1e-4})
        lines.append(
            f"The source model's (direct) mean max Lyapunov exponent is {source_lambda:.4f} per step; "
            f"methods that exceed it at some amount: {', '.join(above) if above else 'none'}."
        )
    return lines


def write_report(run_dir: Path, out_dir: Path | None = None) -> Path:
    """Figures (PNG) and ``report.md`` for ``run_dir``; returns the Markdown's path."""
    run_dir = Path(run_dir)
    out_dir = Path(out_dir) if out_dir else run_dir / "report"
    config, rows = load_results(run_dir)  # checked before a figure of an earlier report is replaced
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarise(rows)
    figures = {metric: plot_metric(summary, metric, config, out_dir / f"{metric}.png") for metric in METRICS}
    amounts = sorted({float(r["amount"]) for r in rows})
    paths_fig = plot_paths(run_dir, amounts[0], out_dir / "paths.png") if (run_dir / "config.yaml").exists() else None

    lines = [f"# Experiment `{config['name']}`", ""]
    lines += [
        f"Source: `{json.dumps(config['source'])}`; target: `{json.dumps(config['target'])}`; "
        + (f"test: `{json.dumps(config['test'])}`; " if config.get("test") else "")
        + f"split `{config['split']}`, amounts {amounts}, {config['seeds']} seeds, epsilon {config['epsilon_mm']} mm.",
        "",
        "## Findings",
        "",
    ]
    lines += [f"- {line}" for line in findings(summary, config)]
    for metric, (label, hint) in METRICS.items():
        lines += ["", f"## {label}" + (f" ({hint})" if hint else ""), "", f"![{metric}]({figures[metric].name})", ""]
        lines.append("| method | " + " | ".join(str(a) for a in amounts) + " |")
        lines.append("|---|" + "---|" * len(amounts))
        digits = 4 if metric == "lyapunov_mean" else 1
        for method, by_amount in summary.items():
            cells = [_fmt(by_amount[a][metric], digits) if a in by_amount else "" for a in amounts]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    lines += ["", "## Quantities of the paper's bound", ""]
    lines += [
        "r: covering radius of the target training states over the test states; epsilon: max one-step "
        "training error; both in units of the target states' standard deviation (epsilon also in mm for x, y).",
        "",
        "| method | amount | r | epsilon | epsilon x,y (mm) |",
        "|---|---|---|---|---|",
    ]
    for method, by_amount in summary.items():
        for a in amounts:
            if a in by_amount:
                s = by_amount[a]
                lines.append(
                    f"| {method} | {a} | {s['covering_radius'][0]:.3f} | {s['train_error_normalised'][0]:.3f} "
                    f"| {s['train_error_xy_mm'][0]:.2f} |"
                )
    if paths_fig:
        lines += ["", "## Predicted and true paths", "", f"![paths]({paths_fig.name})"]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report
